"""Experiment kinds: the trajectory each kind moves. Their options (defaults, validation) are
on the door (``robid_link/kinds.py``), checked by the daemon config at load and here again.

One table, ``EXPERIMENT_KINDS``: a new kind (``elasticity``, ``verify``) is its options in
``kinds.KIND_OPTIONS`` and one ``register_kind(ExperimentKind(...))`` here. Numerical work is
imported only when a trajectory is made.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from robid_link.exceptions import ConfigError
from robid_link.kinds import KIND_OPTIONS, KindOptions, experiment_options

if TYPE_CHECKING:
    import numpy as np

    from robid_link.ident.excite.excitation import Trajectory
    from robid_link.ident.model.robot import Robot

__all__ = ["ExperimentKind", "EXPERIMENT_KINDS", "register_kind", "experiment_trajectory"]

Generator = Callable[["Robot", Mapping[str, Any], "Path | None"], "Trajectory"]


@dataclass(frozen=True)
class ExperimentKind:
    """One kind of experiment: ``generate(robot, opts, base_dir)``; its options are
    ``kinds.KIND_OPTIONS[name]``."""

    name: str
    generate: Generator

    @property
    def options(self) -> KindOptions:
        return KIND_OPTIONS[self.name]


#: kind name → ExperimentKind, in the order users see them
EXPERIMENT_KINDS: dict[str, ExperimentKind] = {}


def register_kind(kind: ExperimentKind) -> ExperimentKind:
    """Add a kind to the table (a name is registered once, and has its options)."""
    if kind.name in EXPERIMENT_KINDS:
        raise ValueError(f"experiment kind {kind.name!r} is already registered")
    if kind.name not in KIND_OPTIONS:
        raise ValueError(f"experiment kind {kind.name!r} has no options in kinds.KIND_OPTIONS")
    EXPERIMENT_KINDS[kind.name] = kind
    return kind


def experiment_trajectory(robot: Robot, kind: str, opts: Mapping[str, Any],
                          base_dir: Path | None = None, where: str = "experiment") -> Trajectory:
    """Generate the trajectory of one experiment (numerical work: run it off the event loop);
    its options are checked again (``where`` names them in errors)."""
    spec = EXPERIMENT_KINDS.get(kind)
    if spec is None:
        raise ConfigError(f"{where}.kind: expected one of {', '.join(EXPERIMENT_KINDS)}, "
                          f"got {kind!r}")
    checked = experiment_options(kind, opts, where)
    try:
        return spec.generate(robot, checked, base_dir)
    except ConfigError as err:  # the checks against the robot name the option, not the entry
        if str(err).startswith(where):
            raise
        raise type(err)(f"{where}: {err}") from err


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


# ----------------------------------------------------------------------------- friction


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


register_kind(ExperimentKind("rigid_body", _rigid_body))
register_kind(ExperimentKind("friction", _friction))
register_kind(ExperimentKind("custom", _custom))


# ----------------------------------------------------------------------------- verify


def _verify(robot: Robot, opts: Mapping[str, Any], base_dir: Path | None) -> Trajectory:
    from robid_link.ident.excite.verify import verify_trajectory

    return verify_trajectory(robot, speed=float(opts["speed"]), rate_hz=float(opts["rate_hz"]))


register_kind(ExperimentKind("verify", _verify))


# ----------------------------------------------------------------------------- elasticity


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


register_kind(ExperimentKind("elasticity", _elasticity))
