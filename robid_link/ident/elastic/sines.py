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
    cos_sin = np.empty((len(t), 2))  # cos ωt, sin ωt: the residual's pass reads them again
    _window_sums(t, x, w, edges, harmonics_of or 0, nh, gram, rhs, trig, cos_sin)
    coef = _solve(gram, rhs)  # [0]: the whole window, then the blocks
    span = float(t[-1] - t[0]) + float(np.median(np.diff(t), overwrite_input=True))
    bins = np.zeros((2 * most_bins, m), dtype=complex)
    _residual_bins(t, x, cos_sin, np.ascontiguousarray(coef[0]), span, bins)
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
    below, on_or_below = _lower_masks(gram.shape[-1])  # np.triu's, made once
    full = np.where(below, 0.0, gram) + np.swapaxes(np.where(on_or_below, 0.0, gram), -1, -2)
    try:
        return np.linalg.solve(full, rhs)
    except np.linalg.LinAlgError:
        return np.array([np.linalg.lstsq(g, r, rcond=None)[0] for g, r in zip(full, rhs,
                                                                                strict=True)])


@functools.lru_cache(maxsize=8)
def _lower_masks(size: int) -> tuple[np.ndarray, np.ndarray]:
    """The masks np.triu(·) and np.triu(·, 1) clear: below and on-or-below the diagonal."""
    return np.tri(size, size, -1, dtype=bool), np.tri(size, size, 0, dtype=bool)


@numba.njit(cache=True, nogil=True)
def _window_sums(t, x, w, edges, hcol, nh, gram, rhs, trig, cos_sin):
    """Upper triangles of the normal equations of [1, u, cos ωt, sin ωt] per column: the whole
    window into [0], block b into [b + 1] (u each one's time scaled to [−1, 1]); for the
    harmonics of column ``hcol`` (nh > 0) the sums their normal equations are made of
    (``_harmonic_system``): Σ cos kωt, Σ sin kωt (k ≤ 2 nh; [0, 0] the count), Σ u cos kωt,
    Σ u sin kωt, Σ x cos kωt, Σ x sin kωt (k ≤ nh), Σ u, Σ u², Σ x, Σ x u in [2…5, 0]; cos ωt
    and sin ωt per sample into ``cos_sin``. Every sum runs over the samples in their order
    (the same numbers however the passes are arranged), the design's and then each column's
    in local variables: a third of the time of sums kept in the arrays."""
    n, m = x.shape
    mid0, half0 = 0.5 * (t[0] + t[n - 1]), 0.5 * (t[n - 1] - t[0])
    half0 = half0 if half0 > 0 else 1.0
    a01 = a02 = a03 = a11 = a12 = a13 = a22 = a23 = a33 = count = 0.0  # the whole window's
    for b in range(edges.size - 1):
        i0, i1 = edges[b], edges[b + 1]
        mid, half = 0.5 * (t[i0] + t[i1 - 1]), max(0.5 * (t[i1 - 1] - t[i0]), 1e-300)
        b01 = b02 = b03 = b11 = b12 = b13 = b22 = b23 = b33 = 0.0  # the block's
        for i in range(i0, i1):
            c, s = math.cos(w * t[i]), math.sin(w * t[i])
            cos_sin[i, 0], cos_sin[i, 1] = c, s
            u0, u = (t[i] - mid0) / half0, (t[i] - mid) / half
            count += 1.0
            a01, a02, a03 = a01 + u0, a02 + c, a03 + s
            a11, a12, a13 = a11 + u0 * u0, a12 + u0 * c, a13 + u0 * s
            a22, a23, a33 = a22 + c * c, a23 + c * s, a33 + s * s
            b01, b02, b03 = b01 + u, b02 + c, b03 + s
            b11, b12, b13 = b11 + u * u, b12 + u * c, b13 + u * s
            b22, b23, b33 = b22 + c * c, b23 + c * s, b33 + s * s
        _upper(gram[b + 1], float(i1 - i0), b01, b02, b03, b11, b12, b13, b22, b23, b33)
    _upper(gram[0], count, a01, a02, a03, a11, a12, a13, a22, a23, a33)
    for j in range(m):
        r0 = r1 = r2 = r3 = 0.0
        for b in range(edges.size - 1):
            i0, i1 = edges[b], edges[b + 1]
            mid, half = 0.5 * (t[i0] + t[i1 - 1]), max(0.5 * (t[i1 - 1] - t[i0]), 1e-300)
            q0 = q1 = q2 = q3 = 0.0
            for i in range(i0, i1):
                xi, c, s = x[i, j], cos_sin[i, 0], cos_sin[i, 1]
                u0, u = (t[i] - mid0) / half0, (t[i] - mid) / half
                r0, r1, r2, r3 = r0 + xi, r1 + u0 * xi, r2 + c * xi, r3 + s * xi
                q0, q1, q2, q3 = q0 + xi, q1 + u * xi, q2 + c * xi, q3 + s * xi
            rhs[b + 1, 0, j], rhs[b + 1, 1, j], rhs[b + 1, 2, j], rhs[b + 1, 3, j] = q0, q1, q2, q3
        rhs[0, 0, j], rhs[0, 1, j], rhs[0, 2, j], rhs[0, 3, j] = r0, r1, r2, r3
    if nh:
        _harmonic_sums(t, x[:, hcol], cos_sin, mid0, half0, nh, trig)


