"""An independent simulator of elastic joints for the elasticity tests: motor and arm on a spring
and damper (one axis, optionally a third mass behind the arm, or a pair whose arms share a
coupled inertia), closed by its own loops,
excited by its own stepped sines, logged as the house CSV (t, q…, tau…) with its schedule.

Written for the tests without the analysis' code or the project's plant (robid_link.ident and
fakes/ are not imported): the linear dynamics are integrated exactly over each controller tick
(matrix exponential, the torque held over the tick), Coulomb friction by events: a velocity
reversal is located on the exact solution, the body then sticks while the force that holds it
stays within the friction and breaks away, in the direction it is pushed, when it leaves it.
Units: joint side, rad, N·m, kg·m²; positions logged are the motor's (what an encoder on the
motor reads, in joint units), torques the motor's.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["Axis", "Loop", "SteppedSine", "Noise", "Run", "simulate", "robot_yaml"]


@dataclass(frozen=True)
class Axis:
    """One elastic joint: motor ``jm`` – spring ``k`` ∥ damper ``d`` – arm ``ja``; ``ba`` the
    arm's viscous friction, ``kg`` gravity's stiffness on the arm at the pose (restoring > 0),
    ``fc_arm`` / ``fc_motor`` Coulomb friction, ``bm`` the motor's viscous friction;
    ``third`` a third mass j3 on a spring k3 ∥ damper d3 behind the arm (a second mode)."""

    jm: float
    ja: float
    k: float
    d: float
    ba: float = 0.0
    kg: float = 0.0
    fc_arm: float = 0.0
    bm: float = 0.0
    fc_motor: float = 0.0
    third: tuple[float, float, float] | None = None  # (j3, k3, d3): a mass behind the arm


@dataclass(frozen=True)
class Loop:
    """The controller, on the measured (quantized) motor position at ``rate_hz``, its torque
    held over the tick: ``pd`` position loop, ``pi_velocity`` (a velocity reference, PI),
    ``cascade`` (P position → PI velocity → a current loop as a first-order torque lag of
    ``torque_lag_s``). Gains from the bandwidths and the axis' total inertia. The velocity is
    the encoder's difference, low-passed at ``velocity_filter_hz``."""

    kind: str = "pd"
    rate_hz: float = 4000.0
    bandwidth_hz: float = 6.0
    velocity_bandwidth_hz: float = 18.0
    torque_lag_s: float = 0.0
    velocity_filter_hz: float = 400.0
    delay_ticks: int = 0  # the torque computed at a tick acts this many ticks later


@dataclass(frozen=True)
class SteppedSine:
    """Stepped sines on the position reference, log-spaced ``f_min_hz``–``f_max_hz``: a sine
    of velocity amplitude ``velocity`` (its acceleration capped at ``accel``), riding on a
    drift of ``drift`` rad/s that alternates direction from step to step (0: none). A pair
    runs every frequency on its first axis, then on its second; the other axis drifts along.
    """

    f_min_hz: float = 2.0
    f_max_hz: float = 60.0
    steps: int = 24
    velocity: float = 0.05
    accel: float = 20.0
    drift: float = 0.0
    settle_s: float = 1.0
    settle_periods: float = 4.0
    measure_s: float = 1.2
    measure_periods: float = 8.0
    ramp_s: float = 0.3


@dataclass(frozen=True)
class Noise:
    """``tau``: white noise on the logged torque; ``disturbance``: a white torque acting on
    the motor, held per controller tick (both 1 σ, N·m); ``q_step``: encoder resolution."""

    tau: float = 0.0
    disturbance: float = 0.0
    q_step: float = 0.0


