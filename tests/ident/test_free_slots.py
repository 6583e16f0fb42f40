"""``in_free_slots``: tasks to whichever of the two slots is free, each whole in one slot."""

from __future__ import annotations

import threading
import time
from typing import Any

import numba
import pytest

from robid_link.ident.model.threads import in_free_slots, kernel_threads


@pytest.fixture(params=[1, 2], ids=["one thread", "two slots"])
def threads(request: pytest.FixtureRequest) -> int:
    before = numba.get_num_threads()
    numba.set_num_threads(min(request.param, numba.config.NUMBA_NUM_THREADS))
    yield numba.get_num_threads()
    numba.set_num_threads(before)


def test_every_task_once_serial_kernels_inside(threads: int) -> None:
    seen: list[tuple[int, int, str]] = []

    def work(task: int, slot: int) -> None:
        time.sleep(0.001 * (task % 3))  # unequal tasks
        seen.append((task, kernel_threads(), threading.current_thread().name))

    in_free_slots(list(range(9)), work)
    assert sorted(s[0] for s in seen) == list(range(9))
    assert {s[1] for s in seen} == {1}  # a task's kernels do not spawn threads of their own
    names = {s[2] for s in seen}
    assert (names == {threading.current_thread().name}) == (threads == 1)


def test_a_task_may_wait_for_an_earlier_one(threads: int) -> None:
    """The elasticity's pattern: the first task (the gravity stiffness) sets what the later
    ones wait for; in one slot they run in order, so nothing waits forever."""
    ready = threading.Event()
    done: list[int] = []

    def work(task: int, slot: int) -> None:
        if task == 0:
            time.sleep(0.02)
            ready.set()
        else:
            assert ready.wait(timeout=10)
        done.append(task)

    in_free_slots([0, 1, 2, 3], work)
    assert sorted(done) == [0, 1, 2, 3]


def test_an_error_is_raised_after_the_other_tasks_ran(threads: int) -> None:
    done: list[int] = []

    def work(task: int, slot: int) -> None:
        if task == 1:
            raise ValueError("task 1")
        time.sleep(0.005)
        done.append(task)

    with pytest.raises(ValueError, match="task 1"):
        in_free_slots([0, 1, 2, 3], work)
    if threads > 1:  # the other slot keeps taking tasks
        assert sorted(done) == [0, 2, 3]


def _both_slots(seen: set[int]) -> None:
    """A pass whose two slots must run at once (a barrier of two): it records their threads."""
    from robid_link.ident.model.threads import in_slots

    barrier = threading.Barrier(2, timeout=20)

    def work(task: int, slot: int) -> None:
        barrier.wait()
        seen.add(threading.get_ident())

    in_slots([0, 1], work)


def test_the_slots_threads_are_the_processs_own_and_a_fork_makes_its_own(threads: int) -> None:
    """Passes reuse the process's two slot threads (none started per pass); a forked child,
    which has none of its parent's threads, runs its passes on two threads of its own (with
    its parent's pool it would wait forever)."""
    import multiprocessing as mp

    if threads == 1:
        pytest.skip("one thread: the passes run in the caller")
    seen: set[int] = set()
    for _ in range(3):
        _both_slots(seen)
    assert len(seen) == 2
    if "fork" not in mp.get_all_start_methods():
        return

    def child(conn: Any) -> None:
        out: set[int] = set()
        _both_slots(out)
        conn.send(len(out))

    ctx = mp.get_context("fork")
    recv, send = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=child, args=(send,))
    proc.start()
    try:
        assert recv.poll(30), "a forked child's pass never finished"
        assert recv.recv() == 2
    finally:
        proc.join(10)
        if proc.is_alive():
            proc.kill()
    assert proc.exitcode == 0
