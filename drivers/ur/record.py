"""One attempt on a Universal Robots controller as its RTDE stream tells it: sent → playing →
on the path (the marker register holds the attempt's tag) → stopped with the path done (−tag);
the rows recorded on the path and the log file made of them (``t,q1..q6,qd1..qd6,tau1..tau6``).

Pure bookkeeping, no I/O: ``feed`` takes one data package's values and says whether the
attempt goes on, ended (``DONE``) or failed (a DriverError naming why).
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass, field

import numpy as np

from robid_link.exceptions import DriverError

__all__ = ["ROBOT_MODES", "SAFETY_MODES", "RUNTIME_STATES", "Recording", "EndedEarly", "DONE",
           "log_header"]

ROBOT_MODES = {-1: "NO_CONTROLLER", 0: "DISCONNECTED", 1: "CONFIRM_SAFETY", 2: "BOOTING",
               3: "POWER_OFF", 4: "POWER_ON", 5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING",
               8: "UPDATING_FIRMWARE"}
SAFETY_MODES = {1: "NORMAL", 2: "REDUCED", 3: "PROTECTIVE_STOP", 4: "RECOVERY",
                5: "SAFEGUARD_STOP", 6: "SYSTEM_EMERGENCY_STOP", 7: "ROBOT_EMERGENCY_STOP",
                8: "VIOLATION", 9: "FAULT", 10: "VALIDATE_JOINT_ID", 11: "UNDEFINED_SAFETY_MODE",
                12: "AUTOMATIC_MODE_SAFEGUARD_STOP", 13: "SYSTEM_THREE_POSITION_ENABLING_STOP"}
RUNTIME_STATES = {0: "STOPPING", 1: "STOPPED", 2: "PLAYING", 3: "PAUSING", 4: "PAUSED",
                  5: "RESUMING"}
RUNNING, PLAYING, STOPPED, STOPPING = 7, 2, 1, 0
DONE = "done"
_CHUNK = 4096


class EndedEarly(DriverError):
    """The program stopped before its path ended: nothing is left to stop."""


def log_header(n: int = 6) -> str:
    return ",".join(["t", *(f"{k}{j}" for k in ("q", "qd", "tau") for j in range(1, n + 1))])


def mode_name(table: dict[int, str], value: int) -> str:
    return f"{table.get(value, 'unknown')} ({value})"


@dataclass
class Recording:
    """The state of one attempt. ``frequency_hz`` is the stream's; ``max_rows`` bounds the
    log (a program that runs far longer than it should is stopped, not recorded forever)."""

    exp_id: str
    tag: int
    frequency_hz: float
    sent_at: float
    start_timeout_s: float
    max_rows: int
    torque_gain: np.ndarray | None = None  # N·m/A when the torque field is actual_current
    stage: str = "sent"  # sent → playing → path → done
    rows: int = 0
    packages: int = 0  # data packages fed
    received: int = 0  # data packages the session read in all (set-up check and pause too)
    missed: int = 0  # packages the controller skipped, from the time stamps
    path_missed: int = 0  # of which on the path (holes in the log)
    arrivals: list[np.ndarray] = field(default_factory=list)
    _chunks: list[np.ndarray] = field(default_factory=list)
    _last_ts: float | None = None
    _t0: float | None = None

    def feed(self, ts: float, q: tuple[float, ...], qd: tuple[float, ...],
             tau: tuple[float, ...], runtime: int, robot_mode: int, safety: int, marker: int,
             now: float) -> str | None:
        """One data package (``now``: the loop's clock when it arrived)."""
        self.packages += 1
        skipped = 0
        if self._last_ts is not None:
            gap = (ts - self._last_ts) * self.frequency_hz
            if gap > 1.5:
                skipped = int(round(gap)) - 1
                self.missed += skipped
        self._last_ts = ts
        if self.stage == "sent":
            if runtime == PLAYING:
                self.stage = "playing"
            elif now - self.sent_at > self.start_timeout_s:
                raise DriverError(f"experiment {self.exp_id}: the controller did not start the "
                                  f"program within {self.start_timeout_s:g} s (runtime state "
                                  f"{mode_name(RUNTIME_STATES, runtime)})")
            else:
                return None
        self._check_modes(robot_mode, safety, runtime)
        if marker == self.tag:
            if self.stage == "path":
                self.path_missed += skipped
            self.stage = "path"
            self._record(ts, q, qd, tau, now)
        if runtime in (STOPPED, STOPPING):
            if marker == -self.tag:
                self.stage = DONE
                return DONE
            raise EndedEarly(f"experiment {self.exp_id}: the program stopped before the end "
                              f"of its path ({self._where()}; stopped on the pendant, a script "
                              "error, or another program took over)")
        return None

    def _check_modes(self, robot_mode: int, safety: int, runtime: int) -> None:
        if safety not in (1, 2):
            raise DriverError(f"controller reports experiment {self.exp_id} failed: safety mode "
                              f"{mode_name(SAFETY_MODES, safety)} {self._where()}")
        if robot_mode != RUNNING:
            raise DriverError(f"controller reports experiment {self.exp_id} failed: robot mode "
                              f"{mode_name(ROBOT_MODES, robot_mode)} {self._where()}")
        if runtime not in (PLAYING, STOPPED, STOPPING):
            raise DriverError(f"experiment {self.exp_id}: the program was paused "
                              f"({mode_name(RUNTIME_STATES, runtime)}) {self._where()}: the log "
                              "would have a hole")

    def _where(self) -> str:
        if self._t0 is None or self._last_ts is None:
            return "before its path began"
        return f"{self._last_ts - self._t0:.3f} s into its path"

    def _record(self, ts: float, q: tuple[float, ...], qd: tuple[float, ...],
                tau: tuple[float, ...], now: float) -> None:
        if self.rows >= self.max_rows:
            raise DriverError(f"experiment {self.exp_id}: still on its path after "
                              f"{self.rows} samples, far longer than the program")
        k = self.rows % _CHUNK
        if k == 0:
            self._chunks.append(np.empty((_CHUNK, 19)))
            self.arrivals.append(np.empty(_CHUNK))
        if self._t0 is None:
            self._t0 = ts
        row = self._chunks[-1][k]
        row[0] = ts - self._t0
        row[1:7], row[7:13], row[13:19] = q, qd, tau
        if not all(math.isfinite(x) for x in row):
            raise DriverError(f"experiment {self.exp_id}: the controller sent a non-finite "
                              f"position, speed or torque {self._where()}")
        self.arrivals[-1][k] = now
        self.rows += 1

    def table(self) -> np.ndarray:
        """The recorded rows (t, q, qd, tau in rad, rad/s, N·m)."""
        if not self._chunks:
            return np.empty((0, 19))
        out = np.concatenate(self._chunks)[: self.rows].copy()
        if self.torque_gain is not None:
            out[:, 13:19] *= self.torque_gain
        return out

    def inter_arrival_s(self) -> np.ndarray:
        if not self.arrivals:
            return np.empty(0)
        return np.diff(np.concatenate(self.arrivals)[: self.rows])

    def log_bytes(self) -> bytes:
        """The house CSV of the path (blocking: a thread renders it)."""
        table = self.table()
        if table.shape[0] < 2:
            raise DriverError(f"experiment {self.exp_id}: the path left fewer than two samples "
                              "in the RTDE stream")
        buf = io.StringIO()
        np.savetxt(buf, table, delimiter=",", header=log_header(), comments="", fmt="%.10g")
        return buf.getvalue().encode()
