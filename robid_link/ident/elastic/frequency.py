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
from typing import Any

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
    period-by-period blocks (1 = noise-free); ``snr`` |T| over its standard error.
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
                          f"{opts.rate_hz:g} Hz (raise the rate)")
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


def _point(t: np.ndarray, qm: np.ndarray, tau: np.ndarray, f: float, periods: float
           ) -> tuple[np.ndarray, np.ndarray, float, float, float]:
    """(Y (m,), U (m,), coherence, snr, drift) of one step window (blocks of whole periods);
    drift the first channel's mean velocity."""
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
    return y, u, coh, snr, drift


def frf_from_schedule(t: np.ndarray, q: np.ndarray, tau: np.ndarray,
                      schedule: Sequence[dict[str, Any]], joints: Sequence[int],
                      tau_model: np.ndarray | None = None) -> Frf:
    """FRF points of ``joints`` (1-based; one joint → SISO, two → the 2×2 matrix) from the
    steps of a known schedule. ``tau_model``: the identified rigid-body + friction torque to
    subtract (same shape as ``tau``). Log times are those of the trajectory."""
    cols = [j - 1 for j in joints]
    if tau_model is not None:
        tau = tau - tau_model
    by_f: dict[float, list[tuple[np.ndarray, np.ndarray, float, float, float]]] = {}
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
    return _assemble(tuple(joints), by_f, "schedule")


def _assemble(joints: tuple[int, ...], by_f: dict[float, list[Any]], source: str) -> Frf:
    fs, gs, cohs, snrs, amps, drifts = [], [], [], [], [], []
    for f in sorted(by_f):
        pts = by_f[f]
        if len(joints) == 1:
            y = np.array([p[0][0] for p in pts])
            u = np.array([p[1][0] for p in pts])
            g = np.sum(y * u.conj()) / np.sum(abs(u) ** 2)
            amps.append(float(np.mean(abs(u))))
            drifts.append(float(min(abs(p[4]) for p in pts)))
        else:
            if len(pts) < len(joints):
                continue  # a 2×2 FRF needs one independent input per axis
            ym = np.column_stack([p[0] for p in pts])
            um = np.column_stack([p[1] for p in pts])
            g = ym @ np.linalg.pinv(um)
        fs.append(f)
        gs.append(g)
        cohs.append(min(p[2] for p in pts))
        snrs.append(min(p[3] for p in pts))
    if not fs and len(joints) > 1 and by_f:
        raise DataError(f"joints {joints[0]},{joints[1]}: a 2×2 FRF needs two independent "
                        "inputs per frequency (steps of each axis, or the pair excited "
                        f"together: robid excite --pair {joints[0]},{joints[1]})")
    if not fs:
        raise DataError(f"no steps of joint(s) {', '.join(map(str, joints))} in the log")
    single = len(joints) == 1
    return Frf(joints, np.array(fs), np.array(gs), np.array(cohs), np.array(snrs), source,
               tau_amp=np.array(amps) if single else None,
               drift=np.array(drifts) if single else None)


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
    r = max(1, int(fs // 500))
    qd = q[::r] if r == 1 else _decimate(q, r)
    spans: list[tuple[float, float, float]] = []
    for win in windows_s:
        for t0, t1, f in _runs(t[::r][:len(qd)], qd, fs / r, win, rel_tol):
            if f * win < 4 or any(min(t1, b) - max(t0, a) > 0.3 * (t1 - t0)
                                  for a, b, _ in spans):
                continue
            spans.append((t0, t1, f))
    acc = np.std(np.diff(q, 2, axis=0), axis=0) * fs * fs
    acc_scale = np.maximum(acc, 0.5 * acc.max() + 1e-300)  # an axis that never moves: noise
    steps = [st for t0, t1, f0 in sorted(spans)
             if (st := _step_in(t, q, t0, t1, f0, acc_scale)) is not None]
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
    (the drift and its ramps); returns (block start indices, amplitudes (blocks, columns))."""
    per = 1.0 / f
    nblk = int((t[-1] - t[0]) // per)
    edges = np.searchsorted(t, t[0] + per * np.arange(nblk + 1))
    amps = np.array([sine_amplitudes(t[a:b], x[a:b], f, degree=2)[0]
                     for a, b in zip(edges[:-1], edges[1:], strict=True)])
    return edges, amps.reshape(nblk, -1)


def _unexplained(t: np.ndarray, x: np.ndarray, f: float) -> float:
    """Share of x's variance (a quadratic trend removed) a sine at f leaves unexplained."""
    tc = t - t.mean()
    w = 2 * math.pi * f * t
    trend = np.column_stack((np.ones(t.size), tc, tc * tc))
    x = x - trend @ np.linalg.lstsq(trend, x, rcond=None)[0]
    a = np.column_stack((trend, np.cos(w), np.sin(w)))
    res = x - a @ np.linalg.lstsq(a, x, rcond=None)[0]
    return float(np.sum(res * res) / max(np.sum(x * x), 1e-300))


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
    level = float(np.median(np.abs(x[in_run])))
    on = np.abs(np.abs(x) / max(level, 1e-300) - 1.0) < 0.03
    best, run = (0, 0), 0
    for i, ok in enumerate(on):  # the longest run of periods on the plateau
        run = run + 1 if ok else 0
        if run > best[1] - best[0]:
            best = (i - run + 1, i + 1)
    first, last = best
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
    of the window (side lobes), then golden section around the best."""
    from scipy.optimize import minimize_scalar

    tc = t - t.mean()
    x = x.reshape(len(t), -1)
    x = x / np.maximum(x.std(axis=0), 1e-300)

    def neg(f: float) -> float:
        w = 2 * math.pi * f * t
        a = np.column_stack((np.ones(t.size), tc, tc * tc, np.cos(w), np.sin(w)))
        res = x - a @ np.linalg.lstsq(a, x, rcond=None)[0]
        return float(np.sum(res * res))

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
