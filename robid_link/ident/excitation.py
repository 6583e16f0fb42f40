"""Excitation trajectories: finite Fourier series per joint (Swevers et al.), scaled into limits.

q_j(t) = q0_j + Σ_l a_jl/(l ω) sin(l ω t) − b_jl/(l ω) cos(l ω t), with analytic derivatives.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from robid_link.ident.robot import Robot

__all__ = ["FourierTrajectory", "random_fourier"]

#: fraction of each limit a scaled trajectory may use
LIMIT_MARGIN = 0.9


@dataclass(frozen=True)
class FourierTrajectory:
    base_hz: float
    q0: np.ndarray  # (n,)
    a: np.ndarray  # (n, L)
    b: np.ndarray  # (n, L)

    @property
    def period_s(self) -> float:
        return 1.0 / self.base_hz

    def evaluate(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """q, q̇, q̈ (len(t), n)."""
        w = 2.0 * math.pi * self.base_hz
        harm = np.arange(1, self.a.shape[1] + 1)
        ph = np.outer(t, harm * w)  # (N, L)
        s, c = np.sin(ph), np.cos(ph)
        lw = harm * w
        q = self.q0 + s @ (self.a / lw).T - c @ (self.b / lw).T
        qd = c @ self.a.T + s @ self.b.T
        qdd = -s @ (self.a * lw).T + c @ (self.b * lw).T
        return q, qd, qdd

    def scaled(self, k: float) -> FourierTrajectory:
        return FourierTrajectory(self.base_hz, self.q0, self.a * k, self.b * k)


def _fit_limits(robot: Robot, traj: FourierTrajectory, margin: float) -> FourierTrajectory:
    """Largest uniform scaling of the harmonics that keeps q, q̇, q̈ inside the limits."""
    t = np.linspace(0.0, traj.period_s, 2000)
    q, qd, qdd = traj.evaluate(t)
    lim = robot.limits
    dev = np.abs(q - traj.q0).max(axis=0)
    room = np.minimum(traj.q0 - np.where(np.isfinite(lim.q_min), lim.q_min, -math.pi),
                      np.where(np.isfinite(lim.q_max), lim.q_max, math.pi) - traj.q0)
    ratios = [room / np.maximum(dev, 1e-12)]
    for x, cap in ((qd, lim.qd_max), (qdd, lim.qdd_max)):
        peak = np.abs(x).max(axis=0)
        ratios.append(np.where(np.isfinite(cap), cap / np.maximum(peak, 1e-12), np.inf))
    k = margin * float(np.min(np.concatenate(ratios)))
    return traj.scaled(k)


def random_fourier(robot: Robot, *, harmonics: int = 5, base_hz: float = 0.1,
                   seed: int = 0, margin: float = LIMIT_MARGIN) -> FourierTrajectory:
    """A Fourier trajectory with random coefficients, scaled into the robot's limits."""
    rng = np.random.default_rng(seed)
    lim = robot.limits
    lo = np.where(np.isfinite(lim.q_min), lim.q_min, -math.pi)
    hi = np.where(np.isfinite(lim.q_max), lim.q_max, math.pi)
    q0 = 0.5 * (lo + hi)
    a = rng.normal(size=(robot.n, harmonics))
    b = rng.normal(size=(robot.n, harmonics))
    return _fit_limits(robot, FourierTrajectory(base_hz, q0, a, b), margin)
