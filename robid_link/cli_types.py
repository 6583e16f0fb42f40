"""argparse ``type=`` checks for ``robid``'s options: finite numbers, bounded integers and output
paths, refused at parse time — before any work — with one line naming the option.
"""

from __future__ import annotations

import argparse
import math
import os
from collections.abc import Callable
from pathlib import Path

__all__ = ["finite_float", "positive_float", "bounded_int", "output_path", "OneLineParser"]

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
    """An output checked before the work: a file path must not name a folder and its folder
    must exist (or be creatable when the command creates folders); a folder path must not
    name a file and must be creatable."""

    def check(text: str) -> str:
        if not text:
            raise argparse.ArgumentTypeError("empty path")
        p = Path(text)
        if kind == "file" and p.is_dir():
            raise argparse.ArgumentTypeError(f"{text}: is a folder, expected a file name")
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


def _writable(folder: Path, text: str) -> None:
    if not os.access(folder, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"{text}: folder {folder} is not writable")


class OneLineParser(argparse.ArgumentParser):
    """Usage errors in one line, like every other error: ``robid: error: …``."""

    def error(self, message: str) -> None:  # type: ignore[override]
        first = message.strip().splitlines()[0] if message.strip() else "invalid usage"
        self.exit(2, f"robid: error: {first} (see {self.prog} --help)\n")