@numba.njit(cache=True, nogil=True)
def _upper(g, s00, s01, s02, s03, s11, s12, s13, s22, s23, s33):
    g[0, 0], g[0, 1], g[0, 2], g[0, 3] = s00, s01, s02, s03
    g[1, 1], g[1, 2], g[1, 3] = s11, s12, s13
    g[2, 2], g[2, 3], g[3, 3] = s22, s23, s33


@numba.njit(cache=True, nogil=True)
def _harmonic_sums(t, xh, cos_sin, mid0, half0, nh, trig):
    """The harmonics' sums of ``_window_sums`` (cos kωt, sin kωt by the angle sum)."""
    for i in range(t.size):
        c, s = cos_sin[i, 0], cos_sin[i, 1]
        u0 = (t[i] - mid0) / half0
        xi = xh[i]
        ck, sk = c, s
        for k in range(1, 2 * nh + 1):
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
    gram = np.empty((2 + 2 * nh, 2 + 2 * nh))
    rhs = np.empty(2 + 2 * nh)
    _harmonic_fill(trig, nh, gram, rhs)
    return gram, rhs


@numba.njit(cache=True, nogil=True)
def _harmonic_fill(trig, nh, gram, rhs):
    cos_sum, sin_sum = trig[0], trig[1]  # [0]: the count, Σ sin 0 = 0
    gram[0, 0], gram[0, 1], gram[1, 1] = cos_sum[0], trig[2, 0], trig[3, 0]
    gram[1, 0] = gram[0, 1]
    rhs[0], rhs[1] = trig[4, 0], trig[5, 0]
    for p in range(1, nh + 1):
        a = 2 * p  # the row of cos pωt; sin pωt is the next
        gram[0, a], gram[0, a + 1] = cos_sum[p], sin_sum[p]  # the rows of 1 and u
        gram[1, a], gram[1, a + 1] = trig[2, p], trig[3, p]
        for r in range(2):
            gram[a, r], gram[a + 1, r] = gram[r, a], gram[r, a + 1]
        rhs[a], rhs[a + 1] = trig[4, p], trig[5, p]
        for q in range(1, nh + 1):
            b, diff = 2 * q, abs(p - q)
            sign = 1.0 if p > q else (-1.0 if p < q else 0.0)
            gram[a, b] = 0.5 * (cos_sum[diff] + cos_sum[p + q])
            gram[a + 1, b + 1] = 0.5 * (cos_sum[diff] - cos_sum[p + q])
            gram[a, b + 1] = 0.5 * (sin_sum[p + q] - sign * sin_sum[diff])
            gram[b + 1, a] = gram[a, b + 1]


@numba.njit(cache=True, nogil=True)
def _residual_bins(t, x, cos_sin, coef, span, bins):
    """Σ r(t) e^{−2πj(f + k/T)t} per column of the residual r of the whole window's fit
    ``coef`` (4, m), k = −K…−1, 1…K in the rows of ``bins`` (2K, m) (cos ωt, sin ωt per
    sample in ``cos_sin``); e^{−2πjkt/T} as powers of one exponential per sample, a bin at a
    time (its sums in local variables, over the samples in their order)."""
    n, m = x.shape
    most = bins.shape[0] // 2
    mid0, half0 = 0.5 * (t[0] + t[n - 1]), 0.5 * (t[n - 1] - t[0])
    half0 = half0 if half0 > 0 else 1.0
    step = np.empty(n, dtype=np.complex128)
    rz = np.empty((m, n), dtype=np.complex128)  # r e^{−jωt} per column and sample
    for i in range(n):
        c, s = cos_sin[i, 0], cos_sin[i, 1]
        u0 = (t[i] - mid0) / half0
        step[i] = complex(math.cos(2 * math.pi * t[i] / span),
                          -math.sin(2 * math.pi * t[i] / span))
        for j in range(m):
            r = x[i, j] - (coef[0, j] + coef[1, j] * u0 + coef[2, j] * c + coef[3, j] * s)
            rz[j, i] = complex(r * c, -r * s)
    power = np.full(n, complex(1.0, 0.0))
    for k in range(most):
        for i in range(n):
            power[i] *= step[i]
        for j in range(m):
            up, down = bins[most + k, j], bins[most - 1 - k, j]
            for i in range(n):
                up += power[i] * rz[j, i]
                down += power[i].conjugate() * rz[j, i]
            bins[most + k, j], bins[most - 1 - k, j] = up, down


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
