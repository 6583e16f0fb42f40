"""Motion programs: an experiment's trajectory (``experiments.py`` makes it) checked against the
robot's limits before it may leave the worker, slowed down on request, and packaged as the
neutral trajectory file (drivers render it for their controller: ``drivers/rapid.py``)."""

from __future__ import annotations

import io
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import yaml

from robid_link.exceptions import ConfigError, UnsafeProgramError
from robid_link.ident.excite import excitation as ex
from robid_link.ident.model.robot import Robot
from robid_link.jobs import MotionProgram, check_name

__all__ = ["check_program", "reduced_speed", "make_program", "trajectory_files",
           "program_trajectory", "with_logged_torques"]

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


def with_logged_torques(robot: Robot, traj: ex.Trajectory, joints: Sequence[int], exp_id: str
                        ) -> ex.Trajectory:
    """The trajectory whose header tells the controller to log the torques of ``joints``
    (from 1) only — its signal budget; positions of every axis are logged regardless (the
    regressor of any joint needs q, q̇, q̈ of all)."""
    js = sorted({int(j) for j in joints})
    if not js or len(js) != len(joints) or js[0] < 1 or js[-1] > robot.n:
        raise ConfigError(f"experiment {exp_id}: log_torques {list(joints)}: expected distinct "
                          f"joint numbers 1..{robot.n}")
    return ex.Trajectory(traj.t, traj.q, traj.rate_hz, traj.kind, traj.robot,
                         {**traj.header, "log_torques": js})


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
