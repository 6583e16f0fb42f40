"""The cyclic motion master of the CANopen driver: one thread that, every SYNC period, reads the
drives' last TPDOs, checks them, sends each drive its RPDO (controlword + target) and the SYNC.

It streams a ``Job`` (counts per SYNC), records what the drives measure, ramps to rest on
request and quick-stops every drive on any fault. It never runs on the event loop.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any

import can
import numpy as np

from robid_link.drivers.canopen.cia402 import (
    CW_ENABLE,
    CW_QUICK_STOP,
    CW_SHUTDOWN,
    RPDO1,
    SYNC_ID,
    SYNC_OVERFLOW,
    TPDO1,
    TPDO2,
    drive_state,
    error_words,
    sync_counter,
)
from robid_link.drivers.canopen.realtime import realtime

__all__ = ["Axis", "Job", "SyncMaster", "quintic", "ramp_to_rest"]

log = logging.getLogger("robid.driver.canopen")

# a drive's answer to one SYNC: status, position (counts), torque, velocity (counts/s: a
# difference of positions, inf when unknown), and in a sample its last EMCY error code
_Answer = tuple[int, int, int, float]
_Sample = tuple[int, int, int, float, int]


@dataclass
class Axis:
    """One drive (= one joint) as the master sees it; the notifier thread fills the inputs.

    ``slots`` holds what the drive answered per SYNC index (its TPDOs carry the SYNC counter),
    ``[(status, pos), (torque,)]`` until both came; ``heard`` the newest SYNC index each of
    its two TPDOs answered (each comes in order; the two may overtake each other on a bus),
    ``newest`` the newest SYNC index it answered completely. The velocity (counts/s) is the
    difference of successive answered positions (``_velocity``)."""

    node: int
    joint: int  # from 1
    name: str
    counts_per_rad: float
    rated_torque_nm: float  # joint torque of 1000 per mille (the torque offset's unit)
    window_counts: float  # following-error window
    torque_unit_nm: float = 0.0  # N·m per unit of the torque object in TPDO2 (0: ‰ of rated)
    slots: dict[int, list[Any]] = field(default_factory=dict)
    heard: list[int] = field(default_factory=lambda: [-1, -1])
    newest: int = -1
    last: _Sample | None = None  # status, pos, torque, vel, error
    missed: int = 0
    seen: tuple[int, int] | None = None  # (SYNC index, position) of ``last``
    row_seen: tuple[int, int] | None = None  # (SYNC index, position) of the last recorded row
    heartbeat_at: float = 0.0
    nmt_state: int = -1
    emcy: int = 0

    def label(self) -> str:
        return f"node {self.node} (joint {self.joint} {self.name})"


@dataclass
class Job:
    """One experiment streamed by the master: targets in counts (approach, then program), the
    recorded samples of the program part, and how it ended (``result`` for the driver)."""

    exp_id: str
    nonce: str
    targets: np.ndarray  # (N, n) int64 counts per SYNC
    record_from: int  # first target of the program proper
    t0: float
    period: float
    settle_timeout_s: float
    offsets: np.ndarray | None = None  # (N, n) torque offsets 0x60B2, per mille; None: zero
    rows: list[tuple[float, tuple[int, ...], tuple[int, ...]]] = field(default_factory=list)
    k: int = 0
    sync0: int | None = None
    settled: int = 0
    settle_start: float | None = None
    settle_from: int = 0  # the first SYNC after the last setpoint
    error: str | None = None
    missing_rows: int = 0
    quick_stop: bool = False  # ended by a fault (else finished, or ramped to rest on request)
    drive_fault: Axis | None = None  # the drive whose own fault ended it (0x603F to be read)
    ended: threading.Event = field(default_factory=threading.Event)
    result: Future[Any] = field(default_factory=Future)


def quintic(a: np.ndarray, b: np.ndarray, qd_cap: np.ndarray, qdd_cap: np.ndarray,
            period: float) -> np.ndarray:
    """A rest-to-rest move a → b (quintic smoothstep) within the caps (peaks 1.875·D/T and
    5.77·D/T²), sampled at ``period``; empty when already there."""
    dist = np.abs(b - a)
    if not np.any(dist > 0):
        return np.empty((0, a.size))
    duration = max(0.2, float(np.max(1.875 * dist / qd_cap)),
                   float(np.sqrt(np.max(5.774 * dist / qdd_cap))))
    x = (np.arange(1, int(math.ceil(duration / period)) + 1) * period / duration)[:, None]
    x = np.minimum(x, 1.0)
    return a + (x**3 * (10.0 - 15.0 * x + 6.0 * x**2)) * (b - a)


def ramp_to_rest(pos: np.ndarray, vel: np.ndarray, decel: np.ndarray, period: float
                 ) -> np.ndarray:
    """Targets that bring moving axes to rest at ``decel`` (per axis), from ``pos``, ``vel``."""
    steps = int(np.ceil(np.max(np.abs(vel) / decel) / period)) if np.any(vel) else 0
    out, p, v = [], pos.astype(float), vel.astype(float)
    for _ in range(steps):
        v = np.sign(v) * np.maximum(np.abs(v) - decel * period, 0.0)
        p = p + v * period
        out.append(p.copy())
    return np.array(out).reshape(-1, pos.size)


def _lost(axis: Axis, part: list[Any] | None, index: int) -> bool:
    """Whether what ``axis`` has not answered of SYNC ``index`` is lost: each missing TPDO
    answered a later SYNC already."""
    return all((part is not None and part[k] is not None) or axis.heard[k] > index
               for k in (0, 1))


class _Stop(Exception):
    def __init__(self, axis: Axis | None, cause: str, drive_fault: bool = False) -> None:
        super().__init__(cause)
        self.axis, self.cause, self.drive_fault = axis, cause, drive_fault


class SyncMaster:
    """The SYNC producer and setpoint streamer (a dedicated thread with absolute deadlines).

    ``mode``: ``hold`` (every drive keeps its target), ``job`` (stream a Job), ``ramp`` (come to
    rest, then hold or disable), ``halted`` (after a fault: quick stop, latched).
    """

    def __init__(self, bus: can.BusABC, axes: Sequence[Axis], period: float, *,
                 heartbeat_timeout_s: float, max_missed: int, overrun_streak: int,
                 standstill_rad_s: float, decel_rad_s2: np.ndarray,
                 on_end: Callable[[Job], None], tap: Callable[[can.Message], None],
                 send_lock: threading.Lock | None = None, tpdo2: Any = TPDO2,
                 priority: int = 0) -> None:
        self.bus, self.axes, self.period = bus, list(axes), period
        self.priority = priority  # SCHED_FIFO for the SYNC thread (0: normal scheduling)
        self.tpdo2 = tpdo2  # the torque object's width decides it (cia402.tpdo2_struct)
        # one frame at a time on the bus: SDO and NMT go out from other threads (a socketcand
        # client writes each frame to one TCP stream)
        self.send_lock = send_lock or threading.Lock()
        self.heartbeat_timeout_s, self.max_missed = heartbeat_timeout_s, max_missed
        self.overrun_streak, self.on_end, self.tap = overrun_streak, on_end, tap
        cpr = np.array([a.counts_per_rad for a in axes])
        self.standstill = standstill_rad_s * cpr
        self.decel = decel_rad_s2 * cpr
        self.lock = threading.Lock()  # the notifier thread's inputs and the mode
        self.mode = "hold"
        self.hold = np.zeros(len(axes), dtype=np.int64)
        self.cmd = self.hold.copy()
        self.cmd_prev = self.hold.copy()
        self.sent: dict[int, np.ndarray] = {}  # the target sent with each recent SYNC
        self.offset = np.zeros(len(axes), dtype=np.int64)  # kept after a job: no torque step
        self.job: Job | None = None
        self.ramp: np.ndarray | None = None
        self.ramp_then = "hold"
        self.halt_reason: str | None = None
        # something no drive of ours may send (another node on our COB-ID, two different
        # answers to one SYNC, a TPDO mapped otherwise): seen on the notifier thread, the
        # master stops at its next tick
        self.protocol_fault: _Stop | None = None
        self.duplicates = 0  # identical TPDOs repeated for one SYNC (ignored)
        self.sync_count = 0  # SYNCs sent; the next one has index sync_count
        self.next_row = 0  # the oldest SYNC index not yet recorded or given up
        # the SYNC indices every drive answered (status, pos, torque, vel per drive), None for
        # one a drive left unanswered, oldest first; the running job takes what is its own
        self.answered: list[tuple[int, list[_Answer] | None]] = []
        self.overruns = 0
        self.worst_late_s = 0.0  # the longest interval between two SYNCs beyond a period
        self.late_streak = 0
        self.sync_times: list[float] = []
        self.keep_times = False
        self.tick_hook: Callable[[], None] | None = None  # tests: a slow host
        self.spin_s = 0.0003
        self.scheduling = "normal"  # the SYNC thread's, once it runs
        self._quit = threading.Event()
        self._thread: threading.Thread | None = None
        self.idle = threading.Event()

    # -- inputs (notifier thread)
    def on_tpdo1(self, i: int, data: bytes | bytearray) -> None:
        if len(data) != TPDO1.size:
            self._refuse(i, f"TPDO1 of {len(data)} bytes, {TPDO1.size} mapped")
            return
        status, pos, counter = TPDO1.unpack(data)
        self._answer(i, 0, counter, (status, pos))

    def on_tpdo2(self, i: int, data: bytes | bytearray) -> None:
        if len(data) != self.tpdo2.size:
            self._refuse(i, f"TPDO2 of {len(data)} bytes, {self.tpdo2.size} mapped")
            return
        torque, counter = self.tpdo2.unpack(data)
        self._answer(i, 1, counter, (torque,))

    def _refuse(self, i: int, cause: str) -> None:
        """A frame no drive of ours sends: the master stops every drive at its next tick."""
        if self.protocol_fault is None:
            self.protocol_fault = _Stop(self.axes[i], f"{cause}: not this drive's answer "
                                                      "(another node on its COB-ID, or mapped "
                                                      "otherwise); refused")

    def _answer(self, i: int, part: int, counter: int, values: tuple[int, ...]) -> None:
        """A TPDO put at the SYNC it answers: the newest SYNC sent (or being sent) with its
        counter. ``max_missed`` < SYNC_OVERFLOW keeps that unambiguous: a drive whose answers
        come later than that is stopped first. The same answer twice is ignored; a different
        second answer to one SYNC is refused (two senders on one COB-ID)."""
        if not 1 <= counter <= SYNC_OVERFLOW:
            self._refuse(i, f"TPDO{part + 1} with SYNC counter {counter} (1..{SYNC_OVERFLOW})")
            return
        with self.lock:
            newest = self.sync_count  # this SYNC may be out while its count is not yet up
            index = newest - (newest - counter + 1) % SYNC_OVERFLOW
            if index < self.next_row:
                return  # given up already (or before the master started)
            axis = self.axes[i]
            slot = axis.slots.setdefault(index, [None, None])
            if slot[part] is not None:
                if slot[part] == values:
                    self.duplicates += 1
                    return
                self._refuse(i, f"two different TPDO{part + 1} for SYNC {index} ({slot[part]} "
                                f"and {values})")
                return
            slot[part] = values
            axis.heard[part] = max(axis.heard[part], index)

    def on_heartbeat(self, i: int, data: bytes) -> None:
        axis = self.axes[i]
        axis.heartbeat_at, axis.nmt_state = time.monotonic(), data[0] if data else -1

    def on_emcy(self, i: int, data: bytes | bytearray) -> None:
        if len(data) >= 2:
            self.axes[i].emcy = int.from_bytes(data[:2], "little")

    # -- control (other threads)
    def start(self, hold: np.ndarray) -> None:
        self.hold = hold.astype(np.int64)
        self.cmd = self.cmd_prev = self.hold.copy()
        now = time.monotonic()
        for a in self.axes:
            a.heartbeat_at = max(a.heartbeat_at, now)
        self._thread = threading.Thread(target=self._run, name="canopen-sync-master",
                                        daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._quit.set()
        if self._thread is not None:
            self._thread.join(5.0)

    def submit(self, job: Job) -> None:
        with self.lock:
            if self.mode == "halted":
                raise RuntimeError(self.halt_reason or "halted")
            if self.mode != "hold":
                raise RuntimeError(f"busy ({self.mode})")
            self.job, self.mode = job, "job"
            self.idle.clear()

    def request_rest(self, then: str = "hold", reason: str = "stopped") -> None:
        """Ramp a moving job to rest (SIGTERM, withdraw, close); ``then`` hold or disable."""
        with self.lock:
            if self.mode == "halted":
                return
            vel = (self.cmd - self.cmd_prev) / self.period
            self.ramp = ramp_to_rest(self.cmd, vel, self.decel, self.period)
            self.ramp_then = then
            if self.job is not None:
                self._end_job(self.job, f"{reason}: ramped to rest")
            self.mode = "ramp"
            self.idle.clear()

    # -- the loop
    def _run(self) -> None:
        if self.priority:
            why = realtime(self.priority)
            if why is not None:
                log.warning("driver.sync_priority: SCHED_FIFO %d refused for the SYNC thread "
                            "(%s); it runs at normal priority", self.priority, why)
            else:  # a real-time thread wakes within tens of µs: a shorter spin will do
                self.scheduling = f"SCHED_FIFO {self.priority}"
                self.spin_s = min(self.spin_s, 1e-4)
        deadline, last = time.perf_counter(), 0.0
        while not self._quit.is_set():
            now = time.perf_counter()
            if deadline - now > self.spin_s:
                time.sleep(deadline - now - self.spin_s)
            while time.perf_counter() < deadline:  # the last bit: sleep's wake-up is coarse;
                time.sleep(0)  # sleep(0) lets the notifier threads have the GIL meanwhile
            start = time.perf_counter()
            self._overrun(start - last if last else 0.0)
            last = start
            if self.tick_hook is not None:
                self.tick_hook()
            try:
                self._tick()
            except _Stop as stop:
                self._halt(stop.axis, stop.cause, stop.drive_fault)
            except Exception as err:  # noqa: BLE001 - a bug must stop the drives, not the thread
                log.exception("sync master: internal error")
                self._halt(None, f"internal error in the motion master: {err}")
            deadline += self.period
            if time.perf_counter() - deadline > self.period:  # fell behind: no burst of SYNCs
                deadline = time.perf_counter() + self.period

    def _overrun(self, interval: float) -> None:
        """A SYNC more than half a period after its nominal time (counted between sends, and
        logged: the first, the tenth, then every thousandth)."""
        if interval > 1.5 * self.period:
            self.overruns += 1
            self.late_streak += 1
            self.worst_late_s = max(self.worst_late_s, interval - self.period)
            if self.overruns in (1, 10) or self.overruns % 1000 == 0:
                log.warning("SYNC overrun: %.3g ms between two SYNCs of %g ms (%d overruns so "
                            "far, the worst %.3g ms late)", 1e3 * interval, 1e3 * self.period,
                            self.overruns, 1e3 * self.worst_late_s)
        else:
            self.late_streak = 0
        if (self.late_streak >= self.overrun_streak and self.mode in ("job", "ramp")
                and self.halt_reason is None):
            self.late_streak = 0
            self._halt(None, f"SYNC overrun: {self.overrun_streak} periods in a row late by "
                             f"more than {500 * self.period:.3g} ms (the host cannot keep a "
                             f"{1000 * self.period:.3g} ms SYNC)")

    def _tick(self) -> None:
        samples = self._collect()
        self._check(samples)
        cw, target = self._command(samples)
        self._send(cw, target)
        self._record(self.job)

    def _collect(self) -> list[_Sample | None]:
        """Per drive its newest complete answer if newer than at the last tick (else None);
        the SYNCs every drive answered, in order, into ``answered``. A SYNC some drive left
        unanswered is given up once that drive answered a later one (its frames come in
        order: the answer was lost) or ``max_missed`` periods passed."""
        out: list[_Sample | None] = []
        last = self.sync_count - 1
        with self.lock:
            for a in self.axes:
                fresh: _Sample | None = None
                for index, (p1, p2) in a.slots.items():
                    if p1 is not None and p2 is not None and index > a.newest:
                        a.newest = index
                        vel = self._velocity(a.seen, index, p1[1])
                        a.seen = (index, p1[1])
                        fresh = (p1[0], p1[1], p2[0], vel, a.emcy)
                if fresh is not None:
                    a.last = fresh
                out.append(fresh)
                a.missed = last - a.newest if self.sync_count else 0
            while self.next_row <= last:
                index = self.next_row
                parts = [a.slots.get(index) for a in self.axes]
                done = [p for p in parts if p is not None and p[0] is not None
                        and p[1] is not None]
                if len(done) == len(parts):
                    row: list[_Answer] = []
                    for a, p in zip(self.axes, done, strict=True):
                        row.append((p[0][0], p[0][1], p[1][0],
                                    self._velocity(a.row_seen, index, p[0][1])))
                        a.row_seen = (index, p[0][1])
                    self.answered.append((index, row))
                elif (all(_lost(a, p, index) for a, p in zip(self.axes, parts, strict=True))
                      or last - index >= self.max_missed):
                    self.answered.append((index, None))
                else:
                    break
                for a in self.axes:
                    a.slots.pop(index, None)
                self.next_row += 1
        return out

    def _velocity(self, before: tuple[int, int] | None, index: int, pos: int) -> float:
        """Counts/s from the position answered before (at most a few SYNCs back); an
        unknown velocity counts as moving (never taken for standstill)."""
        if before is None or not 0 < index - before[0] <= 4:
            return math.inf
        return (pos - before[1]) / ((index - before[0]) * self.period)

    def _check(self, samples: list[_Sample | None]) -> None:
        if self.mode == "halted":
            return
        if self.protocol_fault is not None:
            raise self.protocol_fault
        now = time.monotonic()
        for a, s in zip(self.axes, samples, strict=True):
            if a.missed >= self.max_missed:
                raise _Stop(a, f"no TPDO for {a.missed} SYNC periods (node silent, frames lost "
                               "or malformed, or answers later than max_missed "
                               f"{self.max_missed})")
            if now - a.heartbeat_at > self.heartbeat_timeout_s:
                raise _Stop(a, f"lost heartbeat (none for {now - a.heartbeat_at:.3g} s)")
            if s is None:
                continue
            status, pos, _, _, err = s
            state = drive_state(status)
            if state in ("Fault", "Fault reaction active"):
                emcy = err or a.emcy  # the driver reads 0x603F after the stop and names it
                raise _Stop(a, "drive fault" + (f" (EMCY {error_words(emcy)})" if emcy else
                                                " (no EMCY received)"), drive_fault=True)
            if state != "Operation enabled" and self.mode != "ramp":
                raise _Stop(a, f"drive left Operation enabled (now {state})")
            error = abs(pos - int(self.sent.get(a.newest, self.cmd)[a.joint - 1]))
            if self.mode in ("job", "ramp") and error > a.window_counts:
                raise _Stop(a, f"following error {error / a.counts_per_rad:.4g} rad beyond the "
                               f"window {a.window_counts / a.counts_per_rad:.4g} rad")

    def _command(self, samples: list[Any]) -> tuple[int, np.ndarray]:
        if self.mode == "halted":
            return CW_QUICK_STOP, self.cmd
        if self.mode == "job" and self.job is not None:
            job = self.job
            if job.k < len(job.targets):
                if job.k == job.record_from:
                    job.sync0 = self.sync_count
                return CW_ENABLE, job.targets[min(job.k, len(job.targets) - 1)]
            self._settle(job, samples)
            return CW_ENABLE, job.targets[-1]
        if self.mode == "ramp":
            if self.ramp is not None and len(self.ramp):
                target, self.ramp = np.rint(self.ramp[0]).astype(np.int64), self.ramp[1:]
                return CW_ENABLE, target
            if self.ramp_then == "disable":
                self.idle.set()
                return CW_SHUTDOWN, self.cmd
            if any(self._at_rest(parts, self.cmd) for _, parts in self.answered
                   if parts is not None):
                self.hold, self.mode = self.cmd.copy(), "hold"
                self.idle.set()
        return CW_ENABLE, self.hold if self.mode == "hold" else self.cmd

    def _at_rest(self, parts: Sequence[_Answer], target: np.ndarray) -> bool:
        """Every drive's answer to one SYNC (status, pos, torque, vel) at rest on target."""
        for a, p in zip(self.axes, parts, strict=True):
            if abs(p[3]) > self.standstill[a.joint - 1]:
                return False
            if abs(p[1] - int(target[a.joint - 1])) > 0.1 * a.window_counts:
                return False
        return True

    def _settle(self, job: Job, samples: list[Any]) -> None:
        """After the last setpoint: three SYNCs in a row whose answers show every drive at rest
        end the job (counted per answered SYNC, not per tick: answers may come in batches),
        with every row answered so far in its log."""
        now = time.monotonic()
        if job.settle_start is None:
            job.settle_start, job.settle_from = now, self.sync_count
        for index, parts in self.answered:
            if parts is not None and index >= job.settle_from:
                job.settled = job.settled + 1 if self._at_rest(parts, job.targets[-1]) else 0
        if job.settled >= 3:
            self._record(job)
            self.hold, self.mode = job.targets[-1].copy(), "hold"
            self.job = None
            self._end_job(job, None)
            self.idle.set()
        elif now - job.settle_start > job.settle_timeout_s:
            moving = next((a for a in self.axes if a.last is None
                           or abs(a.last[3]) > self.standstill[a.joint - 1]), self.axes[0])
            raise _Stop(moving, f"no standstill within {job.settle_timeout_s:g} s after the "
                                "trajectory ended")

    def _send(self, cw: int, target: np.ndarray) -> None:
        job = self.job
        if self.mode == "job" and job is not None and job.k < len(job.targets):
            if job.offsets is not None:
                self.offset = job.offsets[job.k]
            job.k += 1
        self.cmd_prev, self.cmd = self.cmd, np.asarray(target, dtype=np.int64)
        stamp = time.time()
        try:
            for a in self.axes:
                j = a.joint - 1
                msg = can.Message(arbitration_id=0x200 + a.node, is_extended_id=False,
                                  data=RPDO1.pack(cw, int(self.cmd[j]), int(self.offset[j])),
                                  timestamp=stamp, is_rx=False)
                with self.send_lock:
                    self.bus.send(msg)
                self.tap(msg)
            self.sent[self.sync_count] = self.cmd
            self.sent.pop(self.sync_count - 2 * SYNC_OVERFLOW, None)
            sync = can.Message(arbitration_id=SYNC_ID, is_extended_id=False,
                               data=bytes([sync_counter(self.sync_count)]), timestamp=stamp,
                               is_rx=False)
            with self.send_lock:
                self.bus.send(sync)
            self.tap(sync)
        except (can.CanError, OSError) as err:  # socketcand: a lost TCP link
            if self.mode != "halted":
                raise _Stop(None, f"CAN bus error ({err}): bus-off or no bus") from err
            return
        if self.keep_times:
            self.sync_times.append(time.perf_counter())
        self.sync_count += 1

    def _record(self, job: Job | None) -> None:
        """The answered SYNCs from the job's first program setpoint on become its rows, each at
        the time of its own SYNC; a SYNC a drive left unanswered is a hole in the time stamps
        (the log loader splits there)."""
        answered, self.answered = self.answered, []
        if job is None or job.sync0 is None or job.ended.is_set():
            return
        for index, parts in answered:
            if index < job.sync0:
                continue
            if parts is None:
                job.missing_rows += 1
                continue
            t = job.t0 + (index - job.sync0) * job.period
            job.rows.append((t, tuple(p[1] for p in parts), tuple(p[2] for p in parts)))

    def _halt(self, axis: Axis | None, cause: str, drive_fault: bool = False) -> None:
        """Quick stop on every drive (latched); the running job fails with one line."""
        where = axis.label() if axis is not None else "bus"
        line = f"{where}: {cause}"
        with self.lock:
            self.mode, self.halt_reason = "halted", line
            job, self.job = self.job, None
        log.error("quick stop on every drive: %s", line)
        if job is not None:
            job.quick_stop = True
            job.drive_fault = axis if drive_fault else None
            self._end_job(job, line)
        self.idle.set()
        try:  # at once, not only at the next period
            self._send(CW_QUICK_STOP, self.cmd)
        except _Stop:
            pass

    def _end_job(self, job: Job, error: str | None) -> None:
        if job.ended.is_set():
            return
        job.error = error
        job.ended.set()
        if self.job is job:
            self.job = None
        self.on_end(job)
