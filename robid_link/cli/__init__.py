"""The ``robid`` command: the parser assembled from the command groups, and the one error path
(one line ``robid: error: …``, exit 2; ``--debug`` for the traceback).

A command group is one module with a ``COMMANDS`` table (``types.Command``); adding a group is
that module and its line in ``GROUPS``.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from collections.abc import Sequence
from typing import Any

from robid_link import __version__
from robid_link.cli import analyse, campaign, daemon, demo, fleet, params, robot, runs, web
from robid_link.cli.types import Command, OneLineParser, error_line
from robid_link.exceptions import RobidError

__all__ = ["main", "GROUPS"]

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


def _one_line_warnings() -> None:
    def show(message: Warning | str, category: type[Warning], *args: Any, **kw: Any) -> None:
        print(f"robid: warning: {message}", file=sys.stderr)

    warnings.showwarning = show  # type: ignore[assignment]
    warnings.simplefilter("default")


def _single_threaded_blas() -> None:
    """BLAS on one thread unless the user chose (OPENBLAS_NUM_THREADS and the like): the
    numerical passes spread their chunks over the cores themselves (``threads.in_slots``),
    and a multi-threaded BLAS on small products only spins against them, and against the
    other processes of a shared machine. Read by OpenBLAS when numpy is first imported."""
    import os

    if not any(k in os.environ for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS",
                                         "MKL_NUM_THREADS")):
        os.environ["OPENBLAS_NUM_THREADS"] = "1"


def main(argv: Sequence[str] | None = None) -> int:
    if "numpy" not in sys.modules:
        _single_threaded_blas()
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
    except RobidError as err:
        if args.debug:
            raise
        print(error_line(str(err)), file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("robid: interrupted", file=sys.stderr)
        return 130
