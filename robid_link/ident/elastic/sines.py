"""Sines in a log: complex amplitudes at one frequency (whole window, blocks, each period),
harmonics, the noise an amplitude carries (from the neighbouring frequencies), the frequency of
a steady sine. Convention x(t) = Re(X e^{jωt}), t the log's time."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

__all__ = ["SineFit", "sine_fit", "sine_amplitudes", "harmonics", "noise_bins",
           "without_transient", "period_blocks", "unexplained_share", "refine_frequency"]


class SineFit(NamedTuple):
    """A sine at one frequency on a polynomial (the drift), per column of a window: the
    complex amplitude over the whole window and over each block, and what the whole window's
    fit leaves."""

    amplitude: np.ndarray  # (m,)
    blocks: np.ndarray  # (blocks, m)
    residual: np.ndarray  # (N, m)


def sine_fit(t: np.ndarray, x: np.ndarray, f_hz: float, blocks: int = 1, degree: int = 1
             ) -> SineFit:
    """X per column of ``x`` (x ≈ a + b·t (+ c·t²) + Re(X e^{jωt})), by least squares on
    [1, t, …, cos, sin] (the drift's ramp removed), over the whole window and over ``blocks``
    equal sub-windows, with the whole window's residual."""
    x = x.reshape(len(t), -1)
    tc = t - t.mean()
    turn = np.exp(1j * (2 * math.pi * f_hz) * t)
    sines = [turn.real, turn.imag]
    a = np.column_stack([tc ** p for p in range(degree + 1)] + sines)
    coef = np.linalg.lstsq(a, x, rcond=None)[0]
    edges = np.linspace(0, len(t), blocks + 1).astype(int)
    return SineFit(_amplitude(coef), _block_amplitudes(t, x, sines, edges, degree),
                   x - a @ coef)


def sine_amplitudes(t: np.ndarray, x: np.ndarray, f_hz: float, blocks: int = 1,
                    degree: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Complex amplitudes X (x ≈ a + b·t (+ c·t²) + Re(X e^{jωt})) per column of ``x``, by
    least squares on [1, t, …, cos, sin] (the drift's ramp removed), over the whole window and
    over ``blocks`` equal sub-windows. Returns (X (m,), X per block (blocks, m))."""
    fit = sine_fit(t, x, f_hz, blocks, degree)
    return fit.amplitude, fit.blocks


def _amplitude(coef: np.ndarray) -> np.ndarray:
    """X from the cos and sin coefficients, the last two rows of a least-squares solution."""
    return coef[-2] - 1j * coef[-1]


def _block_amplitudes(t: np.ndarray, x: np.ndarray, sines: list[np.ndarray],
                      edges: np.ndarray, degree: int) -> np.ndarray:
    """The sine's amplitude over each block [edges[i], edges[i + 1]) with a polynomial of
    ``degree`` of its own: all blocks' normal equations summed at once, the polynomial in each
    block's own centred and scaled time (the sine's coefficients do not depend on how the
    polynomial's span is written; this keeps the small systems well conditioned)."""
    sizes = np.diff(edges)
    if np.any(sizes < degree + 3):  # too short to fit: one least-squares fit per block
        tc = t - t.mean()
        a = np.column_stack([tc ** p for p in range(degree + 1)] + sines)
        return np.array([_amplitude(np.linalg.lstsq(a[i:j], x[i:j], rcond=None)[0])
                         for i, j in zip(edges[:-1], edges[1:], strict=True)])
    block = np.repeat(np.arange(sizes.size), sizes)
    lo, hi = t[edges[:-1]], t[edges[1:] - 1]
    mid, half = 0.5 * (lo + hi), np.maximum(0.5 * (hi - lo), 1e-300)
    local = (t - mid[block]) / half[block]
    a = np.column_stack([local ** p for p in range(degree + 1)] + sines)
    gram = np.add.reduceat(a[:, :, None] * a[:, None, :], edges[:-1], axis=0)
    rhs = np.add.reduceat(a[:, :, None] * x[:, None, :], edges[:-1], axis=0)
    return _amplitude(np.moveaxis(np.linalg.solve(gram, rhs), 1, 0))


def _powers(base: np.ndarray, most: int) -> np.ndarray:
    """base¹ … base^most (most, N) by repeated products (|base| = 1: no exponential each)."""
    out = np.empty((most, base.size), dtype=complex)
    out[0] = base
    for h in range(1, most):
        np.multiply(out[h - 1], base, out=out[h])
    return out


def harmonics(t: np.ndarray, x: np.ndarray, f: float, most: int = 9) -> np.ndarray:
    """Complex amplitudes of x's first ``most`` harmonics of f (on a line: the drift)."""
    tc = t - t.mean()
    turns = _powers(np.exp(2j * math.pi * f * t), most)
    cols = np.empty((t.size, 2 + 2 * most))
    cols[:, 0], cols[:, 1] = 1.0, tc
    cols[:, 2::2], cols[:, 3::2] = turns.real.T, turns.imag.T
    coef = np.linalg.lstsq(cols, x, rcond=None)[0][2:]
    return coef[0::2] - 1j * coef[1::2]


def noise_bins(t: np.ndarray, residual: np.ndarray, f: float, most: int = 8
               ) -> tuple[np.ndarray, np.ndarray]:
    """The ``residual`` of a sine fit at f on a line (the drift; ``sine_fit``), as amplitudes
    at the neighbouring frequencies f ± k/T of the window T (k = 1…``most``, above f/4):
    orthogonal to the sine over whole periods, they carry the noise an amplitude at f carries
    (its spectrum is smooth there) and the leakage of a decaying transient (smooth in k).
    Returns (k, (bins, m) complex amplitudes scaled like X)."""
    res = residual.reshape(len(t), -1)
    span = float(t[-1] - t[0]) + float(np.median(np.diff(t)))
    k = np.r_[-most:0, 1:most + 1]
    keep = f + k / span > 0.25 * f
    # e^{−2πj(f + k/T)t} = (e^{−2πjt/T})^k · e^{−2πjft}: two exponentials per sample
    rot = res * np.exp(-2j * math.pi * f * t)[:, None]
    up = _powers(np.exp(-2j * math.pi * t / span), most)
    bins = np.concatenate((up[::-1].conj() @ rot, up @ rot))
    return k[keep], 2.0 / t.size * bins[keep]


def without_transient(k: np.ndarray, y: np.ndarray, bins: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, float]:
    """A decaying transient in the window (the loop's slowest mode, rung by the step's start
    or the drift's reversal) leaks into the amplitude at f as it does into the neighbouring
    bins, smoothly in k: a quadratic in k through the bins |k| ≤ 3, taken at k = 0, is its
    share of X (the local polynomial method; over ±5 bins a ring at half the step's frequency
    left 0.7 % of G, over ±3 0.2 %). The noise is what a quartic through all the bins leaves.
    Returns (X less the transient, the noise per bin, the factor from the noise's mean square
    to the variance of X)."""
    local = np.abs(k) <= 3
    deg = 2 if local.sum() >= 5 else (1 if local.sum() >= 3 else 0)
    basis = np.vander(k[local].astype(float), deg + 1, increasing=True)
    coef, *_ = np.linalg.lstsq(basis, bins[local], rcond=None)
    lever = float(np.linalg.inv(basis.T @ basis)[0, 0])
    wide = np.vander(k.astype(float), min(5, max(k.size - 3, 1)), increasing=True)
    noise = bins - wide @ np.linalg.lstsq(wide, bins, rcond=None)[0]
    dof = max(k.size - wide.shape[1], 1)
    return y - coef[0], noise, k.size / dof * (1.0 + lever)


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
