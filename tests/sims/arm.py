"""An independent rigid-body plant for tests: logs the analysis has not been tuned to.

It shares nothing with ``robid_link.fakes`` or the worker's effect code: its own inertial
parameters (physical bodies perturbed from the robot's a-priori ones), its own laws for every
catalog effect (friction with a Stribeck shape exponent, a Dahl-like pre-sliding, cogging with
a second harmonic, a linear and a gas spring, friction that follows a thermal state, gear
load friction, rotor inertia, a torque log that lags), its own noise (white, coloured,
quantised), a Fourier motion of its own, sampling rates from 250 Hz to 4 kHz, a CSV writer
with any time unit and a subset of torque columns, and an optional closed loop (PD with the
a-priori model's computed torque, forward dynamics by a linearly implicit Euler step). From the
project it takes only the robot description: its Pinocchio model, limits and nominal inertials.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

__all__ = ["Effect", "Noise", "Loop", "Motion", "Arm", "Record", "CATALOG", "physical_inertials",
           "fourier_motion", "write_csv", "TIME_UNITS"]


# ----------------------------------------------------------------------------- effects


@dataclass(frozen=True)
class Effect:
    """One effect of the plant: ``name`` (a key of LAWS), ``joint`` from 1 (None: every joint,
    or a global effect) and its physical constants."""

    name: str
    joint: int | None = None
    p: dict[str, float] = field(default_factory=dict)


@dataclass
class _Sig:
    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    load: np.ndarray  # the rigid-body torque the gear transmits
    sgn: Callable[[np.ndarray], np.ndarray]  # sign of a velocity (smoothed in closed loop)
    heat: np.ndarray | None = None  # per joint, a thermal state (friction_drift)


def _exact_sign(v: np.ndarray) -> np.ndarray:
    return np.where(np.abs(v) > 1e-9, np.sign(v), 0.0)


def _viscous(p, s, j):
    return p["b"] * s.qd[:, j]


def _coulomb(p, s, j):
    return p["fc"] * s.sgn(s.qd[:, j])


def _coulomb_asymmetric(p, s, j):
    sg = s.sgn(s.qd[:, j])
    return np.where(sg > 0, p["up"] * sg, p["down"] * sg)


def _offset(p, s, j):
    return np.full(s.t.shape, p["bias"])


def _friction_power(p, s, j):
    v = s.qd[:, j]
    return (p["fc"] + p["k"] * np.abs(v) ** p["alpha"]) * s.sgn(v) + p["bias"]


def _stribeck(p, s, j):
    """Breakaway ``fs`` falling to Coulomb ``fc``: exp(−|v/vs|^δ), δ the shape exponent."""
    v = s.qd[:, j]
    return (p["fc"] + (p["fs"] - p["fc"]) * np.exp(-np.abs(v / p["vs"]) ** p["delta"])) * \
        s.sgn(v)


def _presliding(p, s, j):
    """A smooth transition through zero velocity: fp·(2/π)·atan(v/vp) (heavier tails than a
    hyperbolic tangent)."""
    return p["fp"] * (2.0 / math.pi) * np.arctan(s.qd[:, j] / p["vp"])


def _armature(p, s, j):
    return p["jm"] * p["ratio"] ** 2 * s.qdd[:, j]


def _linear_spring(p, s, j):
    """An extension spring from a base point (distance ``b``) to a link point (``a``) at
    angle q + φ: τ = −k (l − l0) ∂l/∂q."""
    psi = s.q[:, j] + p["phi"]
    length = np.sqrt(p["a"] ** 2 + p["b"] ** 2 - 2 * p["a"] * p["b"] * np.cos(psi))
    return -p["k"] * (length - p["l0"]) * p["a"] * p["b"] * np.sin(psi) / length


def _gas_spring(p, s, j):
    """A gas strut (polytropic, exponent κ) between a base point and a link point, pushing
    them apart: force F0·(g/(g − (l_max − l)))^κ along l, τ = F ∂l/∂q. ``g``: the gas column
    at full extension."""
    psi = s.q[:, j] + p["phi"]
    length = np.sqrt(p["a"] ** 2 + p["b"] ** 2 - 2 * p["a"] * p["b"] * np.cos(psi))
    lmax = p["a"] + p["b"]
    force = p["f0"] * (p["g"] / (p["g"] - (lmax - length))) ** p["kappa"]
    return force * p["a"] * p["b"] * np.sin(psi) / length


def _ripple(p, s, j):
    """Cogging: a fundamental of period P in the joint angle and a second harmonic."""
    ph = 2 * math.pi * s.q[:, j] / p["period"]
    return p["amp"] * np.sin(ph + p["phase"]) + p.get("amp2", 0.0) * np.sin(2 * ph + 1.0)


def _friction_drift(p, s, j):
    """Friction of a joint that warms up: viscous and Coulomb scaled by 1 + c·(1 − h), h the
    joint's thermal state (0 cold … 1 warm), driven by its dissipated power."""
    assert s.heat is not None
    v = s.qd[:, j]
    scale = 1.0 + p["cold"] * (1.0 - s.heat[:, j])
    return scale * (p["fc"] * s.sgn(v) + p["b"] * v)


