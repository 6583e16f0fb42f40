"""The stepped-sine elasticity experiment: options, the schedule of steps (one axis, or a pair in
phase then in antiphase), the trajectory with its limits checked."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from robid_link.exceptions import ConfigError
from robid_link.ident.excite.excitation import Trajectory, check_limits
from robid_link.ident.model.robot import Robot

__all__ = ["ElasticityOptions", "stepped_sine_schedule", "step_axes", "excited_axes",
           "elasticity_trajectory"]


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
    groups: list[tuple[tuple[int, ...], tuple[float, ...]]] = [((j,), (1.0,)) for j in joints]
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
