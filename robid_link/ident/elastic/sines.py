"""Sines in a log: complex amplitudes at one frequency (whole window, blocks, each period),
harmonics, the noise an amplitude carries (from the neighbouring frequencies), the frequency of
a steady sine. Convention x(t) = Re(X e^{jωt}), t the log's time."""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numba
import numpy as np

__all__ = ["StepSines", "step_sines", "sine_amplitudes", "without_transient",
           "period_blocks", "unexplained_share", "refine_frequency"]


class StepSines(NamedTuple):
    """What one stepped-sine window shows at its frequency f, per column: the complex amplitude
    over the whole window and over each block (a sine on a line, the drift, by least squares),
    the residual's amplitudes at the neighbouring frequencies f + k/T (``noise_bins``) and one
    column's harmonics (None when not asked)."""

    amplitude: np.ndarray  # (m,)
    blocks: np.ndarray  # (blocks, m)
    k: np.ndarray  # (bins,)
    bins: np.ndarray  # (bins, m)
    harmonics: np.ndarray | None  # (most_harmonics,)


def step_sines(t: np.ndarray, x: np.ndarray, f_hz: float, blocks: int, *,
               harmonics_of: int | None = None, most_bins: int = 8, most_harmonics: int = 9
               ) -> StepSines:
    """The sine at ``f_hz`` in each column of ``x`` over the window t: x ≈ a + b·t +
    Re(X e^{jωt}) over the whole window and over ``blocks`` equal sub-windows; the residual of
    the whole window's fit as amplitudes at f ± k/T (k = 1…``most_bins``, above f/4: orthogonal
    to the sine over whole periods, they carry the noise an amplitude at f carries — its
    spectrum is smooth there — and the leakage of a decaying transient, smooth in k); the
    first ``most_harmonics`` harmonics of column ``harmonics_of`` on a line. The normal
    equations of every fit are summed in one pass over the samples (numba), time centred and
    scaled to [−1, 1] in each window (the sines' coefficients do not depend on how the line is
    written; the small systems stay well conditioned)."""
    t = np.ascontiguousarray(t, dtype=float)
    x = np.ascontiguousarray(x.reshape(len(t), -1), dtype=float)
    m = x.shape[1]
    w = 2 * math.pi * f_hz
    edges = np.linspace(0, len(t), blocks + 1).astype(np.int64)
    nh = most_harmonics if harmonics_of is not None else 0
    gram, rhs = np.zeros((blocks + 1, 4, 4)), np.zeros((blocks + 1, 4, m))
    trig = np.zeros((6, 2 * nh + 1))  # the sums of the harmonics' normal equations
    _window_sums(t, x, w, edges, harmonics_of or 0, nh, gram, rhs, trig)
    coef = _solve(gram, rhs)  # [0]: the whole window, then the blocks
    span = float(t[-1] - t[0]) + float(np.median(np.diff(t)))
    bins = np.zeros((2 * most_bins, m), dtype=complex)
    _residual_bins(t, x, w, np.ascontiguousarray(coef[0]), span, bins)
    k = np.r_[-most_bins:0, 1:most_bins + 1]
    keep = f_hz + k / span > 0.25 * f_hz
    harm = None
    if nh:
        hgram, hrhs = _harmonic_system(trig, nh)
        hc = _solve(hgram[None], hrhs[None, :, None])[0, 2:, 0]
        harm = hc[0::2] - 1j * hc[1::2]
    amp = coef[:, 2] - 1j * coef[:, 3]
    return StepSines(amp[0], amp[1:], k[keep], 2.0 / t.size * bins[keep], harm)


