"""Motion programs: each experiment's trajectory generated from the excitation design, checked
against the robot's limits before it may leave the daemon, packaged as the neutral trajectory
file (drivers render it for their controller: RAPID in ``drivers/rapid.py``)."""

from __future__ import annotations

import io
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from robid_link.exceptions import ConfigError, UnsafeProgramError
from robid_link.ident import excitation as ex
from robid_link.ident.robot import Robot
from robid_link.link.driver import MotionProgram, check_name

__all__ = ["EXPERIMENT_KINDS", "experiment_trajectory", "check_program", "reduced_speed",
           "make_program", "trajectory_files",
           "program_trajectory"]

EXPERIMENT_KINDS = ("rigid_body", "friction", "custom")

_DEFAULTS: dict[str, dict[str, Any]] = {
    "rigid_body": {"duration_s": 40.0, "harmonics": 8, "base_hz": 0.1, "rate_hz": 250.0,
                   "evaluations": 600, "restarts": 1, "seed": 0},
    "friction": {"speeds": [0.05, 0.1, 0.2, 0.4], "joints": None, "rate_hz": 250.0},
    "custom": {"trajectory": None},
}


def experiment_options(kind: str, opts: Mapping[str, Any], where: str) -> dict[str, Any]:
    """The experiment's options over its defaults; unknown keys name their path."""
    if kind not in _DEFAULTS:
        raise ConfigError(f"{where}.kind: expected one of {', '.join(EXPERIMENT_KINDS)}, "
                          f"got {kind!r}")
    bad = set(opts) - set(_DEFAULTS[kind])
    if bad:
        raise ConfigError(f"{where}.{sorted(bad)[0]}: unknown option for a {kind} experiment")
    out = {**_DEFAULTS[kind], **opts}
    if kind == "custom" and not out["trajectory"]:
        raise ConfigError(f"{where}.trajectory: missing (a custom experiment needs a file)")
    for key in ("duration_s", "base_hz", "rate_hz"):
        if key in out:
            v = out[key]
            if isinstance(v, bool) or not isinstance(v, int | float) or v <= 0:
                raise ConfigError(f"{where}.{key}: expected a positive number, got {v!r}")
    if kind == "friction":
        sp = out["speeds"]
        if (not isinstance(sp, list) or not sp
                or not all(isinstance(x, int | float) and 0 < x <= 1 for x in sp)):
            raise ConfigError(f"{where}.speeds: expected fractions of each joint's speed "
                              "limit in (0, 1]")
    return out


def experiment_trajectory(robot: Robot, kind: str, opts: Mapping[str, Any],
                          base_dir: Path | None = None) -> ex.Trajectory:
    """Generate the trajectory of one experiment (numerical work: run it off the event loop)."""
    if kind == "rigid_body":
        four, cond = ex.optimize_fourier(robot, harmonics=int(opts["harmonics"]),
                                         base_hz=float(opts["base_hz"]), seed=int(opts["seed"]),
                                         evaluations=int(opts["evaluations"]),
                                         restarts=int(opts["restarts"]))
        rate = float(opts["rate_hz"])
        periods = max(1, round(float(opts["duration_s"]) * four.base_hz))
        t = np.arange(0.0, periods / four.base_hz, 1.0 / rate)
        q = four.evaluate(t)[0]
        return ex.Trajectory(t, q, rate, "fourier", robot.name, ex.fourier_header(four, cond))
    if kind == "friction":
        rate = float(opts["rate_hz"])
        joints = opts["joints"] or list(range(1, robot.n + 1))
        parts = []
        for j in joints:
            if not isinstance(j, int) or not 1 <= j <= robot.n:
                raise ConfigError(f"joints: {j!r} is not a joint of {robot.name} (1..{robot.n})")
            cap = robot.limits.qd_max[j - 1]
            cap = cap if np.isfinite(cap) else 1.0
            parts.append(ex.constant_velocity_sweeps(robot, j - 1,
                                                     [f * cap for f in opts["speeds"]], rate))
        q = _joined(robot, parts, rate)
        t = np.arange(q.shape[0]) / rate
        return ex.Trajectory(t, q, rate, "sweep", robot.name,
                             {"joints": joints, "speeds": list(opts["speeds"])})
    path = Path(opts["trajectory"])
    if base_dir is not None and not path.is_absolute():
        path = base_dir / path
    traj = ex.read_trajectory(path)
    if traj.q.shape[1] != robot.n:
        raise ConfigError(f"{path}: {traj.q.shape[1]} joints, the robot has {robot.n}")
    return ex.Trajectory(traj.t - traj.t[0], traj.q, traj.rate_hz, "custom", robot.name,
                         {**traj.header, "source": str(path)})


