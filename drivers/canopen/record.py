"""What the CANopen driver records of an experiment: every frame into a BLF file (written off the
motion master's thread) and the samples as the project's CSV log.
"""

from __future__ import annotations

import copy
import logging
import queue
import struct
import threading
from collections.abc import Sequence
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import can

from robid_link.drivers.canopen.master import Axis, Job
from robid_link.drivers.canopen.realtime import realtime

__all__ = ["BlfTap", "log_bytes"]

log = logging.getLogger("robid.driver.canopen")


def log_bytes(job: Job, axes: Sequence[Axis]) -> bytes:
    """The recorded samples as the project's CSV log (``t,q1..qn,tau1..taun``, rad and N·m)."""
    n = len(axes)
    head = ",".join(["t"] + [f"q{j}" for j in range(1, n + 1)]
                    + [f"tau{j}" for j in range(1, n + 1)])
    cpr = [a.counts_per_rad for a in axes]
    scale = [a.torque_unit_nm or a.rated_torque_nm / 1000.0 for a in axes]
    lines = [head]
    for t, pos, tq in job.rows:
        cells = [f"{t:.6f}"] + [f"{p / c:.10g}" for p, c in zip(pos, cpr, strict=True)]
        cells += [f"{x * s:.10g}" for x, s in zip(tq, scale, strict=True)]
        lines.append(",".join(cells))
    return ("\n".join(lines) + "\n").encode()


#: frames waiting for the BLF writer at most (a few seconds of a busy bus): a writer that falls
#: behind loses frames of the raw record (counted), never the motion master's time or memory
MAX_BACKLOG = 200_000


class BlfTap(can.Listener):
    """Every frame of an experiment, both directions, into its BLF file, written off the
    motion master's thread (python-can's BLFWriter compresses in chunks). At most
    ``MAX_BACKLOG`` frames wait; more are dropped and counted in ``dropped``. ``priority``:
    SCHED_FIFO for the writer thread (0: normal scheduling; if refused it keeps that, the
    motion path's own threads say why)."""

    def __init__(self, priority: int = 0) -> None:
        self.priority = priority
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._writer: can.BLFWriter | None = None
        self._backlog = 0  # frames in the queue (the control items are few)
        self._count = threading.Lock()
        self.dropped = 0
        self._thread = threading.Thread(target=self._run, name="canopen-blf", daemon=True)
        self._thread.start()

    def on_message_received(self, msg: can.Message) -> None:
        if self._writer is None:
            return
        with self._count:
            if self._backlog >= MAX_BACKLOG:
                self.dropped += 1
                return
            self._backlog += 1
        self._queue.put(msg)

    def begin(self, path: Path) -> None:
        self._queue.put(("begin", path))

    def end(self) -> Future[None]:
        fut: Future[None] = Future()
        self._queue.put(("end", fut))
        return fut

    def stop(self) -> None:
        self._queue.put(("quit", None))
        self._thread.join(5.0)

    def _run(self) -> None:
        if self.priority:
            realtime(self.priority)
        writer: can.BLFWriter | None = None
        while True:
            item = self._queue.get()
            if isinstance(item, can.Message):
                with self._count:
                    self._backlog -= 1
                if writer is not None:
                    frame = copy.copy(item)
                    frame.channel = 1  # BLF numbers its channels
                    try:
                        writer.on_message_received(frame)
                    except (struct.error, ValueError, OSError) as err:
                        log.warning("BLF: frame not written (%s)", err)
                continue
            kind, arg = item
            if writer is not None and kind in ("begin", "end", "quit"):
                writer.stop()
                writer = self._writer = None
            if kind == "begin":
                writer = self._writer = can.BLFWriter(str(arg))
            elif kind == "end":
                arg.set_result(None)
            else:
                return
