"""An independent closed-loop rigid-body plant for the diagnosis' false-alarm tests: a robot
description's chain with its own bodies, Coulomb and viscous friction that stick for real, run
by a servo at 1 kHz from its quantized encoders, logged as a controller logs (the command of
each tick, the encoder at the tick) with torque noise.

Written for the tests without the analysis' code, the project's plant (``fakes/``) or
``tests/sims/arm.py``'s closed loop: from the project it takes only the robot description
(its Pinocchio model, limits and nominal inertials), and the bodies of ``arm.py``'s
``physical_inertials``. Its own motion (sums of sines at unrelated frequencies, or harmonics of
a period with every joint at rest once a period), its own loops — ``pd``: computed torque on
the a-priori model with PD on the encoder's filtered difference; ``pi``: a P position loop
around a PI velocity loop through the a-priori mass matrix, with the a-priori model's
feed-forward of the reference — and its own plant step: the torque of each tick held over it,
viscous friction implicit, the friction impulses solving a box-constrained problem (projected
Gauss–Seidel on the velocity update), so a joint whose velocity would cross zero sticks while
the friction holds it and breaks away when it cannot, coupled through the mass matrix, and the
positions integrated with the step's mean velocity.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from .arm import physical_inertials

__all__ = ["Servo", "Cell", "Motion", "multisine", "run", "write_log", "case"]


@dataclass(frozen=True)
class Servo:
    """The controller: ``kind`` ``pd`` or ``pi`` at ``rate_hz`` (the log's rate too), position
    bandwidth ``bandwidth_hz``, the encoder difference low-passed at ``velocity_filter_hz``;
    the plant takes ``substeps`` steps per tick with the tick's torque held."""

    kind: str = "pd"
    rate_hz: float = 1000.0
    bandwidth_hz: float = 6.0
    velocity_filter_hz: float = 200.0
    substeps: int = 2


@dataclass(frozen=True)
class Cell:
    """What one log is made of: the friction per joint (N·m, N·m·s/rad), the torque noise σ,
    the encoder's counts per turn, the servo, the bodies' seed; ``extra``: a torque the
    plant adds, τ(q, q̇) per joint (an effect to find; None for a clean cell)."""

    fc: tuple[float, ...]
    fv: tuple[float, ...]
    noise: float = 0.3
    counts: int = 2**20
    servo: Servo = Servo()
    seed: int = 1
    extra: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None


@dataclass(frozen=True)
class Motion:
    """q(t) = c + Σ_k a_k sin(ω_k t) + b_k cos(ω_k t), per joint, at frequencies of its own."""

    centre: np.ndarray  # (n,)
    a: np.ndarray  # (n, K)
    b: np.ndarray  # (n, K)
    omega: np.ndarray  # (n, K)

    def at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ph = t[:, None, None] * self.omega[None]
        s, c = np.sin(ph), np.cos(ph)
        w = self.omega
        q = self.centre + np.sum(self.a * s + self.b * c, axis=2)
        qd = np.sum(w * (self.a * c - self.b * s), axis=2)
        qdd = -np.sum(w**2 * (self.a * s + self.b * c), axis=2)
        return q, qd, qdd


def multisine(robot: Any, seed: int, *, sines: int = 5, f_lo: float = 0.04, f_hi: float = 0.35,
              rest_every_s: float | None = None, reach: float = 0.7, speed: float = 0.6
              ) -> Motion:
    """Sines per joint, scaled into ``reach`` of the joint's range and ``speed`` of its
    velocity and acceleration limits: at random frequencies in [f_lo, f_hi] Hz (nothing
    repeats), or with ``rest_every_s`` the harmonics of that period, every joint at rest with
    no acceleration once a period (as an excitation that starts and ends at rest, repeated)."""
    rng = np.random.default_rng(seed)
    lim, n = robot.limits, robot.n
    lo = np.where(np.isfinite(lim.q_min), lim.q_min, -math.pi)
    hi = np.where(np.isfinite(lim.q_max), lim.q_max, math.pi)
    centre = (lo + hi) / 2 + rng.uniform(-0.1, 0.1, n) * (hi - lo) / 2
    if rest_every_s is None:
        omega = 2 * math.pi * rng.uniform(f_lo, f_hi, (n, sines))
    else:
        omega = np.tile(2 * math.pi / rest_every_s * np.arange(1, sines + 1), (n, 1))
    size = rng.uniform(0.3, 1.0, (n, sines)) * omega.min() / omega
    phase = rng.uniform(0, 2 * math.pi, (n, sines))
    a, b = size * np.cos(phase), size * np.sin(phase)
    if rest_every_s is not None:  # q̇(0) = Σ a ω = 0 and q̈(0) = −Σ b ω² = 0, by the first sine
        a[:, 0] = -np.sum(a[:, 1:] * omega[:, 1:], axis=1) / omega[:, 0]
        b[:, 0] = -np.sum(b[:, 1:] * omega[:, 1:] ** 2, axis=1) / omega[:, 0] ** 2
    amp = np.hypot(a, b)
    room = np.minimum(hi - centre, centre - lo) * reach
    scale = np.min(np.stack([room / np.sum(amp, axis=1),
                             speed * lim.qd_max / np.sum(amp * omega, axis=1),
                             speed * lim.qdd_max / np.sum(amp * omega**2, axis=1)]), axis=0)
    return Motion(centre, a * scale[:, None], b * scale[:, None], omega)


def _friction_step(v_free: np.ndarray, w: np.ndarray, limit: np.ndarray) -> np.ndarray:
    """Friction impulses p (|p_j| ≤ limit_j) with v = v_free + W p: a slipping joint's impulse
    opposes its new velocity at the limit, a sticking one's holds it at rest. The fast path
    (every joint keeps sliding its way) first, else projected Gauss–Seidel on the box QP
    min ½ pᵀWp + pᵀv_free."""
    slip = limit > 0
    p = -limit * np.sign(v_free)
    v = v_free + w @ p
    if np.all(v_free[slip] != 0) and np.all(np.sign(v[slip]) == np.sign(v_free[slip])):
        return p
    p = np.zeros_like(v_free)
    diag = np.diag(w)
    for _ in range(200):
        worst = 0.0
        for j in np.flatnonzero(limit > 0):
            vj = v_free[j] + w[j] @ p
            new = float(np.clip(p[j] - vj / diag[j], -limit[j], limit[j]))
            worst = max(worst, abs(new - p[j]) * diag[j])
            p[j] = new
        if worst < 1e-12:
            break
    return p


def run(robot: Any, cell: Cell, motion: Motion, duration_s: float
        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
    """(t, encoder q, logged τ, truth) of ``duration_s`` under the servo."""
    n, servo = robot.n, cell.servo
    rate = float(servo.rate_hz)
    h = 1.0 / (rate * servo.substeps)
    inertials = physical_inertials(robot, cell.seed)
    plant = robot.model.copy()
    nominal = robot.model.copy()
    for j in range(n):
        plant.inertias[j + 1] = pin.Inertia.FromDynamicParameters(inertials[10 * j: 10 * j + 10])
        nominal.inertias[j + 1] = pin.Inertia.FromDynamicParameters(
            np.asarray(robot.nominal[10 * j: 10 * j + 10]))
    pd_, nd_ = plant.createData(), nominal.createData()
    fc, fv = np.asarray(cell.fc, float), np.asarray(cell.fv, float)
    ticks = int(round(duration_s * rate))
    t = np.arange(ticks) / rate
    q_ref, qd_ref, qdd_ref = motion.at(t)
    lsb = 2 * math.pi / cell.counts
    wn = 2 * math.pi * servo.bandwidth_hz
    wv = 3.0 * wn  # the velocity loop three times faster than the position loop
    alpha = 1.0 - math.exp(-2 * math.pi * servo.velocity_filter_hz / rate)
    q, v = q_ref[0].copy(), qd_ref[0].copy()
    enc_prev = np.round(q / lsb) * lsb
    v_est, integral = v.copy(), np.zeros(n)
    log_q, log_tau = np.empty((ticks, n)), np.empty((ticks, n))
    true_q, true_v = np.empty((ticks, n)), np.empty((ticks, n))
    for k in range(ticks):
        enc = np.round(q / lsb) * lsb
        if k:
            v_est += alpha * ((enc - enc_prev) * rate - v_est)
        enc_prev = enc
        pq = robot.pin_q(enc)
        e, ev = q_ref[k] - enc, qd_ref[k] - v_est
        if servo.kind == "pd":  # computed torque on the a-priori model
            tau = np.array(pin.rnea(nominal, nd_, pq, v_est, qdd_ref[k] + wn * wn * e
                                    + 2 * wn * ev))
        else:  # P position → PI velocity, through the a-priori mass matrix, with its
            # feed-forward of the reference motion
            ev = qd_ref[k] + wn * e - v_est
            integral += ev / rate
            mass = np.asarray(pin.crba(nominal, nd_, pq))
            mass = np.triu(mass) + np.triu(mass, 1).T
            tau = np.array(pin.rnea(nominal, nd_, pq, qd_ref[k], qdd_ref[k])) + mass @ (
                2 * wv * ev + wv * wv * integral)
        log_q[k], log_tau[k], true_q[k], true_v[k] = enc, tau, q, v
        for _ in range(servo.substeps):
            pq = robot.pin_q(q)
            mass = np.asarray(pin.crba(plant, pd_, pq))
            mass = np.triu(mass) + np.triu(mass, 1).T + h * np.diag(fv)  # viscous: implicit
            bias = np.asarray(pin.rnea(plant, pd_, pq, v, np.zeros(n)))
            w = np.linalg.inv(mass)
            push = tau - bias - fv * v
            if cell.extra is not None:
                push = push - cell.extra(q, v)
            v_free = v + h * (w @ push)
            v_new = v_free + w @ _friction_step(v_free, w, h * fc)
            q = q + h * 0.5 * (v + v_new)  # trapezoidal: the positions keep the velocities' time
            v = v_new
    rng = np.random.default_rng(cell.seed + 1000)
    noisy = log_tau + rng.normal(size=log_tau.shape) * cell.noise
    truth = {"inertials": inertials, "fc": fc, "fv": fv, "servo": servo, "q": true_q,
             "qd": true_v, "tau": log_tau}
    return t, log_q, noisy, truth


def write_log(path: str | Path, t: np.ndarray, q: np.ndarray, tau: np.ndarray) -> Path:
    """The log as the house CSV: t, q1..qn, tau1..taun."""
    n = q.shape[1]
    names = ["t", *(f"q{j}" for j in range(1, n + 1)), *(f"tau{j}" for j in range(1, n + 1))]
    with open(path, "w") as fh:
        fh.write(",".join(names) + "\n")
        np.savetxt(fh, np.column_stack([t, q, tau]), delimiter=",", fmt="%.12g")
    return Path(path)


def case(robot: Any, seed: int) -> tuple[Cell, Motion]:
    """A clean cell and its motion varied by ``seed``: the loop (PD on even seeds, PI on odd
    ones) and its bandwidth; the motion (every other pair of seeds at rest once every 10 s);
    the torque noise (0.1 or 0.3 N·m); each joint's Coulomb friction 3–12 % of its
    rigid-body torque (RMS over the motion, on the a-priori model) and at least 1–4 times the
    noise, a viscous friction worth 0.5–2 times that at the joint's typical speed; the
    encoder (2^23–2^26 counts per turn: a motor encoder behind its gear)."""
    rng = np.random.default_rng(seed)
    n = robot.n
    motion = multisine(robot, seed, rest_every_s=10.0 if (seed // 2) % 2 else None)
    nominal = robot.model.copy()
    for j in range(n):
        nominal.inertias[j + 1] = pin.Inertia.FromDynamicParameters(
            np.asarray(robot.nominal[10 * j: 10 * j + 10]))
    data = nominal.createData()
    q, qd, qdd = motion.at(np.linspace(0.0, 40.0, 400))
    tau = np.array([pin.rnea(nominal, data, robot.pin_q(q[k]), qd[k], qdd[k])
                    for k in range(q.shape[0])])
    noise = float(rng.choice([0.1, 0.3]))
    fc = np.maximum(rng.uniform(0.03, 0.12, n) * np.sqrt(np.mean(tau**2, axis=0)),
                    rng.uniform(1.0, 4.0, n) * noise)
    fv = fc * rng.uniform(0.5, 2.0, n) / np.percentile(np.abs(qd), 90, axis=0)
    servo = Servo(kind="pd" if seed % 2 == 0 else "pi",
                  bandwidth_hz=float(rng.uniform(4.0, 8.0)))
    return Cell(fc=tuple(fc), fv=tuple(fv), noise=noise,
                counts=int(2 ** rng.integers(23, 27)), servo=servo, seed=seed), motion
