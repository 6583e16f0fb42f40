"""Frequency responses: the stepped-sine elasticity experiment, FRF estimation (known schedule,
steps detected from the log alone, H1 and reference-based for sweeps), resonance finding.

Convention: an FRF point is G(jω) = Qm(jω)/T(jω), motor position over motor torque, from the
complex amplitudes x(t) = Re(X e^{jωt}) of one step. Both amplitudes are projections on the
frequency the reference was driven at, so noise and the position loop's feedback of it average
out (the indirect / joint input-output estimate, unbiased in closed loop).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from robid_link.exceptions import ConfigError, DataError
from robid_link.ident.excite.excitation import Trajectory, check_limits
from robid_link.ident.model.robot import Robot

__all__ = [
    "ElasticityOptions",
    "Frf",
    "stepped_sine_schedule",
    "step_axes",
    "excited_axes",
    "elasticity_trajectory",
    "sine_amplitudes",
    "frf_from_schedule",
    "detect_steps",
    "frf_from_log",
    "log_schedule",
    "frf_h1",
    "frf_reference",
    "spectral_peaks",
]


@dataclass(frozen=True)
class ElasticityOptions:
    """The stepped-sine experiment around a pose (radians, SI units).

    Each step: the reference drifts at ``drift_fraction`` of the joint's speed limit (so the arm
    never reverses and Coulomb friction stays a constant torque, invisible at the step's
    frequency), a sine rides on it with a velocity amplitude of drift/``drift_over_sine``;
    ``settle_periods`` (at least ``settle_s``) are ramped in (over ``ramp_s``) and discarded,
    then ``measure_periods`` (at least ``measure_s``) are measured. Steps alternate the drift
    direction and each step's travel is centred on the pose (the arm inertia of a coupled axis
    changes with it). The drift's reversal rings the arm on its spring at the antiresonance
    (the motor held by the loop): a slow ramp and a settling of several of that mode's decay
    times keep the ringing out of the measured window.
    """

    joints: tuple[int, ...] = ()  # 1-based; empty = every joint
    pairs: tuple[tuple[int, int], ...] = ()  # informational: axes fitted as coupled pairs
    pose: tuple[float, ...] | None = None  # rad; default mid-range
    f_min_hz: float = 2.0
    f_max_hz: float = 60.0
    steps: int = 24
    rate_hz: float = 2000.0
    settle_periods: float = 3.0
    settle_s: float = 1.0
    ramp_s: float = 0.5
    measure_periods: float = 6.0
    measure_s: float = 1.0  # 0.5 s left the wrist axes' D ±1.4 % (1 σ) at the example's noise
    drift_fraction: float = 0.04
    # the arm swings at most ~0.45× the drift on the example's axes at 3 (the torque's SNR,
    # hence D's scatter, grows with the sine: D5 ±1.05 % at 8, ±0.6 % at 3); where the arm
    # outruns the drift the fit notes it and models the reversing friction
    drift_over_sine: float = 3.0
    accel_fraction: float = 0.5  # of the acceleration limit, caps the sine at high frequency


@dataclass
class Frf:
    """Measured FRF points of one excited joint (or of a pair: ``g`` is then (K, 2, 2)).

    ``g`` motor position / motor torque (rad/(N·m)); ``coherence`` per point from the
    period-by-period blocks (1 = noise-free); ``snr`` |T| over its standard error; ``g_var``
    the variance E|ĝ − g|² of each point (each entry for a pair) from the noise the
    step's sine fit leaves at the neighbouring frequencies (None: unknown, the fit then
    weights by ``snr`` and ``coherence``); ``rate_hz`` the log's sampling rate.
    """

    joints: tuple[int, ...]
    f_hz: np.ndarray
    g: np.ndarray
    coherence: np.ndarray
    snr: np.ndarray
    source: str = "schedule"  # schedule | detected | h1 | reference
    notes: list[str] = field(default_factory=list)
    #: one joint's stepped sines: per point the torque amplitude |T| (N·m) and the motor's mean
    #: velocity over the step (rad/s, the drift); what an amplitude-dependent effect (Coulomb
    #: friction reversing on the arm) needs; None for a pair or an H1 estimate
    tau_amp: np.ndarray | None = None
    drift: np.ndarray | None = None
    g_var: np.ndarray | None = None
    rate_hz: float | None = None
    #: one joint's stepped sines: the motor position's harmonics per point (K, H), Q_1…Q_H
    #: in the log's time base (what a model of an amplitude-dependent effect is driven by)
    qm_harmonics: np.ndarray | None = None

    @property
    def accel(self) -> np.ndarray:
        """Motor acceleration over torque: (jω)²·G."""
        s2 = -(2 * np.pi * self.f_hz) ** 2
        return self.g * (s2 if self.g.ndim == 1 else s2[:, None, None])


# ----------------------------------------------------------------------------- experiment


def _limit(x: np.ndarray, j: int, default: float) -> float:
    v = float(x[j])
    return v if math.isfinite(v) else default


def stepped_sine_schedule(robot: Robot, opts: ElasticityOptions) -> list[dict[str, Any]]:
    """The steps of the experiment: per joint, log-spaced frequencies, each step a dict with
    ``joint`` (1-based), ``f_hz``, ``amplitude_rad``, ``drift_rad_s``, ``t_start``,
    ``t_measure`` (end of settling), ``t_end`` (end of the measured whole periods), ``t_next``."""
    if not 0 < opts.f_min_hz < opts.f_max_hz:
        raise ConfigError(f"elasticity: need 0 < f_min ({opts.f_min_hz}) < f_max "
                          f"({opts.f_max_hz})")
    if opts.f_max_hz > 0.2 * opts.rate_hz:
        raise ConfigError(f"elasticity: f_max {opts.f_max_hz:g} Hz above 20 % of the rate "
                          f"{opts.rate_hz:g} Hz: raise --rate")
    if opts.steps < 3:
        raise ConfigError(f"elasticity: {opts.steps} steps is too few (at least 3)")
    joints = opts.joints or (() if opts.pairs else tuple(range(1, robot.n + 1)))
    for j in (*joints, *(j for p in opts.pairs for j in p)):
        if not 1 <= j <= robot.n:
            raise ConfigError(f"elasticity: joint {j} not in 1..{robot.n}")
    for p in opts.pairs:
        if len(p) != 2 or p[0] == p[1]:
            raise ConfigError(f"elasticity: pair {list(p)} needs two different joints")
    freqs = np.geomspace(opts.f_min_hz, opts.f_max_hz, opts.steps)
    lim = robot.limits
    out: list[dict[str, Any]] = []
    t = 0.0
    # one axis at a time, then each pair with both axes drifting (friction never reverses on
    # either) and sines in phase, then in antiphase: two independent inputs per frequency
    groups = [((j,), (1.0,)) for j in joints]
    for p in opts.pairs:
        groups.append((tuple(p), (1.0, 1.0)))
        groups.append((tuple(p), (1.0, -1.0)))
    # every pattern runs through all frequencies in turn: the in-phase and the antiphase step
    # of one frequency back to back read as one long step from the log alone (the 2×2 FRF
    # then lost 7 of 24 frequencies: D3 of the example's pair +3.25 %)
    order = [(g, f) for g in groups for f in freqs]
    sign = 1.0
    for (axes, pattern), f in order:
        w = 2 * math.pi * f
        drifts, amps = [], []
        for j, c in zip(axes, pattern, strict=True):
            drift = opts.drift_fraction * _limit(lim.qd_max, j - 1, 2.0)
            acc = opts.accel_fraction * _limit(lim.qdd_max, j - 1, 10.0)
            drifts.append(sign * drift)
            amps.append(c * min(drift / opts.drift_over_sine, acc / w) / w)
        settle = max(opts.settle_periods / f, opts.settle_s)
        measure = math.ceil(max(opts.measure_periods, opts.measure_s * f)) / f
        ramp = min(opts.ramp_s, settle / 2)
        step: dict[str, Any] = {
            "joint": int(axes[0]), "f_hz": float(f), "amplitude_rad": float(amps[0]),
            "drift_rad_s": float(drifts[0]), "t_start": float(t),
            "t_measure": float(t + settle), "t_end": float(t + settle + measure),
            "t_next": float(t + settle + measure + ramp)}
        if len(axes) > 1:
            step.update(joints=[int(j) for j in axes], amplitudes_rad=[float(a) for a in amps],
                        drifts_rad_s=[float(d) for d in drifts])
        out.append(step)
        t = step["t_next"]
        sign = -sign
    return out


def excited_axes(steps: Sequence[dict[str, Any]]
                 ) -> tuple[list[int], list[tuple[int, int]]]:
    """The axes a schedule (or the detected steps) excites alone, and the pairs excited
    together: what ``robid elasticity`` fits when no joint is named."""
    singles: set[int] = set()
    pairs: set[tuple[int, int]] = set()
    for st in steps:
        axes = sorted({int(a[0]) for a in step_axes(st)})
        if len(axes) == 1:
            singles.add(axes[0])
        elif len(axes) == 2:
            pairs.add((axes[0], axes[1]))
    return sorted(singles), sorted(pairs)


def step_axes(step: dict[str, Any]) -> list[tuple[int, float, float]]:
    """(joint, amplitude_rad, drift_rad_s) of each axis a schedule step moves."""
    if "joints" in step:
        return list(zip(step["joints"], step["amplitudes_rad"], step["drifts_rad_s"],
                        strict=True))
    return [(step["joint"], step.get("amplitude_rad", 0.0), step.get("drift_rad_s", 0.0))]


def _smooth_ramp(x: np.ndarray) -> np.ndarray:
    """0 → 1 on [0, 1] with zero slope at both ends."""
    x = np.clip(x, 0.0, 1.0)
    return 0.5 - 0.5 * np.cos(np.pi * x)


def elasticity_trajectory(robot: Robot, opts: ElasticityOptions) -> Trajectory:
    """The stepped-sine trajectory (kind ``stepped_sine``), limits checked, with the schedule
    and the options in the header (what the FRF estimation reads back)."""
    sched = stepped_sine_schedule(robot, opts)
    lo, hi = robot.limits.q_min, robot.limits.q_max
    pose = (np.asarray(opts.pose, dtype=float) if opts.pose is not None else
            np.where(np.isfinite(lo) & np.isfinite(hi), 0.5 * (lo + hi), 0.0))
    if pose.shape != (robot.n,):
        raise ConfigError(f"elasticity: pose needs {robot.n} values, got {pose.size}")
    h = 1.0 / opts.rate_hz
    t = np.arange(0.0, sched[-1]["t_next"] + 0.5 + h / 2, h)
    q = np.tile(pose, (t.size, 1))
    offset = np.zeros(robot.n)
    for st in sched:
        k0 = int(round(st["t_start"] / h))
        k1 = int(round(st["t_next"] / h))
        tt = t[k0:k1] - st["t_start"]
        ramp = st["t_next"] - st["t_end"]
        t_end = st["t_end"] - st["t_start"]
        env = _smooth_ramp(tt / ramp) * _smooth_ramp((t_end + ramp - tt) / ramp)
        meas = (tt >= st["t_measure"] - st["t_start"]) & (tt <= t_end)
        for joint, amp, drift in step_axes(st):
            j = joint - 1
            # drift velocity v·env integrated exactly enough on the grid (cumulative trapezoid)
            vel = drift * env
            pos = np.concatenate(([0.0], np.cumsum(0.5 * (vel[1:] + vel[:-1]) * h)))
            centre = float(pos[meas].mean()) if meas.any() else 0.0
            # from where the last step left the joint to travel centred on the pose
            shift = offset[j] + (-centre - offset[j]) * _smooth_ramp(tt / ramp)
            sine = amp * env * np.sin(2 * math.pi * st["f_hz"] * tt)
            q[k0:k1, j] = pose[j] + shift + pos + sine
            offset[j] = (pos[-1] - centre) if pos.size else offset[j]
            q[k1:, j] = pose[j] + offset[j]
    qd = np.gradient(q, h, axis=0)
    check_limits(robot, q, qd, np.gradient(qd, h, axis=0), where="elasticity trajectory")
    header = {"schedule": sched, "pose": pose.tolist(),
              "elasticity": {"joints": list(opts.joints), "pairs": [list(p) for p in opts.pairs],
                             "f_min_hz": opts.f_min_hz, "f_max_hz": opts.f_max_hz,
                             "steps": opts.steps},
              "limits_checked": True}
    return Trajectory(t, q, opts.rate_hz, "stepped_sine", robot.name, header)


# ----------------------------------------------------------------------------- estimation


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


class _Point(NamedTuple):
    """One step: amplitudes Y, U (m,), coherence and snr of the first channel, its drift,
    and the residuals' amplitudes at the neighbouring frequencies (bins, m) for the noise."""

    y: np.ndarray
    u: np.ndarray
    coherence: float
    snr: float
    drift: float
    noise_y: np.ndarray
    noise_u: np.ndarray
    harmonics: np.ndarray


