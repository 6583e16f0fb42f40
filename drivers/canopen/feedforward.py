"""The CANopen driver's feedforward as data: the uploaded parameter set it keeps (checked, saved,
restored after a restart) and the per-mille torque offsets (0x60B2) of a torque table.

The daemon is the motion master, so the "controller" that loads the set is this driver; the
model torque of each setpoint (the set's inverse dynamics plus its joint friction) is computed
by the worker and handed over as a ``FeedforwardTable`` (``Driver.feedforward_table``).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from robid_link.atomic import atomic_write
from robid_link.exceptions import DriverError, RobidError
from robid_link.jobs import FeedforwardTable, ParameterSet, RobotInfo

__all__ = ["KeptParameterSet", "torque_offsets", "PER_MILLE_MAX"]

log = logging.getLogger("robid.driver.canopen")

PER_MILLE_MAX = 32767  # 0x60B2 is INTEGER16


def torque_offsets(table: FeedforwardTable, rated_nm: Sequence[float]) -> np.ndarray:
    """Per-mille torque offsets (N, n) of a torque table (N·m), rounded and clipped to 16 bit."""
    tau = np.asarray(table.tau, dtype=float).reshape(len(table.tau), len(rated_nm))
    pm = np.rint(tau / np.asarray(rated_nm, dtype=float) * 1000.0)
    return np.clip(pm, -PER_MILLE_MAX, PER_MILLE_MAX).astype(np.int64)


class KeptParameterSet:
    """The parameter set in use for one robot, kept as its exact bytes in ``path`` so that a
    restarted daemon goes on with the set it had acknowledged. ``in_use`` is None (zero
    offsets) until a set is loaded or restored."""

    def __init__(self, robot: RobotInfo, path: Path) -> None:
        self.robot, self.path = robot, path
        self.in_use: ParameterSet | None = None

    @property
    def sha256(self) -> str | None:
        return None if self.in_use is None else self.in_use.sha256

    def check(self, body: bytes) -> ParameterSet:
        """The set in ``body``, or DriverError naming why it is refused (format, hash, robot,
        sizes)."""
        try:
            pset = ParameterSet.from_doc(json.loads(body))
            pset.check(self.robot.n)
        except (ValueError, RobidError) as err:
            raise DriverError(f"parameter set refused: {err}") from err
        if pset.robot not in (None, self.robot.name):
            raise DriverError(f"parameter set refused: it is for robot {pset.robot}, the "
                              f"drives move {self.robot.name}")
        return pset

    def load(self, body: bytes) -> None:
        """Check, persist, then use the set (a refused set leaves the previous one in use)."""
        pset = self.check(body)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(self.path, body)
        self.in_use = pset
        log.info("parameter set %s in use: torque offsets (0x60B2) from its inverse "
                 "dynamics and friction", pset.sha256[:12])

    def restore(self) -> None:
        """The set a previous daemon acknowledged, if any (a damaged file: zero offsets)."""
        if not self.path.is_file():
            return
        try:
            self.in_use = self.check(self.path.read_bytes())
            log.info("parameter set %s restored from %s", self.in_use.sha256[:12], self.path)
        except (OSError, RobidError) as err:
            log.warning("%s: saved parameter set not used (%s); torque offsets are zero",
                        self.path, err)
