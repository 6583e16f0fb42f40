"""The worker process runner: a job record crosses to a fresh process as JSON, the child imports
the worker's entry point by name (``jobs.WORKER_ENTRY``) and answers with a result record as
JSON, so the event loop never blocks on numerical work and the link imports no worker code."""

from __future__ import annotations

import importlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

from robid_link.exceptions import RecordError, RobidError, WorkerError
from robid_link.jobs import WORKER_ENTRY, Job, Record

__all__ = ["run_in_worker", "run_here"]


def _entry(name: str) -> Callable[[str], str]:
    """The function ``module:function`` names (the worker's entry point)."""
    module_name, _, func = name.partition(":")
    return getattr(importlib.import_module(module_name), func)


def _answer(job: Job, text: str) -> Record:
    """The worker's JSON answer as the record ``job`` expects; a malformed one is a bug of the
    worker (WorkerError), never trusted."""
    try:
        result = Record.from_json(text)
    except RecordError as err:
        raise WorkerError(f"worker {job.TYPE} answered a record this side cannot read: "
                          f"{err}") from err
    if not isinstance(result, job.RESULT):
        raise WorkerError(f"worker {job.TYPE} answered a {result.TYPE} record, expected "
                          f"{job.RESULT.TYPE}")
    return result


def run_here(job: Job, entry: str = WORKER_ENTRY) -> Record:
    """The same door without a process (JSON both ways): for ``robid config check``, which
    runs every campaign's pre-flight in the CLI's process, and quick pure-Python jobs."""
    return _answer(job, _entry(entry)(job.to_json()))


# ----------------------------------------------------------------------------- process runner


def _error_name(err: BaseException) -> str:
    cls = type(err)
    return f"{cls.__module__}:{cls.__qualname__}"


def _error_class(name: str) -> type[RobidError]:
    """The RobidError subclass a worker named (``module:Class``); RobidError itself for a
    name that is not one (the pipe carries names, never code)."""
    import sys

    module_name, _, qualname = name.partition(":")
    if module_name not in sys.modules and not module_name.startswith("robid_link."):
        return RobidError
    try:
        obj: Any = importlib.import_module(module_name)
        for part in qualname.split("."):
            obj = getattr(obj, part)
    except (ImportError, AttributeError):
        return RobidError
    return obj if isinstance(obj, type) and issubclass(obj, RobidError) else RobidError


def _tie_to_daemon(daemon_pid: int) -> None:
    """Die with the daemon: the kernel's parent-death signal (the parent is the daemon, or
    the fork server, which exits with it), and a thread that waits on a pidfd of the daemon
    itself and ends this process when the daemon is gone (whatever the parent is)."""
    import ctypes
    import os
    import signal
    import threading

    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # not Linux: the watchdog thread alone
        pass
    try:
        fd = os.pidfd_open(daemon_pid)
    except ProcessLookupError:
        os._exit(1)  # the daemon died before we got here
    except (OSError, AttributeError):
        return

    def watch() -> None:
        import select

        poller = select.poll()
        poller.register(fd, select.POLLIN)
        poller.poll()  # readable when the daemon has exited (even before it is reaped)
        os._exit(1)

    threading.Thread(target=watch, name="robid-daemon-watch", daemon=True).start()


def _child(conn: Any, entry: str, kind: str, job_json: str, daemon_pid: int | None = None
           ) -> None:
    if daemon_pid is not None:
        _tie_to_daemon(daemon_pid)
    try:
        result: tuple[str, str, str] = ("ok", _entry(entry)(job_json), "")
    except RobidError as err:
        result = ("error", _error_name(err), str(err))
    except Exception as err:  # a bug: report it with where it happened; the daemon lives on
        import traceback

        where = traceback.extract_tb(err.__traceback__)[-1]
        result = ("error", _error_name(WorkerError()), f"worker {kind} crashed: "
                  f"{type(err).__name__}: {err} ({Path(where.filename).name}:{where.lineno})")
    conn.send(result)
    conn.close()


async def run_in_worker(ctx: Any, job: Job, *, on_start: Callable[[], None] | None = None,
                        entry: str = WORKER_ENTRY) -> Any:
    """Run ``job`` in a fresh process of the multiprocessing context ``ctx`` (the child calls
    ``entry`` with the job's JSON) and return its result record (of ``job.RESULT``); a
    cancelled caller terminates the process. A RobidError comes back as its own class
    (``UnsafeProgramError`` stays one); a crash, a dead process or an unreadable answer as
    WorkerError. The child dies with the daemon (``_tie_to_daemon``); ``on_start`` runs once
    it was started."""
    import asyncio

    recv, send = ctx.Pipe(duplex=False)
    import os

    proc = ctx.Process(target=_child, args=(send, entry, job.TYPE, job.to_json(), os.getpid()),
                       name=f"robid-{job.TYPE}",
                       daemon=True)
    proc.start()
    send.close()
    if on_start is not None:
        on_start()
    answered = False
    try:
        try:
            status, value, message = await asyncio.to_thread(recv.recv)
            answered = True
        except EOFError:
            await asyncio.to_thread(proc.join, 5.0)
            raise WorkerError(f"worker process {job.TYPE} died (exit code "
                              f"{proc.exitcode})") from None
    finally:
        if answered:  # it ends on its own: its exit runs multiprocessing's finalizers, which
            # unlink and unregister the named semaphore numba's threads made; terminated
            # here, it left that to the resource tracker ("leaked semaphore" at exit)
            await asyncio.to_thread(proc.join, 5.0)
        if proc.is_alive():
            proc.terminate()
        await asyncio.to_thread(proc.join, 5.0)
        recv.close()
    if status != "ok":
        cls = _error_class(value)
        try:
            error = cls(message)
        except TypeError:  # a subclass with another constructor: keep the message
            error = RobidError(message)
        raise error
    return _answer(job, value)