def _load_friction(p, s, j):
    """Gear friction of efficiency η: (1 − η)·|τ_load|·sign(q̇)."""
    return (1.0 - p["eta"]) * np.abs(s.load[:, j]) * s.sgn(s.qd[:, j])


LAWS: dict[str, Callable[[dict[str, float], _Sig, int], np.ndarray]] = {
    "viscous": _viscous, "coulomb": _coulomb, "coulomb_asymmetric": _coulomb_asymmetric,
    "offset": _offset, "friction_power": _friction_power, "stribeck": _stribeck,
    "presliding": _presliding, "armature": _armature, "spring": _linear_spring,
    "gas_spring": _gas_spring, "ripple": _ripple, "friction_drift": _friction_drift,
    "load_friction": _load_friction,
}
#: effects not evaluated per sample: a time shift of the torque log
GLOBAL = {"delay"}

#: one instance of every catalog effect (the diagnosis' names), for tests over all of them;
#: the joint is given by the test. Sizes: a few times a 0.3 N·m noise on a light arm.
CATALOG: dict[str, Effect] = {
    "viscous": Effect("viscous", p={"b": 3.0}),
    "coulomb": Effect("coulomb", p={"fc": 2.0}),
    "coulomb_asymmetric": Effect("coulomb_asymmetric", p={"up": 2.4, "down": 0.6}),
    "offset": Effect("offset", p={"bias": 0.8}),
    "friction_power": Effect("friction_power", p={"fc": 1.0, "k": 4.0, "alpha": 0.4,
                                                  "bias": 0.0}),
    "stribeck": Effect("stribeck", p={"fs": 4.0, "fc": 1.5, "vs": 0.06, "delta": 1.0}),
    "presliding": Effect("presliding", p={"fp": 1.5, "vp": 0.02}),
    "armature": Effect("armature", p={"jm": 4e-5, "ratio": 100.0}),
    "spring": Effect("spring", p={"k": 300.0, "a": 0.12, "b": 0.22, "l0": 0.28,
                                  "phi": 0.5}),
    "ripple": Effect("ripple", p={"amp": 0.6, "period": 0.1, "phase": 0.3, "amp2": 0.12}),
    "friction_drift": Effect("friction_drift", p={"fc": 1.2, "b": 1.5, "cold": 1.0,
                                                  "heat_s": 12.0}),
    "load_friction": Effect("load_friction", p={"eta": 0.92}),
    "delay": Effect("delay", p={"seconds": 0.008}),
}


# ----------------------------------------------------------------------------- noise, loop


