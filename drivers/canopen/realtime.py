"""What the CANopen motion path asks of the process it runs in: SCHED_FIFO for its threads
(``realtime``, ``RealtimeListener``), the heap out of the cyclic collector's way and a short GIL
switch interval while it runs (``ProcessHold``).

Every Python thread of the process shares one GIL, so the SYNC thread waits for whichever
thread holds it. Two stalls of tens of milliseconds come from the process, not the host: a
full (generation 2) collection, which holds the GIL while it walks every tracked object (some
90,000 after start-up: 40–130 ms), and a thread under normal scheduling that holds or asks for
the GIL while other processes keep it off the CPU (CPython's forced switching makes even the
thread that releases the GIL wait until the asking thread runs). ``ProcessHold`` answers the
first (and a shorter switch interval bounds how long a running thread keeps the GIL); the
driver's own threads run under SCHED_FIFO for the second.
"""

from __future__ import annotations

import gc
import logging
import os
import sys
import threading

import can

__all__ = ["ProcessHold", "RealtimeListener", "realtime"]

log = logging.getLogger("robid.driver.canopen")


def realtime(priority: int) -> str | None:
    """Put the calling thread under SCHED_FIFO at ``priority`` (Linux); None when it took, else
    why not (the thread keeps its normal scheduling)."""
    if not hasattr(os, "sched_setscheduler"):
        return "no SCHED_FIFO on this system"
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
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


_holds: list[ProcessHold] = []  # the holds in force, oldest first
_saved: list[float] = []  # the switch interval before the first of them
_set: list[float] = []  # the switch interval they set (another one set since is left alone)
_holds_lock = threading.Lock()


class ProcessHold:
    """What the motion master needs of the whole process while it runs, taken by ``hold`` and
    given back by ``release`` (each safe to call twice; holds of several drivers nest, the last
    release restores):

    - the heap frozen (``gc.freeze``): the objects alive at the hold sit in CPython's permanent
      generation, so a full collection walks only what was made since (0.1–0.3 ms in the
      bench, against 40–130 ms that held the GIL every ~15 s at 1 ms). ``release`` gives them
      back to the collector: garbage among them (what was garbage at the hold) goes then.
    - the GIL switch interval at most ``switch_s`` (CPython's default is 5 ms): a thread that
      waits for the GIL asks its holder to let go after that long, so a running thread that
      computes (the log writer formatting a job's CSV, the daemon's loop) delays the SYNC
      thread by about that much, not by 5 ms or more each period. Released, the interval goes
      back to what it was unless someone else changed it meanwhile.
    """

    def __init__(self, switch_s: float) -> None:
        self.switch_s = switch_s

    def hold(self) -> None:
        with _holds_lock:
            if self in _holds:
                return
            if not _holds:
                _saved[:] = [sys.getswitchinterval()]
            _holds.append(self)
            gc.freeze()  # again with a second hold: objects made since join the frozen ones
            _apply()

    def release(self) -> None:
        with _holds_lock:
            if self not in _holds:
                return
            _holds.remove(self)
            if _holds:
                _apply()
                return
            gc.unfreeze()
            if _set and sys.getswitchinterval() == _set[0]:
                sys.setswitchinterval(_saved[0])
            _set.clear()


def _apply() -> None:
    """The shortest interval any hold asks for (never longer than the one before the holds)."""
    want = min([_saved[0], *(h.switch_s for h in _holds)])
    if _set and sys.getswitchinterval() != _set[0]:
        return  # someone else set one since: theirs stands
    sys.setswitchinterval(want)
    _set[:] = [sys.getswitchinterval()]
