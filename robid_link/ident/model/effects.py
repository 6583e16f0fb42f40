"""A model: the list of effects it holds (``EffectSpec`` entries, resolved into ``Block``s of
regressor columns), read from and written to YAML. The effects themselves are the catalog's
(``model.catalog``); its names are re-exported here, where the rest of the worker imports them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from robid_link.exceptions import ModelError
from robid_link.ident.model.catalog import (
    REGISTRY,
    SIDES,
    V_REST,
    Effect,
    Hyper,
    KnownTorqueEffect,
    States,
    moving_sign,
    register,
)
from robid_link.ident.model.known import KnownTorque, parse_known_torques
from robid_link.ident.model.robot import Robot
from robid_link.yamlio import check_keys, read_yaml_mapping, yaml_type

__all__ = [
    "States",
    "Effect",
    "Hyper",
    "EffectSpec",
    "Block",
    "Model",
    "REGISTRY",
    "register",
    "DEFAULT_MODEL",
    "parse_effect",
    "load_model",
    "save_model",
    "SIDES",
    "V_REST",
    "moving_sign",
    "effect_label",
]


# ----------------------------------------------------------------------------- model


@dataclass(frozen=True)
class EffectSpec:
    """One model entry: ``NAME``, ``NAME@J`` (``@jJ`` joint side, ``@mM`` motor side) or a
    mapping with options (J from 1)."""

    name: str
    joint: int | None = None  # 1-based, None = all joints (per-joint) or global
    options: tuple[tuple[str, Any], ...] = ()
    side: str | None = None  # "joint" | "motor"; None: the logs' side

    @property
    def opts(self) -> dict[str, Any]:
        return dict(self.options)

    def label(self) -> str:
        return effect_label(self.name, self.joint, self.side)

    def to_yaml(self) -> str | dict[str, Any]:
        if not self.options and (self.joint is not None or self.side is None):
            return self.label()
        out: dict[str, Any] = {"name": self.name}
        if self.joint is not None:
            out["joint"] = self.joint
        if self.side is not None:
            out["side"] = self.side
        out.update(self.opts)
        return out


def effect_label(name: str, joint: int | None, side: str | None = None) -> str:
    """``viscous``, ``viscous@3``, ``viscous@m6`` (joint from 1)."""
    if joint is None:
        return name if side is None else f"{name}@{side}"
    return f"{name}@{'' if side is None else side[0]}{joint}"


@dataclass(frozen=True)
class Block:
    """A resolved effect instance: one effect on one joint (or global), with its columns.

    ``side`` ("joint" or "motor") pins a sided effect to a joint's bearing or a motor
    whatever the logs' side; None follows the problem (motor-side logs: the motors)."""

    effect: Effect
    joint: int | None  # 0-based
    opts: dict[str, Any] = field(default_factory=dict, hash=False, compare=False)
    side: str | None = None

    @property
    def key(self) -> str:
        return effect_label(self.effect.name, None if self.joint is None else self.joint + 1,
                            self.side)

    def free_hypers(self) -> list[str]:
        return [h for h in self.effect.hypers if h not in self.opts]

    def with_opts(self, **opts: Any) -> Block:
        return replace(self, opts={**self.opts, **opts})

    def transmission(self, robot: Robot, default: np.ndarray | None) -> np.ndarray | None:
        """T the block's velocities go through: None on a joint's bearing."""
        if self.side is None:
            return default
        return robot.transmission if self.side == "motor" else None

    def states(self, robot: Robot, st: States) -> States:
        """``st`` seen from the block's side."""
        if self.side is None:
            return st
        t_mat = self.transmission(robot, st.transmission)
        return st if t_mat is st.transmission else replace(st, transmission=t_mat)

    def columns(self, robot: Robot, st: States) -> np.ndarray:
        return self.effect.columns(robot, self.states(robot, st), self.joint, self.opts)

    def row_columns(self, robot: Robot, st: States) -> tuple[list[int], np.ndarray]:
        """``columns`` on the rows the block loads only: (those rows, (N, len(rows), k))."""
        return self.effect.row_columns(robot, self.states(robot, st), self.joint, self.opts)

    def param_names(self, robot: Robot) -> list[str]:
        names = self.effect.param_names(robot, self.joint, self.opts)
        if self.side is None or self.joint is None:
            return names
        tail = f"_{self.joint + 1}"
        return [nm[: -len(tail)] + f"_{self.side[0]}{self.joint + 1}" if nm.endswith(tail)
                else nm for nm in names]

    def rows(self, robot: Robot, default: np.ndarray | None) -> list[int]:
        """Joints (0-based) whose torque the block loads: a coupled motor's loads several."""
        if self.joint is None:
            return list(range(robot.n))
        t_mat = self.transmission(robot, default) if self.effect.sided else None
        if t_mat is None:
            return [self.joint]
        return [int(i) for i in np.flatnonzero(t_mat[self.joint])]

    def velocity_scale(self, robot: Robot, default: np.ndarray | None) -> float:
        """How much faster the block's velocity runs than its joint's (the gear ratio)."""
        t_mat = self.transmission(robot, default) if self.effect.sided else None
        if t_mat is None or self.joint is None:
            return 1.0
        return float(abs(t_mat[self.joint, self.joint]))

    def grid(self, hyper: str, robot: Robot, default: np.ndarray | None) -> tuple[float, ...]:
        """The hyper-parameter's search grid on the block's side."""
        return self.effect.hypers[hyper].scaled_grid(self.velocity_scale(robot, default))