def _solve(gram: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Each symmetric system (upper triangles summed) solved; by the SVD where singular."""
    full = np.triu(gram) + np.swapaxes(np.triu(gram, 1), -1, -2)
    try:
        return np.linalg.solve(full, rhs)
    except np.linalg.LinAlgError:
        return np.array([np.linalg.lstsq(g, r, rcond=None)[0] for g, r in zip(full, rhs,
                                                                                strict=True)])


@numba.njit(cache=True, nogil=True)
def _window_sums(t, x, w, edges, hcol, nh, gram, rhs, trig):
    """Upper triangles of the normal equations of [1, u, cos ωt, sin ωt] per column: the whole
    window into [0], block b into [b + 1] (u each one's time scaled to [−1, 1]); for the
    harmonics of column ``hcol`` (nh > 0) the sums their normal equations are made of
    (``_harmonic_system``): Σ cos kωt, Σ sin kωt (k ≤ 2 nh; [0, 0] the count), Σ u cos kωt,
    Σ u sin kωt, Σ x cos kωt, Σ x sin kωt (k ≤ nh), Σ u, Σ u², Σ x, Σ x u in [2…5, 0]."""
    n, m = x.shape
    mid0, half0 = 0.5 * (t[0] + t[n - 1]), 0.5 * (t[n - 1] - t[0])
    half0 = half0 if half0 > 0 else 1.0
    row = np.empty(4)
    for b in range(edges.size - 1):
        i0, i1 = edges[b], edges[b + 1]
        mid, half = 0.5 * (t[i0] + t[i1 - 1]), max(0.5 * (t[i1 - 1] - t[i0]), 1e-300)
        for i in range(i0, i1):
            c, s = math.cos(w * t[i]), math.sin(w * t[i])
            u0 = (t[i] - mid0) / half0
            row[0], row[1], row[2], row[3] = 1.0, u0, c, s
            _add_outer(row, x[i], gram[0], rhs[0])
            row[1] = (t[i] - mid) / half
            _add_outer(row, x[i], gram[b + 1], rhs[b + 1])
            if nh:
                xi = x[i, hcol]
                ck, sk = c, s
                for k in range(1, 2 * nh + 1):  # cos, sin of kωt by the angle sum
                    trig[0, k] += ck
                    trig[1, k] += sk
                    if k <= nh:
                        trig[2, k] += u0 * ck
                        trig[3, k] += u0 * sk
                        trig[4, k] += xi * ck
                        trig[5, k] += xi * sk
                    ck, sk = ck * c - sk * s, sk * c + ck * s
                trig[0, 0] += 1.0
                trig[2, 0] += u0
                trig[3, 0] += u0 * u0
                trig[4, 0] += xi
                trig[5, 0] += xi * u0


def _harmonic_system(trig: np.ndarray, nh: int) -> tuple[np.ndarray, np.ndarray]:
    """The normal equations of [1, u, cos ωt, sin ωt, …, cos nh ωt, sin nh ωt] from the sums of
    ``_window_sums``: products of harmonics are sums of harmonics, cos p cos q =
    (cos(p−q) + cos(p+q))/2, sin p sin q = (cos(p−q) − cos(p+q))/2, cos p sin q =
    (sin(p+q) − sin(p−q))/2."""
    cos_sum, sin_sum = trig[0], trig[1]  # [0]: the count, Σ sin 0 = 0
    h = np.arange(1, nh + 1)
    p, q = np.meshgrid(h, h, indexing="ij")
    gram = np.empty((2 + 2 * nh, 2 + 2 * nh))
    gram[2::2, 2::2] = 0.5 * (cos_sum[np.abs(p - q)] + cos_sum[p + q])
    gram[3::2, 3::2] = 0.5 * (cos_sum[np.abs(p - q)] - cos_sum[p + q])
    gram[2::2, 3::2] = 0.5 * (sin_sum[p + q] - np.sign(p - q) * sin_sum[np.abs(p - q)])
    gram[3::2, 2::2] = gram[2::2, 3::2].T
    first = np.empty((2, 2 + 2 * nh))  # the rows of 1 and u
    first[0, :2] = cos_sum[0], trig[2, 0]
    first[1, :2] = trig[2, 0], trig[3, 0]
    first[0, 2::2], first[0, 3::2] = cos_sum[h], sin_sum[h]
    first[1, 2::2], first[1, 3::2] = trig[2, h], trig[3, h]
    gram[:2], gram[:, :2] = first, first.T
    rhs = np.concatenate(([trig[4, 0], trig[5, 0]], np.ravel((trig[4, h], trig[5, h]), "F")))
    return gram, rhs


@numba.njit(cache=True, nogil=True)
def _add_outer(row, xi, gram, rhs):
    for p in range(row.size):
        for j in range(xi.size):
            rhs[p, j] += row[p] * xi[j]
        for q in range(p, row.size):
            gram[p, q] += row[p] * row[q]


@numba.njit(cache=True, nogil=True)
def _residual_bins(t, x, w, coef, span, bins):
    """Σ r(t) e^{−2πj(f + k/T)t} per column of the residual r of the whole window's fit
    ``coef`` (4, m), k = −K…−1, 1…K in the rows of ``bins`` (2K, m); e^{−2πjkt/T} as powers
    of one exponential per sample."""
    n, m = x.shape
    most = bins.shape[0] // 2
    mid0, half0 = 0.5 * (t[0] + t[n - 1]), 0.5 * (t[n - 1] - t[0])
    half0 = half0 if half0 > 0 else 1.0
    turns = np.empty(most, dtype=np.complex128)
    for i in range(n):
        c, s = math.cos(w * t[i]), math.sin(w * t[i])
        u0 = (t[i] - mid0) / half0
        step = complex(math.cos(2 * math.pi * t[i] / span), -math.sin(2 * math.pi * t[i] / span))
        power = complex(1.0, 0.0)
        for k in range(most):
            power *= step
            turns[k] = power
        for j in range(m):
            r = x[i, j] - (coef[0, j] + coef[1, j] * u0 + coef[2, j] * c + coef[3, j] * s)
            rz = complex(r * c, -r * s)  # r e^{−jωt}
            for k in range(most):
                bins[most + k, j] += turns[k] * rz
                bins[most - 1 - k, j] += turns[k].conjugate() * rz


def sine_amplitudes(t: np.ndarray, x: np.ndarray, f_hz: float, blocks: int = 1,
                    degree: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Complex amplitudes X (x ≈ a + b·t (+ c·t²) + Re(X e^{jωt})) per column of ``x``, by
    least squares on [1, t, …, cos, sin] (the drift's ramp removed), over the whole window and
    over ``blocks`` equal sub-windows. Returns (X (m,), X per block (blocks, m))."""
    x = x.reshape(len(t), -1)
    tc = t - t.mean()

    def fit(sl: slice) -> np.ndarray:
        w = 2 * math.pi * f_hz * t[sl]
        a = np.column_stack([tc[sl] ** p for p in range(degree + 1)] + [np.cos(w), np.sin(w)])
        coef = np.linalg.lstsq(a, x[sl], rcond=None)[0]
        return coef[-2] - 1j * coef[-1]

    whole = fit(slice(None))
    edges = np.linspace(0, len(t), blocks + 1).astype(int)
    per = np.array([fit(slice(a, b)) for a, b in zip(edges[:-1], edges[1:], strict=True)])
    return whole, per


def without_transient(k: np.ndarray, y: np.ndarray, bins: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, float]:
    """A decaying transient in the window (the loop's slowest mode, rung by the step's start
    or the drift's reversal) leaks into the amplitude at f as it does into the neighbouring
    bins, smoothly in k: a quadratic in k through the bins |k| ≤ 3, taken at k = 0, is its
    share of X (the local polynomial method; over ±5 bins a ring at half the step's frequency
    left 0.7 % of G, over ±3 0.2 %). The noise is what a quartic through all the bins leaves.
    Returns (X less the transient, the noise per bin, the factor from the noise's mean square
    to the variance of X)."""
    at_zero, residual, factor = _bin_projections(tuple(int(v) for v in k))
    return y - at_zero @ bins, residual @ bins, factor


@functools.lru_cache(maxsize=64)
def _bin_projections(k: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray, float]:
    """For the bins k (one set serves most steps): the row that takes the local quadratic's
    value at k = 0 from the bins, the projection onto what the quartic leaves, and the factor
    from the noise's mean square to the variance of X."""
    ks = np.array(k, dtype=float)
    local = np.abs(ks) <= 3
    deg = 2 if local.sum() >= 5 else (1 if local.sum() >= 3 else 0)
    basis = np.vander(ks[local], deg + 1, increasing=True)
    at_zero = np.zeros(ks.size)
    at_zero[local] = np.linalg.pinv(basis)[0]
    lever = float(np.linalg.inv(basis.T @ basis)[0, 0])
    wide = np.vander(ks, min(5, max(ks.size - 3, 1)), increasing=True)
    residual = np.eye(ks.size) - wide @ np.linalg.pinv(wide)
    dof = max(ks.size - wide.shape[1], 1)
    return at_zero, residual, ks.size / dof * (1.0 + lever)


def period_blocks(t: np.ndarray, x: np.ndarray, f: float) -> tuple[np.ndarray, np.ndarray]:
    """Complex amplitudes at f of each whole period of x (columns), a local quadratic removed
    (the drift and its ramps); returns (block start indices, amplitudes (blocks, columns)).
    On a uniform time base every block has one design matrix (local time): one projection."""
    x = x.reshape(len(t), -1)
    per = 1.0 / f
    nblk = int((t[-1] - t[0]) // per)
    edges = np.searchsorted(t, t[0] + per * np.arange(nblk + 1))
    steps = np.diff(t)
    dt = float(np.median(steps))
    size = int(round(per / dt))
    if np.ptp(steps) > 1e-6 * dt or nblk == 0 or edges[-2] + size > len(t):
        amps = np.array([sine_amplitudes(t[a:b], x[a:b], f, degree=2)[0]
                         for a, b in zip(edges[:-1], edges[1:], strict=True)])
        return edges, amps.reshape(nblk, -1)
    loc = np.arange(size) * dt
    lc = loc - loc.mean()
    w = 2 * math.pi * f
    design = np.column_stack((np.ones(size), lc, lc * lc, np.cos(w * loc), np.sin(w * loc)))
    rows = np.linalg.pinv(design)[-2:]  # the cos and sin coefficients
    blocks = x[edges[:-1, None] + np.arange(size)]  # (blocks, size, columns)
    coef = np.einsum("kl,blm->bkm", rows, blocks)
    local = coef[:, 0] - 1j * coef[:, 1]
    return edges, local * np.exp(-1j * w * t[edges[:-1]])[:, None]


def unexplained_share(t: np.ndarray, x: np.ndarray, f: float) -> float:
    """Share of x's variance (a quadratic trend removed) a sine at f leaves unexplained."""
    tc = t - t.mean()
    w = 2 * math.pi * f * t
    trend = np.column_stack((np.ones(t.size), tc, tc * tc))
    x = x - trend @ np.linalg.lstsq(trend, x, rcond=None)[0]
    a = np.column_stack((trend, np.cos(w), np.sin(w)))
    res = x - a @ np.linalg.lstsq(a, x, rcond=None)[0]
    return float(np.sum(res * res) / max(np.sum(x * x), 1e-300))


def refine_frequency(t: np.ndarray, x: np.ndarray, f0: float, span_bins: float = 1.5) -> float:
    """The frequency near f0 whose sinusoid (on a quadratic trend) leaves the least residual
    (least squares; the projected power alone is biased by the trend): a grid over ±1.5 bins
    of the window (side lobes), then golden section around the best. The trend is projected
    out once; per frequency only the sine pair is."""
    from scipy.optimize import minimize_scalar

    tc = t - t.mean()
    x = x.reshape(len(t), -1)
    x = x / np.maximum(x.std(axis=0), 1e-300)
    trend = np.linalg.qr(np.column_stack((np.ones(t.size), tc, tc * tc)))[0]
    xd = x - trend @ (trend.T @ x)
    total = float(np.sum(xd * xd))

    def neg(f: float) -> float:
        w = 2 * math.pi * f * t
        b = np.column_stack((np.cos(w), np.sin(w)))
        b = b - trend @ (trend.T @ b)
        r = b.T @ xd
        return total - float(np.sum(r * np.linalg.solve(b.T @ b, r)))

    span = span_bins / (t[-1] - t[0])
    grid = f0 + np.linspace(-span, span, 31)
    best = float(grid[int(np.argmin([neg(f) for f in grid]))])
    step = grid[1] - grid[0]
    res = minimize_scalar(neg, bounds=(best - step, best + step), method="bounded",
                          options={"xatol": 1e-6 * f0})
    return float(res.x)
