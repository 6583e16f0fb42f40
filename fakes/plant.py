"""A simulated robot whose truth is known: rigid body plus physical effects, noise, encoders.

Effects are written as physics with physical parameters (not as the model's regressor
columns), so a bug in the model cannot hide behind the same bug in the plant.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from robid_link.exceptions import ConfigError
from robid_link.fakes.plant_kernel import COMPILED_EFFECTS, integrate, model_params
from robid_link.ident.model.effects import moving_sign
from robid_link.ident.model.robot import Robot
from robid_link.ident.model.robot_check import inertia_problem
from robid_link.kinds import MAX_RATE_HZ, MIN_RATE_HZ
from robid_link.yamlio import check_keys, read_yaml_mapping

__all__ = ["Truth", "Plant", "perturbed_inertials", "load_truth", "EFFECT_PARAMS"]

#: physical parameters of each plant effect (required, optional with defaults)
EFFECT_PARAMS: dict[str, tuple[tuple[str, ...], dict[str, float]]] = {
    "viscous": (("fv",), {}),
    "coulomb": (("fc",), {}),
    "coulomb_asymmetric": (("fc_pos", "fc_neg"), {}),
    "offset": (("b",), {}),
    "friction_power": (("fc", "fv", "alpha"), {"b": 0.0}),
    "stribeck": (("fs", "fc", "vs"), {"shape": 2.0, "fv": 0.0}),
    "armature": (("ia",), {}),
    "spring": (("k", "a", "b", "l0"), {"phi": 0.0}),
    "ripple": (("amplitude", "period"), {"phase": 0.0}),
    "friction_drift": (("fc", "fv", "change", "tau_s"), {}),
    "load_friction": (("mu",), {}),
    "delay": (("seconds",), {}),
    "payload": (("mass",), {"com": 0.0}),
    # two-mass joint: motor inertia jm (joint units) behind spring k, damper d; optionally a
    # third mass j2 hung on the arm by k2, d2 (a second resonance: three-mass check)
    "elasticity": (("k", "d", "jm"), {"j2": 0.0, "k2": 0.0, "d2": 0.0}),
}
GLOBAL_EFFECTS = {"delay", "payload"}
#: parameters that must be > 0 (a division or an exponent) or ≥ 0 (a physical magnitude)
_POSITIVE = {"period", "vs", "shape", "tau_s", "alpha", "jm"}
_NON_NEGATIVE = {"fv", "fc", "fs", "fc_pos", "fc_neg", "ia", "mu", "mass", "k", "d", "a"}
CLOSED_LOOP_ONLY = {"elasticity"}


@dataclass(frozen=True)
class Truth:
    """Physical truth of a simulated robot."""

    inertials: np.ndarray  # standard parameters (10 n), joint frames
    effects: tuple[dict[str, Any], ...] = ()  # {"name", "joint" (from 1), params…}
    noise_tau: float | Sequence[float] = 0.0  # N·m, std of white torque noise (per joint)
    q_resolution: float = 0.0  # rad per encoder count (0 = none)
    rate_hz: float = 1000.0
    mode: str = "inverse"  # inverse | closed_loop
    side: str = "joint"  # joint | motor (log through the robot's transmission)
    controller: dict[str, Any] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)


def perturbed_inertials(robot: Robot, seed: int, spread: float = 0.2) -> np.ndarray:
    """The nominal inertials with mass, COM and inertia perturbed (physically consistent)."""
    if robot.nominal is None:
        raise ConfigError(f"{robot.source}: no nominal inertials to perturb")
    rng = np.random.default_rng(seed)
    out = []
    for j in range(robot.n):
        inert = pin.Inertia.FromDynamicParameters(robot.nominal[10 * j: 10 * j + 10])
        m = inert.mass * (1.0 + spread * rng.uniform(-1, 1))
        c = np.array(inert.lever) + spread * 0.1 * rng.uniform(-1, 1, 3)
        ic = np.array(inert.inertia) * (1.0 + spread * rng.uniform(-1, 1))
        out.append(pin.Inertia(m, c, ic).toDynamicParameters())
    return np.concatenate(out)


# ----------------------------------------------------------------------------- truth file


def _check_effects(entries: Any, n: int, where: str) -> tuple[dict[str, Any], ...]:
    if not isinstance(entries, list):
        raise ConfigError(f"{where}: expected a list")
    out = []
    for i, e in enumerate(entries):
        w = f"{where}[{i}]"
        check_keys(e, w, required=("name",), optional=e.keys() if isinstance(e, dict) else ())
        name = e["name"]
        if not isinstance(name, str) or name not in EFFECT_PARAMS:
            raise ConfigError(f"{w}: unknown plant effect {_short(name)} "
                              f"(known: {', '.join(sorted(EFFECT_PARAMS))})")
        req, opt = EFFECT_PARAMS[name]
        check_keys(e, f"{w} ({name})", required=("name", *req), optional=("joint", *opt))
        joint = e.get("joint")
        if joint is not None:
            if name in GLOBAL_EFFECTS:
                raise ConfigError(f"{w}: '{name}' is global and takes no joint")
            if isinstance(joint, bool) or not isinstance(joint, int) or not 1 <= joint <= n:
                raise ConfigError(f"{w}.joint: expected a joint number in 1..{n}")
        for key in (*req, *opt):
            v = e.get(key, opt.get(key))
            if key == "com" and isinstance(v, list):
                if len(v) != 3 or not all(_finite(x) for x in v):
                    raise ConfigError(f"{w}.com: expected 3 finite numbers")
                continue
            if not _finite(v):
                raise ConfigError(f"{w}.{key}: expected a finite number, got {_short(v)}")
            if key in _POSITIVE and v <= 0 or key in _NON_NEGATIVE and v < 0:
                sign = "positive" if key in _POSITIVE else "non-negative"
                raise ConfigError(f"{w}.{key}: expected a {sign} number, got {v!r}")
            if key == "seconds" and abs(v) > 10:
                raise ConfigError(f"{w}.seconds: expected a delay within ±10 s, got {v!r}")
        out.append({**opt, **e})
    return tuple(out)


def _finite(v: Any) -> bool:
    try:
        return not isinstance(v, bool) and isinstance(v, int | float) and math.isfinite(v)
    except OverflowError:  # an integer beyond float range
        return False


def _short(x: Any) -> str:
    text = repr(x)
    return text if len(text) <= 40 else text[:37] + "..."


def _number(v: Any, where: str, lo: float, hi: float, *, integer: bool = False) -> float:
    kinds = int if integer else int | float
    if not (_finite(v) and isinstance(v, kinds) and lo <= v <= hi):
        kind = "a whole number" if integer else "a number"
        raise ConfigError(f"{where}: expected {kind} in [{lo:g}, {hi:g}], got {_short(v)}")
    return v


def _inertials(raw: Any, robot: Robot) -> np.ndarray:
    """``inertials``: n rows of 10 standard parameters, each link physically consistent."""
    n = robot.n
    if (not isinstance(raw, list) or len(raw) != n
            or not all(isinstance(r, list) and len(r) == 10 for r in raw)):
        raise ConfigError(f"inertials: expected {n} rows of 10 standard parameters")
    for j, row in enumerate(raw):
        for k, v in enumerate(row):
            if not _finite(v):
                raise ConfigError(f"inertials[{j}][{k}]: expected a finite number, got "
                                  f"{_short(v)}")
    arr = np.array(raw, dtype=float)
    for j, row in enumerate(arr):
        problem = _link_problem(row)
        if problem:
            raise ConfigError(f"inertials[{j}] (link {j + 1}): {problem}")
    return arr.reshape(-1)


def _link_problem(row: np.ndarray) -> str | None:
    m, first = row[0], row[1:4]
    if m < 0:
        return f"mass {m:g} is negative"
    if m == 0:
        if np.any(first != 0):
            return "a massless link has no first moment (mx, my, mz must be 0)"
        i_c = np.array([[row[4], row[5], row[7]], [row[5], row[6], row[8]],
                        [row[7], row[8], row[9]]])
    else:
        i_c = np.array(pin.Inertia.FromDynamicParameters(row).inertia)
    return inertia_problem(i_c)


def load_truth(path: str | Path, robot: Robot) -> Truth:
    """Read a truth file; every error names the key path."""
    p = Path(path)
    doc = read_yaml_mapping(p, "truth file")
    check_keys(doc, str(p), optional=("robot", "inertials", "perturb", "effects", "noise",
                                      "rate_hz", "mode", "side", "controller"))
    try:
        return _truth_from_doc(doc, robot)
    except ConfigError as err:
        raise ConfigError(f"{p}: {err}") from err


def _or_empty(doc: dict[str, Any], key: str, empty: Any) -> Any:
    """``doc[key]``, ``empty`` when absent or null: an empty value of the wrong type (``[]``
    where a mapping belongs) stays wrong and is refused by the check that follows."""
    value = doc.get(key)
    return empty if value is None else value


def _truth_from_doc(doc: dict[str, Any], robot: Robot) -> Truth:
    n = robot.n
    if "robot" in doc and str(doc["robot"]) != robot.name:
        raise ConfigError(f"robot: this truth is for {doc['robot']!r}, not {robot.name!r}")
    if "inertials" in doc:
        inertials = _inertials(doc["inertials"], robot)
    elif "perturb" in doc:
        pert = check_keys(_or_empty(doc, "perturb", {}), "perturb", optional=("seed", "spread"))
        inertials = perturbed_inertials(
            robot, int(_number(pert.get("seed", 0), "perturb.seed", 0, 2**32 - 1, integer=True)),
            float(_number(pert.get("spread", 0.2), "perturb.spread", 0.0, 0.9)))
    elif robot.nominal is not None:
        inertials = robot.nominal.copy()
    else:
        raise ConfigError("inertials: missing (and the robot has no nominal inertials)")
    noise = check_keys(_or_empty(doc, "noise", {}), "noise", optional=("tau", "q_resolution"))
    tau_noise = noise.get("tau", 0.0)
    if isinstance(tau_noise, list):
        if len(tau_noise) != n:
            raise ConfigError(f"noise.tau: expected one number or {n} (one per joint)")
        for j, v in enumerate(tau_noise):
            _number(v, f"noise.tau[{j}]", 0.0, 1e6)
    else:
        _number(tau_noise, "noise.tau", 0.0, 1e6)
    _number(noise.get("q_resolution", 0.0), "noise.q_resolution", 0.0, 1.0)
    if not isinstance(_or_empty(doc, "controller", {}), dict):
        raise ConfigError("controller: expected a mapping")
    mode = doc.get("mode", "inverse")
    if mode not in ("inverse", "closed_loop"):
        raise ConfigError(f"mode: expected inverse or closed_loop, got {mode!r}")
    side = doc.get("side", "joint")
    if side not in ("joint", "motor"):
        raise ConfigError(f"side: expected joint or motor, got {side!r}")
    effects = _check_effects(_or_empty(doc, "effects", []), n, "effects")
    if mode == "inverse" and any(e["name"] in CLOSED_LOOP_ONLY for e in effects):
        raise ConfigError("effects: 'elasticity' needs mode: closed_loop")
    rate = doc.get("rate_hz", 1000.0)
    if not _finite(rate) or not MIN_RATE_HZ <= rate <= MAX_RATE_HZ:
        raise ConfigError(f"rate_hz: expected a sampling rate in [{MIN_RATE_HZ:g}, "
                          f"{MAX_RATE_HZ:g}] Hz, got {_short(rate)}")
    return Truth(inertials, effects, noise.get("tau", 0.0), float(noise.get("q_resolution", 0.0)),
                 float(rate), mode, side, dict(doc.get("controller") or {}))


# ----------------------------------------------------------------------------- effects

EffectFn = Callable[[dict[str, Any], "Signals", int], np.ndarray]


@dataclass
class Signals:
    """What an effect may depend on, for all samples."""

    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    tau_rigid: np.ndarray


def _viscous(e, s, j):
    return e["fv"] * s.qd[:, j]


# Coulomb-type friction switches with moving_sign: a held pose commanded through a spline has
# velocities of rounding noise (up to ~1e-6 rad/s); the plant treats such a joint as resting,
# as the model does (friction static, none predicted)
def _coulomb(e, s, j):
    return e["fc"] * moving_sign(s.qd[:, j])


def _coulomb_asym(e, s, j):
    sgn = moving_sign(s.qd[:, j])
    return np.where(sgn > 0, e["fc_pos"], np.where(sgn < 0, -e["fc_neg"], 0.0))


def _offset(e, s, j):
    return np.full(s.t.shape, float(e["b"]))


def _friction_power(e, s, j):
    v = s.qd[:, j]
    return (e["fc"] + e["fv"] * np.abs(v) ** e["alpha"]) * moving_sign(v) + e["b"]


def _stribeck(e, s, j):
    """Static friction fs falling to Coulomb fc over the Stribeck velocity vs."""
    v = s.qd[:, j]
    decay = np.exp(-np.abs(v / e["vs"]) ** e["shape"])
    return (e["fc"] + (e["fs"] - e["fc"]) * decay) * moving_sign(v) + e["fv"] * v


def _armature(e, s, j):
    """Rotor inertia seen on the joint (J_m·r²)."""
    return e["ia"] * s.qdd[:, j]


def spring_torque(k: float, a: float, b: float, l0: float, phi: float, q: np.ndarray
                  ) -> np.ndarray:
    """Gravity-balancing spring between a base point at distance b and a link point at
    distance a from the axis: l = √(a² + b² − 2ab·cos(q + φ)), τ = −k (l − l0)·ab·sin(q + φ)/l."""
    psi = q + phi
    length = np.sqrt(a * a + b * b - 2 * a * b * np.cos(psi))
    return -k * (length - l0) * a * b * np.sin(psi) / np.maximum(length, 1e-9)


def _spring(e, s, j):
    return spring_torque(e["k"], e["a"], e["b"], e["l0"], e["phi"], s.q[:, j])


def _ripple(e, s, j):
    return e["amplitude"] * np.sin(2 * np.pi * s.q[:, j] / e["period"] + e["phase"])


def _friction_drift(e, s, j):
    """A joint warming up: friction starts (1 + change)× higher and relaxes with tau_s."""
    scale = 1.0 + e["change"] * np.exp(-(s.t - s.t[0]) / e["tau_s"])
    v = s.qd[:, j]
    return scale * (e["fc"] * moving_sign(v) + e["fv"] * v)


def _load_friction(e, s, j):
    """Gear friction growing with the transmitted load torque."""
    return e["mu"] * np.abs(s.tau_rigid[:, j]) * moving_sign(s.qd[:, j])


EFFECTS: dict[str, EffectFn] = {
    "viscous": _viscous, "coulomb": _coulomb, "coulomb_asymmetric": _coulomb_asym,
    "offset": _offset, "friction_power": _friction_power, "stribeck": _stribeck,
    "armature": _armature, "spring": _spring, "ripple": _ripple,
    "friction_drift": _friction_drift, "load_friction": _load_friction,
}
#: effects the closed-loop integrator treats as (set-valued) Coulomb friction
_COULOMB_LIKE = {"coulomb", "coulomb_asymmetric", "stribeck", "friction_power",
                 "friction_drift", "load_friction"}


# ----------------------------------------------------------------------------- plant


def _with_inertials(model: pin.Model, params: np.ndarray) -> pin.Model:
    """A copy of the model whose links carry these standard parameters (10 per link)."""
    out = model.copy()
    for j in range(len(params) // 10):
        out.inertias[j + 1] = pin.Inertia.FromDynamicParameters(params[10 * j: 10 * j + 10])
    return out


class Plant:
    """The simulated robot: inverse dynamics (positions follow the command exactly) or
    closed loop (forward dynamics under a computed-torque controller)."""

    def __init__(self, robot: Robot, truth: Truth) -> None:
        self.robot = robot
        defaults = [{**EFFECT_PARAMS.get(e["name"], ((), {}))[1], **e} for e in truth.effects]
        self.truth = truth = replace(truth, effects=tuple(defaults))
        self.model = _with_inertials(robot.model, truth.inertials)
        for e in truth.effects:
            if e["name"] == "payload":  # a point mass at the flange (last joint frame)
                com = e["com"] if isinstance(e["com"], list) else [0.0, 0.0, float(e["com"])]
                self.model.inertias[robot.n] += pin.Inertia(
                    e["mass"], np.asarray(com, dtype=float), np.zeros((3, 3)))
        self.data = self.model.createData()

    # -- helpers
    def _per_joint(self) -> list[tuple[dict[str, Any], int]]:
        out = []
        for e in self.truth.effects:
            if e["name"] in GLOBAL_EFFECTS or e["name"] in CLOSED_LOOP_ONLY:
                continue
            joints = [e["joint"] - 1] if e.get("joint") else range(self.robot.n)
            out += [(e, j) for j in joints]
        return out

    def _delay(self) -> float:
        return sum(e["seconds"] for e in self.truth.effects if e["name"] == "delay")

    def rigid_torque(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
        pq = self.robot.pin_q(q)
        out = np.empty_like(qd)
        for k in range(q.shape[0]):
            out[k] = pin.rnea(self.model, self.data, pq[k], qd[k], qdd[k])
        return out

    def effect_torque(self, t: np.ndarray, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray,
                      tau_rigid: np.ndarray | None = None) -> np.ndarray:
        if tau_rigid is None:
            tau_rigid = self.rigid_torque(q, qd, qdd)
        sig = Signals(t, q, qd, qdd, tau_rigid)
        tau = np.zeros_like(qd)
        for e, j in self._per_joint():
            tau[:, j] += EFFECTS[e["name"]](e, sig, j)
        return tau

    def _finish(self, t: np.ndarray, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray,
                tau_true: np.ndarray, seed: int) -> dict[str, np.ndarray]:
        rng = np.random.default_rng(seed)
        delay = self._delay()
        if delay:  # the torque log lags the positions: τ_log(t) = τ(t − delay)
            tau_true = np.stack([np.interp(t - delay, t, tau_true[:, j])
                                 for j in range(tau_true.shape[1])], axis=1)
        noise = np.broadcast_to(np.asarray(self.truth.noise_tau, dtype=float), (self.robot.n,))
        tau = tau_true + rng.normal(size=tau_true.shape) * noise
        res = self.truth.q_resolution
        q_meas = np.round(q / res) * res if res > 0 else q.copy()
        out = {"t": t, "q": q_meas, "qd": qd, "qdd": qdd, "tau": tau, "tau_true": tau_true}
        if self.truth.side == "motor":
            out["q"], out["tau"] = self.robot.to_motor_side(out["q"], out["tau"])
            t_mat = self.robot.transmission
            assert t_mat is not None  # to_motor_side refused a robot without one
            out["qd"], out["qdd"] = qd @ t_mat.T, qdd @ t_mat.T
        else:  # the encoders read the robot's offsets (motor side: in to_motor_side)
            out["q"] = self.robot.add_offsets(out["q"])
        return out

    # -- inverse dynamics
    def run(self, t: np.ndarray, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray,
            seed: int = 0, feedforward: Any = None) -> dict[str, np.ndarray]:
        """Log of a commanded motion: t, quantized q, noisy τ (and the noise-free τ).
        ``feedforward``: the controller's uploaded parameter set (closed loop only)."""
        if self.truth.mode == "closed_loop":
            return self.run_closed_loop(t, q, qd, qdd, seed, feedforward)
        tau_rigid = self.rigid_torque(q, qd, qdd)
        tau_true = tau_rigid + self.effect_torque(t, q, qd, qdd, tau_rigid)
        return self._finish(t, q, qd, qdd, tau_true, seed)

    # -- closed loop
    def run_closed_loop(self, t: np.ndarray, q_ref: np.ndarray, qd_ref: np.ndarray,
                        qdd_ref: np.ndarray, seed: int = 0, feedforward: Any = None
                        ) -> dict[str, np.ndarray]:
        """Forward dynamics tracking the reference with a computed-torque PID on the a-priori
        model (what a real controller has), integrated at ≥ 1 kHz (``controller.rate_hz``).
        ``feedforward`` (a ``paramset.Feedforward``: an uploaded parameter set) replaces the
        a-priori inertials and adds the identified joint friction to the command.

        Coulomb-like friction is handled by a time-stepping stick-slip step (no smoothing):
        the friction impulse of each step is solved with the full M⁻¹ on an active set, a
        joint whose velocity would cross zero sticks while its static bound holds, so the
        integration stays stable and non-stiff at the control rate.
        """
        ctrl = self.truth.controller
        n = self.robot.n
        wn = float(ctrl.get("bandwidth_hz", 8.0)) * 2 * math.pi
        kp, kd, ki = 3 * wn * wn, 3 * wn, wn**3  # PID with a triple pole at the bandwidth
        nominal = (self.robot.model.copy() if self.robot.nominal is None
                   else _with_inertials(self.robot.model, self.robot.nominal))
        ndata = nominal.createData()
        theta = None if feedforward is None else feedforward.inertials
        integral = np.zeros(n)

        def command(k: int, h: float, q_meas: np.ndarray, qd_meas: np.ndarray) -> np.ndarray:
            err = q_ref[k] - q_meas
            integral[:] += h * err
            acc = qdd_ref[k] + kp * err + kd * (qd_ref[k] - qd_meas) + ki * integral
            pq = self.robot.pin_q(q_meas)
            if theta is None:
                tau = np.array(pin.rnea(nominal, ndata, pq, qd_meas, acc))
            else:  # the uploaded parameters: Y(q, q̇, q̈)·θ, linear, no body needed
                tau = pin.computeJointTorqueRegressor(nominal, ndata, pq, qd_meas, acc) @ theta
            if feedforward is not None:  # friction of the reference motion, as controllers do
                tau += feedforward.extra(q_ref[k], qd_ref[k])
            return tau

        if feedforward is None and self._compiled():
            params = (self.robot.nominal if self.robot.nominal is not None
                      else model_params(self.robot.model))
            ctrl_args = {"kp": kp, "kd": kd, "ki": ki, "q": q_ref, "qd": qd_ref,
                         "qdd": qdd_ref, "nominal": params}
            out = integrate(self.robot, model_params(self.model), t, self._substeps(t),
                            self._compiled_effects(), q_ref[0], qd_ref[0], ctrl_args, None)
        else:
            out = self._integrate(t, command, q_ref[0], qd_ref[0])
        return self._finish(t, *out, seed)

    def run_open_loop(self, t: np.ndarray, tau_motor: np.ndarray, q0: np.ndarray,
                      seed: int = 0) -> dict[str, np.ndarray]:
        """Forward dynamics under given motor torques (no controller)."""
        if self._compiled():
            out = integrate(self.robot, model_params(self.model), t, self._substeps(t),
                            self._compiled_effects(), q0, np.zeros_like(q0), None, tau_motor)
        else:
            out = self._integrate(t, lambda k, h, q, qd: tau_motor[k], q0, np.zeros_like(q0))
        return self._finish(t, *out, seed)

    def _compiled(self) -> bool:
        """Whether the compiled loop simulates every effect of this plant."""
        return all(e["name"] in COMPILED_EFFECTS for e, _ in self._per_joint())

    def _substeps(self, t: np.ndarray) -> int:
        h_log = float(t[1] - t[0])
        rate = max(float(self.truth.controller.get("rate_hz", 1000.0)), 1.0 / h_log)
        return max(1, int(math.ceil(h_log * rate - 1e-9)))

    def _compiled_effects(self) -> dict[str, np.ndarray]:
        """Per joint: viscous and Coulomb coefficients, and the elastic joints' parameters."""
        n = self.robot.n
        out = {key: np.zeros(n) for key in ("fv", "fc", "k", "d", "jm", "j2", "k2", "d2")}
        out["elastic"] = np.zeros(n, dtype=bool)
        for e, j in self._per_joint():
            key = "fv" if e["name"] == "viscous" else "fc"
            out[key][j] += e[key]
        for e in self.truth.effects:
            if e["name"] != "elasticity":
                continue
            for j in ([e["joint"] - 1] if e.get("joint") else range(n)):
                out["elastic"][j] = True
                for key in ("k", "d", "jm", "j2", "k2", "d2"):
                    out[key][j] = e[key]
        return out

    def _integrate(self, t: np.ndarray, command: Callable[..., np.ndarray], q0: np.ndarray,
                   v0: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Semi-implicit Euler at ``controller.rate_hz`` (≥ the log rate); logs, per sample,
        the measured state each logged torque was computed at."""
        n = self.robot.n
        sub = self._substeps(t)
        h = float(t[1] - t[0]) / sub
        # per 0-based joint; an entry without a joint (the last) holds for every joint
        springs = [e for e in self.truth.effects if e["name"] == "elasticity"]
        everywhere = [e for e in springs if not e.get("joint")]
        elastic = ({j: everywhere[-1] for j in range(n)} if everywhere
                   else {e["joint"] - 1: e for e in springs})
        is_elastic = np.array([j in elastic for j in range(n)])
        per_joint = self._per_joint()
        # viscous and Coulomb as vectors (the common case); other effects one by one
        fv = np.zeros(n)
        fc = np.zeros(n)
        for e, j in per_joint:
            if e["name"] == "viscous":
                fv[j] += e["fv"]
            elif e["name"] == "coulomb":
                fc[j] += e["fc"]
        rest = [(e, j) for e, j in per_joint if e["name"] not in ("viscous", "coulomb")]
        smooth = [(e, j) for e, j in rest if e["name"] not in _COULOMB_LIKE]
        sticky = [(e, j) for e, j in rest if e["name"] in _COULOMB_LIKE]
        q, v = np.array(q0, dtype=float), np.array(v0, dtype=float)
        th, thd = q.copy(), v.copy()  # motor side of elastic joints (joint units)
        th2, thd2 = q.copy(), v.copy()  # third masses (elastic joints with j2 > 0)
        # the joint damper's relative velocity, a step ago: the semi-implicit step's velocities
        # lag the positions by h/2, which would make a damper D a spring D·ω²·h/2 too (+0.5 %
        # of K at 35 Hz); extrapolated by half a step it acts at the positions' time
        rel_prev = {j: 0.0 for j in elastic}
        third = {j: e for j, e in elastic.items() if e["j2"] > 0}
        logs = [np.empty((t.size, n)) for _ in range(4)]  # q, qd, qdd, tau
        one = np.zeros(1)

        def bounds(vel: np.ndarray, tau_cmd: np.ndarray, k: int) -> np.ndarray:
            out = fc.copy()
            for e, j in sticky:
                probe = Signals(one + t[k], q[None], vel[None], np.zeros((1, n)), tau_cmd[None])
                out[j] += abs(EFFECTS[e["name"]](e, probe, j)[0])
            return out

        for k in range(t.size):
            for step in range(sub):
                q_meas = np.where(is_elastic, th, q)
                qd_meas = np.where(is_elastic, thd, v)
                tau_cmd = command(k, h, q_meas, qd_meas)
                tau_arm = np.array(tau_cmd, dtype=float)
                for j, e in elastic.items():  # the arm feels the spring, the motor drives it
                    rel = thd[j] - v[j]
                    tau_arm[j] = e["k"] * (th[j] - q[j]) + e["d"] * (1.5 * rel - 0.5 * rel_prev[j])
                    rel_prev[j] = rel
                tau_third = {j: e["k2"] * (q[j] - th2[j]) + e["d2"] * (v[j] - thd2[j])
                             for j, e in third.items()}
                for j, t3 in tau_third.items():
                    tau_arm[j] -= t3
                f_smooth = fv * v
                if smooth:
                    sig = Signals(one + t[k], q[None], v[None], np.zeros((1, n)), tau_cmd[None])
                    for e, j in smooth:
                        f_smooth[j] += EFFECTS[e["name"]](e, sig, j)[0]
                pq = self.robot.pin_q(q)
                bound = bounds(v, tau_cmd, k)
                # fast path: every joint keeps slipping the way it moves
                a = pin.aba(self.model, self.data, pq, v, tau_arm - f_smooth - bound * np.sign(v))
                v_new = v + h * a
                crossing = (bound > 0) & ((v == 0) | (np.sign(v_new) != np.sign(v)))
                if crossing.any():  # exact step: active set with the full M⁻¹
                    a = pin.aba(self.model, self.data, pq, v, tau_arm - f_smooth)
                    v_free = v + h * a
                    minv = pin.computeMinverse(self.model, self.data, pq)
                    v_new = _stick_slip(v_free, bounds(v_free, tau_cmd, k),
                                        np.triu(minv) + np.triu(minv, 1).T, h)
                for j, e in elastic.items():
                    thd[j] += h * (tau_cmd[j] - tau_arm[j]) / e["jm"]
                    th[j] += h * thd[j]
                for j, e in third.items():
                    thd2[j] += h * tau_third[j] / e["j2"]
                    th2[j] += h * thd2[j]
                if step == 0:
                    logs[0][k], logs[1][k] = q_meas, qd_meas
                    logs[2][k] = (v_new - v) / h
                    logs[3][k] = tau_cmd
                v = v_new
                q = q + h * v
        return logs[0], logs[1], logs[2], logs[3]

    def elastic_truth(self, q: np.ndarray) -> dict[int, dict[str, Any]]:
        """Per elastic joint (1-based) at the pose q: jm, k, d, the arm inertia ja = M_jj(q) and
        the coupled inertia ``jcop`` {other elastic joint: M_ij(q)} (the rigid body's mass
        matrix couples the arms of two elastic axes)."""
        m = pin.crba(self.model, self.data, self.robot.pin_q(np.asarray(q)[None])[0])
        m = np.triu(m) + np.triu(m, 1).T
        elastic = {e["joint"] if e.get("joint") else j + 1: e
                   for e in self.truth.effects if e["name"] == "elasticity"
                   for j in ([e["joint"] - 1] if e.get("joint") else range(self.robot.n))}
        return {j: {"jm": float(e["jm"]), "k": float(e["k"]), "d": float(e["d"]),
                    "ja": float(m[j - 1, j - 1]),
                    "jcop": {i: float(m[j - 1, i - 1]) for i in elastic if i != j}}
                for j, e in sorted(elastic.items())}


def _stick_slip(v_free: np.ndarray, bound: np.ndarray, minv: np.ndarray, h: float
                ) -> np.ndarray:
    """Velocity after one step of Coulomb-like friction with bounds F (≥ 0) per joint.

    Slipping joints get −F·sign(v); sticking ones (active set) the generalized force that
    holds them at rest, if within ±F. A few active-set sweeps settle it.
    """
    stick = np.zeros(v_free.size, dtype=bool)
    direction = -np.sign(v_free)
    for _ in range(2 * v_free.size + 2):
        force = np.where(stick, 0.0, direction * bound)
        if stick.any():
            s_idx = np.flatnonzero(stick)
            rhs = -(v_free + h * minv @ force)[s_idx] / h
            force[s_idx] = np.linalg.solve(minv[np.ix_(s_idx, s_idx)], rhs)
        v_new = v_free + h * minv @ force
        # a slipping joint must move against its friction (-direction); one that does not
        # (it would cross zero, or starts at rest) sticks
        crossed = ~stick & (bound > 0) & (np.sign(v_new) != -direction)
        released = stick & (np.abs(force) > bound * (1 + 1e-9))
        if not crossed.any() and not released.any():
            return np.where(stick, 0.0, v_new)
        stick = (stick | crossed) & ~released
        # a released joint slides away from its holding force: friction keeps that force's
        # sign at its bound
        direction = np.where(released, np.sign(force), direction)
    return np.where(stick, 0.0, v_new)
