"""What the command groups of ``robid`` share: the command record, the one-line error, the
options several groups take, and the ``type=`` checks that refuse a bad value at parse time —
before any work — with one line naming the option.
"""

from __future__ import annotations

import argparse
import math
import os
import stat
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from robid_link.exceptions import ConfigError, RobidError
from robid_link.kinds import MAX_RATE_HZ, MIN_RATE_HZ

__all__ = ["Command", "OneLineParser", "error_line", "finite_float", "positive_float",
           "bounded_int", "output_path", "figure_path", "FIGURE_FORMATS", "robot_options",
           "seed_option", "config_option", "axis_pair", "rate_hz", "MIN_RATE_HZ", "given",
           "refuse_given", "known_peer", "axes_of"]


@dataclass(frozen=True, kw_only=True)
class Command:
    """One sub-command of ``robid``. ``options`` adds its arguments to its parser; ``check``
    refuses contradictory options before any work (raise a ``RobidError``); ``run`` does the
    work and returns the exit status. A command with ``commands`` is a group (``campaign
    start``, ``model add``): its sub-commands run; with ``run`` too, the group alone runs it
    (``robid fleet``, ``robid fleet reidentify``)."""

    name: str
    help: str
    options: Callable[[argparse.ArgumentParser], None] | None = None
    run: Callable[[argparse.Namespace], int] | None = None
    check: Callable[[argparse.Namespace], None] | None = None
    commands: tuple[Command, ...] = ()

    def __post_init__(self) -> None:
        if self.run is None and not self.commands:
            raise ValueError(f"command {self.name!r}: give it run or sub-commands")


def error_line(message: str) -> str:
    """Every error of ``robid``, usage or run, is this one line on stderr."""
    return f"robid: error: {message}"


#: magnitudes beyond any joint angle, frequency or duration the tool deals with
_HUGE = 1e9


def _shown(text: str) -> str:
    return repr(text) if len(text) <= 30 else repr(text[:27] + "...")