def _joined(robot: Robot, parts: list[np.ndarray], rate: float) -> np.ndarray:
    """Concatenate per-joint sweeps with transfers between their poses that start and end at
    rest with zero acceleration (quintic smoothstep, at least 2 s, at most half of each joint's
    velocity and acceleration limits: peaks 1.875·D/T and 5.77·D/T²)."""
    qd_cap = np.where(np.isfinite(robot.limits.qd_max), robot.limits.qd_max, 1.0)
    qdd_cap = np.where(np.isfinite(robot.limits.qdd_max), robot.limits.qdd_max, 2.0)
    out = [parts[0]]
    for nxt in parts[1:]:
        a, b = out[-1][-1], nxt[0]
        dist = np.abs(b - a)
        duration = max(2.0, float(np.max(1.875 * dist / (0.5 * qd_cap))),
                       float(np.sqrt(np.max(5.774 * dist / (0.5 * qdd_cap)))))
        steps = max(2, int(rate * duration))
        x = np.linspace(0.0, 1.0, steps)[:, None]
        s = x**3 * (10.0 - 15.0 * x + 6.0 * x**2)
        out.append(a + s * (b - a))
        out.append(nxt)
    return np.concatenate(out)


def program_trajectory(traj: ex.Trajectory) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """q, q̇, q̈ of a program at its own rate (analytic for Fourier runs)."""
    if traj.kind == "fourier" and "base_hz" in traj.header:
        _, q, qd, qdd = ex.trajectory_states(traj, traj.rate_hz)
        return q, qd, qdd
    qd, qdd = traj.derivatives()
    return traj.q, qd, qdd


def check_program(robot: Robot, traj: ex.Trajectory, exp_id: str) -> None:
    """Motion safety: position, velocity, acceleration and (with an a-priori model) torque
    limits. Raises UnsafeProgramError naming the experiment, joint and quantity."""
    if traj.q.ndim != 2 or traj.q.shape[1] != robot.n:
        raise UnsafeProgramError(f"experiment {exp_id}: program has {traj.q.shape[-1]} joints, the "
                          f"robot has {robot.n}")
    if not np.all(np.isfinite(traj.q)):
        raise UnsafeProgramError(f"experiment {exp_id}: program holds non-finite positions")
    q, qd, qdd = program_trajectory(traj)
    try:
        ex.check_limits(robot, q, qd, qdd, ex.nominal_torque(robot, q, qd, qdd),
                        f"experiment {exp_id}")
    except ConfigError as err:
        raise UnsafeProgramError(f"unsafe program refused: {err}") from err


def reduced_speed(traj: ex.Trajectory, k: float) -> ex.Trajectory:
    """The same path at ``k`` of its speed (time stretched by 1/k): q̇·k, q̈·k²."""
    t = np.arange(0.0, traj.t[-1] / k + 0.5 / traj.rate_hz, 1.0 / traj.rate_hz)
    h = dict(traj.header)
    if traj.kind == "fourier":
        four = ex.FourierTrajectory(float(h["base_hz"]) * k, np.asarray(h["q0"]),
                                    np.asarray(h["a"]) * k, np.asarray(h["b"]) * k)
        h.update(base_hz=four.base_hz, a=four.a.tolist(), b=four.b.tolist())
        q = four.evaluate(t)[0]
    else:
        from scipy.interpolate import CubicSpline

        q = CubicSpline(traj.t, traj.q, axis=0)(np.minimum(t * k, traj.t[-1]))
    h["reduced_speed"] = k
    return ex.Trajectory(t, q, traj.rate_hz, traj.kind, traj.robot, h)


# ----------------------------------------------------------------------------- rendering


def trajectory_files(traj: ex.Trajectory, joint_types: Sequence[str] | None = None
                     ) -> dict[str, bytes]:
    """The neutral trajectory file (CSV t,q1..qn + YAML header) as bytes; the header names
    each joint's type so a driver can convert units without the robot file."""
    n = traj.q.shape[1]
    buf = io.StringIO()
    np.savetxt(buf, np.column_stack((traj.t, traj.q)), delimiter=",", fmt="%.10g",
               header=",".join(["t"] + [f"q{j}" for j in range(1, n + 1)]), comments="")
    meta = {"robot": traj.robot, "rate_hz": traj.rate_hz, "kind": traj.kind,
            "samples": int(traj.t.size), **traj.header}
    if joint_types is not None:
        meta["joint_types"] = list(joint_types)
    return {"traj.csv": buf.getvalue().encode(),
            "traj.yaml": yaml.safe_dump(meta, sort_keys=False).encode()}


def make_program(robot: Robot, traj: ex.Trajectory, exp_id: str,
                 meta: Mapping[str, Any] | None = None) -> MotionProgram:
    """Check the trajectory and package it; nothing unchecked becomes a program."""
    check_name(exp_id, "experiment id")
    check_program(robot, traj, exp_id)
    files = trajectory_files(traj, robot.joint_types)
    return MotionProgram(exp_id, files, float(traj.t[-1] - traj.t[0]), dict(meta or {}))