@dataclass(frozen=True)
class Noise:
    """Torque noise σ (N·m, per joint or one for all); ``colour``: AR(1) coefficient of the
    noise (0 white; same variance σ² whatever the colour); ``tau_lsb``, ``q_lsb``: sensor
    quantisation steps of the torque (N·m) and the encoders (rad)."""

    tau: float | Sequence[float] = 0.3
    colour: float = 0.0
    tau_lsb: float = 0.0
    q_lsb: float = 0.0

    def sigma(self, n: int) -> np.ndarray:
        return np.broadcast_to(np.asarray(self.tau, dtype=float), (n,)).copy()

    def draw(self, rng: np.random.Generator, shape: tuple[int, int]) -> np.ndarray:
        w = rng.standard_normal(shape) * self.sigma(shape[1])
        if self.colour == 0.0:
            return w
        a = self.colour
        out = np.empty_like(w)
        out[0] = w[0]
        gain = math.sqrt(1.0 - a * a)
        for k in range(1, shape[0]):
            out[k] = a * out[k - 1] + gain * w[k]
        return out


@dataclass(frozen=True)
class Loop:
    """A closed position loop: PD on the measured state with the a-priori model's computed
    torque (what a controller has), at ``rate_hz`` (≥ the log rate), ``substeps`` plant steps
    per control period; ``bandwidth_hz`` of the PD; Coulomb-like friction smoothed over
    ``v_eps`` rad/s (a stiff but finite slope, integrated implicitly)."""

    rate_hz: float = 2000.0
    substeps: int = 2
    bandwidth_hz: float = 6.0
    v_eps: float = 2e-4


# ----------------------------------------------------------------------------- motion


@dataclass(frozen=True)
class Motion:
    """q(t) = c + Σ_k a_k sin(2π k f0 t) + b_k cos(2π k f0 t), per joint."""

    centre: np.ndarray
    a: np.ndarray  # (n, K)
    b: np.ndarray  # (n, K)
    f0: float

    def at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        k = np.arange(1, self.a.shape[1] + 1)
        w = 2 * math.pi * self.f0 * k
        ph = np.outer(t, w)
        s, c = np.sin(ph), np.cos(ph)
        q = self.centre + s @ self.a.T + c @ self.b.T
        qd = (c * w) @ self.a.T - (s * w) @ self.b.T
        qdd = -(s * w**2) @ self.a.T - (c * w**2) @ self.b.T
        return q, qd, qdd


def fourier_motion(robot: Any, seed: int, *, harmonics: int = 5, base_hz: float = 0.1,
                   reach: float = 0.75, speed: float = 0.7) -> Motion:
    """A random Fourier motion inside ``reach`` of each joint's range, ``speed`` of its velocity
    and acceleration limits."""
    rng = np.random.default_rng(seed)
    lim = robot.limits
    n = robot.n
    lo = np.where(np.isfinite(lim.q_min), lim.q_min, -math.pi)
    hi = np.where(np.isfinite(lim.q_max), lim.q_max, math.pi)
    centre = (lo + hi) / 2 + rng.uniform(-0.1, 0.1, n) * (hi - lo) / 2
    k = np.arange(1, harmonics + 1)
    a = rng.standard_normal((n, harmonics)) / k
    b = rng.standard_normal((n, harmonics)) / k
    m = Motion(centre, a, b, base_hz)
    t = np.linspace(0.0, 1.0 / base_hz, 4000, endpoint=False)
    q, qd, qdd = m.at(t)
    room = np.minimum(hi - centre, centre - lo) * reach
    scale = np.min(np.stack([room / np.abs(q - centre).max(axis=0),
                             speed * lim.qd_max / np.abs(qd).max(axis=0),
                             speed * lim.qdd_max / np.abs(qdd).max(axis=0)]), axis=0)
    return Motion(centre, a * scale[:, None], b * scale[:, None], base_hz)


# ----------------------------------------------------------------------------- inertials


