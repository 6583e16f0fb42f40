"""Experiment kinds: each kind's options (defaults, validation) and the trajectory it moves.

One table, ``EXPERIMENT_KINDS``: a new kind (``elasticity``, ``verify``) is one
``register_kind(ExperimentKind(...))``; the daemon config, the campaign runner and the
program generator all read the table. Numerical work is imported only when a trajectory is made.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from robid_link.exceptions import ConfigError
from robid_link.yamlio import check_keys

if TYPE_CHECKING:
    import numpy as np

    from robid_link.ident.excite.excitation import Trajectory
    from robid_link.ident.model.robot import Robot

__all__ = ["ExperimentKind", "EXPERIMENT_KINDS", "register_kind", "experiment_options",
           "experiment_trajectory"]

Generator = Callable[["Robot", Mapping[str, Any], "Path | None"], "Trajectory"]
Validator = Callable[[dict[str, Any], str], None]


def _no_check(opts: dict[str, Any], where: str) -> None:
    return None


@dataclass(frozen=True)
class ExperimentKind:
    """One kind of experiment: its options over ``defaults`` (``required`` keys have no
    default), an extra ``validate(opts, where)`` and ``generate(robot, opts, base_dir)``."""

    name: str
    defaults: Mapping[str, Any]
    generate: Generator
    validate: Validator = _no_check
    required: tuple[str, ...] = ()
    summary: str = ""
    positive: tuple[str, ...] = field(default=("duration_s", "base_hz", "rate_hz"))


#: kind name → ExperimentKind, in the order users see them
EXPERIMENT_KINDS: dict[str, ExperimentKind] = {}


def register_kind(kind: ExperimentKind) -> ExperimentKind:
    """Add a kind to the table (a name is registered once)."""
    if kind.name in EXPERIMENT_KINDS:
        raise ValueError(f"experiment kind {kind.name!r} is already registered")
    EXPERIMENT_KINDS[kind.name] = kind
    return kind


def experiment_options(kind: str, opts: Mapping[str, Any], where: str) -> dict[str, Any]:
    """The experiment's options over its kind's defaults; errors name the key path."""
    spec = EXPERIMENT_KINDS.get(kind)
    if spec is None:
        raise ConfigError(f"{where}.kind: expected one of {', '.join(EXPERIMENT_KINDS)}, "
                          f"got {kind!r}")
    check_keys(dict(opts), where, required=spec.required,
               optional=[k for k in spec.defaults if k not in spec.required])
    out = {**spec.defaults, **opts}
    for key in spec.positive:
        if key in out:
            v = out[key]
            if isinstance(v, bool) or not isinstance(v, int | float) or v <= 0:
                raise ConfigError(f"{where}.{key}: expected a positive number, got {v!r}")
    spec.validate(out, where)
    return out


def experiment_trajectory(robot: Robot, kind: str, opts: Mapping[str, Any],
                          base_dir: Path | None = None) -> Trajectory:
    """Generate the trajectory of one experiment (numerical work: run it off the event loop)."""
    spec = EXPERIMENT_KINDS.get(kind)
    if spec is None:
        raise ConfigError(f"kind: expected one of {', '.join(EXPERIMENT_KINDS)}, got {kind!r}")
    return spec.generate(robot, opts, base_dir)


# ----------------------------------------------------------------------------- rigid_body


def _rigid_body(robot: Robot, opts: Mapping[str, Any], base_dir: Path | None) -> Trajectory:
    import numpy as np

    from robid_link.ident.excite import excitation as ex

    four, cond = ex.optimize_fourier(robot, harmonics=int(opts["harmonics"]),
                                     base_hz=float(opts["base_hz"]), seed=int(opts["seed"]),
                                     evaluations=int(opts["evaluations"]),
                                     restarts=int(opts["restarts"]))
    rate = float(opts["rate_hz"])
    periods = max(1, round(float(opts["duration_s"]) * four.base_hz))
    t = np.arange(0.0, periods / four.base_hz, 1.0 / rate)
    q = four.evaluate(t)[0]
    return ex.Trajectory(t, q, rate, "fourier", robot.name, ex.fourier_header(four, cond))


def _bounded(opts: Mapping[str, Any], where: str, key: str, lo: float, hi: float, *,
             integer: bool = False) -> None:
    """``opts[key]`` within [lo, hi] (an integer when ``integer``); absurd values are refused
    at load, before any motion, instead of misbehaving after it."""
    v = opts[key]
    ok_type = isinstance(v, int) if integer else isinstance(v, int | float)
    if isinstance(v, bool) or not ok_type or not (lo <= v <= hi) or v != v:
        what = "an integer" if integer else "a number"
        raise ConfigError(f"{where}.{key}: expected {what} in [{lo:g}, {hi:g}], got {v!r}")


def _check_common(opts: Mapping[str, Any], where: str) -> None:
    if "duration_s" in opts:
        _bounded(opts, where, "duration_s", 0.1, 3600.0)
    if "rate_hz" in opts:
        _bounded(opts, where, "rate_hz", 1.0, 10_000.0)


def _check_rigid_body(opts: dict[str, Any], where: str) -> None:
    _check_common(opts, where)
    _bounded(opts, where, "harmonics", 1, 50, integer=True)
    _bounded(opts, where, "base_hz", 1e-3, 10.0)
    _bounded(opts, where, "evaluations", 1, 100_000, integer=True)
    _bounded(opts, where, "restarts", 1, 100, integer=True)
    _bounded(opts, where, "seed", 0, 2**32 - 1, integer=True)


# ----------------------------------------------------------------------------- friction


def _check_friction(opts: dict[str, Any], where: str) -> None:
    sp = opts["speeds"]
    if (not isinstance(sp, list) or not sp
            or not all(isinstance(x, int | float) and not isinstance(x, bool) and 0 < x <= 1
                       for x in sp)):
        raise ConfigError(f"{where}.speeds: expected fractions of each joint's speed limit "
                          "in (0, 1]")
    joints = opts["joints"]
    if joints is not None and (not isinstance(joints, list) or not joints or not all(
            isinstance(j, int) and not isinstance(j, bool) and j >= 1 for j in joints)):
        raise ConfigError(f"{where}.joints: expected a list of joint numbers (from 1)")
    if joints is not None and (len(set(joints)) != len(joints) or max(joints) > 64):
        raise ConfigError(f"{where}.joints: expected distinct joint numbers (1..64), "
                          f"got {joints!r}")
    if len(sp) > 100:
        raise ConfigError(f"{where}.speeds: at most 100 speeds, got {len(sp)}")
    _check_common(opts, where)


def _friction(robot: Robot, opts: Mapping[str, Any], base_dir: Path | None) -> Trajectory:
    import numpy as np

    from robid_link.ident.excite import excitation as ex

    rate = float(opts["rate_hz"])
    joints = opts["joints"] or list(range(1, robot.n + 1))
    parts = []
    for j in joints:
        if not isinstance(j, int) or not 1 <= j <= robot.n:
            raise ConfigError(f"joints: {j!r} is not a joint of {robot.name} (1..{robot.n})")
        cap = robot.limits.qd_max[j - 1]
        cap = cap if np.isfinite(cap) else 1.0
        parts.append(ex.constant_velocity_sweeps(robot, j - 1,
                                                 [f * cap for f in opts["speeds"]], rate))
    q = _joined(robot, parts, rate)
    t = np.arange(q.shape[0]) / rate
    return ex.Trajectory(t, q, rate, "sweep", robot.name,
                         {"joints": joints, "speeds": list(opts["speeds"])})


def _joined(robot: Robot, parts: list[np.ndarray], rate: float) -> np.ndarray:
    """Concatenate per-joint sweeps with transfers between their poses that start and end at
    rest with zero acceleration (quintic smoothstep, at least 2 s, at most half of each joint's
    velocity and acceleration limits: peaks 1.875·D/T and 5.77·D/T²)."""
    import numpy as np

    qd_cap = np.where(np.isfinite(robot.limits.qd_max), robot.limits.qd_max, 1.0)
    qdd_cap = np.where(np.isfinite(robot.limits.qdd_max), robot.limits.qdd_max, 2.0)
    out = [parts[0]]
    for nxt in parts[1:]:
        a, b = out[-1][-1], nxt[0]
        dist = np.abs(b - a)
        duration = max(2.0, float(np.max(1.875 * dist / (0.5 * qd_cap))),
                       float(np.sqrt(np.max(5.774 * dist / (0.5 * qdd_cap)))))
        steps = max(2, int(rate * duration))
        x = np.linspace(0.0, 1.0, steps)[:, None]
        s = x**3 * (10.0 - 15.0 * x + 6.0 * x**2)
        out.append(a + s * (b - a))
        out.append(nxt)
    return np.concatenate(out)


# ----------------------------------------------------------------------------- custom


def _check_custom(opts: dict[str, Any], where: str) -> None:
    if not isinstance(opts["trajectory"], str) or not opts["trajectory"]:
        raise ConfigError(f"{where}.trajectory: expected the path of a trajectory file "
                          f"(CSV t,q1..qn + its .yaml header), got {opts['trajectory']!r}")


def _custom(robot: Robot, opts: Mapping[str, Any], base_dir: Path | None) -> Trajectory:
    from robid_link.ident.excite import excitation as ex

    path = Path(opts["trajectory"])
    if base_dir is not None and not path.is_absolute():
        path = base_dir / path
    traj = ex.read_trajectory(path)
    if traj.q.shape[1] != robot.n:
        raise ConfigError(f"{path}: {traj.q.shape[1]} joints, the robot has {robot.n}")
    return ex.Trajectory(traj.t - traj.t[0], traj.q, traj.rate_hz, "custom", robot.name,
                         {**traj.header, "source": str(path)})


register_kind(ExperimentKind(
    "rigid_body", {"duration_s": 40.0, "harmonics": 8, "base_hz": 0.1, "rate_hz": 250.0,
                   "evaluations": 600, "restarts": 1, "seed": 0},
    _rigid_body, _check_rigid_body,
    summary="optimised Fourier excitation of the rigid-body parameters"))
register_kind(ExperimentKind(
    "friction", {"speeds": [0.05, 0.1, 0.2, 0.4], "joints": None, "rate_hz": 250.0},
    _friction, _check_friction, summary="constant-velocity sweeps, one joint at a time"))
register_kind(ExperimentKind(
    "custom", {"trajectory": None}, _custom, _check_custom, required=("trajectory",),
    summary="a trajectory file given by the user"))


# ----------------------------------------------------------------------------- verify


def _check_verify(opts: dict[str, Any], where: str) -> None:
    sp = opts["speed"]
    if isinstance(sp, bool) or not isinstance(sp, int | float) or not 0 < sp <= 1:
        raise ConfigError(f"{where}.speed: expected a fraction of the limits in (0, 1], "
                          f"got {sp!r}")


def _verify(robot: Robot, opts: Mapping[str, Any], base_dir: Path | None) -> Trajectory:
    from robid_link.ident.excite.verify import verify_trajectory

    return verify_trajectory(robot, speed=float(opts["speed"]), rate_hz=float(opts["rate_hz"]))


register_kind(ExperimentKind(
    "verify", {"speed": 0.6, "rate_hz": 250.0}, _verify, _check_verify,
    summary="a fixed, fast path run before and after an upload: tracking and tool error"))


# ----------------------------------------------------------------------------- elasticity


def _check_elasticity(opts: dict[str, Any], where: str) -> None:
    joints = opts["joints"]
    if joints is not None and (not isinstance(joints, list) or not joints or not all(
            isinstance(j, int) and not isinstance(j, bool) and 1 <= j <= 64 for j in joints)):
        raise ConfigError(f"{where}.joints: expected a list of joint numbers (from 1)")
    pairs = opts["pairs"]
    if not isinstance(pairs, list) or not all(
            isinstance(p, list) and len(p) == 2 and p[0] != p[1] and all(
                isinstance(j, int) and not isinstance(j, bool) and 1 <= j <= 64 for j in p)
            for p in pairs):
        raise ConfigError(f"{where}.pairs: expected pairs of joint numbers, e.g. [[2, 3]]")
    pose = opts["pose_deg"]
    if pose is not None and (not isinstance(pose, list) or not all(
            isinstance(x, int | float) and not isinstance(x, bool) and abs(x) <= 3600
            for x in pose)):
        raise ConfigError(f"{where}.pose_deg: expected one angle (degrees) per joint")
    lo, hi = opts["f_min_hz"], opts["f_max_hz"]
    if not (isinstance(lo, int | float) and isinstance(hi, int | float) and 0 < lo < hi <= 500):
        raise ConfigError(f"{where}.f_max_hz: expected 0 < f_min_hz < f_max_hz ≤ 500, got "
                          f"{lo!r}, {hi!r}")
    steps = opts["steps"]
    if isinstance(steps, bool) or not isinstance(steps, int) or not 4 <= steps <= 200:
        raise ConfigError(f"{where}.steps: expected a whole number in 4..200, got {steps!r}")


def _elasticity(robot: Robot, opts: Mapping[str, Any], base_dir: Path | None) -> Trajectory:
    import math

    from robid_link.ident.elastic.frequency import ElasticityOptions, elasticity_trajectory

    pose = opts["pose_deg"]
    if pose is not None and len(pose) != robot.n:
        raise ConfigError(f"pose_deg: {len(pose)} angles, the robot has {robot.n} joints")
    if opts["joints"] and max(opts["joints"]) > robot.n:
        raise ConfigError(f"joints: {max(opts['joints'])} is not a joint of {robot.name}")
    if any(max(p) > robot.n for p in opts["pairs"]):
        raise ConfigError(f"pairs: {opts['pairs']} has a joint beyond {robot.n}")
    return elasticity_trajectory(robot, ElasticityOptions(
        joints=tuple(opts["joints"] or ()), pairs=tuple(tuple(p) for p in opts["pairs"]),
        pose=None if pose is None else tuple(math.radians(x) for x in pose),
        f_min_hz=float(opts["f_min_hz"]), f_max_hz=float(opts["f_max_hz"]),
        steps=int(opts["steps"]), rate_hz=float(opts["rate_hz"])))


register_kind(ExperimentKind(
    "elasticity", {"joints": None, "pairs": [], "pose_deg": None, "f_min_hz": 2.0, "f_max_hz": 60.0,
                   "steps": 24, "rate_hz": 2000.0}, _elasticity, _check_elasticity,
    summary="stepped sines per axis (pairs: two axes together) around a pose: FRFs, "
            "two-mass fit (Jm, Ja, K, D), coupled fit (Jcop)"))
