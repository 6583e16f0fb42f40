"""The verification path and its figures: a fixed, fast joint-space path run before and after
parameters are uploaded, and what it shows of the controller's tracking — joint errors, the
tool's position error through the robot's forward kinematics, and the tool's residual
oscillation after the final stop."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import pinocchio as pin

from robid_link.exceptions import DataError
from robid_link.ident.excite.excitation import Trajectory, check_limits
from robid_link.ident.model.robot import Robot

__all__ = ["verify_trajectory", "Tracking", "tracking", "tool_positions"]

#: the path: moves between these fractions of each joint's range, then a hold at rest
_WAYPOINTS = (0.0, 0.55, -0.45, 0.35, -0.25, 0.0)
_SETTLE_S = 1.0
#: the tool error's trace over time keeps at most this many points (each the peak of its bin)
TRACE_POINTS = 600


def _quintic(s: np.ndarray) -> np.ndarray:
    return s**3 * (10 - 15 * s + 6 * s * s)


def verify_trajectory(robot: Robot, *, speed: float = 0.6, rate_hz: float = 250.0,
                      range_fraction: float = 0.5) -> Trajectory:
    """A fixed, fast path: every joint moves through the same waypoints (fractions of half
    its range around the middle), each move a quintic timed at ``speed`` of the joint's
    velocity and acceleration limits, then a hold of ``_SETTLE_S`` s to show the tool's
    residual oscillation. Checked against the robot's limits; the same for every run."""
    lim = robot.limits
    lo = np.where(np.isfinite(lim.q_min), lim.q_min, -math.pi)
    hi = np.where(np.isfinite(lim.q_max), lim.q_max, math.pi)
    mid, half = (lo + hi) / 2, range_fraction * (hi - lo) / 2
    qd_max = np.where(np.isfinite(lim.qd_max), lim.qd_max, 1.0) * speed
    qdd_max = np.where(np.isfinite(lim.qdd_max), lim.qdd_max, 5.0) * speed
    points = [mid + f * half for f in _WAYPOINTS]
    segments = []
    for a, b in zip(points[:-1], points[1:], strict=True):
        d = np.abs(b - a)
        # quintic peaks: velocity 1.875·d/T, acceleration 5.774·d/T²
        dur = float(max(np.max(1.875 * d / qd_max), np.max(np.sqrt(5.774 * d / qdd_max)),
                        0.2))
        s = _quintic(np.arange(0.0, dur, 1.0 / rate_hz) / dur)
        segments.append(a + s[:, None] * (b - a))
    hold = np.repeat(points[-1][None], int(_SETTLE_S * rate_hz) + 1, axis=0)
    q = np.vstack([*segments, hold])
    t = np.arange(q.shape[0]) / rate_hz
    traj = Trajectory(t, q, rate_hz, "custom", robot.name,
                      {"experiment": "verify", "settle_s": _SETTLE_S, "speed": speed})
    qd, qdd = traj.derivatives()
    check_limits(robot, q, qd, qdd, where="verification path")
    return traj


def tool_positions(robot: Robot, q: np.ndarray) -> np.ndarray:
    """Position of the last joint's frame (the flange) in metres, per sample."""
    model, data = robot.model, robot.model.createData()
    fid = model.njoints - 1
    out = np.empty((q.shape[0], 3))
    for k in range(q.shape[0]):
        pin.forwardKinematics(model, data, robot.pin_q(q[k]))
        out[k] = data.oMi[fid].translation
    return out


@dataclass(frozen=True)
class Tracking:
    """How well the controller followed the verification path."""

    joint_rms: list[float]       # rad (m for prismatic)
    joint_max: list[float]
    tool_rms_mm: float
    tool_max_mm: float
    residual_mm: float           # peak tool deviation from its final rest after the stop
    #: the tool's position error over the path: bin start times (s from the path's start)
    #: and each bin's peak (mm), at most TRACE_POINTS of them
    trace_t: tuple[float, ...] = ()
    trace_mm: tuple[float, ...] = ()

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "joint_rms": self.joint_rms, "joint_max": self.joint_max,
            "tool_rms_mm": self.tool_rms_mm, "tool_max_mm": self.tool_max_mm,
            "residual_mm": self.residual_mm}
        if self.trace_t:
            out["trace"] = {"t": list(self.trace_t), "mm": list(self.trace_mm)}
        return out


def _peak_trace(t: np.ndarray, e: np.ndarray) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """``e`` over ``t`` in at most TRACE_POINTS bins, each its peak (a plain stride could
    step over the largest error)."""
    edges = np.linspace(t[0], t[-1], min(TRACE_POINTS, t.size) + 1)
    idx = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, edges.size - 2)
    peak = np.full(edges.size - 1, np.nan)
    np.fmax.at(peak, idx, e)
    keep = np.isfinite(peak)
    return (tuple(round(float(x), 4) for x in edges[:-1][keep]),
            tuple(round(float(x), 5) for x in peak[keep]))


def tracking(robot: Robot, ref: Trajectory, t_log: np.ndarray, q_log: np.ndarray,
             where: str = "verification log") -> Tracking:
    """Errors of a log against the path it was asked to follow (the reference is
    interpolated onto the log's time stamps; the log's time starts with the path's).
    ``where`` names the log in errors."""
    if q_log.ndim != 2 or q_log.shape[1] != robot.n or q_log.shape[0] < 10:
        raise DataError(f"{where}: expected ≥ 10 samples of {robot.n} joints, got shape "
                        f"{q_log.shape}")
    t = t_log - t_log[0]
    inside = t <= ref.t[-1]
    q_ref = np.column_stack([np.interp(t[inside], ref.t, ref.q[:, j]) for j in range(robot.n)])
    err = q_log[inside] - q_ref
    step = max(1, int(inside.sum()) // 4000)  # forward kinematics on ≤ 4000 samples
    tool_ref = tool_positions(robot, q_ref[::step])
    tool = tool_positions(robot, q_log[inside][::step])
    e_tool = 1000.0 * np.linalg.norm(tool - tool_ref, axis=1)
    settle = float(ref.header.get("settle_s", _SETTLE_S))
    after = (t[inside] >= ref.t[-1] - settle + 0.05)[::step]
    final = tool_ref[-1]
    residual = 1000.0 * np.linalg.norm(tool[after] - final, axis=1) if after.any() else [0.0]
    trace_t, trace_mm = _peak_trace(t[inside][::step], e_tool)
    return Tracking([float(x) for x in np.sqrt(np.mean(err**2, axis=0))],
                    [float(x) for x in np.abs(err).max(axis=0)],
                    float(np.sqrt(np.mean(e_tool**2))), float(e_tool.max()),
                    float(np.max(residual)), trace_t, trace_mm)
