"""YAML at the edge: read a file into a mapping, with one-line errors that name the file.

Callers validate keys and raise their own error class (robot, model, truth, trajectory).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from robid_link.exceptions import ConfigError, RobidError

__all__ = ["read_yaml_mapping"]


def read_yaml_mapping(path: str | Path, what: str, error: type[RobidError] = ConfigError,
                      must_exist: bool = True) -> dict[str, Any]:
    """``safe_load`` a YAML file that must hold a mapping; ``what`` names it in errors."""
    p = Path(path)
    if not p.is_file():
        if must_exist:
            raise error(f"{p}: {what} not found")
        return {}
    try:
        doc = yaml.safe_load(p.read_text())
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise error(f"{p}: invalid YAML{where}") from err
    except UnicodeDecodeError as err:
        raise error(f"{p}: not a text file") from err
    if not isinstance(doc, dict):
        raise error(f"{p}: expected a mapping")
    return doc
