"""The ``robid`` command: the parser assembled from the command groups, and the one error path
(one line ``robid: error: …``, exit 2; ``--debug`` for the traceback).

A command group is one module with a ``COMMANDS`` table (``types.Command``); adding a group is
that module and its line in ``GROUPS``.
"""

from __future__ import annotations

import argparse
import atexit
import gc
import logging
import os
import sys
import traceback
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from robid_link import __version__
from robid_link.cli import analyse, campaign, daemon, demo, fleet, params, robot, runs, web
from robid_link.cli.types import Command, OneLineParser, error_line
from robid_link.exceptions import RobidError

__all__ = ["main", "GROUPS", "EXIT_INTERNAL"]

#: the command groups, in the order ``robid --help`` lists their commands
GROUPS = (analyse, robot, demo, daemon, campaign, runs, params, fleet, web)


def _add(sub: Any, command: Command) -> None:
    p = sub.add_parser(command.name, help=command.help)
    if command.options is not None:
        command.options(p)
    if command.run is not None:
        p.set_defaults(command=command)
    if command.commands:
        inner = p.add_subparsers(dest=f"{command.name}_cmd", required=command.run is None)
        for c in command.commands:
            _add(inner, c)


def _parser() -> argparse.ArgumentParser:
    ap = OneLineParser(prog="robid", description="Dynamic-model identification of "
                       "industrial robots.")
    ap.add_argument("--debug", action="store_true", help="show tracebacks")
    ap.add_argument("--version", action="version", version=f"robid {__version__}",
                    help="print the version and exit")
    sub = ap.add_subparsers(dest="cmd", required=True)
    for group in GROUPS:
        for command in group.COMMANDS:
            _add(sub, command)
    return ap


class _OneLineLog(logging.Handler):
    """The library's logged warnings (an unlimited joint accepted, a URDF part skipped) as
    ``robid: warning: …`` lines on the stderr of the moment."""

    def emit(self, record: logging.LogRecord) -> None:
        print(f"robid: {record.levelname.lower()}: {record.getMessage()}", file=sys.stderr)


def _one_line_warnings() -> None:
    def show(message: Warning | str, category: type[Warning], *args: Any, **kw: Any) -> None:
        print(f"robid: warning: {message}", file=sys.stderr)

    warnings.showwarning = show
    warnings.simplefilter("default")
    library = logging.getLogger("robid_link")
    if not any(isinstance(h, _OneLineLog) for h in library.handlers):
        handler = _OneLineLog(logging.WARNING)
        library.addHandler(handler)


def _os_error_line(err: OSError) -> str:
    """An OSError the command's own checks did not foresee, as ``file: reason``."""
    reason = err.strerror or str(err) or type(err).__name__
    if err.filename is None:
        return reason
    if err.filename2 is not None:
        return f"{err.filename} → {err.filename2}: {reason}"
    return f"{err.filename}: {reason}"


def _internal_error_line(err: BaseException) -> str:
    """A bug: one line with where it happened, and how to see the whole traceback."""
    frames = traceback.extract_tb(err.__traceback__)
    where = f" ({Path(frames[-1].filename).name}:{frames[-1].lineno})" if frames else ""
    text = " ".join(str(err).split())[:200]
    return (f"robid: internal error: {type(err).__name__}: {text}{where}; rerun with --debug "
            "for the traceback and report it")


def _quiet_broken_pipe() -> int:
    """``robid status | head``: the reader left; no traceback, no 'Exception ignored'."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)
    return 128 + 13  # the shell's status for a process ended by SIGPIPE


#: exit status of a bug (an exception no check foresaw): EX_SOFTWARE of sysexits.h
EXIT_INTERNAL = 70


def _single_threaded_blas() -> None:
    """BLAS on one thread unless the user chose (OPENBLAS_NUM_THREADS and the like): the
    numerical passes spread their chunks over the cores themselves (``threads.in_slots``),
    and a multi-threaded BLAS on small products only spins against them, and against the
    other processes of a shared machine. Read by OpenBLAS when numpy is first imported."""

    if not any(k in os.environ for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS",
                                         "MKL_NUM_THREADS")):
        os.environ["OPENBLAS_NUM_THREADS"] = "1"


_exit_hook = False


def _quick_exit() -> None:
    """At the interpreter's exit, the objects of the run are left to the system instead of
    collected one by one: after numba's compiler has loaded (every identification), the last
    collection took 0.1–0.3 s of a short command (LLVM's modules disposed of object by object).
    Registered once; an in-process caller (the tests) is not affected until it exits."""
    global _exit_hook
    if not _exit_hook:
        atexit.register(gc.freeze)
        _exit_hook = True


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command. Exit 0 on success, 2 on an error (one line on stderr), 70 on a bug
    (one line; ``--debug`` shows the traceback), 130 when interrupted; a command may return
    a status of its own (``campaign start --trigger timer`` with nothing to do)."""
    if "numpy" not in sys.modules:
        _single_threaded_blas()
    _quick_exit()
    try:
        args = _parser().parse_args(argv)
    except SystemExit as exc:  # a usage error (already printed in one line), --help, --version
        return exc.code if isinstance(exc.code, int) else 2
    _one_line_warnings()
    command: Command = args.command
    assert command.run is not None  # only commands that run are set as defaults
    try:
        if command.check is not None:
            command.check(args)
        return int(command.run(args) or 0)
    except BrokenPipeError:
        return _quiet_broken_pipe()
    except RobidError as err:
        if args.debug:
            raise
        print(error_line(str(err)), file=sys.stderr)
        return 2
    except OSError as err:  # a file the command reads or writes, beyond what it checked
        if args.debug:
            raise
        print(error_line(_os_error_line(err)), file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("robid: interrupted", file=sys.stderr)
        return 130
    except Exception as err:  # a bug: still one line, with a status of its own
        if args.debug:
            raise
        print(_internal_error_line(err), file=sys.stderr)
        return EXIT_INTERNAL
