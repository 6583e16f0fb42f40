"""Logs of the independent plant (``arm.py``) as the truth tests use them: a friction base,
one effect hidden on a joint, written as CSV and read back as the identification reads logs."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

from robid_link.exceptions import ConditioningWarning, DataWarning, ExcitationWarning

from .arm import CATALOG, Arm, Effect, Loop, Noise, Record, fourier_motion, write_csv

__all__ = ["BASE", "hidden", "plant_log", "quiet"]

#: the friction every plant has unless a test takes it away
BASE = (Effect("viscous", p={"b": 2.0}), Effect("coulomb", p={"fc": 1.5}))


def hidden(name: str, joint: int | None, **p: float) -> Effect:
    """The catalog instance of ``name`` on ``joint`` (None for a global effect), constants
    overridden by ``p``."""
    e = CATALOG[name]
    return Effect(e.name, joint, {**e.p, **p})


def plant_log(robot: Any, path: Path, *, effects: tuple[Effect, ...] = BASE,
              rate_hz: float = 250.0, duration_s: float = 40.0, noise: Noise | None = None,
              seed: int = 1, motion_seed: int = 3, loop: Loop | None = None,
              **csv: Any) -> tuple[Path, Record]:
    """One log of the plant following its own Fourier motion, written to ``path``."""
    arm = Arm(robot, effects=effects, noise=noise or Noise(0.3), seed=seed)
    rec = arm.run(fourier_motion(robot, motion_seed), rate_hz=rate_hz, duration_s=duration_s,
                  seed=seed + 100, loop=loop)
    return write_csv(path, rec, **csv), rec


def quiet() -> None:
    """Inside ``warnings.catch_warnings()``: what these logs are known to raise (weakly
    excited columns, torques unlike the a-priori model's, extrapolation) is not an error."""
    warnings.simplefilter("ignore", ConditioningWarning)
    warnings.simplefilter("ignore", ExcitationWarning)
    warnings.simplefilter("ignore", DataWarning)
