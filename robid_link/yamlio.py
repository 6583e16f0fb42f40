"""YAML at the edge, importable from everywhere (it imports no wing): read a file into a
mapping, and check a mapping's keys with one message format that names the key path.

    <file>: <key.path>: unknown key 'x' (known: a, b)
    <file>: <key.path>: missing key 'y'
    <file>: <key.path>: expected a mapping, got list
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

import yaml

from robid_link.exceptions import ConfigError, RobidError
from robid_link.safeopen import file_problem
from robid_link.safeyaml import load_yaml_file

__all__ = ["read_yaml_mapping", "check_keys", "yaml_type"]

_TYPE_NAMES = {dict: "mapping", list: "list", str: "string", bool: "boolean", int: "integer",
               float: "number", type(None): "nothing"}


def yaml_type(value: Any) -> str:
    """The YAML name of a loaded value's type (``mapping``, ``list``, ``string``, …)."""
    return _TYPE_NAMES.get(type(value), type(value).__name__)


def _prefix(where: str) -> str:
    return f"{where}: " if where else ""


def check_keys(doc: Any, where: str, *, required: Iterable[str] = (),
               optional: Iterable[str] = (), error: type[RobidError] = ConfigError
               ) -> dict[str, Any]:
    """``doc`` must be a mapping holding every ``required`` key and nothing but ``required``
    and ``optional`` keys; ``where`` names it (``"robot.yaml: joints[2]"``). Returns ``doc``."""
    if not isinstance(doc, dict):
        raise error(f"{_prefix(where)}expected a mapping, got {yaml_type(doc)}")
    req = list(required)
    known = [*req, *(k for k in optional if k not in req)]
    unknown = [k for k in doc if k not in known]
    if unknown:
        raise error(f"{_prefix(where)}unknown key {str(sorted(map(str, unknown))[0])!r} "
                    f"(known: {', '.join(sorted(known))})")
    for key in req:
        if key not in doc:
            raise error(f"{_prefix(where)}missing key {key!r}")
    return doc


def read_yaml_mapping(path: str | Path, what: str, error: type[RobidError] = ConfigError,
                      must_exist: bool = True) -> dict[str, Any]:
    """``safe_load`` a YAML file that must hold a mapping; ``what`` names it in errors."""
    p = Path(path)
    problem = file_problem(p)
    if problem == "not found" and not must_exist:
        return {}
    if problem:
        raise error(f"{p}: {what} {problem}")
    try:
        doc = load_yaml_file(p, error=error)  # bounded: size, aliases, nesting
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise error(f"{p}: invalid YAML{where}") from err
    except UnicodeDecodeError as err:
        raise error(f"{p}: not a text file") from err
    if not isinstance(doc, dict):
        raise error(f"{p}: expected a mapping, got {yaml_type(doc)} ({what})")
    return doc