def physical_inertials(robot: Any, seed: int, spread: float = 0.15) -> np.ndarray:
    """Standard parameters (10 per link) of bodies near the robot's a-priori ones that can
    exist: mass scaled, centre of mass moved, principal moments scaled within the triangle
    inequality, axes turned a little."""
    rng = np.random.default_rng(seed)
    out = []
    for j in range(robot.n):
        nominal = pin.Inertia.FromDynamicParameters(robot.nominal[10 * j: 10 * j + 10])
        mass = nominal.mass * (1 + spread * rng.uniform(-1, 1))
        com = np.asarray(nominal.lever) + spread * 0.1 * rng.uniform(-1, 1, 3)
        evals, evecs = np.linalg.eigh(np.asarray(nominal.inertia))
        evals = evals * (1 + spread * rng.uniform(-1, 1, 3))
        evals = np.maximum(evals, 1e-5)
        for i in range(3):  # each principal moment under the sum of the other two
            others = evals.sum() - evals[i]
            evals[i] = min(evals[i], 0.98 * others)
        axis = rng.standard_normal(3)
        turn = pin.exp3(axis / np.linalg.norm(axis) * spread * 0.3)
        rot = turn @ evecs
        out.append(pin.Inertia(mass, com, rot @ np.diag(evals) @ rot.T).toDynamicParameters())
    return np.concatenate(out)


# ----------------------------------------------------------------------------- the arm


@dataclass
class Record:
    """A log: time (s), measured positions, logged torques; and what made them."""

    t: np.ndarray
    q: np.ndarray
    tau: np.ndarray
    qd: np.ndarray  # the true velocity (not written unless asked)
    tau_true: np.ndarray  # the torque before noise and quantisation
    noise: np.ndarray  # what the noise added
    truth: dict[str, Any]

    @property
    def rate_hz(self) -> float:
        return 1.0 / float(self.t[1] - self.t[0])


