"""The effect catalog: each physical effect is a block of regressor columns (a model,
``model.effects``, is a list of them).

Effects with nonlinear hyper-parameters declare them with a search range; the estimator
profiles them when the model does not fix them.

Friction-type effects ("sided") act on a joint's bearing or on a motor: ``viscous@j5`` is
friction of joint 5's velocity, ``viscous@m6`` of motor 6's (through the transmission, so a
coupled wrist's motor 6 turns with q̇5 + q̇6, and its torque loads both joints through Tᵀ);
plain ``viscous@5`` acts on the side of the logs (the motors' with ``--motor-side``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from robid_link.ident.model.known import KnownTorque
from robid_link.ident.model.regressor import rigid_regressor
from robid_link.ident.model.robot import Robot, standard_parameter_names

__all__ = ["States", "Effect", "Hyper", "REGISTRY", "register", "SIDES", "V_REST", "moving_sign",
           "KnownTorqueEffect"]

#: the sides a sided effect can name: its joint's bearing or its motor
SIDES = ("joint", "motor")


#: below this speed (rad/s, or m/s) a joint counts as at rest: a held pose's velocity, from
#: filtered positions or a spline through the commanded ones, is rounding noise up to ~1e-6
#: whose sign would switch Coulomb friction at random; a resting joint's friction is static
#: (anywhere in ±Fc), so none is predicted. 1e-6 rad/s is 0.2 degrees per hour.
V_REST = 1e-6


def moving_sign(v: np.ndarray) -> np.ndarray:
    """sign(v) where the joint moves, 0 at rest (|v| ≤ V_REST)."""
    return np.where(np.abs(v) > V_REST, np.sign(v), 0.0)


@dataclass
class States:
    """Joint states (N, n) on which regressor columns are evaluated."""

    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    t: np.ndarray | None = None  # seconds since the start of the log
    #: T (q_m = T q) when friction acts on the motors (motor-side logs), else None
    transmission: np.ndarray | None = None
    #: the current model's rigid-body torque and torque rate (load_friction, delay)
    tau_rigid: np.ndarray | None = None
    tau_rate: np.ndarray | None = None
    #: motor velocities and their moving signs made so far (friction effects read them on
    #: every trial of a grid); not copied by ``replace``, which may change the transmission
    _motor: dict[tuple[str, int], np.ndarray] = field(
        default_factory=dict, init=False, repr=False, compare=False)

    def __len__(self) -> int:
        return int(self.q.shape[0])

    def rows(self, sl: slice | np.ndarray) -> States:
        """The states of rows ``sl`` (a slice or an index array)."""
        def take(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else a[sl]

        return States(self.q[sl], self.qd[sl], self.qdd[sl], take(self.t), self.transmission,
                      take(self.tau_rigid), take(self.tau_rate))

    def motor_velocity(self, joint: int) -> np.ndarray:
        """Velocity of motor ``joint`` (the joint's own velocity without a transmission)."""
        if self.transmission is None:
            return self.qd[:, joint]
        if ("v", joint) not in self._motor:
            self._motor["v", joint] = self.qd @ self.transmission[joint]
        return self._motor["v", joint]

    def motor_sign(self, joint: int) -> np.ndarray:
        """``moving_sign`` of motor ``joint``'s velocity."""
        if ("sign", joint) not in self._motor:
            self._motor["sign", joint] = moving_sign(self.motor_velocity(joint))
        return self._motor["sign", joint]


@dataclass(frozen=True)
class Hyper:
    """A nonlinear hyper-parameter: profiled over ``grid`` when the model does not set it."""

    default: float
    grid: tuple[float, ...]
    doc: str = ""
    #: "velocity": the grid is in rad/s of the joint and scales with the gear ratio on a motor
    scales_with: str = ""

    def scaled_grid(self, scale: float) -> tuple[float, ...]:
        """The grid for a side whose speeds are ``scale``× the joint's."""
        return self.grid if self.scales_with != "velocity" else tuple(
            g * scale for g in self.grid)


class Effect:
    """One physical effect; subclasses fill regressor columns.

    ``per_joint`` effects act on one joint each (``viscous@3``; bare ``viscous`` means all
    joints); global ones (``rigid_body``) act on the robot as a whole.
    """

    name: ClassVar[str]
    per_joint: ClassVar[bool] = True
    hypers: ClassVar[dict[str, Hyper]] = {}
    options: ClassVar[frozenset[str]] = frozenset()
    #: per-joint effects this one replaces on its joint (declared overlaps)
    replaces: ClassVar[tuple[str, ...]] = ()
    #: acts on a joint's or a motor's velocity (``NAME@jJ`` / ``NAME@mM``)
    sided: ClassVar[bool] = False
    #: the diagnosis scores it on every joint (False: only where a coupling makes it new)
    catalog: ClassVar[bool] = True
    #: its columns are smooth functions of the filtered states — no step at a velocity
    #: reversal, no position frequency the filter would cut — so the filter leaves them as
    #: they are: the diagnosis reads them on its decimated rows without filtering them
    smooth: ClassVar[bool] = False
    doc: ClassVar[str] = ""

    def param_names(self, robot: Robot, joint: int | None, opts: dict[str, Any]) -> list[str]:
        raise NotImplementedError

    #: a per-joint effect given by its ``vectors``: "motor" loads the joints its motor turns
    #: (τ_joint = Tᵀ τ_motor), "joint" its own row; "" fills its ``columns`` itself
    loads: ClassVar[str] = ""

    def vectors(self, robot: Robot, st: States, joint: int, opts: dict[str, Any]
                ) -> list[np.ndarray]:
        """A per-joint effect's columns as N-vectors, before they reach the joints' rows."""
        raise NotImplementedError

    def columns(self, robot: Robot, st: States, joint: int | None,
                opts: dict[str, Any]) -> np.ndarray:
        """(N, n, k) block; for a per-joint effect only row ``joint`` is non-zero."""
        if not self.loads or joint is None:
            raise NotImplementedError
        place = _motor_row if self.loads == "motor" else _row
        return place(st, robot.n, joint, self.vectors(robot, st, joint, opts))

    def row_columns(self, robot: Robot, st: States, joint: int | None, opts: dict[str, Any]
                    ) -> tuple[list[int], np.ndarray]:
        """The rows the block loads and its columns there, (N, len(rows), k): ``columns``
        without the rows that are zero (every row for an effect that fills its own)."""
        if not self.loads or joint is None:
            return list(range(robot.n)), self.columns(robot, st, joint, opts)
        cols = self.vectors(robot, st, joint, opts)
        if self.loads == "joint" or st.transmission is None:
            rows, coefs = [joint], None
        else:
            rows = [int(i) for i in np.flatnonzero(st.transmission[joint])]
            coefs = st.transmission[joint]
        out = np.empty((len(st), len(rows), len(cols)))
        for r, i in enumerate(rows):
            for k, c in enumerate(cols):
                out[:, r, k] = c if coefs is None else coefs[i] * c
        return rows, out


REGISTRY: dict[str, Effect] = {}


def register(cls: type[Effect]) -> type[Effect]:
    REGISTRY[cls.name] = cls()
    return cls


def _row(st: States, n: int, joint: int, cols: Sequence[np.ndarray]) -> np.ndarray:
    out = np.zeros((len(st), n, len(cols)))
    for k, c in enumerate(cols):
        out[:, joint, k] = c
    return out


def _motor_row(st: States, n: int, motor: int, cols: Sequence[np.ndarray]) -> np.ndarray:
    """Torques acting on one motor, seen on the joints: τ_joint = Tᵀ τ_motor.

    Without a transmission this is the joint's own row; with a wrist coupling a motor's
    friction also loads the joints it turns with.
    """
    if st.transmission is None:
        return _row(st, n, motor, cols)
    out = np.zeros((len(st), n, len(cols)))
    for i in np.flatnonzero(st.transmission[motor]):
        for k, c in enumerate(cols):
            out[:, i, k] = st.transmission[motor, i] * c
    return out


@register
class RigidBody(Effect):
    name = "rigid_body"
    smooth = True
    per_joint = False
    doc = "inertia, Coriolis/centrifugal and gravity torques (10 standard parameters per link)"

    def param_names(self, robot, joint, opts):
        return standard_parameter_names(robot.n)

    def columns(self, robot, st, joint, opts):
        return rigid_regressor(robot, st.q, st.qd, st.qdd)


@register
class Viscous(Effect):
    name = "viscous"
    smooth = True
    loads = "motor"
    sided = True
    doc = "viscous friction fv·q̇ (of the motor's velocity for motor-side logs)"

    def param_names(self, robot, joint, opts):
        return [f"fv_{joint + 1}"]

    def vectors(self, robot, st, joint, opts):
        return [st.motor_velocity(joint)]


@register
class Coulomb(Effect):
    name = "coulomb"
    loads = "motor"
    sided = True
    doc = "Coulomb friction fc·sign(q̇)"

    def param_names(self, robot, joint, opts):
        return [f"fc_{joint + 1}"]

    def vectors(self, robot, st, joint, opts):
        return [st.motor_sign(joint)]


@register
class Friction(Effect):
    """Viscous and Coulomb friction of one velocity together. The catalog scores it on coupled
    drives only: on a coupled wrist's motor (velocity q̇5 + q̇6 through the coupling) it is the
    friction neither joint's own viscous and Coulomb terms can express."""

    name = "friction"
    loads = "motor"
    sided = True
    catalog = False  # a candidate only where a coupling makes the other side's friction new
    doc = "viscous and Coulomb friction together, fv·q̇ + fc·sign(q̇) (a coupled motor's)"
    replaces = ("viscous", "coulomb")

    def param_names(self, robot, joint, opts):
        return [f"fv_{joint + 1}", f"fc_{joint + 1}"]

    def vectors(self, robot, st, joint, opts):
        return [st.motor_velocity(joint), st.motor_sign(joint)]


@register
class Offset(Effect):
    name = "offset"
    smooth = True
    loads = "motor"
    sided = True
    doc = "constant torque offset (sensor bias, unmodelled static load)"

    def param_names(self, robot, joint, opts):
        return [f"off_{joint + 1}"]

    def vectors(self, robot, st, joint, opts):
        return [np.ones(len(st))]


@register
class FrictionPower(Effect):
    name = "friction_power"
    loads = "motor"
    sided = True
    doc = "FDURoID's friction (Fc + Fv·|q̇|^α)·sign(q̇) + B"
    hypers = {"alpha": Hyper(0.5, (0.2, 0.35, 0.5, 0.65, 0.8, 1.0, 1.25, 1.5),
                             "exponent of the velocity term")}
    options = frozenset({"alpha"})
    replaces = ("viscous", "coulomb", "offset")

    def param_names(self, robot, joint, opts):
        j = joint + 1
        return [f"fpc_{j}", f"fpv_{j}", f"fpb_{j}"]

    def vectors(self, robot, st, joint, opts):
        v = st.motor_velocity(joint)
        alpha = float(opts.get("alpha", self.hypers["alpha"].default))
        sgn = st.motor_sign(joint)
        return [sgn, np.abs(v) ** alpha * sgn, np.ones(len(st))]


@register
class CoulombAsymmetric(Effect):
    name = "coulomb_asymmetric"
    loads = "motor"
    sided = True
    doc = "Coulomb friction with different levels in the two directions"
    replaces = ("coulomb", "offset")

    def param_names(self, robot, joint, opts):
        return [f"fcp_{joint + 1}", f"fcn_{joint + 1}"]

    def vectors(self, robot, st, joint, opts):
        sgn = st.motor_sign(joint)
        return [(sgn > 0).astype(float), -(sgn < 0).astype(float)]


@register
class Stribeck(Effect):
    name = "stribeck"
    loads = "motor"
    sided = True
    doc = "breakaway friction above Coulomb, decaying as exp(−|q̇/vs|^δ)"
    # both profiled (the velocity first): a fixed shape leaves part of a breakaway unexplained
    hypers = {"vs": Hyper(0.05, (0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.4),
                          "Stribeck velocity, rad/s (of the side's velocity)", "velocity"),
              "shape": Hyper(2.0, (0.35, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0),
                             "shape exponent δ of exp(−|q̇/vs|^δ): 1 exponential, 2 Gaussian")}
    options = frozenset({"vs", "shape"})

    def param_names(self, robot, joint, opts):
        return [f"fst_{joint + 1}"]

    def vectors(self, robot, st, joint, opts):
        v = st.motor_velocity(joint)
        vs = float(opts.get("vs", self.hypers["vs"].default))
        shape = float(opts.get("shape", self.hypers["shape"].default))
        return [np.exp(-np.abs(v / vs) ** shape) * st.motor_sign(joint)]


@register
class Presliding(Effect):
    name = "presliding"
    loads = "motor"
    sided = True
    doc = ("friction's smooth transition through zero velocity (pre-sliding): fp·tanh(q̇/vp) "
           "beside Coulomb's step (fc → 0 when the transition is all smooth)")
    hypers = {"vp": Hyper(0.01, (0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1),
                          "transition velocity, rad/s (of the side's velocity)", "velocity")}
    options = frozenset({"vp"})

    def param_names(self, robot, joint, opts):
        return [f"fp_{joint + 1}"]

    def vectors(self, robot, st, joint, opts):
        v = st.motor_velocity(joint)
        vp = float(opts.get("vp", self.hypers["vp"].default))
        return [np.tanh(v / vp)]


@register
class Armature(Effect):
    name = "armature"
    smooth = True
    loads = "motor"
    sided = True
    doc = "rotor inertia through the gear (J_m·r² on the joint side)"

    def param_names(self, robot, joint, opts):
        return [f"ia_{joint + 1}"]

    def vectors(self, robot, st, joint, opts):
        acc = st.qdd[:, joint] if st.transmission is None else st.qdd @ st.transmission[joint]
        return [acc]


@register
class Spring(Effect):
    name = "spring"
    smooth = True
    loads = "joint"
    doc = "a smooth function of the joint angle (Fourier series in q, with its mean)"
    options = frozenset({"order"})

    def param_names(self, robot, joint, opts):
        order = int(opts.get("order", 4))
        return [f"spr0_{joint + 1}"] + [f"spr{k}{c}_{joint + 1}" for k in range(1, order + 1)
                                        for c in ("s", "c")]

    def vectors(self, robot, st, joint, opts):
        q = st.q[:, joint]
        order = int(opts.get("order", 4))
        return [np.ones_like(q)] + [f(k * q) for k in range(1, order + 1)
                                    for f in (np.sin, np.cos)]


@register
class Ripple(Effect):
    name = "ripple"
    loads = "joint"
    doc = "position-periodic torque (cogging, gear meshing) with period P in the joint angle"
    # the grid is the catalogued range (cogging, gear meshing: a few degrees); the diagnosis
    # searches every period the data resolves, up to half the joint's travel (two cycles)
    hypers = {"period": Hyper(0.1, tuple(float(x) for x in np.geomspace(0.01, 0.5, 41)),
                              "period in rad (found from the residual)")}
    options = frozenset({"period"})

    def param_names(self, robot, joint, opts):
        return [f"rps_{joint + 1}", f"rpc_{joint + 1}"]

    def vectors(self, robot, st, joint, opts):
        period = float(opts.get("period", self.hypers["period"].default))
        ph = 2 * np.pi * st.q[:, joint] / period
        return [np.sin(ph), np.cos(ph)]


@register
class FrictionDrift(Effect):
    name = "friction_drift"
    loads = "motor"
    sided = True
    doc = "friction changing over the log's time (a joint warming up): exp(−t/τ) terms"
    hypers = {"tau_s": Hyper(60.0, (5.0, 10.0, 20.0, 40.0, 80.0, 160.0, 320.0, 1e6),
                             "time constant of the change, s")}
    options = frozenset({"tau_s"})

    def param_names(self, robot, joint, opts):
        return [f"dfc_{joint + 1}", f"dfv_{joint + 1}"]

    def vectors(self, robot, st, joint, opts):
        tau_s = float(opts.get("tau_s", self.hypers["tau_s"].default))
        t = st.t if st.t is not None else np.zeros(len(st))  # seconds since the log's start
        g = np.exp(-t / tau_s) if tau_s < 1e5 else t / 100.0  # "1e6": a linear drift
        v = st.motor_velocity(joint)
        return [g * st.motor_sign(joint), g * v]


@register
class LoadFriction(Effect):
    name = "load_friction"
    loads = "joint"
    doc = "friction growing with the transmitted load: μ·|τ_load|·sign(q̇)"

    def param_names(self, robot, joint, opts):
        return [f"mu_{joint + 1}"]

    def vectors(self, robot, st, joint, opts):
        load = st.tau_rigid[:, joint] if st.tau_rigid is not None else np.zeros(len(st))
        return [np.abs(load) * moving_sign(st.qd[:, joint])]


@register
class Delay(Effect):
    """A time shift between the torque and position logs; applied to the data on identify.

    As a candidate its column is the model's torque rate (τ(t − d) ≈ τ(t) − d·τ̇): the
    coefficient estimates −d.
    """

    name = "delay"
    per_joint = False
    doc = "time shift between torque and position logs"
    options = frozenset({"seconds"})

    def param_names(self, robot, joint, opts):
        return [] if "seconds" in opts else ["delay_s"]

    def columns(self, robot, st, joint, opts):
        if "seconds" in opts:
            return np.zeros((len(st), robot.n, 0))
        rate = st.tau_rate if st.tau_rate is not None else np.zeros((len(st), robot.n))
        return -rate[:, :, None]


class KnownTorqueEffect(Effect):
    """The identified constants of a known torque (``known_torque:`` with ``identify``): one
    column per constant, the torque per unit of it. Not in the catalog: made per entry."""

    doc = "a known torque law with constants identified from the data"

    def __init__(self, known: KnownTorque) -> None:
        self.known = known
        self.name = f"known_torque:{known.name}"  # type: ignore[misc]
        self.per_joint = known.joint is not None  # type: ignore[misc]

    def param_names(self, robot, joint, opts):
        return self.known.param_names()

    def columns(self, robot, st, joint, opts):
        return self.known.columns(st.q, st.qd, st.qdd)
