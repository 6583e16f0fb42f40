"""Robot descriptions (modified-DH YAML or URDF) turned into one Pinocchio model.

Owns joint numbering and naming, limits, nominal inertials and the motor↔joint transmission.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from robid_link.exceptions import RobidError, RobotError
from robid_link.ident.model.robot_check import (
    UrdfJoint,
    check_urdf,
    inertia_problem,
    native_stderr,
    parser_summary,
)
from robid_link.safeopen import file_problem
from robid_link.yamlio import check_keys, read_yaml_mapping

__all__ = ["Robot", "Limits", "load_robot", "description_name", "STANDARD_NAMES",
           "standard_parameter_names"]

#: Pinocchio's order of the ten standard inertial parameters of one link.
STANDARD_NAMES = ("m", "mx", "my", "mz", "xx", "xy", "yy", "xz", "yz", "zz")

_REVOLUTE = {"RX": (1.0, 0.0, 0.0), "RY": (0.0, 1.0, 0.0), "RZ": (0.0, 0.0, 1.0)}
_PRISMATIC = {"PX": (1.0, 0.0, 0.0), "PY": (0.0, 1.0, 0.0), "PZ": (0.0, 0.0, 1.0)}

_log = logging.getLogger(__name__)


def standard_parameter_names(n_joints: int) -> list[str]:
    """``m_1, mx_1, …, zz_n`` in Pinocchio's order (joints numbered from 1)."""
    return [f"{p}_{j + 1}" for j in range(n_joints) for p in STANDARD_NAMES]


@dataclass(frozen=True)
class Limits:
    """Joint limits in SI units (rad or m, /s, /s², N·m or N); ``inf`` where unknown."""

    q_min: np.ndarray
    q_max: np.ndarray
    qd_max: np.ndarray
    qdd_max: np.ndarray
    tau_max: np.ndarray


