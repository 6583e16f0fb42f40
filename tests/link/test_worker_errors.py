"""Errors cross the worker-process boundary as their own class: an unsafe program stays an
UnsafeProgramError, a bug, a dead process or an answer of the wrong record becomes a
WorkerError, nothing else is trusted. The child runs this module's ``entry`` (named like the
worker's entry point, imported by name) on a LogCheckJob whose ``log`` says what to do."""

from __future__ import annotations

import asyncio
import multiprocessing
import os

import pytest

from robid_link.exceptions import (
    CycleError,
    DataError,
    RobidError,
    UnsafeProgramError,
    WorkerError,
)
from robid_link.jobs import LogCheckJob, ModelCheck
from robid_link.link import worker

ENTRY = f"{__name__}:entry"


class _Odd(RobidError):
    """A RobidError whose constructor takes more than the message."""

    def __init__(self, message: str, code: int) -> None:
        super().__init__(message)
        self.code = code


def entry(job_json: str) -> str:
    """A worker entry point that misbehaves as the job's ``log`` says."""
    kind = LogCheckJob.from_json(job_json).log
    if kind == "wrong_record":
        return ModelCheck(("rigid_body",)).to_json()
    if kind == "not_json":
        return "{"
    _raise(kind)
    raise AssertionError(kind)


def _raise(kind: str) -> None:
    if kind == "unsafe":
        raise UnsafeProgramError("experiment e1: q2 above its limit")
    if kind == "cycle":
        raise CycleError("experiment e1: no answer (after 3 attempts)")
    if kind == "data":
        raise DataError("log.csv: column tau3 missing")
    if kind == "odd":
        raise _Odd("odd one", 7)
    if kind == "bug":
        raise ZeroDivisionError("division by zero")
    if kind == "die":
        os._exit(3)


def _run(kind: str) -> None:
    ctx = multiprocessing.get_context("spawn")
    asyncio.run(worker.run_in_worker(ctx, LogCheckJob(kind, 3), entry=ENTRY))


@pytest.mark.parametrize(("kind", "cls", "message"), [
    ("unsafe", UnsafeProgramError, "q2 above its limit"),
    ("cycle", CycleError, "after 3 attempts"),
    ("data", DataError, "column tau3 missing"),
    ("odd", _Odd, "odd one"),
])
def test_worker_errors_come_back_as_their_class(kind: str, cls: type, message: str) -> None:
    if cls is _Odd:  # its constructor needs a code: the message survives as a RobidError
        with pytest.raises(RobidError, match=message) as err:
            _run(kind)
        assert type(err.value) is RobidError
        return
    with pytest.raises(cls, match=message) as err:
        _run(kind)
    assert type(err.value) is cls


def test_a_crash_or_a_dead_worker_is_a_worker_error() -> None:
    with pytest.raises(WorkerError, match=r"worker log-check-job crashed: ZeroDivisionError"):
        _run("bug")
    with pytest.raises(WorkerError,
                       match=r"worker process log-check-job died \(exit code 3\)"):
        _run("die")


def test_an_answer_of_the_wrong_record_is_a_worker_error() -> None:
    with pytest.raises(WorkerError, match=r"answered a model-check record, expected log-check"):
        _run("wrong_record")
    with pytest.raises(WorkerError, match=r"cannot read: record: not JSON"):
        _run("not_json")


@pytest.mark.parametrize("name", ["os:system", "builtins:ValueError", "nowhere.at.all:X",
                                  "robid_link.exceptions:RobidWarning",
                                  "robid_link.exceptions:__all__"])
def test_only_robid_errors_are_rebuilt_by_name(name: str) -> None:
    assert worker._error_class(name) is RobidError
    assert worker._error_class("robid_link.exceptions:DriverTimeoutError").__name__ == \
        "DriverTimeoutError"
