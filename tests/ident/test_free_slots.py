"""``in_free_slots``: tasks to whichever of the two slots is free, each whole in one slot."""

from __future__ import annotations

import threading
import time

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