def finite_float(text: str) -> float:
    """A finite number of at most 1e9 in magnitude (no nan, inf, 1e999)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {_shown(text)}") from None
    if not math.isfinite(value) or abs(value) > _HUGE:
        raise argparse.ArgumentTypeError(f"expected a finite number within ±{_HUGE:g}, got "
                                         f"{_shown(text)}")
    return value


def positive_float(upper: float = _HUGE) -> Callable[[str], float]:
    """A finite number in (0, upper]."""

    def check(text: str) -> float:
        value = finite_float(text)
        if not 0 < value <= upper:
            raise argparse.ArgumentTypeError(f"expected a number in (0, {upper:g}], got "
                                             f"{_shown(text)}")
        return value

    check.__name__ = "positive number"
    return check


def rate_hz(upper: float = MAX_RATE_HZ) -> Callable[[str], float]:
    """A sampling or controller rate in [MIN_RATE_HZ, upper] Hz."""

    def check(text: str) -> float:
        value = finite_float(text)
        if not MIN_RATE_HZ <= value <= upper:
            raise argparse.ArgumentTypeError(f"expected a rate in [{MIN_RATE_HZ:g}, {upper:g}] "
                                             f"Hz, got {_shown(text)}")
        return value

    check.__name__ = "rate"
    return check


def bounded_int(lower: int, upper: int) -> Callable[[str], int]:
    """A whole number in [lower, upper] (no 1.5, no 10**100)."""

    def check(text: str) -> int:
        stripped = text.strip()
        digits = stripped.removeprefix("-").removeprefix("+")
        if not digits.isdigit() or len(digits) > 19 or not digits.isascii():
            raise argparse.ArgumentTypeError(f"expected a whole number in [{lower}, {upper}], "
                                             f"got {_shown(text)}")
        value = int(stripped)
        if not lower <= value <= upper:
            raise argparse.ArgumentTypeError(f"expected a whole number in [{lower}, {upper}], "
                                             f"got {_shown(text)}")
        return value

    check.__name__ = "whole number"
    return check


def output_path(kind: str = "file", *, create_parents: bool = False) -> Callable[[str], str]:
    """An output checked before the work: a file path must not name a folder, a FIFO or a
    device (an atomic write would replace it), and its folder must exist (or be creatable
    when the command creates folders); a folder path must not name a file and must be
    creatable. Writability is tried (a probe file), not guessed from the mode bits: root
    passes ``os.access`` everywhere, yet cannot write under /proc or /sys."""

    def check(text: str) -> str:
        if not text:
            raise argparse.ArgumentTypeError("empty path")
        p = Path(text)
        if kind == "file" and p.is_dir():
            raise argparse.ArgumentTypeError(f"{text}: is a folder, expected a file name")
        if kind == "file" and p.exists() and not p.is_file():
            raise argparse.ArgumentTypeError(f"{text}: is {_file_kind(p)}, expected a regular "
                                             "file")
        if kind == "dir" and p.exists() and not p.is_dir():
            raise argparse.ArgumentTypeError(f"{text}: exists and is not a folder")
        if kind == "dir" and p.is_dir():
            _writable(p, text)
            return text
        parent = p.absolute().parent
        if not (create_parents or kind == "dir"):
            if not parent.is_dir():
                raise argparse.ArgumentTypeError(f"{text}: folder {parent} does not exist")
            _writable(parent, text)
            return text
        ancestor = parent
        while not ancestor.exists():
            ancestor = ancestor.parent
        if not ancestor.is_dir():
            raise argparse.ArgumentTypeError(f"{text}: {ancestor} is not a folder")
        _writable(ancestor, text)
        return text

    check.__name__ = "output path"
    return check


#: image formats the figures can be written in (matplotlib's Agg and vector backends)
FIGURE_FORMATS = ("png", "svg", "pdf", "jpg", "jpeg")


def figure_path(*, create_parents: bool = False) -> Callable[[str], str]:
    """An output figure: an :func:`output_path` whose suffix is a known image format (no
    suffix: PNG)."""
    path_check = output_path("file", create_parents=create_parents)

    def check(text: str) -> str:
        suffix = Path(text).suffix.lower().lstrip(".")
        if suffix and suffix not in FIGURE_FORMATS:
            raise argparse.ArgumentTypeError(f"{text}: unknown image format .{suffix[:20]} "
                                             f"(expected .{', .'.join(FIGURE_FORMATS)})")
        return path_check(text)

    check.__name__ = "figure path"
    return check


def _file_kind(p: Path) -> str:
    mode = p.stat().st_mode
    for test, name in ((stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a regular file"


def _writable(folder: Path, text: str) -> None:
    try:
        fd, probe = tempfile.mkstemp(dir=folder, prefix=".robid-probe-")
    except OSError as err:
        raise argparse.ArgumentTypeError(f"{text}: cannot write in folder {folder} "
                                         f"({err.strerror or err})") from None
    os.close(fd)
    os.unlink(probe)


def given(args: argparse.Namespace, flag: str) -> bool:
    """Whether the user gave ``flag`` (an option whose default is None, False or empty)."""
    return getattr(args, flag.lstrip("-").replace("-", "_")) not in (None, False, [])


def refuse_given(args: argparse.Namespace, flags: Sequence[str], reason: str) -> None:
    """Refuse the first of ``flags`` the user gave, where it would be ignored: one line
    naming the option and why (``--weight: applies to --method irls only, not ols``)."""
    for flag in flags:
        if given(args, flag):
            raise ConfigError(f"{flag}: {reason}")


def known_peer(args: argparse.Namespace) -> None:
    """``--driver`` of the fake controller (demo, fake-controller): a peer that exists, checked
    before anything starts."""
    from robid_link.link.registry import available_peers

    peers = available_peers()
    if args.driver not in peers:
        raise ConfigError(f"--driver {args.driver}: no fake peer of that name (available: "
                          f"{', '.join(sorted(peers))})")


class OneLineParser(argparse.ArgumentParser):
    """Usage errors in one line, like every other error: ``robid: error: …``."""

    def error(self, message: str) -> None:  # type: ignore[override]
        first = message.strip().splitlines()[0] if message.strip() else "invalid usage"
        self.exit(2, error_line(f"{first} (see {self.prog} --help)") + "\n")


def robot_options(p: argparse.ArgumentParser) -> None:
    """``--robot``, ``--lock``, ``--allow-unlimited``: the robot description and how to read it."""
    p.add_argument("--robot", required=True,
                   help="robot description: MDH YAML (.yaml) or URDF (.urdf)")
    p.add_argument("--lock", action="append", default=[], metavar="NAME",
                   help="URDF joint to lock (e.g. gripper fingers); repeatable")
    p.add_argument("--allow-unlimited", action="store_true",
                   help="accept revolute/prismatic joints without consistent position limits "
                   "(logged as a warning); otherwise such a robot file is refused")


def seed_option(p: argparse.ArgumentParser, default: int | None = 0) -> None:
    """``--seed``; ``default=None`` where a check must see whether it was given."""
    p.add_argument("--seed", type=bounded_int(0, 2**32 - 1), default=default,
                   help="random seed (default 0)")


def config_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", required=True, metavar="C", help="daemon config (YAML)")


def axis_pair(text: str, option: str = "--pair") -> tuple[int, int]:
    """``J1,J2``: two axes excited or fitted together."""
    try:
        a, b = (int(x) for x in text.split(","))
    except ValueError as err:
        raise RobidError(f"{option} {text}: expected two axes J1,J2") from err
    if a < 1 or b < 1 or a == b:
        raise RobidError(f"{option} {text}: expected two different axes, numbered from 1")
    return (a, b)


def axes_of(robot: Any, option: str, axes: Sequence[int]) -> None:
    """The axes an option names exist on the robot (checked once it is read)."""
    n = int(robot.n)
    beyond = [j for j in axes if j > n]
    if beyond:
        raise RobidError(f"{option} {beyond[0]}: the robot has {n} joints")