@dataclass
class Run:
    """A simulated log: ``t`` (s), ``q`` motor positions, ``tau`` motor torques (N, n), the
    ``schedule`` (the analysis' step keys) and the ``truth`` per joint."""

    t: np.ndarray
    q: np.ndarray
    tau: np.ndarray
    schedule: list[dict[str, Any]]
    truth: dict[int, dict[str, float]]
    pose: tuple[float, ...]
    meta: dict[str, Any] = field(default_factory=dict)

    def write(self, directory: str | Path, name: str = "twomass") -> tuple[Path, Path]:
        """``<name>.csv`` (t, q1…, tau1…) and ``<name>.yaml`` (``schedule:``, JSON text)."""
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        n = self.q.shape[1]
        head = ",".join(["t"] + [f"q{j}" for j in range(1, n + 1)]
                        + [f"tau{j}" for j in range(1, n + 1)])
        csv = d / f"{name}.csv"
        np.savetxt(csv, np.column_stack((self.t, self.q, self.tau)), delimiter=",",
                   header=head, comments="", fmt="%.12g")
        yml = d / f"{name}.yaml"
        yml.write_text(json.dumps({"schedule": self.schedule, "pose": list(self.pose)},
                                  indent=1))
        return csv, yml


# ----------------------------------------------------------------------------- mechanics


class _Mechanics:
    """M p̈ + C ṗ + K p = E·τ + friction, p = (motors…, arms…) relative to the pose; with a
    torque lag the motor torque is a state: τ̇ = (τ_cmd − τ)/T. Input w = (τ_cmd…,
    disturbance…, 1); the constant channel carries the sliding friction forces. A *mode* is
    the set of stuck bodies and the sliding directions: linear in each, integrated exactly."""

    def __init__(self, axes: Sequence[Axis], jcop: float, lag_s: float, h: float) -> None:
        n = len(axes)
        tools = [i for i, a in enumerate(axes) if a.third is not None]
        nd = 2 * n + len(tools)  # motors, arms, then the third masses
        self.n, self.dof, self.h = n, nd, h
        m = np.zeros((nd, nd))
        c = np.zeros((nd, nd))
        k = np.zeros((nd, nd))

        def couple(i: int, j: int, stiff: float, damp: float) -> None:
            for mat, v in ((k, stiff), (c, damp)):
                mat[i, i] += v
                mat[j, j] += v
                mat[i, j] -= v
                mat[j, i] -= v

        for i, a in enumerate(axes):
            mo, ar = i, n + i
            m[mo, mo], m[ar, ar] = a.jm, a.ja
            couple(mo, ar, a.k, a.d)
            c[mo, mo] += a.bm
            c[ar, ar] += a.ba
            k[ar, ar] += a.kg
        for t, i in enumerate(tools):
            j3, k3, d3 = axes[i].third  # type: ignore[misc]
            m[2 * n + t, 2 * n + t] = j3
            couple(n + i, 2 * n + t, k3, d3)
        if n == 2:
            m[2, 3] = m[3, 2] = jcop
        if np.any(np.linalg.eigvalsh(m) <= 0):
            raise ValueError("twomass: the inertia matrix is not positive definite")
        self.m, self.c, self.k = m, c, k
        self.fc = np.array([a.fc_motor for a in axes] + [a.fc_arm for a in axes]
                           + [0.0] * len(tools))
        self.lag = lag_s
        self.dz = 2 * nd + (n if lag_s > 0 else 0)
        self.nw = 2 * n + 1
        e = np.zeros((nd, n))
        e[:n] = np.eye(n)
        # the force as a map of the state and the input (without the friction constants)
        self.fz = np.hstack((-k, -c) + ((e,) if lag_s > 0 else ()))
        self.fw = np.hstack((np.zeros((nd, n)) if lag_s > 0 else e, e, np.zeros((nd, 1))))
        self._modes: dict[tuple[frozenset[int], tuple[int, ...]], _Mode] = {}

    def mode(self, stuck: frozenset[int], signs: tuple[int, ...]) -> _Mode:
        key = (stuck, signs)
        if key not in self._modes:
            self._modes[key] = _Mode(self, stuck, signs)
        return self._modes[key]


