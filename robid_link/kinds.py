"""Experiment kinds' options, on the door between the link and the worker: the daemon config
checks them at load and the worker again when it makes a program (``ident/excite/experiments.py``
holds each kind's trajectory generator). Errors name the key path."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from robid_link.exceptions import ConfigError
from robid_link.yamlio import check_keys

__all__ = ["KindOptions", "KIND_OPTIONS", "experiment_options"]

Validator = Callable[[dict[str, Any], str], None]
#: the rates a robot's log, trajectory or controller can plausibly have (Hz): below, the
#: samples cannot carry the dynamics (the default 10 Hz cutoff would be above Nyquist, or the
#: time is not in seconds); above, no robot controller runs. The one home of these bounds:
#: the config, the CLI, the worker's logs and trajectories and the fake plant read them here.
MIN_RATE_HZ = 10.0
MAX_RATE_HZ = 100_000.0


def _no_check(opts: dict[str, Any], where: str) -> None:
    return None


@dataclass(frozen=True)
class KindOptions:
    """One experiment kind's options, checked alike by the daemon config (at load) and the
    worker (when it makes the program): ``defaults`` (``required`` keys have none), numbers
    that must be ``positive``, and an extra ``validate(opts, where)``."""

    name: str
    defaults: Mapping[str, Any]
    validate: Validator = _no_check
    required: tuple[str, ...] = ()
    summary: str = ""
    positive: tuple[str, ...] = ("duration_s", "base_hz", "rate_hz")


def experiment_options(kind: str, opts: Mapping[str, Any], where: str) -> dict[str, Any]:
    """The experiment's options over its kind's defaults; errors name the key path."""
    spec = KIND_OPTIONS.get(kind)
    if spec is None:
        raise ConfigError(f"{where}.kind: expected one of {', '.join(KIND_OPTIONS)}, "
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
    if "rate_hz" in opts:  # the plausible rates of a trajectory (ident.excite MIN_RATE_HZ)
        _bounded(opts, where, "rate_hz", MIN_RATE_HZ, 10_000.0)


def _check_rigid_body(opts: dict[str, Any], where: str) -> None:
    _check_common(opts, where)
    _bounded(opts, where, "harmonics", 1, 50, integer=True)
    _bounded(opts, where, "base_hz", 1e-3, 10.0)
    _bounded(opts, where, "evaluations", 1, 100_000, integer=True)
    _bounded(opts, where, "restarts", 1, 100, integer=True)
    _bounded(opts, where, "seed", 0, 2**32 - 1, integer=True)


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


def _check_custom(opts: dict[str, Any], where: str) -> None:
    if not isinstance(opts["trajectory"], str) or not opts["trajectory"]:
        raise ConfigError(f"{where}.trajectory: expected the path of a trajectory file "
                          f"(CSV t,q1..qn + its .yaml header), got {opts['trajectory']!r}")


def _check_verify(opts: dict[str, Any], where: str) -> None:
    _check_common(opts, where)
    sp = opts["speed"]
    if isinstance(sp, bool) or not isinstance(sp, int | float) or not 0 < sp <= 1:
        raise ConfigError(f"{where}.speed: expected a fraction of the limits in (0, 1], "
                          f"got {sp!r}")


def _check_elasticity(opts: dict[str, Any], where: str) -> None:
    _check_common(opts, where)
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
    _bounded(opts, where, "f_min_hz", 1e-3, 500.0)
    _bounded(opts, where, "f_max_hz", 1e-3, 500.0)
    lo, hi = opts["f_min_hz"], opts["f_max_hz"]
    if lo >= hi:
        raise ConfigError(f"{where}.f_min_hz: expected a frequency below f_max_hz {hi:g} Hz, "
                          f"got {lo:g}")
    if isinstance(opts.get("rate_hz"), int | float) and hi > 0.2 * opts["rate_hz"]:
        raise ConfigError(f"{where}.f_max_hz: {hi:g} Hz is above 20 % of rate_hz "
                          f"{opts['rate_hz']:g} (the sines need ≥ 5 samples a period)")
    steps = opts["steps"]
    if isinstance(steps, bool) or not isinstance(steps, int) or not 4 <= steps <= 200:
        raise ConfigError(f"{where}.steps: expected a whole number in 4..200, got {steps!r}")


#: kind name → its options, in the order users see them (the worker's
#: ``ident/excite/experiments.py`` holds each kind's trajectory generator)
KIND_OPTIONS: dict[str, KindOptions] = {k.name: k for k in (
    KindOptions("rigid_body", {"duration_s": 40.0, "harmonics": 8, "base_hz": 0.1,
                               "rate_hz": 250.0, "evaluations": 600, "restarts": 1, "seed": 0},
                _check_rigid_body,
                summary="optimised Fourier excitation of the rigid-body parameters"),
    KindOptions("friction", {"speeds": [0.05, 0.1, 0.2, 0.4], "joints": None, "rate_hz": 250.0},
                _check_friction, summary="constant-velocity sweeps, one joint at a time"),
    KindOptions("custom", {"trajectory": None}, _check_custom, required=("trajectory",),
                summary="a trajectory file given by the user"),
    KindOptions("verify", {"speed": 0.6, "rate_hz": 250.0}, _check_verify,
                summary="a fixed, fast path run before and after an upload: tracking and "
                        "tool error"),
    KindOptions("elasticity", {"joints": None, "pairs": [], "pose_deg": None, "f_min_hz": 2.0,
                               "f_max_hz": 60.0, "steps": 24, "rate_hz": 2000.0},
                _check_elasticity,
                summary="stepped sines per axis (pairs: two axes together) around a pose: "
                        "FRFs, two-mass fit (Jm, Ja, K, D), coupled fit (Jcop)"),
)}