#: option → (smallest, largest, integer): a value outside makes NaN columns or no sense
OPTION_RANGES: dict[str, tuple[float, float, bool]] = {
    "alpha": (1e-3, 3.0, False),  # friction_power exponent
    "vs": (1e-6, 1e3, False),  # Stribeck velocity, rad/s
    "shape": (0.1, 10.0, False),  # Stribeck shape exponent
    "order": (1, 20, True),  # spring harmonics
    "period": (1e-4, 100.0, False),  # ripple period, rad
    "tau_s": (1e-3, 1e9, False),  # friction_drift time constant, s
    "vp": (1e-7, 1e3, False),  # pre-sliding transition velocity, rad/s
    "seconds": (-10.0, 10.0, False),  # delay, s
}
#: more joints than any robot has; a joint beyond the robot's own count is refused later
MAX_JOINT = 1000


def _short(x: Any) -> str:
    text = repr(x)
    return text if len(text) <= 40 else text[:37] + "..."


def _parse_at(entry: str, text: str, where: str) -> tuple[int, str | None]:
    side = None
    if text[:1] in ("j", "m"):
        side, text = SIDES[text[0] == "m"], text[1:]
    if not text.isdigit() or not 1 <= int(text) <= MAX_JOINT:
        raise ModelError(f"{where}: {_short(entry)}: after '@' a joint number from 1 is needed "
                         "(NAME@J, NAME@jJ on the joint's bearing, NAME@mM on motor M)")
    return int(text), side


def parse_effect(entry: Any, where: str = "effect") -> EffectSpec:
    if isinstance(entry, str):
        name, at, after = entry.strip().partition("@")
        spec_joint, side = _parse_at(entry, after, where) if at else (None, None)
        return _checked(EffectSpec(name, spec_joint, side=side), where)
    if isinstance(entry, dict):
        if "name" not in entry:
            raise ModelError(f"{where}: a mapping entry needs 'name'")
        opts = {k: v for k, v in entry.items() if k not in ("name", "joint", "side")}
        joint = entry.get("joint")
        if joint is not None and (isinstance(joint, bool) or not isinstance(joint, int)
                                  or not 1 <= joint <= MAX_JOINT):
            raise ModelError(f"{where}.joint: expected a joint number from 1, got {_short(joint)}")
        side = entry.get("side")
        if side is not None and side not in SIDES:
            raise ModelError(f"{where}.side: expected joint or motor, got {_short(side)}")
        if not isinstance(entry["name"], str):
            raise ModelError(f"{where}.name: expected an effect name, got {_short(entry['name'])}")
        if not all(isinstance(k, str) for k in opts):
            raise ModelError(f"{where}: option names must be words")
        return _checked(EffectSpec(entry["name"], joint, tuple(sorted(opts.items())), side),
                        where)
    raise ModelError(f"{where}: expected NAME, NAME@J or a mapping, got {_short(entry)}")


def _checked(spec: EffectSpec, where: str) -> EffectSpec:
    if spec.name not in REGISTRY:
        known = ", ".join(sorted(REGISTRY))
        raise ModelError(f"{where}: unknown effect {_short(spec.name)} (known: {known})")
    eff = REGISTRY[spec.name]
    if not eff.per_joint and spec.joint is not None:
        raise ModelError(f"{where}: '{spec.name}' is global and takes no joint")
    if spec.side is not None and not eff.sided:
        sided = ", ".join(sorted(k for k, e in REGISTRY.items() if e.sided))
        raise ModelError(f"{where}: '{spec.name}' acts on the joint angle and has no side "
                         f"(effects on a joint's or a motor's velocity: {sided})")
    bad = set(spec.opts) - set(eff.options)
    if bad:
        raise ModelError(f"{where}: '{spec.name}' has no option '{sorted(bad)[0]}'")
    for key, val in spec.opts.items():
        lo, hi, integer = OPTION_RANGES[key]
        kinds = int if integer else int | float
        try:
            ok = (not isinstance(val, bool) and isinstance(val, kinds) and math.isfinite(val)
                  and lo <= val <= hi)
        except OverflowError:  # an integer beyond float range
            ok = False
        if not ok:
            kind = "a whole number" if integer else "a number"
            raise ModelError(f"{where}: '{spec.name}' option {key}: expected {kind} in "
                             f"[{lo:g}, {hi:g}], got {_short(val)}")
    return spec