class Arm:
    """The plant: a robot description's chain with its own inertials and effects."""

    def __init__(self, robot: Any, *, inertials: np.ndarray | None = None,
                 effects: Sequence[Effect] = (), noise: Noise | None = None,
                 seed: int = 1) -> None:
        self.robot = robot
        self.inertials = physical_inertials(robot, seed) if inertials is None else inertials
        self.effects = tuple(effects)
        self.noise = noise or Noise()
        self.model = robot.model.copy()
        for j in range(robot.n):
            self.model.inertias[j + 1] = pin.Inertia.FromDynamicParameters(
                np.asarray(self.inertials[10 * j: 10 * j + 10]))
        self.data = self.model.createData()

    # -- pieces of the dynamics
    def rigid(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
        pq = self.robot.pin_q(q)
        out = np.empty_like(qd)
        for k in range(q.shape[0]):
            out[k] = pin.rnea(self.model, self.data, pq[k], qd[k], qdd[k])
        return out

    def _per_joint(self) -> list[tuple[Effect, int]]:
        out = []
        for e in self.effects:
            if e.name in GLOBAL:
                continue
            if e.name not in LAWS:
                raise ValueError(f"unknown plant effect {e.name!r}")
            joints = [e.joint - 1] if e.joint else range(self.robot.n)
            out += [(e, j) for j in joints]
        return out

    def effect_torque(self, sig: _Sig) -> np.ndarray:
        tau = np.zeros_like(sig.qd)
        for e, j in self._per_joint():
            tau[:, j] += LAWS[e.name](e.p, sig, j)
        return tau

    def _heat(self, t: np.ndarray, qd: np.ndarray, sgn: Callable) -> np.ndarray | None:
        """Per joint, the thermal state of friction_drift joints: h' = (P/P̄ − h)/heat_s with P
        the friction power, normalised so the state settles near 1."""
        drift = [(e, j) for e, j in self._per_joint() if e.name == "friction_drift"]
        if not drift:
            return None
        heat = np.zeros_like(qd)
        for e, j in drift:
            power = np.abs(e.p["fc"] * sgn(qd[:, j]) * qd[:, j] + e.p["b"] * qd[:, j] ** 2)
            drive = power / max(float(power.mean()), 1e-12)
            h = 0.0
            dt = np.diff(t, prepend=t[0])
            col = np.empty(t.size)
            for k in range(t.size):
                h += dt[k] * (drive[k] - h) / e.p["heat_s"]
                col[k] = h
            heat[:, j] = np.clip(col, 0.0, 1.0)
        return heat

    def _delay(self) -> float:
        return sum(e.p["seconds"] for e in self.effects if e.name == "delay")

    def torque(self, t: np.ndarray, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray,
               sgn: Callable = _exact_sign) -> np.ndarray:
        """The joint torque that makes the arm follow (q, q̇, q̈)."""
        load = self.rigid(q, qd, qdd)
        sig = _Sig(t, q, qd, qdd, load, sgn, self._heat(t, qd, sgn))
        return load + self.effect_torque(sig)

    # -- logs
    def run(self, motion: Motion, *, rate_hz: float, duration_s: float, seed: int = 0,
            loop: Loop | None = None) -> Record:
        """A log of ``motion`` at ``rate_hz``: the inverse dynamics of the exact motion, or a
        closed loop tracking it (``loop``)."""
        t = np.arange(int(round(duration_s * rate_hz))) / rate_hz
        if loop is None:
            q, qd, qdd = motion.at(t)
            delay = self._delay()
            if delay:  # the torque log lags: τ_log(t) = τ(t − d), exactly, from the motion
                tau = self.torque(t - delay, *motion.at(t - delay))
            else:
                tau = self.torque(t, q, qd, qdd)
        else:
            q, qd, tau = self._closed_loop(motion, t, loop)
        rng = np.random.default_rng(seed)
        noise = self.noise.draw(rng, tau.shape)
        logged = tau + noise
        if self.noise.tau_lsb > 0:
            logged = np.round(logged / self.noise.tau_lsb) * self.noise.tau_lsb
        q_meas = q if self.noise.q_lsb <= 0 else np.round(q / self.noise.q_lsb) * self.noise.q_lsb
        truth = {"inertials": self.inertials, "noise": self.noise.sigma(self.robot.n),
                 "effects": self.effects, "rate_hz": rate_hz, "closed_loop": loop is not None}
        return Record(t, q_meas, logged, qd, tau, logged - tau, truth)

    def _closed_loop(self, motion: Motion, t: np.ndarray, loop: Loop
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Forward dynamics under a PD + computed-torque controller; the logged torque is the
        command held over each control period (what the drive was asked for)."""
        robot, n = self.robot, self.robot.n
        rate = float(loop.rate_hz)
        log_rate = 1.0 / float(t[1] - t[0])
        per_log = max(1, int(round(rate / log_rate)))
        rate = per_log * log_rate
        h = 1.0 / (rate * loop.substeps)
        steps = t.size * per_log
        tc = np.arange(steps) / rate
        q_ref, qd_ref, qdd_ref = motion.at(tc)
        nominal = robot.model.copy()
        for j in range(n):
            nominal.inertias[j + 1] = pin.Inertia.FromDynamicParameters(
                np.asarray(robot.nominal[10 * j: 10 * j + 10]))
        ndata = nominal.createData()
        wn = 2 * math.pi * loop.bandwidth_hz
        kp, kd = wn * wn, 2 * wn
        eps = loop.v_eps

        def sgn(v: np.ndarray) -> np.ndarray:
            return np.tanh(v / eps)

        per_joint = self._per_joint()
        drift = any(e.name == "friction_drift" for e, _ in per_joint)
        armature = np.zeros(n)
        for e, j in per_joint:
            if e.name == "armature":
                armature[j] += e.p["jm"] * e.p["ratio"] ** 2
        forces = [(e, j) for e, j in per_joint if e.name != "armature"]
        q, v = q_ref[0].copy(), qd_ref[0].copy()
        acc = qdd_ref[0].copy()
        heat = np.zeros(n)
        lsb = self.noise.q_lsb
        q_prev_meas = q.copy()
        out_q, out_v, out_tau = np.empty((t.size, n)), np.empty((t.size, n)), np.empty((t.size, n))

        def effect_force(qq: np.ndarray, vv: np.ndarray, load: np.ndarray, tk: float
                         ) -> np.ndarray:
            sig = _Sig(np.array([tk]), qq[None], vv[None], acc[None], load[None], sgn,
                       heat[None] if drift else None)
            f = np.zeros(n)
            for e, j in forces:
                f[j] += LAWS[e.name](e.p, sig, j)[0]
            return f

        for k in range(steps):
            q_meas = q if lsb <= 0 else np.round(q / lsb) * lsb
            v_meas = v if lsb <= 0 else (q_meas - q_prev_meas) * rate if k else v
            q_prev_meas = q_meas
            a_cmd = qdd_ref[k] + kp * (q_ref[k] - q_meas) + kd * (qd_ref[k] - v_meas)
            tau_cmd = np.array(pin.rnea(nominal, ndata, robot.pin_q(q_meas), v_meas, a_cmd))
            if k % per_log == 0:
                i = k // per_log
                out_q[i], out_v[i], out_tau[i] = q, v, tau_cmd
            for _ in range(loop.substeps):
                pq = robot.pin_q(q)
                mass = np.array(pin.crba(self.model, self.data, pq))
                mass = np.triu(mass) + np.triu(mass, 1).T + np.diag(armature)
                bias = np.array(pin.rnea(self.model, self.data, pq, v, np.zeros(n)))
                load = bias + (mass - np.diag(armature)) @ acc
                f = effect_force(q, v, load, tc[k])
                dv = 1e-7
                damp = (effect_force(q, v + dv, load, tc[k]) - effect_force(q, v - dv, load,
                                                                              tc[k])) / (2 * dv)
                lhs = mass + h * np.diag(np.maximum(damp, 0.0))
                dvel = np.linalg.solve(lhs, h * (tau_cmd - bias - f))
                acc = dvel / h
                v = v + dvel
                q = q + h * v
                if drift:
                    for e, j in forces:
                        if e.name == "friction_drift":
                            power = abs((e.p["fc"] * sgn(v[j:j + 1])[0] + e.p["b"] * v[j]) * v[j])
                            norm = e.p["fc"] * 0.5 + e.p["b"] * 0.25
                            heat[j] = min(1.0, heat[j] + h * (power / norm - heat[j])
                                          / e.p["heat_s"])
        delay = self._delay()
        if delay:
            out_tau = np.stack([np.interp(t - delay, t, out_tau[:, j]) for j in range(n)],
                               axis=1)
        return out_q, out_v, out_tau


# ----------------------------------------------------------------------------- writing

#: seconds per unit of a written time column
TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}


def write_csv(path: str | Path, rec: Record, *, time_unit: str = "s",
              tau_joints: Sequence[int] | None = None, velocities: bool = False,
              degrees: bool = False) -> Path:
    """The log as CSV ``t, q1..qn, [qd1..qdn,] tau<j>…``: time in ``time_unit``, only the torque
    columns of ``tau_joints`` (from 1; default all), positions in degrees if asked."""
    n = rec.q.shape[1]
    joints = list(range(1, n + 1)) if tau_joints is None else list(tau_joints)
    q = np.degrees(rec.q) if degrees else rec.q
    cols = [rec.t / TIME_UNITS[time_unit], *q.T]
    names = ["t", *(f"q{j}" for j in range(1, n + 1))]
    if velocities:
        cols += list(rec.qd.T)
        names += [f"qd{j}" for j in range(1, n + 1)]
    cols += [rec.tau[:, j - 1] for j in joints]
    names += [f"tau{j}" for j in joints]
    with open(path, "w") as fh:
        fh.write(",".join(names) + "\n")
        np.savetxt(fh, np.column_stack(cols), delimiter=",", fmt="%.12g")
    return Path(path)
