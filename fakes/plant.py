"""A simulated robot whose truth is known: rigid body plus physical effects, noise, encoders.

Effects are written as physics with physical parameters (not as the model's regressor
columns), so a bug in the model cannot hide behind the same bug in the plant.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pinocchio as pin

from robid_link.ident.robot import Robot

__all__ = ["Truth", "Plant", "perturbed_inertials"]


@dataclass(frozen=True)
class Truth:
    """Physical truth of a simulated robot."""

    inertials: np.ndarray  # standard parameters (10 n)
    effects: tuple[dict[str, Any], ...] = ()  # {"name", "joint" (from 1), params…}
    noise_tau: float | Sequence[float] = 0.0  # N·m, std of white torque noise (per joint)
    q_resolution: float = 0.0  # rad per encoder count (0 = none)
    extra: dict[str, Any] = field(default_factory=dict)


def perturbed_inertials(robot: Robot, seed: int, spread: float = 0.2) -> np.ndarray:
    """The nominal inertials with mass, COM and inertia perturbed (physically consistent)."""
    if robot.nominal is None:
        raise ValueError(f"{robot.source}: no nominal inertials to perturb")
    rng = np.random.default_rng(seed)
    out = []
    for j in range(robot.n):
        inert = pin.Inertia.FromDynamicParameters(robot.nominal[10 * j: 10 * j + 10])
        m = inert.mass * (1.0 + spread * rng.uniform(-1, 1))
        c = np.array(inert.lever) + spread * 0.1 * rng.uniform(-1, 1, 3)
        ic = np.array(inert.inertia) * (1.0 + spread * rng.uniform(-1, 1))
        out.append(pin.Inertia(m, c, ic).toDynamicParameters())
    return np.concatenate(out)


class Plant:
    """Inverse-dynamics plant: positions follow the command exactly; torques are physics."""

    def __init__(self, robot: Robot, truth: Truth) -> None:
        self.robot = robot
        self.truth = truth
        self.model = robot.model.copy()
        for j in range(robot.n):
            self.model.inertias[j + 1] = pin.Inertia.FromDynamicParameters(
                truth.inertials[10 * j: 10 * j + 10])
        self.data = self.model.createData()

    def rigid_torque(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
        pq = self.robot.pin_q(q)
        out = np.empty_like(qd)
        for k in range(q.shape[0]):
            out[k] = pin.rnea(self.model, self.data, pq[k], qd[k], qdd[k])
        return out

    def effect_torque(self, t: np.ndarray, q: np.ndarray, qd: np.ndarray,
                      qdd: np.ndarray) -> np.ndarray:
        tau = np.zeros_like(qd)
        for eff in self.truth.effects:
            name = eff["name"]
            joints = [eff["joint"] - 1] if eff.get("joint") else range(self.robot.n)
            for j in joints:
                tau[:, j] += _EFFECTS[name](eff, t, q[:, j], qd[:, j], qdd[:, j])
        return tau

    def run(self, t: np.ndarray, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray,
            seed: int = 0) -> dict[str, np.ndarray]:
        """Log of a commanded motion: t, quantized q, noisy τ (and the noise-free τ)."""
        rng = np.random.default_rng(seed)
        tau_true = self.rigid_torque(q, qd, qdd) + self.effect_torque(t, q, qd, qdd)
        noise = np.broadcast_to(np.asarray(self.truth.noise_tau, dtype=float), (self.robot.n,))
        tau = tau_true + rng.normal(size=tau_true.shape) * noise
        res = self.truth.q_resolution
        q_meas = np.round(q / res) * res if res > 0 else q.copy()
        return {"t": t, "q": q_meas, "qd": qd, "qdd": qdd, "tau": tau, "tau_true": tau_true}


def _viscous(e, t, q, qd, qdd):
    return e["fv"] * qd


def _coulomb(e, t, q, qd, qdd):
    return e["fc"] * np.sign(qd)


def _offset(e, t, q, qd, qdd):
    return e["b"] * np.ones_like(q)


def _friction_power(e, t, q, qd, qdd):
    return (e["fc"] + e["fv"] * np.abs(qd) ** e["alpha"]) * np.sign(qd) + e.get("b", 0.0)


_EFFECTS = {"viscous": _viscous, "coulomb": _coulomb, "offset": _offset,
            "friction_power": _friction_power}