@dataclass(frozen=True)
class Robot:
    """A serial or tree robot with 1-DoF revolute/prismatic joints, as one Pinocchio model."""

    name: str
    model: pin.Model
    joint_names: tuple[str, ...]
    joint_types: tuple[str, ...]  # "revolute" | "prismatic"
    axes: np.ndarray  # (n, 3) joint axis in its own frame
    parents: tuple[int, ...]  # parent joint index (0-based), -1 for the base
    placements: tuple[pin.SE3, ...]  # parent joint frame -> joint frame at q = 0
    unbounded: tuple[bool, ...]  # Pinocchio stores (cos, sin) for these
    limits: Limits
    nominal: np.ndarray | None  # standard parameters (10 n) when inertials were given
    transmission: np.ndarray | None = None  # T with q_m = T q
    #: joint-side reading of each encoder (rad or m) when the model's joint is at zero
    encoder_offsets: np.ndarray | None = None
    #: torque per ampere of each drive, on the log's side; NaN: identify it from the logs
    current_gain: np.ndarray | None = None
    #: (n,) joints whose ROS effort is a drive current (``transmission.effort``)
    effort_current: np.ndarray | None = None
    source: str = ""
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def n(self) -> int:
        return len(self.joint_names)

    @property
    def gravity(self) -> np.ndarray:
        return np.array(self.model.gravity.linear, dtype=float)

    def pin_q(self, q: np.ndarray) -> np.ndarray:
        """Joint angles (…, n) → Pinocchio configuration (…, nq)."""
        q = np.asarray(q, dtype=float)
        if not any(self.unbounded):
            return q
        cols = []
        for j, ub in enumerate(self.unbounded):
            if ub:
                cols += [np.cos(q[..., j]), np.sin(q[..., j])]
            else:
                cols.append(q[..., j])
        return np.stack(cols, axis=-1)

    def rnea(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
        """Rigid-body inverse dynamics with the model's inertias (one sample)."""
        data = self.model.createData()
        return np.array(pin.rnea(self.model, data, self.pin_q(q), qd, qdd))

    def to_joint_side(
        self, q: np.ndarray, qd: np.ndarray | None, qdd: np.ndarray | None, tau: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None, np.ndarray]:
        """Motor-side log (samples × n) → joint side: q = T⁻¹ q_m − offsets, τ = Tᵀ τ_m."""
        if self.transmission is None:
            where = ("transmission.ratios" if self.source.endswith((".yaml", ".yml"))
                     else f"transmission.ratios in {transmission_path(self.source).name}")
            raise RobotError(f"{self.source}: --motor-side needs the gear ratios "
                             f"({where})")
        t_inv_t = np.linalg.inv(self.transmission).T
        conv = [None if x is None else x @ t_inv_t for x in (q, qd, qdd)]
        q_j = self.remove_offsets(conv[0])  # type: ignore[arg-type]
        return q_j, conv[1], conv[2], tau @ self.transmission

    def to_motor_side(self, q: np.ndarray, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Joint side → motor side: q_m = T (q + offsets), τ_m = T⁻ᵀ τ."""
        if self.transmission is None:
            raise RobotError(f"{self.source}: no 'transmission' section")
        return self.add_offsets(q) @ self.transmission.T, tau @ np.linalg.inv(self.transmission)

    def remove_offsets(self, q: np.ndarray) -> np.ndarray:
        """Encoder readings (joint side) → the model's joint positions: q − offsets."""
        return q if self.encoder_offsets is None else q - self.encoder_offsets

    def add_offsets(self, q: np.ndarray) -> np.ndarray:
        """The model's joint positions → what the encoders read: q + offsets."""
        return q if self.encoder_offsets is None else q + self.encoder_offsets

    def mapping(self) -> list[dict[str, Any]]:
        """The joint number ↔ name mapping printed in summaries and JSON."""
        return [
            {"joint": j + 1, "name": nm, "type": tp}
            for j, (nm, tp) in enumerate(zip(self.joint_names, self.joint_types, strict=True))
        ]


# ----------------------------------------------------------------------------- loading


def load_robot(path: str | Path, lock: Sequence[str] = (), *, allow_unlimited: bool = False
               ) -> Robot:
    """Load an MDH YAML (``.yaml``/``.yml``) or a URDF (``.urdf``) robot description.

    A revolute or prismatic joint without consistent position limits (lower < upper) is
    refused: excitation and the safety check would otherwise allow ±0.9π. ``allow_unlimited``
    (``--allow-unlimited``; ``allow_unlimited: true`` in an MDH file) accepts it with a logged
    warning. A URDF continuous joint is bounded to one turn (±180°) for those checks.
    """
    p = Path(path)
    problem = file_problem(p)
    if problem:
        raise RobotError(f"{p}: robot description {problem}")
    suffix = p.suffix.lower()
    if suffix in (".yaml", ".yml"):
        if lock:
            raise RobotError(f"{p}: --lock applies to URDF robots only")
        return _load_mdh(p, allow_unlimited)
    if suffix == ".urdf":
        return _load_urdf(p, lock, allow_unlimited)
    raise RobotError(f"{p}: unknown robot format '{suffix}' (expected .yaml, .yml or .urdf)")


def description_name(path: str | Path, lock: Sequence[str] = ()) -> str | None:
    """The name a robot description gives its robot; None when it does not load (the
    operator's read-only commands still open the store: ``config.robot_name``)."""
    try:
        return load_robot(path, lock).name
    except RobidError:
        return None


def _num(x: Any, where: str, src: Path) -> float:
    try:
        ok = not isinstance(x, bool) and isinstance(x, int | float) and math.isfinite(x)
    except OverflowError:  # an integer beyond float range
        ok = False
    if not ok:
        shown = repr(x) if len(repr(x)) <= 40 else repr(x)[:37] + "..."
        raise RobotError(f"{src}: {where}: expected a finite number, got {shown}")
    return float(x)


def _vec(x: Any, size: int, where: str, src: Path) -> np.ndarray:
    if not isinstance(x, list) or len(x) != size:
        shown = repr(x) if len(repr(x)) <= 40 else repr(x)[:37] + "..."
        raise RobotError(f"{src}: {where}: expected a list of {size} numbers, got {shown}")
    return np.array([_num(v, f"{where}[{i}]", src) for i, v in enumerate(x)])


_JOINT_OPTIONAL = ("name", "type", "limits", "inertial")


def _load_mdh(p: Path, allow_unlimited: bool) -> Robot:
    doc = read_yaml_mapping(p, "robot description", RobotError)
    check_keys(doc, str(p), required=("joints",), error=RobotError,
               optional=("name", "gravity", "transmission", "description", "allow_unlimited"))
    if not isinstance(doc.get("allow_unlimited", False), bool):
        raise RobotError(f"{p}: allow_unlimited: expected true or false")
    allow_unlimited = allow_unlimited or doc.get("allow_unlimited", False)
    rows = doc.get("joints")
    if not isinstance(rows, list) or not rows:
        raise RobotError(f"{p}: joints: expected a non-empty list")
    gravity = _vec(doc.get("gravity", [0, 0, -9.81]), 3, "gravity", p)
    model = pin.Model()
    model.name = str(doc.get("name", p.stem))
    model.gravity = pin.Motion(gravity, np.zeros(3))
    names: list[str] = []
    types: list[str] = []
    lim: dict[str, list[float]] = {k: [] for k in ("q_min", "q_max", "qd_max", "qdd_max",
                                                   "tau_max")}
    inertials: list[np.ndarray | None] = []
    parent = 0
    for i, row in enumerate(rows):
        where = f"joints[{i}]"
        check_keys(row, f"{p}: {where}", required=("alpha", "a", "theta", "d"),
                   optional=_JOINT_OPTIONAL, error=RobotError)
        name = str(row.get("name", f"j{i + 1}"))
        if name in names:
            raise RobotError(f"{p}: {where}.name: duplicate joint name '{name}'")
        jtype = row.get("type", "revolute")
        if jtype not in ("revolute", "prismatic"):
            raise RobotError(f"{p}: {where}.type: expected revolute or prismatic, "
                             f"got {str(jtype)[:40]!r}")
        alpha = math.radians(_num(row["alpha"], f"{where}.alpha", p))
        a = _num(row["a"], f"{where}.a", p)
        theta = math.radians(_num(row["theta"], f"{where}.theta", p))
        d = _num(row["d"], f"{where}.d", p)
        # Craig: T = RotX(alpha) TransX(a) RotZ(theta) TransZ(d); q adds to theta or d.
        placement = (
            pin.SE3(_rotx(alpha), np.zeros(3))
            * pin.SE3(np.eye(3), np.array([a, 0.0, 0.0]))
            * pin.SE3(_rotz(theta), np.array([0.0, 0.0, d]))
        )
        jm = pin.JointModelRZ() if jtype == "revolute" else pin.JointModelPZ()
        jid = model.addJoint(parent, jm, placement, name)
        inertial = _mdh_inertial(row.get("inertial"), f"{where}.inertial", p)
        inertials.append(inertial)
        inertia = (
            pin.Inertia.FromDynamicParameters(inertial)
            if inertial is not None
            else pin.Inertia(1e-3, np.zeros(3), 1e-6 * np.eye(3))
        )
        model.appendBodyToJoint(jid, inertia, pin.SE3.Identity())
        _mdh_limits(row.get("limits"), jtype, f"{where}.limits", p, lim, allow_unlimited)
        names.append(name)
        types.append(jtype)
        parent = jid
    n = len(names)
    given = [x for x in inertials if x is not None]
    nominal = np.concatenate(given) if len(given) == len(inertials) else None
    limits = Limits(**{k: np.array(v, dtype=float) for k, v in lim.items()})
    model.lowerPositionLimit = limits.q_min.copy()
    model.upperPositionLimit = limits.q_max.copy()
    tx = _transmission(doc.get("transmission"), names, types, p, "transmission")
    return Robot(
        name=model.name,
        model=model,
        joint_names=tuple(names),
        joint_types=tuple(types),
        axes=np.tile([0.0, 0.0, 1.0], (n, 1)),
        parents=tuple(range(-1, n - 1)),
        placements=tuple(model.jointPlacements[j + 1] for j in range(n)),
        unbounded=(False,) * n,
        limits=limits,
        nominal=nominal,
        transmission=tx.matrix,
        encoder_offsets=tx.offsets,
        current_gain=tx.current_gain,
        effort_current=tx.effort_current,
        source=str(p),
    )


def _urdf_limits(p: Path, names: Sequence[str], joints: dict[str, UrdfJoint],
                 allow_unlimited: bool) -> Limits:
    """Limits from the URDF's text, by joint name (Pinocchio's q-limit vectors are per
    configuration slot, and a continuous joint has two)."""
    rows = []
    for name in names:
        j = joints.get(name, UrdfJoint(name, "revolute", limit_problem="not found in the file"))
        lo, hi = j.lower, j.upper
        if j.kind == "continuous":  # unbounded by definition; excitation and checks: one turn
            lo, hi = -math.pi, math.pi
        elif j.limit_problem and not allow_unlimited:
            raise RobotError(f"{p}: joint '{name}': {j.limit_problem}; position limits are "
                             "needed (or --allow-unlimited to accept an unlimited joint)")
        elif j.limit_problem:
            _log.warning("%s: joint '%s': %s; accepted as unlimited (--allow-unlimited)",
                         p, name, j.limit_problem)
            lo, hi = -math.inf, math.inf
        rows.append((lo, hi, j.velocity, math.inf, j.effort))
    arr = np.array(rows, dtype=float).reshape(len(names), 5)
    return Limits(*(arr[:, k].copy() for k in range(5)))


def _rotx(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rotz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _mdh_inertial(x: Any, where: str, p: Path) -> np.ndarray | None:
    """``{m, com, I}`` with I about the centre of mass, link-frame axes → 10 parameters."""
    if x is None:
        return None
    if not isinstance(x, dict) or set(x) - {"m", "com", "I"} or "m" not in x:
        raise RobotError(f"{p}: {where}: expected {{m, com: [x,y,z], I: [xx,xy,yy,xz,yz,zz]}}")
    m = _num(x["m"], f"{where}.m", p)
    if m < 0:
        raise RobotError(f"{p}: {where}.m: mass must not be negative")
    com = _vec(x.get("com", [0, 0, 0]), 3, f"{where}.com", p)
    ii = _vec(x.get("I", [0, 0, 0, 0, 0, 0]), 6, f"{where}.I", p)
    i_c = np.array([[ii[0], ii[1], ii[3]], [ii[1], ii[2], ii[4]], [ii[3], ii[4], ii[5]]])
    problem = inertia_problem(i_c)
    if problem:
        raise RobotError(f"{p}: {where}.I: {problem}")
    return np.array(pin.Inertia(m, com, i_c).toDynamicParameters())


def _mdh_limits(x: Any, jtype: str, where: str, p: Path, out: dict[str, list[float]],
                allow_unlimited: bool) -> None:
    x = {} if x is None else x
    if not isinstance(x, dict) or set(x) - {"q", "qd", "qdd", "tau"}:
        raise RobotError(f"{p}: {where}: expected keys among q, qd, qdd, tau")
    scale = math.radians(1.0) if jtype == "revolute" else 1.0
    if "q" in x:
        lo, hi = _vec(x["q"], 2, f"{where}.q", p)
        if lo >= hi:
            raise RobotError(f"{p}: {where}.q: lower limit {lo} not below upper {hi}")
        out["q_min"].append(lo * scale)
        out["q_max"].append(hi * scale)
    elif allow_unlimited:
        _log.warning("%s: %s.q: no position limits; accepted as unlimited (allow_unlimited)",
                     p, where)
        out["q_min"].append(-math.inf)
        out["q_max"].append(math.inf)
    else:
        raise RobotError(f"{p}: {where}.q: position limits missing (give q: [lower, upper], "
                         "or allow_unlimited: true to accept an unlimited joint)")
    for key in ("qd", "qdd", "tau"):
        if key not in x:
            out[f"{key}_max"].append(math.inf)
            continue
        v = _num(x[key], f"{where}.{key}", p) * (scale if key != "tau" else 1.0)
        if v <= 0:
            raise RobotError(f"{p}: {where}.{key}: must be positive, got {x[key]!r}")
        out[f"{key}_max"].append(v)


@dataclass(frozen=True)
class _Transmission:
    matrix: np.ndarray | None = None
    offsets: np.ndarray | None = None
    current_gain: np.ndarray | None = None
    effort_current: np.ndarray | None = None


_TX_KEYS = ("ratios", "coupling", "offsets", "current_gain", "effort")


def transmission_path(urdf: str | Path) -> Path:
    """The transmission file read with a URDF: ``robot.urdf`` → ``robot.transmission.yaml``."""
    p = Path(urdf)
    return p.with_name(p.stem + ".transmission.yaml")


def _urdf_transmission(p: Path, names: Sequence[str], types: Sequence[str]) -> _Transmission:
    side = transmission_path(p)
    if not side.is_file():
        return _Transmission()
    doc = read_yaml_mapping(side, "transmission file", RobotError)
    check_keys(doc, str(side), optional=("transmission", "description"), error=RobotError)
    return _transmission(doc.get("transmission"), names, types, side, "transmission")


def _per_joint(x: Any, names: Sequence[str], where: str, src: Path, *, allow_null: bool = False
               ) -> list[Any]:
    """A per-joint value: a list in joint order, or a mapping joint name → value (joints
    left out: None)."""
    n = len(names)
    if isinstance(x, dict):
        unknown = [k for k in x if k not in names]
        if unknown:
            raise RobotError(f"{src}: {where}: no joint named {str(unknown[0])[:40]!r} "
                             f"(joints: {', '.join(names)})")
        if not allow_null and len(x) != n:
            missing = next(nm for nm in names if nm not in x)
            raise RobotError(f"{src}: {where}: joint {missing!r} missing")
        return [x.get(nm) for nm in names]
    if not isinstance(x, list) or len(x) != n:
        shown = repr(x) if len(repr(x)) <= 40 else repr(x)[:37] + "..."
        raise RobotError(f"{src}: {where}: expected a list of {n} values (joints "
                         f"{', '.join(names)}) or a mapping joint name → value, got {shown}")
    return list(x)


def _transmission(x: Any, names: Sequence[str], types: Sequence[str], p: Path, key: str
                  ) -> _Transmission:
    """The ``transmission`` section: gear ratios and couplings (T with q_m = T q), encoder
    offsets (degrees, or metres for prismatic joints) and drive current gains."""
    if x is None:
        return _Transmission()
    if not isinstance(x, dict) or not x or set(x) - set(_TX_KEYS):
        raise RobotError(f"{p}: {key}: expected a mapping with keys among "
                         f"{', '.join(_TX_KEYS)}")
    t = None
    if "ratios" in x:
        raw = _per_joint(x["ratios"], names, f"{key}.ratios", p)
        ratios = np.array([_num(v, f"{key}.ratios[{i}]", p) for i, v in enumerate(raw)])
        if np.any(ratios == 0):
            raise RobotError(f"{p}: {key}.ratios: a gear ratio of 0 is not invertible")
        t = np.diag(ratios) @ _coupling(x.get("coupling"), names, p, key)
        if not np.all(np.isfinite(t)) or np.linalg.cond(t) > 1e12:
            raise RobotError(f"{p}: {key}: the coupling matrix is singular")
    elif x.get("coupling"):
        raise RobotError(f"{p}: {key}.coupling: needs {key}.ratios")
    offsets = None
    if "offsets" in x:
        raw = _per_joint(x["offsets"], names, f"{key}.offsets", p)
        offsets = np.array([_num(v, f"{key}.offsets[{i}]", p)
                            * (math.radians(1.0) if types[i] == "revolute" else 1.0)
                            for i, v in enumerate(raw)])
    gains = None
    if "current_gain" in x:
        raw = _per_joint(x["current_gain"], names, f"{key}.current_gain", p, allow_null=True)
        gains = np.array([math.nan if v is None else _num(v, f"{key}.current_gain[{i}]", p)
                          for i, v in enumerate(raw)])
        if np.any(gains == 0):
            raise RobotError(f"{p}: {key}.current_gain: a gain of 0 turns every current into "
                             "no torque (null: identify it from the logs)")
    return _Transmission(t, offsets, gains, _effort(x.get("effort"), names, p, key))


def _effort(x: Any, names: Sequence[str], p: Path, key: str) -> np.ndarray | None:
    """``effort``: what a ROS joint state's effort holds, ``torque`` (default) or ``current``
    (the drive's current, turned into a torque by ``current_gain``); one word or per joint."""
    if x is None:
        return None
    raw = [x] * len(names) if isinstance(x, str) else _per_joint(x, names, f"{key}.effort", p)
    bad = next((v for v in raw if v not in ("torque", "current")), None)
    if bad is not None or not raw:
        raise RobotError(f"{p}: {key}.effort: expected torque or current, got {str(bad)[:40]!r}")
    return np.array([v == "current" for v in raw])


def _coupling(coupling: Any, names: Sequence[str], p: Path, key: str) -> np.ndarray:
    n = len(names)
    c = np.eye(n)
    coupling = coupling or []
    if not isinstance(coupling, list):
        raise RobotError(f"{p}: {key}.coupling: expected a list of [joint, motor, factor]")
    for k, entry in enumerate(coupling):
        where = f"{key}.coupling[{k}]"
        if not isinstance(entry, list) or len(entry) != 3:
            raise RobotError(f"{p}: {where}: expected [joint, motor, factor]")
        idx = [names.index(v) + 1 if isinstance(v, str) and v in names else v
               for v in entry[:2]]
        if not all(type(v) is int for v in idx):
            raise RobotError(f"{p}: {where}: joint and motor must be whole numbers in 1..{n} "
                             f"or joint names, got {str(entry[:2])[:40]}")
        src, dst = idx
        if not (1 <= src <= n and 1 <= dst <= n) or src == dst:
            raise RobotError(f"{p}: {where}: joints must be distinct numbers in 1..{n}")
        c[dst - 1, src - 1] = _num(entry[2], f"{where}[2]", p)
    return c


def _load_urdf(p: Path, lock: Sequence[str], allow_unlimited: bool) -> Robot:
    text, urdf_joints = check_urdf(p)
    try:
        with native_stderr() as said:
            full = pin.buildModelFromXML(text)
    except (RuntimeError, ValueError) as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise RobotError(f"{p}: cannot parse URDF: {parser_summary(said) or first[:200]}"
                         ) from err
    if parser_summary(said):  # a part robid does not use (a visual's mesh) did not parse
        _log.warning("%s: the URDF parser skipped: %s", p, parser_summary(said))
    if lock:
        ids = []
        for nm in lock:
            if not full.existJointName(nm):
                raise RobotError(f"{p}: --lock {nm}: no joint of that name")
            ids.append(full.getJointId(nm))
        full = pin.buildReducedModel(full, ids, pin.neutral(full))
    names, types, axes, unbounded = [], [], [], []
    for jid in range(1, full.njoints):
        jm = full.joints[jid]
        kind = jm.shortname().removeprefix("JointModel")
        name = full.names[jid]
        if jm.nv != 1:
            raise RobotError(f"{p}: joint '{name}' ({kind}) has {jm.nv} DoF; only 1-DoF "
                             "revolute/prismatic joints are supported (lock it with --lock)")
        ub = kind.startswith("RUB") or kind == "RevoluteUnboundedUnaligned"
        kind = kind.replace("RUB", "R").replace("RevoluteUnbounded", "Revolute")
        if kind in _REVOLUTE:
            types.append("revolute")
            axes.append(_REVOLUTE[kind])
        elif kind in _PRISMATIC:
            types.append("prismatic")
            axes.append(_PRISMATIC[kind])
        elif kind in ("RevoluteUnaligned", "PrismaticUnaligned"):
            types.append("revolute" if kind.startswith("R") else "prismatic")
            axes.append(tuple(np.array(jm.extract().axis, dtype=float)))
        else:
            raise RobotError(f"{p}: joint '{name}' of type {kind} is not supported")
        names.append(name)
        unbounded.append(ub)
    n = len(names)
    if n == 0:
        raise RobotError(f"{p}: the URDF has no movable joint")
    limits = _urdf_limits(p, names, urdf_joints, allow_unlimited)
    nominal = np.concatenate([full.inertias[j].toDynamicParameters() for j in range(1, n + 1)])
    parents = tuple(int(full.parents[j]) - 1 for j in range(1, n + 1))
    tx = _urdf_transmission(p, names, types)
    return Robot(
        name=full.name or p.stem,
        model=full,
        joint_names=tuple(names),
        joint_types=tuple(types),
        axes=np.array(axes, dtype=float),
        parents=parents,
        placements=tuple(full.jointPlacements[j] for j in range(1, n + 1)),
        unbounded=tuple(unbounded),
        limits=limits,
        nominal=nominal,
        transmission=tx.matrix,
        encoder_offsets=tx.offsets,
        current_gain=tx.current_gain,
        effort_current=tx.effort_current,
        source=str(p),
    )
