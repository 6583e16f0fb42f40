"""The fuzz tests' harness (issues 14 and 25): one malformed case in, one verdict out, and the
tally that ``test_fuzz_cli.py::test_zz_fuzz_counts`` prints and checks.

Every case is malformed by construction. It must end in one ``RobidError`` of one line naming
its object — the file, key, option or joint (for the CLI: exit 2 and one ``robid: error:``
line). Anything else is counted: a traceback (any other exception, or the CLI's ``internal
error`` line), a hang (more than ``CASE_S`` seconds), an unnamed error (a message that is not
one line or does not name the object) or a wrong success.
"""

from __future__ import annotations

import copy
import os
import signal
import time
import warnings
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

from robid_link.cli import EXIT_INTERNAL, main
from robid_link.exceptions import RobidError

__all__ = ["SLOW", "EXAMPLES", "FUZZ", "COUNTS", "FAILURES", "check", "check_cli",
           "check_report", "write",
           "not_a_number", "json_like", "set_path", "yaml_junk", "is_float", "VERDICTS"]

SLOW = bool(os.environ.get("ROBID_VALIDATE"))
#: examples per file kind, command or option family: ≥ 2000 cases in make validate
EXAMPLES = 100 if SLOW else 6
CASE_S = 20
COUNTS: Counter[str] = Counter()
FAILURES: list[tuple[str, str]] = []  # (verdict, what happened)
VERDICTS = ("traceback", "hang", "unnamed error", "wrong success")

FUZZ = settings(max_examples=EXAMPLES, deadline=None, database=None,
                suppress_health_check=list(HealthCheck))


class _Hang(Exception):
    pass


class _Internal(Exception):
    """The CLI printed its ``internal error`` line: a traceback the user did not see."""


class _NotOneLine(Exception):
    """The CLI's error was not one ``robid: error:`` line with exit status 2."""


def _alarm(signum: int, frame: Any) -> None:
    raise _Hang


def _fail(verdict: str, text: str) -> None:
    FAILURES.append((verdict, text[:300]))
    pytest.fail(f"{verdict}: {text[:300]}")


def check(kind: str, name: Path | str, run: Callable[[], Any]) -> None:
    """Run one malformed case: it must raise a one-line RobidError naming ``name``."""
    COUNTS[kind] += 1
    old_handler = signal.signal(signal.SIGALRM, _alarm)
    prev, _ = signal.setitimer(signal.ITIMER_REAL, CASE_S)  # pytest-timeout's alarm, restored
    start = time.monotonic()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            run()
    except _Hang:
        _fail("hang", f"{kind}: more than {CASE_S} s on {name}")
    except RobidError as err:
        msg = str(err)
        if "\n" in msg or str(name) not in msg:
            _fail("unnamed error", f"{kind}: not one line naming {name}: {msg!r}")
    except _Internal as err:
        _fail("traceback", f"{kind}: {err}")
    except _NotOneLine as err:
        _fail("unnamed error", f"{kind}: {err}")
    except Exception as err:  # a traceback for the user
        FAILURES.append(("traceback", f"{kind}: {type(err).__name__}: {err}"[:300]))
        raise
    else:
        _fail("wrong success", f"{kind}: on {name}")
    finally:
        elapsed = time.monotonic() - start
        signal.setitimer(signal.ITIMER_REAL, max(prev - elapsed, 0.001) if prev else 0)
        signal.signal(signal.SIGALRM, old_handler)


def check_cli(kind: str, argv: list[str], capsys: pytest.CaptureFixture[str],
              name: Path | str) -> None:
    """``robid argv`` must exit 2 with one ``robid: error:`` line naming ``name``."""

    def run() -> None:
        rc = main([str(a) for a in argv])
        err = [line for line in capsys.readouterr().err.strip().splitlines()
               if not line.startswith("robid: warning:")]
        if rc == 0:
            return  # check() counts it as a wrong success
        if rc == EXIT_INTERNAL:
            raise _Internal(f"{' '.join(map(str, argv))[:120]}: {err}")
        if rc != 2 or len(err) != 1 or not err[0].startswith("robid: error: "):
            raise _NotOneLine(f"exit {rc}, stderr {err!r}")
        raise RobidError(err[0])

    check(kind, name, run)


def check_report(kind: str, argv: list[str], capsys: pytest.CaptureFixture[str],
                 name: Path | str) -> None:
    """``robid config check``'s report: exit 1 and a line naming ``name`` (or, for a config
    that does not load, exit 2 and one ``robid: error:`` line naming it)."""

    def run() -> None:
        rc = main([str(a) for a in argv])
        out = capsys.readouterr()
        err = [ln for ln in out.err.strip().splitlines() if not ln.startswith("robid: warning:")]
        said = [ln for ln in out.out.splitlines() if not ln.endswith(": ok")]
        if rc == 0:
            return
        if rc == EXIT_INTERNAL:
            raise _Internal(f"{' '.join(map(str, argv))[:120]}: {err}")
        if rc == 2 and len(err) == 1 and err[0].startswith("robid: error: "):
            raise RobidError(err[0])
        if rc == 1 and said and not err:
            raise RobidError(next((ln for ln in said if str(name) in ln), said[0]))
        raise _NotOneLine(f"exit {rc}, stdout {out.out[-300:]!r}, stderr {err!r}")

    check(kind, name, run)


def write(path: Path, data: bytes | str) -> Path:
    if path.is_dir() or (path.exists() and not path.is_file()):
        path.rename(path.with_name(f"{path.name}.{time.monotonic_ns()}.old"))
    path.write_bytes(data.encode("utf-8", "surrogateescape") if isinstance(data, str) else data)
    return path


# ----------------------------------------------------------------------------- generators

not_a_number = st.one_of(
    st.sampled_from([float("nan"), float("inf"), -float("inf"), 10 ** 400, -(10 ** 400)]),
    st.text(max_size=8), st.none(), st.booleans(), st.lists(st.integers(), max_size=2),
    st.dictionaries(st.text(max_size=3), st.integers(), max_size=2))
json_like = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=10)),
    lambda children: st.lists(children, max_size=4)
    | st.dictionaries(st.text(max_size=6), children, max_size=4), max_leaves=20)


def set_path(doc: Any, path: tuple[Any, ...], value: Any) -> Any:
    """A deep copy of ``doc`` with the value at ``path`` replaced."""
    doc = copy.deepcopy(doc)
    target = doc
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = value
    return doc


def alias_bomb(levels: int) -> str:
    text = 'a0: &a0 ["x","x","x","x","x","x","x","x","x","x"]\n'
    for i in range(1, levels):
        text += f"a{i}: &a{i} [{','.join([f'*a{i - 1}'] * 10)}]\n"
    return text


def yaml_junk() -> st.SearchStrategy[str]:
    """Documents that no YAML file kind of the tool accepts."""
    return st.one_of(
        st.integers(6, 12).map(alias_bomb),
        st.integers(40, 200).map(lambda d: "[" * d + "]" * d),
        json_like.filter(lambda v: not isinstance(v, dict) or v and "effects" not in v).map(
            lambda v: yaml.safe_dump(v)),
        st.binary(min_size=1, max_size=64).map(lambda b: b.decode("latin-1") + "\x00: [\n"),
        st.sampled_from(["a: 2024-13-45\n", "a: [\n", "{a: 1\n", "a: !!python/object:os.system"
                         " x\n", "- &x [*x]\n", "a: *missing\n", "? [1]\n: 2\n"]))


def is_float(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True