@dataclass(frozen=True)
class Model:
    """An ordered list of effect entries, and the known torques of the model file."""

    specs: tuple[EffectSpec, ...]
    known: tuple[KnownTorque, ...] = ()
    #: where each entry came from (``model.yaml: effects[2]``, ``--add viscous@9``), for the
    #: errors found once the robot is known; not part of the model's identity
    origins: tuple[str, ...] = field(default=(), compare=False)

    @classmethod
    def parse(cls, entries: Sequence[Any], where: str = "effects") -> Model:
        specs = tuple(parse_effect(e, f"{where}[{i}]") for i, e in enumerate(entries))
        return cls(specs, origins=tuple(f"{where}[{i}]" for i in range(len(specs))))

    def _origin(self, k: int) -> str:
        return self.origins[k] if len(self.origins) == len(self.specs) else "effects"

    def labels(self) -> list[str]:
        return [s.label() for s in self.specs]

    def with_added(self, spec: EffectSpec, origin: str = "") -> Model:
        kept = [(s, self._origin(k)) for k, s in enumerate(self.specs)
                if not (s.name == spec.name and s.joint == spec.joint and s.side == spec.side)]
        return Model((*(s for s, _ in kept), spec), self.known,
                     (*(o for _, o in kept), origin or f"added {spec.label()}"))

    def blocks(self, robot: Robot) -> list[Block]:
        """Resolve entries to per-joint blocks; declared replacements drop overlapping blocks."""
        chosen: dict[tuple[str, int | None, str | None], Block] = {}
        for k, s in enumerate(self.specs):
            eff = REGISTRY[s.name]
            if s.joint is not None and s.joint > robot.n:
                raise ModelError(f"{self._origin(k)}: effect {s.label()}: the robot has "
                                 f"{robot.n} joints")
            if s.side == "motor" and robot.transmission is None:
                raise ModelError(f"{self._origin(k)}: effect {s.label()}: a motor's friction "
                                 f"needs the robot's 'transmission' (gear ratios and couplings; "
                                 f"{robot.source} has none)")
            joints: list[int | None]
            if not eff.per_joint:
                joints = [None]
            elif s.joint is None:
                joints = list(range(robot.n))
            else:
                joints = [s.joint - 1]
            for j in joints:
                prev = chosen.get((s.name, j, s.side))
                opts = dict(prev.opts) if prev is not None else {}
                if s.joint is not None or prev is None or not prev.opts:
                    opts.update(s.opts)
                chosen[(s.name, j, s.side)] = Block(eff, j, opts, s.side)
        for (_name, j, side), blk in list(chosen.items()):
            for other in blk.effect.replaces:
                chosen.pop((other, j, side), None)
        rng = np.random.default_rng(11)
        lo = np.where(np.isfinite(robot.limits.q_min), robot.limits.q_min, -math.pi)
        hi = np.where(np.isfinite(robot.limits.q_max), robot.limits.q_max, math.pi)
        known = []
        for kt in self.known:
            kt.check(lo, hi, rng)
            if kt.identify:
                known.append(Block(KnownTorqueEffect(kt), None if kt.joint is None
                                   else kt.joint - 1, {"known": repr(sorted(kt.raw.items()))}))
        if ("rigid_body", None, None) in chosen:  # rigid body first: it reads best in tables
            rb = chosen.pop(("rigid_body", None, None))
            return [rb, *chosen.values(), *known]
        return [*chosen.values(), *known]


DEFAULT_MODEL = Model.parse(["rigid_body", "viscous", "coulomb"])


def load_model(path: str | Path | None) -> Model:
    """Read a model file (YAML with ``effects:``); the default model when path is None."""
    if path is None:
        return DEFAULT_MODEL
    p = Path(path)
    doc = read_yaml_mapping(p, "model file", ModelError)
    check_keys(doc, str(p), required=("effects",), optional=("description", "known_torque"),
               error=ModelError)
    if not isinstance(doc["effects"], list):
        raise ModelError(f"{p}: effects: expected a list, got {yaml_type(doc['effects'])}")
    if not doc["effects"]:
        raise ModelError(f"{p}: effects: the list is empty (the default model is "
                         f"[{', '.join(DEFAULT_MODEL.labels())}])")
    try:
        model = Model.parse(doc["effects"], "effects")
    except ModelError as err:
        raise ModelError(f"{p}: {err}") from err
    origins = tuple(f"{p}: {o}" for o in model.origins)
    known = (parse_known_torques(doc["known_torque"], f"{p}: known_torque")
             if "known_torque" in doc else ())  # errors found later name the file too
    model = Model(model.specs, known, origins)
    if not any(spec.name == "rigid_body" for spec in model.specs):
        # identification, validation and diagnosis all start from the rigid-body model
        raise ModelError(f"{p}: effects: 'rigid_body' missing (every model identifies the rigid "
                         "body; friction and other effects add to it)")
    return model


def save_model(path: str | Path, model: Model) -> None:
    doc: dict[str, Any] = {"effects": [s.to_yaml() for s in model.specs]}
    if model.known:
        doc["known_torque"] = [kt.raw for kt in model.known]
    try:
        Path(path).write_text(yaml.safe_dump(doc, sort_keys=False))
    except OSError as err:
        raise ModelError(f"{path}: cannot write the model file: {err.strerror or err}") from err
