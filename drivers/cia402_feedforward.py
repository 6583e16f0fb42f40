"""The CANopen driver's own feedforward: an uploaded parameter set turned into the torque offset
(0x60B2, per mille of rated torque) of every streamed setpoint, and kept across restarts.

The daemon is the motion master, so the "controller" that loads the set is this driver: the
rigid-body inverse dynamics with the set's standard inertials plus its joint friction.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from robid_link.atomic import atomic_write
from robid_link.exceptions import ConfigError, DriverError, RobidError

__all__ = ["TorqueFeedforward", "setpoint_states", "PER_MILLE_MAX"]

log = logging.getLogger("robid.driver.canopen")

PER_MILLE_MAX = 32767  # 0x60B2 is INTEGER16


def setpoint_states(q: np.ndarray, period: float) -> tuple[np.ndarray, np.ndarray]:
    """Velocity and acceleration of a setpoint series (N, n) by central differences (one-sided
    velocity and zero acceleration at the ends, where a program is at rest)."""
    if len(q) < 3:
        return np.zeros_like(q), np.zeros_like(q)
    qd = np.gradient(q, period, axis=0)
    qdd = np.zeros_like(q)
    qdd[1:-1] = (q[2:] - 2 * q[1:-1] + q[:-2]) / period**2
    return qd, qdd


class TorqueFeedforward:
    """One robot's model (from its description file) and the parameter set in use.

    ``load`` checks a set (``paramset.feedforward``) against the robot; ``offsets`` gives the
    per-mille offsets of a setpoint series; ``save``/``restore`` keep the set's exact bytes in
    ``path`` so that a restarted daemon goes on with the set it had acknowledged.
    """

    def __init__(self, robot_file: str | None, joint_names: Sequence[str], path: Path) -> None:
        self.robot_file, self.joint_names, self.path = robot_file, tuple(joint_names), path
        self._robot: Any = None
        self.ff: Any = None  # paramset.Feedforward of the set in use, None: zero offsets
        self.body: bytes | None = None

    @property
    def sha256(self) -> str | None:
        return None if self.ff is None else str(self.ff.sha256)

    def robot(self) -> Any:
        """The Pinocchio model, loaded once (needs ``driver.robot_file``)."""
        if self._robot is None:
            from robid_link.ident.model.robot import load_robot

            if self.robot_file is None:
                raise DriverError("driver.robot_file: missing; the drives' torque feedforward "
                                  "needs the robot description (MDH YAML or URDF)")
            try:
                robot = load_robot(self.robot_file)
            except RobidError as err:
                raise ConfigError(f"driver.robot_file: {err}") from err
            if tuple(robot.joint_names) != self.joint_names:
                raise ConfigError(f"driver.robot_file: joints {list(robot.joint_names)} are "
                                  f"not the daemon's robot's {list(self.joint_names)}")
            self._robot = robot
        return self._robot

    def check(self, body: bytes) -> Any:
        """The set's feedforward, or DriverError naming why it is refused."""
        from robid_link.ident.fit.paramset import feedforward

        try:
            doc = json.loads(body)
            ff = feedforward(doc, len(self.joint_names))
        except (ValueError, RobidError) as err:
            raise DriverError(f"parameter set refused: {err}") from err
        if doc.get("robot") not in (None, self.robot().name):
            raise DriverError(f"parameter set refused: it is for robot {doc.get('robot')}, "
                              f"the drives move {self.robot().name}")
        return ff

    def load(self, body: bytes) -> None:
        """Check, persist, then use the set (a refused set leaves the previous one in use)."""
        ff = self.check(body)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(self.path, body)
        self.ff, self.body = ff, body
        log.info("parameter set %s in use: torque offsets (0x60B2) from its inverse "
                 "dynamics and friction", ff.sha256[:12])

    def restore(self) -> None:
        """The set a previous daemon acknowledged, if any (a damaged file: zero offsets)."""
        if not self.path.is_file():
            return
        try:
            body = self.path.read_bytes()
            self.ff, self.body = self.check(body), body
            log.info("parameter set %s restored from %s", self.ff.sha256[:12], self.path)
        except (OSError, RobidError) as err:
            log.warning("%s: saved parameter set not used (%s); torque offsets are zero",
                        self.path, err)

    def torque(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
        """Model torque (N, n) in N·m: τ = Y(q, q̇, q̈)·θ + friction(q̇)."""
        from robid_link.ident.model.regressor import reference_regressor

        ff = self.ff
        tau = np.zeros_like(q)
        if ff is None:
            return tau
        if ff.inertials is not None:
            tau += reference_regressor(self.robot(), q, qd, qdd) @ ff.inertials
        return tau + ff.friction(qd)

    def offsets(self, counts: np.ndarray, counts_per_rad: Sequence[float],
                rated_nm: Sequence[float], period: float) -> np.ndarray | None:
        """Per-mille torque offsets (N, n) of a setpoint series in counts; None without a set."""
        if self.ff is None:
            return None
        q = counts / np.asarray(counts_per_rad, dtype=float)
        qd, qdd = setpoint_states(q, period)
        tau = self.torque(q, qd, qdd)
        pm = np.rint(tau / np.asarray(rated_nm, dtype=float) * 1000.0)
        return np.clip(pm, -PER_MILLE_MAX, PER_MILLE_MAX).astype(np.int64)