def _expm(m: np.ndarray) -> np.ndarray:
    """e^M by scaling and squaring a Taylor series (‖M/2^s‖ ≤ 1/4, 14 terms: below double
    precision); small matrices, many calls: cheaper here than a Padé with its checks."""
    norm = float(np.max(np.sum(np.abs(m), axis=0)))
    s = max(0, int(math.ceil(math.log2(norm / 0.25)))) if norm > 0.25 else 0
    x = m / 2.0 ** s
    term = np.eye(m.shape[0])
    out = term.copy()
    for i in range(1, 15):
        term = term @ x / i
        out = out + term
    for _ in range(s):
        out = out @ out
    return out


class _Mode:
    def __init__(self, mech: _Mechanics, stuck: frozenset[int], signs: tuple[int, ...]) -> None:
        nd, n = mech.dof, mech.n
        self.stuck = stuck
        self.signs = signs
        free = [i for i in range(nd) if i not in stuck]
        st = sorted(stuck)
        self.stuck_order = st
        p = np.zeros((nd, nd))
        p[np.ix_(free, free)] = np.linalg.inv(mech.m[np.ix_(free, free)])
        fw = mech.fw.copy()
        sliding = [i for i in range(nd) if mech.fc[i] > 0 and i not in stuck]
        for i in sliding:
            fw[i, -1] -= mech.fc[i] * signs[i]
        a = np.zeros((mech.dz, mech.dz))
        b = np.zeros((mech.dz, mech.nw))
        a[:nd, nd:2 * nd] = np.eye(nd)
        a[nd:2 * nd] = p @ mech.fz
        b[nd:2 * nd] = p @ fw
        if mech.lag > 0:
            a[2 * nd:, 2 * nd:] = -np.eye(n) / mech.lag
            b[2 * nd:, :n] = np.eye(n) / mech.lag
        self.a, self.b = a, b
        self.h = mech.h
        self.phi, self.gam = self._exact(mech.h)
        # the force that holds each stuck body (acting on it): M_S· a − F_S
        hold = mech.m[st] @ p - np.eye(nd)[st]
        self.lz, self.lw = hold @ mech.fz, hold @ fw
        self.sliding = sliding
        self.vel = nd  # index of the first velocity in the state

    def _exact(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        dz, nw = self.b.shape
        big = np.zeros((dz + nw, dz + nw))
        big[:dz, :dz] = self.a * t
        big[:dz, dz:] = self.b * t
        e = _expm(big)
        return e[:dz, :dz], e[:dz, dz:]

    def advance(self, z: np.ndarray, w: np.ndarray, t: float) -> np.ndarray:
        phi, gam = (self.phi, self.gam) if t == self.h else self._exact(t)
        return phi @ z + gam @ w

    def holding(self, z: np.ndarray, w: np.ndarray) -> np.ndarray:
        return self.lz @ z + self.lw @ w


def _step(mech: _Mechanics, state: dict[str, Any], z: np.ndarray, w: np.ndarray) -> np.ndarray:
    """One controller tick from z under input w, switching modes at friction events."""
    left = mech.h
    for _ in range(64):
        mode: _Mode = mech.mode(state["stuck"], state["signs"])
        z1 = mode.advance(z, w, left)
        event = _first_event(mech, mode, z, z1, w, left)
        if event is None:
            return z1
        t_ev, i, kind = event
        z = mode.advance(z, w, t_ev) if t_ev > 0 else z
        left -= t_ev
        _switch(mech, state, z, w, i, kind)
        if left <= 1e-15:
            return z
    raise RuntimeError("twomass: more than 64 friction events in one tick")


def _events(mech: _Mechanics, mode: _Mode, z: np.ndarray, w: np.ndarray
            ) -> dict[tuple[int, str], float]:
    """Event functions at z (an event when > 0): a sliding body's velocity against its
    direction, a stuck body's holding force beyond its friction."""
    out = {}
    for i in mode.sliding:
        out[(i, "reverse")] = -mode.signs[i] * z[mode.vel + i]
    if mode.stuck_order:
        lam = mode.holding(z, w)
        for j, i in enumerate(mode.stuck_order):
            if mech.fc[i] > 0:
                out[(i, "break")] = abs(lam[j]) - mech.fc[i]
    return out


def _first_event(mech: _Mechanics, mode: _Mode, z0: np.ndarray, z1: np.ndarray,
                 w: np.ndarray, left: float) -> tuple[float, int, str] | None:
    g0, g1 = _events(mech, mode, z0, w), _events(mech, mode, z1, w)
    hits = [key for key, v in g1.items() if v > 0 and g0[key] <= 0]
    if not hits:
        return None
    best: tuple[float, int, str] | None = None
    for key in hits:
        # regula falsi (Illinois) on the exact solution: g(0) ≤ 0 < g(left)
        ta, tb, ga, gb = 0.0, left, g0[key], g1[key]
        side = 0
        for _ in range(60):
            tc = tb - gb * (tb - ta) / (gb - ga) if gb != ga else 0.5 * (ta + tb)
            tc = min(max(tc, ta + 1e-3 * (tb - ta)), tb - 1e-3 * (tb - ta))
            gc = _events(mech, mode, mode.advance(z0, w, tc), w)[key]
            if gc > 0:
                tb, gb = tc, gc
                if side == 1:
                    ga *= 0.5
                side = 1
            else:
                ta, ga = tc, gc
                if side == -1:
                    gb *= 0.5
                side = -1
            if tb - ta < 1e-12:
                break
        if best is None or tb < best[0]:
            best = (tb, key[0], key[1])
    return best


def _switch(mech: _Mechanics, state: dict[str, Any], z: np.ndarray, w: np.ndarray, i: int,
            kind: str) -> None:
    """At a reversal the body stops and sticks unless its holding force exceeds its
    friction; at a breakaway it slides the way it is pushed (against the holding force)."""
    signs = list(state["signs"])
    if kind == "reverse":
        z[mech.dof + i] = 0.0
        trial = mech.mode(state["stuck"] | {i}, state["signs"])
        lam = trial.holding(z, w)[trial.stuck_order.index(i)]
        if abs(lam) <= mech.fc[i]:
            state["stuck"] = state["stuck"] | {i}
            return
        signs[i] = -int(np.sign(lam))
    else:
        mode = mech.mode(state["stuck"], state["signs"])
        lam = mode.holding(z, w)[mode.stuck_order.index(i)]
        state["stuck"] = state["stuck"] - {i}
        signs[i] = -int(np.sign(lam))
    state["signs"] = tuple(signs)


# ----------------------------------------------------------------------------- excitation


def _smooth(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return 0.5 - 0.5 * np.cos(np.pi * x)


def _reference(n: int, exc: SteppedSine, h: float
               ) -> tuple[np.ndarray, np.ndarray, list[dict[str, Any]]]:
    """Reference positions relative to the pose (ticks × n), velocities, and the schedule."""
    if not 0 < exc.f_min_hz < exc.f_max_hz or exc.steps < 2:
        raise ValueError("twomass: need 0 < f_min < f_max and at least 2 steps")
    freqs = np.geomspace(exc.f_min_hz, exc.f_max_hz, exc.steps)
    order = [(ax, f) for ax in range(n) for f in freqs]
    plan, t = [], 0.0
    for ax, f in order:
        settle = max(exc.settle_s, exc.settle_periods / f)
        measure = math.ceil(max(exc.measure_periods, exc.measure_s * f)) / f
        plan.append((ax, float(f), t, t + settle, t + settle + measure))
        t += settle + measure + exc.ramp_s
    total = t + 0.5
    tt = np.arange(0.0, total, h)
    r = np.zeros((tt.size, n))
    offset = np.zeros(n)
    schedule: list[dict[str, Any]] = []
    direction = 1.0
    for ax, f, t0, t_meas, t_end in plan:
        t_next = t_end + exc.ramp_s
        sel = (tt >= t0) & (tt < t_next)
        loc = tt[sel] - t0
        env = _smooth(loc / exc.ramp_s) * _smooth((t_end - t0 + exc.ramp_s - loc) / exc.ramp_s)
        w = 2 * math.pi * f
        amp = min(exc.velocity / w, exc.accel / (w * w))
        drift = direction * exc.drift
        vel = drift * env
        pos = np.concatenate(([0.0], np.cumsum(0.5 * (vel[1:] + vel[:-1]) * h)))
        meas = (loc >= t_meas - t0) & (loc <= t_end - t0)
        centre = float(pos[meas].mean())
        for j in range(n):
            moved = pos if exc.drift > 0 else np.zeros_like(pos)
            shift = offset[j] + (-centre * (exc.drift > 0) - offset[j]) * _smooth(
                loc / exc.ramp_s)
            r[sel, j] = shift + moved + (amp * env * np.sin(w * loc) if j == ax else 0.0)
            offset[j] = float(moved[-1] - centre * (exc.drift > 0))
            r[tt >= t_next, j] = offset[j]
        step: dict[str, Any] = {"joint": ax + 1, "f_hz": f, "amplitude_rad": amp,
                                "drift_rad_s": drift, "t_start": t0, "t_measure": t_meas,
                                "t_end": t_end, "t_next": t_next}
        if n > 1:
            step.update(joints=list(range(1, n + 1)),
                        amplitudes_rad=[amp if j == ax else 0.0 for j in range(n)],
                        drifts_rad_s=[drift] * n)
        schedule.append(step)
        direction = -direction
    rd = np.gradient(r, h, axis=0)
    return r, rd, schedule


# ----------------------------------------------------------------------------- the run


def _gains(loop: Loop, inertia: float) -> dict[str, float]:
    wp = 2 * math.pi * loop.bandwidth_hz
    wv = 2 * math.pi * loop.velocity_bandwidth_hz
    if loop.kind == "pd":
        return {"kp": inertia * wp * wp, "kd": 2 * 0.7 * inertia * wp}
    if loop.kind in ("pi_velocity", "cascade"):
        return {"kx": wp, "kv": inertia * wv, "ki": inertia * wv * wv / 4}
    raise ValueError(f"twomass: unknown loop kind {loop.kind!r} (pd, pi_velocity, cascade)")


def simulate(axes: Sequence[Axis], loop: Loop, excitation: SteppedSine, *,
             log_rate_hz: float = 2000.0, noise: Noise | None = None, jcop: float = 0.0,
             pose: Sequence[float] | None = None, seed: int = 0) -> Run:
    """Run the stepped sines through the closed loop; log every ``rate_hz/log_rate_hz``-th
    tick: the measured motor position and the torque acting from that tick on (with the
    torque lag, the lagged torque at the tick), plus the log's torque noise."""
    noise = noise or Noise()
    n = len(axes)
    if n not in (1, 2):
        raise ValueError("twomass: one axis or a pair")
    every = loop.rate_hz / log_rate_hz
    if abs(every - round(every)) > 1e-9 or every < 1:
        raise ValueError("twomass: the controller rate must be a multiple of the log rate")
    every = int(round(every))
    h = 1.0 / loop.rate_hz
    pose_a = np.zeros(n) if pose is None else np.asarray(pose, dtype=float)
    r, rd, schedule = _reference(n, excitation, h)
    ticks = r.shape[0] - r.shape[0] % every
    rng = np.random.default_rng(seed)
    dist = rng.normal(scale=noise.disturbance, size=(ticks, n)) if noise.disturbance else \
        np.zeros((ticks, n))
    mech = _Mechanics(axes, jcop, loop.torque_lag_s if loop.kind == "cascade" else 0.0, h)
    gains = [_gains(loop, a.jm + a.ja) for a in axes]
    alpha = 1.0 - math.exp(-2 * math.pi * loop.velocity_filter_hz * h)
    z = np.zeros(mech.dz)
    state: dict[str, Any] = {"stuck": frozenset(i for i in range(mech.dof) if mech.fc[i] > 0),
                             "signs": (1,) * mech.dof}
    y_prev = np.zeros(n)
    vf = np.zeros(n)
    integ = np.zeros(n)
    queue = [np.zeros(n)] * loop.delay_ticks
    q_log = np.empty((ticks // every, n))
    tau_log = np.empty((ticks // every, n))
    w = np.zeros(mech.nw)
    w[-1] = 1.0
    step_q = noise.q_step
    for k in range(ticks):
        qm = z[:n]
        y = np.round(qm / step_q) * step_q if step_q > 0 else qm.copy()
        vf += alpha * ((y - y_prev) / h - vf) if k else 0.0
        y_prev = y
        u = np.empty(n)
        for j, g in enumerate(gains):
            if loop.kind == "pd":
                u[j] = g["kp"] * (r[k, j] - y[j]) + g["kd"] * (rd[k, j] - vf[j])
            else:
                wref = rd[k, j] + (g["kx"] * (r[k, j] - y[j]) if loop.kind == "cascade" else 0.0)
                e = wref - vf[j]
                integ[j] += g["ki"] * e * h
                u[j] = g["kv"] * e + integ[j]
        if queue:
            queue.append(u)
            u = queue.pop(0)
        if k % every == 0:
            q_log[k // every] = y + pose_a
            tau_log[k // every] = z[2 * mech.dof:] if mech.lag > 0 else u
        w[:n] = u
        w[n:2 * n] = dist[k]
        z = _step(mech, state, z, w)
    if noise.tau:
        tau_log = tau_log + rng.normal(scale=noise.tau, size=tau_log.shape)
    t = np.arange(q_log.shape[0]) / log_rate_hz
    truth = {i + 1: {"jm": a.jm, "ja": a.ja, "k": a.k, "d": a.d, "ba": a.ba, "kg": a.kg,
                     "fc_arm": a.fc_arm, "bm": a.bm, "fc_motor": a.fc_motor, "jcop": jcop,
                     "third": a.third}
             for i, a in enumerate(axes)}
    return Run(t, q_log, tau_log, schedule, truth, tuple(map(float, pose_a)),
               {"loop": loop.kind, "rate_hz": loop.rate_hz, "log_rate_hz": log_rate_hz})


# ----------------------------------------------------------------------------- robot


def robot_yaml(name: str, axes: Sequence[Axis], pose: Sequence[float]) -> str:
    """An MDH robot description whose gravity stiffness at ``pose`` is each axis' ``kg``
    (what the analysis reads from a robot model): one axis horizontal with a point-like mass
    m at l = 0.3 m (g(q) = m·9.81·l·cos q, ∂g/∂q = −m·9.81·l·sin q); vertical axes (no
    gravity torque) where kg = 0. A pair has parallel vertical axes."""
    rows = []
    for i, a in enumerate(axes):
        horizontal = a.kg != 0
        if horizontal:
            if len(axes) > 1:
                raise ValueError("twomass: gravity stiffness on a pair is not described")
            s = -math.sin(pose[i])
            if abs(s) < 0.1 or a.kg / s < 0:
                raise ValueError("twomass: kg needs a pose where gravity restores (sin q < 0)")
            mass = a.kg / (9.81 * 0.3 * s)
            com = "[0.3, 0, 0]"
        else:
            mass, com = 2.0, "[0.1, 0, 0]"
        rows.append(
            f"  - {{name: j{i + 1}, alpha: {90 if horizontal else 0}, a: {0.4 * i}, theta: 0, "
            f"d: 0, limits: {{q: [-175, 175], qd: 200, qdd: 2000, tau: 5000}},\n"
            f"     inertial: {{m: {mass:.10g}, com: {com}, I: [0.001, 0, 0.001, 0, 0, 0.001]}}}}")
    return f"name: {name}\ngravity: [0, 0, -9.81]\njoints:\n" + "\n".join(rows) + "\n"
