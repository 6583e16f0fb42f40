"""The ``robid`` package's layout: every command of the groups' tables reachable and run by the
one error path; contradictory options refused by a command's check before any work."""

from __future__ import annotations

import argparse
import subprocess
import sys
from collections.abc import Iterator

import pytest

from robid_link.cli import GROUPS, _parser, main
from robid_link.cli.types import Command
from robid_link.exceptions import RobidError


def _leaves(commands: tuple[Command, ...], path: tuple[str, ...] = ()
            ) -> Iterator[tuple[tuple[str, ...], Command]]:
    for c in commands:
        if c.commands:
            yield from _leaves(c.commands, (*path, c.name))
        else:
            yield (*path, c.name), c


def _parser_leaves(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()
                   ) -> Iterator[tuple[tuple[str, ...], argparse.ArgumentParser]]:
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield path, parser
    for action in subs:
        for name, sub in action.choices.items():
            yield from _parser_leaves(sub, (*path, name))


def test_every_command_of_the_tables_is_in_the_parser_with_its_handler() -> None:
    table = dict(kv for g in GROUPS for kv in _leaves(g.COMMANDS))
    parsed = dict(_parser_leaves(_parser()))
    assert set(table) == set(parsed)
    assert {("identify",), ("campaign", "start"), ("config", "check"), ("params",),
            ("model", "add"), ("demo",)} <= set(table)
    for path, parser in parsed.items():
        assert parser.get_default("command") is table[path], path


def test_a_command_runs_or_has_sub_commands_or_both() -> None:
    """A group may run alone too (``robid fleet``, ``robid fleet reidentify``)."""
    with pytest.raises(ValueError, match="'x'"):
        Command(name="x", help="neither")
    ap = _parser()
    alone = ap.parse_args(["fleet", "--store", "s"])
    sub = ap.parse_args(["fleet", "reidentify", "--store", "s", "--model", "m.yaml"])
    assert alone.command.name == "fleet" and sub.command.name == "reidentify"


def test_contradictory_options_are_refused_before_any_work(tmp_path, capsys) -> None:
    """The check runs before the robot or the logs are read: neither exists here."""
    rc = main(["identify", "--robot", str(tmp_path / "none.yaml"), "--data",
               str(tmp_path / "none.csv"), "--export-urdf", str(tmp_path / "x.urdf")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert err == ["robid: error: --export-urdf needs --method consistent (standard parameters)"]
    rc = main(["params", "diff", "1", "--config", str(tmp_path / "none.yaml"), "--robot", "a"])
    assert rc == 2 and "params diff: give two sets" in capsys.readouterr().err


def test_debug_shows_the_traceback(tmp_path) -> None:
    argv = ["results", "--config", str(tmp_path / "none.yaml"), "--trend"]
    assert main(argv) == 2
    with pytest.raises(RobidError, match="--trend: name the robot"):
        main(["--debug", *argv])


def test_python_m_runs_the_command() -> None:
    out = subprocess.run([sys.executable, "-m", "robid_link.cli", "--version"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.startswith("robid ")
