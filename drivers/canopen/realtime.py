"""What the CANopen motion path asks of the process it runs in: SCHED_FIFO for its threads
(``realtime``, ``RealtimeListener``) and the heap out of the cyclic collector's way (``HeapHold``).

Every Python thread of the process shares one GIL, so the SYNC thread waits for whichever
thread holds it. Two stalls of tens of milliseconds come from the process, not the host: a
full (generation 2) collection, which holds the GIL while it walks every tracked object (some
90,000 after start-up: 40–100 ms), and a thread under normal scheduling that holds or asks for
the GIL while other processes keep it off the CPU (CPython's forced switching makes even the
thread that releases the GIL wait until the asking thread runs). ``HeapHold`` answers the
first; the driver's own threads run under SCHED_FIFO for the second.
"""

from __future__ import annotations

import gc
import logging
import os
import threading

import can

__all__ = ["HeapHold", "RealtimeListener", "realtime"]

log = logging.getLogger("robid.driver.canopen")


def realtime(priority: int, tid: int = 0) -> str | None:
    """Put the calling thread (or the thread ``tid``, a native id) under SCHED_FIFO at
    ``priority`` (Linux); None when it took, else why not (the thread keeps its scheduling)."""
    if not hasattr(os, "sched_setscheduler"):
        return "no SCHED_FIFO on this system"
    try:
        os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
    except OSError as err:  # EPERM: no CAP_SYS_NICE and no RLIMIT_RTPRIO
        return err.strerror or str(err)
    return None


class RealtimeListener(can.Listener):
    """Puts the thread that delivers the bus's frames (python-can's notifier) under SCHED_FIFO
    at the first frame; the SYNC thread's ``priority`` (one warning line if refused)."""

    def __init__(self, priority: int) -> None:
        self.priority, self.threads = priority, set[int]()

    def on_message_received(self, msg: can.Message) -> None:
        if threading.get_ident() not in self.threads:
            self.threads.add(threading.get_ident())
            why = realtime(self.priority)
            if why is not None:
                log.warning("driver.sync_priority: SCHED_FIFO %d refused for the CAN receive "
                            "thread (%s)", self.priority, why)


_held = 0  # HeapHolds holding: the heap is frozen while one does
_held_lock = threading.Lock()


class HeapHold:
    """While held, the objects alive when the hold began sit in CPython's permanent generation
    (``gc.freeze``): a full collection walks only what was made since, so it takes a few
    milliseconds instead of the 40–100 ms that stalled the SYNC thread every ~15 s at 1 ms.
    ``release`` gives them back to the collector (garbage among them is collected later, none
    leaks for good). Holds nest across drivers of one process (the last release unfreezes);
    ``hold`` and ``release`` are each safe to call twice. Frozen garbage lives until then: what
    was garbage at the hold, not what the driver makes while it runs."""

    def __init__(self) -> None:
        self.holding = False

    def hold(self) -> None:
        global _held
        with _held_lock:
            if self.holding:
                return
            self.holding = True
            _held += 1
            gc.freeze()  # again with a second hold: objects made since join the frozen ones

    def release(self) -> None:
        global _held
        with _held_lock:
            if not self.holding:
                return
            self.holding = False
            _held -= 1
            if _held == 0:
                gc.unfreeze()
