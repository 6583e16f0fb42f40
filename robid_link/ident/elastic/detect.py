"""Stepped sines found in a log alone (an operator's own log, no schedule): runs of windows where
a joint is one steady sine, each candidate's amplitude plateau, its frequency and its measured
window; steps of two axes at one frequency keyed together for the 2×2 estimate."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from robid_link.exceptions import DataError
from robid_link.ident.elastic.sines import period_blocks, refine_frequency, unexplained_share

__all__ = ["detect_steps", "log_schedule"]


def detect_steps(t: np.ndarray, q: np.ndarray, tau: np.ndarray, *,
                 windows_s: Sequence[float] = (2.0, 1.4, 1.0, 0.7, 0.5, 0.3),
                 rel_tol: float = 0.02
                 ) -> list[dict[str, Any]]:
    """Steps of constant-frequency sinusoidal motion found in the log alone (an operator's own
    log), from the positions (the position loop puts the reference's sine there at every
    frequency; ``tau`` is not needed). Per window (several lengths, longer first; a step holds
    ≥ 4 periods of its window) and per joint (decimated, a quadratic trend removed: the
    drift) the dominant frequency and how much of the power it holds; runs of windows where a
    joint is a clean sine of a steady frequency become candidate steps. In each, period by
    period, the amplitude plateau is found, the frequency refined on it, and its last 60 %
    measured. A stretch that is not one steady sine is dropped. Returns schedule-like dicts:
    ``joint`` (largest acceleration relative to that joint's own), ``joints`` when several
    axes drift and oscillate at the step's frequency (a held axis that only reacts through
    the coupling does not drift), ``f_hz``, ``t_measure``, ``t_end``."""
    fs = 1.0 / float(np.median(np.diff(t)))
    if t[-1] - t[0] < 2 * min(windows_s):
        raise DataError(f"log of {t[-1] - t[0]:.3g} s is too short for a stepped-sine analysis")
    # the search on the positions (the reference's sine shows there at every frequency),
    # decimated to ~500 Hz; the measured windows then on the full log
    r = max(1, int(round(fs / 500)))  # fs from the times' median step: 1999.99… Hz is 2 kHz
    qd = q[::r] if r == 1 else _decimate(q, r)
    spans: list[tuple[float, float, float]] = []
    for win in windows_s:
        for t0, t1, f in _runs(t[::r][:len(qd)], qd, fs / r, win, rel_tol):
            # one candidate per step and frequency: the longest run (windows longer first)
            if f * win >= 4 and not any(
                    abs(f - g) < 0.03 * f and min(t1, b) - max(t0, a) > 0.5 * (t1 - t0)
                    for a, b, g in spans):
                spans.append((t0, t1, f))
    acc = np.std(np.diff(q, 2, axis=0), axis=0) * fs * fs
    acc_scale = np.maximum(acc, 0.5 * acc.max() + 1e-300)  # an axis that never moves: noise
    # every candidate's own plateau, then the longest plateaus first: a long window's run
    # may straddle two steps (its plateau then fails or shrinks), a shorter one's fits one
    found = [st for t0, t1, f0 in sorted(spans)
             for f in _span_peaks(t, q, t0, t1, f0, acc_scale)
             if (st := _step_in(t, q, t0, t1, f, acc_scale)) is not None]
    steps: list[dict[str, Any]] = []
    for st in sorted(found, key=lambda s: s["t_measure"] - s["t_end"]):
        a, b = st["t_measure"], st["t_end"]
        if not any(min(b, o["t_end"]) - max(a, o["t_measure"]) > 0.3 * (b - a)
                   for o in steps):
            steps.append(st)
    steps.sort(key=lambda s: s["t_measure"])
    if not steps:
        raise DataError("no sinusoidal steps found in the log (no stretch of constant-frequency "
                        "motion): is it a stepped-sine log?")
    return steps


def _decimate(x: np.ndarray, r: int) -> np.ndarray:
    import scipy.signal as sig

    return np.asarray(sig.decimate(x, r, ftype="fir", axis=0, zero_phase=True))


def _runs(t: np.ndarray, x: np.ndarray, fs: float, win: float, rel_tol: float
          ) -> list[tuple[float, float, float]]:
    """(t0, t1, f) of runs of windows of length ``win`` where a channel is a clean sine of one
    steady frequency."""
    n = int(win * fs)
    hop = max(1, n // 4)
    nfft = 4 * n
    freqs = np.fft.rfftfreq(nfft, 1.0 / fs)
    low = freqs < 2.0 / win
    u = np.linspace(-1.0, 1.0, n)
    trend = np.column_stack((np.ones(n), u, u * u))
    proj = np.linalg.pinv(trend)
    han = np.hanning(n)[:, None]
    starts = np.arange(0, max(len(t) - n, 1), hop)
    f_win = np.zeros(starts.size)
    good = np.zeros(starts.size, dtype=bool)
    near = 4 * 3  # ± 3 bins of the unpadded transform
    for i, s0 in enumerate(starts):
        seg = x[s0:s0 + n]
        seg = seg - trend @ (proj @ seg)
        spec = np.abs(np.fft.rfft(seg * han, nfft, axis=0)) ** 2
        spec[low] = 0.0
        k = np.argmax(spec, axis=0)
        total = np.maximum(spec.sum(axis=0), 1e-300)
        csum = np.vstack((np.zeros((1, spec.shape[1])), np.cumsum(spec, axis=0)))
        lo, hi = np.maximum(k - near, 0), np.minimum(k + near + 1, spec.shape[0])
        cols = np.arange(spec.shape[1])
        conc = (csum[hi, cols] - csum[lo, cols]) / total
        c = int(np.argmax(conc))
        f_win[i] = freqs[k[c]]
        good[i] = conc[c] > 0.8 and f_win[i] >= 4.0 / win
    out = []
    a = 0
    for i in range(1, starts.size + 1):
        if (i == starts.size or not good[i] or not good[a]
                or abs(f_win[i] - f_win[a]) > rel_tol * f_win[a] + 2 * fs / nfft):
            if good[a] and i - a >= 3:
                out.append((float(t[starts[a]]), float(t[min(starts[i - 1] + n - 1, len(t) - 1)]),
                            float(np.median(f_win[a:i]))))
            a = i
    return out


def _span_peaks(t: np.ndarray, q: np.ndarray, t0: float, t1: float, f0: float,
                acc_scale: np.ndarray, most: int = 3) -> list[float]:
    """f0 and the strongest spectral peaks of a candidate span (the accelerations relative to
    each joint's own, a quadratic trend removed): a run of windows may straddle two steps of
    close frequencies (its median frequency then lies between them, where neither has a
    plateau); each peak is tried for a step of its own."""
    sel = (t >= t0) & (t <= t1)
    ts, x = t[sel], q[sel]
    if ts.size < 16:
        return [f0]
    u = np.linspace(-1.0, 1.0, ts.size)
    trend = np.column_stack((np.ones(ts.size), u, u * u))
    x = x - trend @ np.linalg.lstsq(trend, x, rcond=None)[0]
    nfft = 1 << int(math.ceil(math.log2(8 * ts.size)))
    freqs = np.fft.rfftfreq(nfft, float(np.median(np.diff(ts))))
    spec = np.abs(np.fft.rfft(x * np.hanning(ts.size)[:, None], nfft, axis=0)) ** 2
    power = np.sum(spec * ((2 * np.pi * freqs[:, None]) ** 4 / acc_scale ** 2), axis=1)
    # the neighbouring steps' frequencies (ω⁴ lifts the noise far above them)
    power[(freqs < max(2.0 / (ts[-1] - ts[0]), f0 / 1.5)) | (freqs > 1.5 * f0)] = 0.0
    peaks = [i for i in range(1, power.size - 1)
             if power[i] >= power[i - 1] and power[i] > power[i + 1]
             and power[i] > 0.05 * power.max()]
    peaks.sort(key=lambda i: -power[i])
    return [f0] + [float(freqs[i]) for i in peaks[:most] if abs(freqs[i] - f0) > 0.01 * f0]


def _plateau(mag: np.ndarray, levels: np.ndarray, tol: float = 0.03) -> tuple[int, int]:
    """The longest run of periods whose amplitudes stay within ±``tol`` of one of ``levels``
    (the amplitudes of the candidate's own periods: a span may hold two steps of different
    amplitudes). Returns (first, end) period indices."""
    levels = levels[levels > 0]
    if not mag.size or not levels.size:
        return 0, 0
    on = np.abs(mag[None, :] / levels[:, None] - 1.0) < tol
    count = np.cumsum(on, axis=1)
    runs = count - np.maximum.accumulate(np.where(on, 0, count), axis=1)  # run lengths
    level, end = np.unravel_index(int(np.argmax(runs)), runs.shape)
    length = int(runs[level, end])
    return int(end) - length + 1, int(end) + 1


def _step_in(t: np.ndarray, q: np.ndarray, t0: float, t1: float, f0: float,
             acc_scale: np.ndarray) -> dict[str, Any] | None:
    """The measured window of one candidate step (a run of clean windows from t0 to t1, at
    about f0): period by period (each with its own quadratic trend, so the drift's ramps do
    not leak in), the moving joint, the plateau of its amplitude (within 3 % of the run's
    level, less its last period when long), the frequency from the phase advance over the
    plateau then by least squares on it; the measured window is the plateau's last 60 %."""
    ext = (t >= t0 - 0.5 * (t1 - t0)) & (t <= t1 + 0.5 * (t1 - t0))
    ts = t[ext]
    if ts.size < 64 or (ts[-1] - ts[0]) * f0 < 8:
        return None
    edges, amps = period_blocks(ts, q[ext], f0)
    in_run = (ts[edges[:-1]] >= t0) & (ts[edges[1:] - 1] <= t1)
    if in_run.sum() < 3:
        return None
    rel = np.median(np.abs(amps[in_run]), axis=0) * (2 * math.pi * f0) ** 2 / acc_scale
    joint = int(np.argmax(rel)) + 1
    x = amps[:, joint - 1]
    # looser where a transient beats with the sine (the arm ringing, lightly damped, at an
    # antiresonance close to the step's frequency)
    for tol in (0.03, 0.06, 0.1):
        first, last = _plateau(np.abs(x), np.abs(x[in_run]), tol)
        if last - first >= 8:
            break
    last -= 1 if last - first > 8 else 0  # the ramp out may start in the last one
    if int(0.6 * (last - first)) < 4:
        return None
    # the phase advances by 2π (f − f0)/f0 per block of the plateau
    phase = np.unwrap(np.angle(x[first:last]))
    slope = np.polyfit(np.arange(last - first), phase, 1)[0]
    f = f0 * (1.0 + slope / (2 * math.pi))
    t_start, t_end = float(ts[edges[first]]), float(ts[edges[last] - 1])
    plateau = (t >= t_start) & (t <= t_end)
    f = refine_frequency(t[plateau], q[plateau, joint - 1:joint], f, span_bins=0.25)
    periods = math.floor(0.6 * (t_end - t_start) * f)
    t_meas = t_end - periods / f
    if unexplained_share(t[(t >= t_meas) & (t <= t_end)],
                    q[(t >= t_meas) & (t <= t_end), joint - 1], f) > 0.02:
        return None  # not one steady sine (two steps mixed, a sweep, a transient)
    step: dict[str, Any] = {"joint": joint, "f_hz": f, "t_measure": t_meas, "t_end": t_end}
    # excited axes: they oscillate at f and drift (an axis the loop holds only reacts)
    mean_v = (q[plateau][-1] - q[plateau][0]) / max(t_end - t_start, 1e-9)
    sine_v = np.median(np.abs(amps[first:last]), axis=0) * 2 * math.pi * f
    drifting = np.abs(mean_v) > 2 * sine_v
    excited = drifting & (rel > 0.3 * (rel[drifting].max() if drifting.any() else 0.0))
    if excited.any():
        step["joint"] = int(np.argmax(np.where(excited, rel, -np.inf))) + 1
    moving = [int(j) + 1 for j in np.flatnonzero(excited)]
    if len(moving) > 1:
        step.update(joints=moving, amplitudes_rad=[0.0] * len(moving),
                    drifts_rad_s=[0.0] * len(moving))
    return step


def log_schedule(t: np.ndarray, q: np.ndarray, tau: np.ndarray) -> list[dict[str, Any]]:
    """The steps found in a log, as a schedule (steps of two axes at one frequency share a
    key for the 2×2 estimate): detect once, estimate every target's FRF from it."""
    return _merge_close(detect_steps(t, q, tau))


def _merge_close(steps: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Steps of two joints at the same nominal frequency share one key for the 2×2 estimate."""
    out = sorted(steps, key=lambda s: s["f_hz"])
    for a, b in zip(out[:-1], out[1:], strict=True):
        if abs(b["f_hz"] - a["f_hz"]) < 0.005 * a["f_hz"]:
            b["f_key"] = a.get("f_key", a["f_hz"])
    return out
