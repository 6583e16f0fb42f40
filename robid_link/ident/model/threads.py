"""How the numerical kernels share the cores: a pass over a long log runs its chunks in
``SLOTS`` slots, each on a thread of its own with serial kernels (no barrier per kernel call,
no two threads writing one row); outside a slot a kernel uses numba's threads itself.

Slot k takes chunks k, k + SLOTS, … in order, whatever the machine: what a slot sums up is
the same on every run, so results do not depend on the scheduler or the number of cores.
Tasks whose results do not depend on the slot at all (each computed whole, nothing summed
across tasks) may instead go to whichever slot is free (``in_free_slots``): unequal tasks then
share the cores evenly.

The slots' threads live as long as the process (``_pool``): an identification makes about ten
passes, and starting two threads for each cost 1–3 ms a pass on a busy machine. A forked child
makes its own.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

import numba

__all__ = ["SLOTS", "in_slots", "in_free_slots", "kernel_threads"]

#: slots of a pass (the machine's two cores)
SLOTS = 2

T = TypeVar("T")
_local = threading.local()


def kernel_threads() -> int:
    """Threads a kernel may use here: 1 inside a slot, else numba's."""
    return 1 if getattr(_local, "serial", False) else numba.get_num_threads()


def in_slots(tasks: Sequence[T], work: Callable[[T, int], None], slots: int = SLOTS) -> None:
    """``work(task, slot)`` for every task, slot k taking tasks k, k + slots, … in order on
    a thread of its own (one thread, the caller's, when there is one task or one core, or
    when the caller is a slot itself: passes do not nest threads).
    The first error raised in a slot is raised here, after every slot stopped."""
    if len(tasks) <= 1 or slots <= 1 or numba.get_num_threads() <= 1 or \
            getattr(_local, "serial", False):
        for i, task in enumerate(tasks):
            _serial(work, task, i % slots)
        return

    def run(slot: int) -> None:
        for task in tasks[slot::slots]:
            _serial(work, task, slot)

    _run_slots(run, slots)


def in_free_slots(tasks: Sequence[T], work: Callable[[T, int], None],
                  slots: int = SLOTS) -> None:
    """As ``in_slots``, each task to the first slot free, in the tasks' order (a task may wait
    for an earlier one: in one slot they run in order). For tasks whose results do not depend
    on the slot that ran them."""
    if len(tasks) <= 1 or slots <= 1 or numba.get_num_threads() <= 1 or \
            getattr(_local, "serial", False):
        for task in tasks:
            _serial(work, task, 0)
        return
    queue = iter(range(len(tasks)))
    lock = threading.Lock()

    def run(slot: int) -> None:
        while True:
            with lock:
                k = next(queue, -1)
            if k < 0:
                return
            _serial(work, tasks[k], slot)

    _run_slots(run, slots)


_pools: dict[int, ThreadPoolExecutor] = {}
_pools_lock = threading.Lock()
# a forked child has none of its parent's threads: it starts pools of its own
os.register_at_fork(after_in_child=_pools.clear)


def _pool(slots: int) -> ThreadPoolExecutor:
    """The process's pool of ``slots`` threads (made on first use)."""
    with _pools_lock:
        pool = _pools.get(slots)
        if pool is None:
            pool = _pools[slots] = ThreadPoolExecutor(max_workers=slots,
                                                      thread_name_prefix="robid-slot")
        return pool


def _run_slots(run: Callable[[int], None], slots: int) -> None:
    """``run(k)`` for k < slots, each on a thread of the pool; the first error is raised after
    every one has stopped."""
    futures = [_pool(slots).submit(run, k) for k in range(slots)]
    errors = [f.exception() for f in futures]
    for err in errors:
        if err is not None:
            raise err


def _serial(work: Callable[[T, int], None], task: T, slot: int) -> None:
    before = getattr(_local, "serial", False)
    _local.serial = True
    try:
        work(task, slot)
    finally:
        _local.serial = before