def _point(t: np.ndarray, qm: np.ndarray, tau: np.ndarray, f: float, periods: float) -> _Point:
    """One step window (blocks of whole periods); drift the first channel's mean velocity."""
    blocks = int(max(2, min(10, periods // 2)))
    y, yb = sine_amplitudes(t, qm, f, blocks)
    u, ub = sine_amplitudes(t, tau, f, blocks)
    # coherence of the first channel pair from the blocks (Welch-like, 1 = noise-free)
    sy, su = yb[:, 0], ub[:, 0]
    coh = float(abs(np.sum(sy * su.conj())) ** 2
                / max(np.sum(abs(sy) ** 2) * np.sum(abs(su) ** 2), 1e-300))
    spread = float(np.std(su) / math.sqrt(blocks))
    snr = float(abs(u[0]) / max(spread, 1e-300))
    tc = t - t.mean()
    drift = float(tc @ (qm[:, 0] - qm[:, 0].mean()) / max(float(tc @ tc), 1e-300))
    return _Point(y, u, coh, snr, drift, _noise_bins(t, qm, f), _noise_bins(t, tau, f),
                  _harmonics(t, qm[:, 0], f))


def _harmonics(t: np.ndarray, x: np.ndarray, f: float, most: int = 9) -> np.ndarray:
    """Complex amplitudes of x's first ``most`` harmonics of f (on a line: the drift)."""
    tc = t - t.mean()
    w = 2 * math.pi * f * t
    cols = [np.ones(t.size), tc]
    for h in range(1, most + 1):
        cols += [np.cos(h * w), np.sin(h * w)]
    coef = np.linalg.lstsq(np.column_stack(cols), x, rcond=None)[0][2:]
    return coef[0::2] - 1j * coef[1::2]


def _noise_bins(t: np.ndarray, x: np.ndarray, f: float, most: int = 8) -> np.ndarray:
    """The residual of x's sine fit at f (on a line: the drift), as amplitudes at the
    neighbouring frequencies f ± k/T of the window T (k = 1…, within f/2…3f/2): orthogonal to
    the sine over whole periods, each carries the noise an amplitude at f carries (the noise's
    spectrum is smooth there). Returns (bins, m) complex amplitudes, scaled like X."""
    x = x.reshape(len(t), -1)
    tc = t - t.mean()
    w = 2 * math.pi * f * t
    a = np.column_stack((np.ones(t.size), tc, np.cos(w), np.sin(w)))
    res = x - a @ np.linalg.lstsq(a, x, rcond=None)[0]
    span = float(t[-1] - t[0]) + float(np.median(np.diff(t)))
    k = max(2, min(most, int(0.5 * f * span)))
    near = f + np.r_[-k:0, 1:k + 1] / span
    near = near[near > 0.25 * f]
    basis = np.exp(-2j * math.pi * np.outer(near, t))
    return 2.0 / t.size * (basis @ res)


def frf_from_schedule(t: np.ndarray, q: np.ndarray, tau: np.ndarray,
                      schedule: Sequence[dict[str, Any]], joints: Sequence[int],
                      tau_model: np.ndarray | None = None) -> Frf:
    """FRF points of ``joints`` (1-based; one joint → SISO, two → the 2×2 matrix) from the
    steps of a known schedule. ``tau_model``: the identified rigid-body + friction torque to
    subtract (same shape as ``tau``). Log times are those of the trajectory."""
    cols = [j - 1 for j in joints]
    if tau_model is not None:
        tau = tau - tau_model
    by_f: dict[float, list[_Point]] = {}
    for st in schedule:
        if "joint" not in st or "f_hz" not in st:
            raise DataError("schedule step without joint/f_hz: not a stepped-sine schedule")
        axes = {a[0] for a in step_axes(st)}
        if not (axes == set(joints) if len(joints) == 1 else axes <= set(joints)):
            continue  # a single axis from its own steps, a pair from its own and its axes'
        a, b = np.searchsorted(t, [st["t_measure"], st["t_end"]])
        if b - a < 8 or b > len(t) - 1:
            raise DataError(f"step at {st['f_hz']:.4g} Hz of joint {st['joint']} "
                            f"({st['t_measure']:.4g}–{st['t_end']:.4g} s) is not in the log")
        f = float(st["f_hz"])
        periods = (st["t_end"] - st["t_measure"]) * f
        by_f.setdefault(round(float(st.get("f_key", f)), 9), []).append(
            _point(t[a:b], q[a:b][:, cols], tau[a:b][:, cols], f, periods))
    frf = _assemble(tuple(joints), by_f, "schedule")
    frf.rate_hz = 1.0 / float(np.median(np.diff(t)))
    return frf


def _siso(pts: Sequence[_Point]) -> tuple[complex, float]:
    """G and its variance from one or more steps at one frequency: Σ y ū / Σ |u|²; the
    noise of y − G u (correlated in closed loop) read at the neighbouring bins."""
    y = np.array([p.y[0] for p in pts])
    u = np.array([p.u[0] for p in pts])
    uu = float(np.sum(abs(u) ** 2))
    g = complex(np.sum(y * u.conj()) / uu)
    e = [float(np.mean(abs(p.noise_y[:, 0] - g * p.noise_u[:, 0]) ** 2)) for p in pts]
    return g, float(np.sum(abs(u) ** 2 * np.array(e))) / uu ** 2


def _mimo(pts: Sequence[_Point]) -> tuple[np.ndarray, np.ndarray]:
    """G = Y U⁺ from the steps at one frequency (columns: steps) and the variance of each
    entry: δG = E U⁺, E the per-step noise of y − G u."""
    ym = np.column_stack([p.y for p in pts])
    um = np.column_stack([p.u for p in pts])
    pinv = np.linalg.pinv(um)
    g = ym @ pinv
    e = np.column_stack([np.mean(abs(p.noise_y - p.noise_u @ g.T) ** 2, axis=0)
                         for p in pts])  # (outputs, steps)
    return g, e @ abs(pinv) ** 2


def _assemble(joints: tuple[int, ...], by_f: dict[float, list[_Point]], source: str) -> Frf:
    fs, gs, gvar, cohs, snrs, amps, drifts, harms = [], [], [], [], [], [], [], []
    for f in sorted(by_f):
        pts = by_f[f]
        if len(joints) == 1:
            g, var = _siso(pts)
            amps.append(float(np.mean([abs(p.u[0]) for p in pts])))
            drifts.append(float(min(abs(p.drift) for p in pts)))
            harms.append(max(pts, key=lambda p: abs(p.u[0])).harmonics)
        else:
            if len(pts) < len(joints):
                continue  # a 2×2 FRF needs one independent input per axis
            g, var = _mimo(pts)
        fs.append(f)
        gs.append(g)
        gvar.append(var)
        cohs.append(min(p.coherence for p in pts))
        snrs.append(min(p.snr for p in pts))
    if not fs and len(joints) > 1 and by_f:
        raise DataError(f"joints {joints[0]},{joints[1]}: a 2×2 FRF needs two independent "
                        "inputs per frequency (steps of each axis, or the pair excited "
                        f"together: robid excite --pair {joints[0]},{joints[1]})")
    if not fs:
        raise DataError(f"no steps of joint(s) {', '.join(map(str, joints))} in the log")
    single = len(joints) == 1
    return Frf(joints, np.array(fs), np.array(gs), np.array(cohs), np.array(snrs), source,
               tau_amp=np.array(amps) if single else None,
               drift=np.array(drifts) if single else None, g_var=np.array(gvar),
               qm_harmonics=np.array(harms) if single else None)


# ----------------------------------------------------------------------------- from the log


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


def _period_blocks(t: np.ndarray, x: np.ndarray, f: float) -> tuple[np.ndarray, np.ndarray]:
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


def _unexplained(t: np.ndarray, x: np.ndarray, f: float) -> float:
    """Share of x's variance (a quadratic trend removed) a sine at f leaves unexplained."""
    tc = t - t.mean()
    w = 2 * math.pi * f * t
    trend = np.column_stack((np.ones(t.size), tc, tc * tc))
    x = x - trend @ np.linalg.lstsq(trend, x, rcond=None)[0]
    a = np.column_stack((trend, np.cos(w), np.sin(w)))
    res = x - a @ np.linalg.lstsq(a, x, rcond=None)[0]
    return float(np.sum(res * res) / max(np.sum(x * x), 1e-300))


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
    edges, amps = _period_blocks(ts, q[ext], f0)
    in_run = (ts[edges[:-1]] >= t0) & (ts[edges[1:] - 1] <= t1)
    if in_run.sum() < 3:
        return None
    rel = np.median(np.abs(amps[in_run]), axis=0) * (2 * math.pi * f0) ** 2 / acc_scale
    joint = int(np.argmax(rel)) + 1
    x = amps[:, joint - 1]
    for tol in (0.03, 0.06, 0.1):  # looser where a transient beats with the sine (the arm
        first, last = _plateau(np.abs(x), np.abs(x[in_run]), tol)  # ringing at the
        # antiresonance, lightly damped)
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
    f = _refine(t[plateau], q[plateau, joint - 1:joint], f, span_bins=0.25)
    periods = math.floor(0.6 * (t_end - t_start) * f)
    t_meas = t_end - periods / f
    if _unexplained(t[(t >= t_meas) & (t <= t_end)],
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


def _refine(t: np.ndarray, x: np.ndarray, f0: float, span_bins: float = 1.5) -> float:
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


def log_schedule(t: np.ndarray, q: np.ndarray, tau: np.ndarray) -> list[dict[str, Any]]:
    """The steps found in a log, as a schedule (steps of two axes at one frequency share a
    key for the 2×2 estimate): detect once, estimate every target's FRF from it."""
    return _merge_close(detect_steps(t, q, tau))


def frf_from_log(t: np.ndarray, q: np.ndarray, tau: np.ndarray, joints: Sequence[int],
                 tau_model: np.ndarray | None = None,
                 steps: Sequence[dict[str, Any]] | None = None) -> Frf:
    """As :func:`frf_from_schedule`, with the steps detected in the log alone (every axis
    looked at, so that a step of another axis is not taken for one of ``joints``), or the
    ``steps`` :func:`log_schedule` found before."""
    if tau_model is not None:
        tau = tau - tau_model
    frf = frf_from_schedule(t, q, tau, steps if steps is not None else log_schedule(t, q, tau),
                            joints)
    frf.source = "detected"
    return frf


def _merge_close(steps: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Steps of two joints at the same nominal frequency share one key for the 2×2 estimate."""
    out = sorted(steps, key=lambda s: s["f_hz"])
    for a, b in zip(out[:-1], out[1:], strict=True):
        if abs(b["f_hz"] - a["f_hz"]) < 0.005 * a["f_hz"]:
            b["f_key"] = a.get("f_key", a["f_hz"])
    return out


# ----------------------------------------------------------------------------- broadband


def frf_h1(u: np.ndarray, y: np.ndarray, fs: float, nperseg: int = 4096
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """H1 = S_yu/S_uu with the coherence, for sweeps and multisines (open loop, or closed loop
    when the noise on y is small): (f, H, γ²)."""
    import scipy.signal as sig

    f, syu = sig.csd(u, y, fs=fs, nperseg=nperseg)
    _, suu = sig.welch(u, fs=fs, nperseg=nperseg)
    _, syy = sig.welch(y, fs=fs, nperseg=nperseg)
    return f, syu / suu, np.abs(syu) ** 2 / np.maximum(suu * syy, 1e-300)


def frf_reference(r: np.ndarray, u: np.ndarray, y: np.ndarray, fs: float, nperseg: int = 4096
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """G = S_yr/S_ur with the excitation r as instrument: unbiased under the position loop's
    feedback (noise is uncorrelated with r). Returns (f, G, γ²_ur)."""
    import scipy.signal as sig

    f, syr = sig.csd(r, y, fs=fs, nperseg=nperseg)
    _, sur = sig.csd(r, u, fs=fs, nperseg=nperseg)
    _, srr = sig.welch(r, fs=fs, nperseg=nperseg)
    _, suu = sig.welch(u, fs=fs, nperseg=nperseg)
    return f, syr / sur, np.abs(sur) ** 2 / np.maximum(srr * suu, 1e-300)


# ----------------------------------------------------------------------------- resonances


def spectral_peaks(f: np.ndarray, spec: np.ndarray, band: np.ndarray, *,
                   min_prominence: float = 20.0) -> tuple[float, float] | None:
    """The highest peak of a power spectrum inside ``band`` (a mask), when it stands
    ``min_prominence``× above the median of its ±50 % neighbourhood: (f_peak, prominence).
    The resonance finder of the diagnosis (a residual's spectrum)."""
    idx = np.flatnonzero(band)
    if idx.size < 20:
        return None
    k = idx[int(np.argmax(spec[idx]))]
    near = (f >= f[k] / 1.5) & (f <= f[k] * 1.5) & (np.abs(np.arange(f.size) - k) > 2)
    if k in (idx[0], idx[-1]) or not near.any():
        return None
    prominence = float(spec[k] / np.median(spec[near]))
    return (float(f[k]), prominence) if prominence > min_prominence else None
