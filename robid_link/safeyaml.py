"""Bounded YAML: every YAML the tool reads goes through :func:`load_yaml`.

A ``yaml.SafeLoader`` that refuses documents over a size, alias references over a count
(billion-laughs bombs) and nesting over a depth; any parse error becomes one line naming
the file and the line. Imports no wing.
"""

from __future__ import annotations

import os
import re
import stat
from pathlib import Path
from typing import Any

import yaml
from yaml.events import AliasEvent, MappingStartEvent, SequenceStartEvent

from robid_link.exceptions import ConfigError, RobidError
from robid_link.safeopen import file_problem

__all__ = ["load_yaml", "load_yaml_file", "read_bounded", "MAX_YAML_BYTES", "MAX_YAML_ALIASES",
           "MAX_YAML_DEPTH", "MAX_YAML_NODES"]

#: robot, model, truth, trajectory-header and daemon-config files are a few kB
MAX_YAML_BYTES = 4 * 1024 * 1024
#: anchors are a convenience (a shared inertial, a shared limit set), not a data format
MAX_YAML_ALIASES = 100
MAX_YAML_DEPTH = 32
#: nodes of the document with every alias expanded (what a consumer walking it visits)
MAX_YAML_NODES = 1_000_000


class _Bounds:
    """Counts alias references and bounds the nesting while composing (mixed into a loader
    before its composer)."""

    max_aliases = MAX_YAML_ALIASES
    max_depth = MAX_YAML_DEPTH
    _aliases = 0
    _depth = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(AliasEvent):  # type: ignore[attr-defined]
            self._aliases += 1
            if self._aliases > self.max_aliases:
                mark = self.peek_event().start_mark  # type: ignore[attr-defined]
                raise _Limit(f"more than {self.max_aliases} alias references (*name)", mark)
            return super().compose_node(parent, index)  # type: ignore[misc]
        nested = self.check_event(SequenceStartEvent, MappingStartEvent)  # type: ignore[attr-defined]
        if nested:
            self._depth += 1
            if self._depth > self.max_depth:
                mark = self.peek_event().start_mark  # type: ignore[attr-defined]
                raise _Limit(f"nested deeper than {self.max_depth} levels", mark)
        try:
            return super().compose_node(parent, index)  # type: ignore[misc]
        finally:
            if nested:
                self._depth -= 1


class _BoundedLoader(_Bounds, yaml.SafeLoader):
    """A SafeLoader (pure Python) with the bounds: where PyYAML was built without libyaml."""


_LOADERS: list[type] = [_BoundedLoader]
if getattr(yaml, "__with_libyaml__", False):
    from yaml._yaml import CParser  # libyaml's parser (yaml.cyaml imports it from here)
    from yaml.composer import Composer
    from yaml.constructor import SafeConstructor
    from yaml.resolver import Resolver

    class _BoundedCLoader(_Bounds, Composer, CParser, SafeConstructor, Resolver):
        """libyaml's parser under the Python composer that keeps the bounds: a fifth of the
        pure-Python loader's time (a stepped-sine header of 144 steps: 11 ms, not 58)."""

        def __init__(self, stream: Any) -> None:
            CParser.__init__(self, stream)
            Composer.__init__(self)
            SafeConstructor.__init__(self)
            Resolver.__init__(self)

    _LOADERS.append(_BoundedCLoader)

# YAML 1.2 floats: PyYAML (YAML 1.1) reads ``-4e-06`` or ``1e3`` (no dot) as strings; a robot
# file's friction or a truth file's noise written that way is a number
for _loader in _LOADERS:
    _loader.add_implicit_resolver(  # type: ignore[attr-defined]
        "tag:yaml.org,2002:float",
        re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
        list("-+0123456789"))


class _Limit(Exception):
    def __init__(self, problem: str, mark: Any) -> None:
        super().__init__(problem)
        self.problem = problem
        self.mark = mark


def _check_expansion(root: yaml.Node, max_nodes: int) -> None:
    """Refuse a document whose alias-expanded tree is huge (a few aliases nest exponentially)."""
    sizes: dict[int, int] = {}

    def size(node: yaml.Node) -> int:
        known = sizes.get(id(node))
        if known is not None:
            return known
        total = 1
        if isinstance(node, yaml.SequenceNode):
            total += sum(size(child) for child in node.value)
        elif isinstance(node, yaml.MappingNode):
            total += sum(size(k) + size(v) for k, v in node.value)
        sizes[id(node)] = total
        if total > max_nodes:
            raise _Limit(f"more than {max_nodes} nodes once aliases are expanded", node.start_mark)
        return total

    size(root)


def _line(mark: Any) -> str:
    return f" at line {mark.line + 1}" if mark is not None else ""


def load_yaml(data: bytes | str, what: str, *, max_bytes: int = MAX_YAML_BYTES,
              max_aliases: int = MAX_YAML_ALIASES, max_depth: int = MAX_YAML_DEPTH,
              max_nodes: int = MAX_YAML_NODES, error: type[RobidError] = ConfigError) -> Any:
    """Parse one YAML document safely; ``what`` (usually the file's path) starts every error.

    Raises ``error`` (a :class:`RobidError`) with one line: too large, not UTF-8 text, an
    alias bomb, too deep, or invalid YAML at a line.
    """
    size = len(data)
    if size > max_bytes:
        raise error(f"{what}: {size} bytes, more than the {max_bytes} allowed for a YAML file")
    if isinstance(data, bytes):
        try:
            data = data.decode("utf-8")
        except UnicodeDecodeError as err:
            raise error(f"{what}: not a UTF-8 text file") from err
    if "\0" in data:
        raise error(f"{what}: not a text file (contains NUL bytes)")
    loader = None
    try:  # the pure-Python reader refuses a control character as it is built
        loader = _LOADERS[-1](data)
        loader.max_aliases = max_aliases
        loader.max_depth = max_depth
        node = loader.get_single_node()
        if node is None:
            return None
        _check_expansion(node, max_nodes)
        return loader.construct_document(node)
    except _Limit as err:
        raise error(f"{what}: refused YAML{_line(err.mark)}: {err.problem}") from None
    except yaml.MarkedYAMLError as err:
        mark = err.problem_mark or err.context_mark
        problem = (err.problem or err.context or "syntax error").strip().splitlines()[0]
        raise error(f"{what}: invalid YAML{_line(mark)}: {problem}") from err
    except yaml.YAMLError as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else "syntax error"
        raise error(f"{what}: invalid YAML: {first}") from err
    except (ValueError, OverflowError, TypeError) as err:
        # the SafeConstructor's own failures: a timestamp like 2024-13-45, a huge exponent
        raise error(f"{what}: invalid YAML value: {str(err).splitlines()[0] if str(err) else err!r}"
                    ) from err
    except RecursionError as err:
        raise error(f"{what}: refused YAML: nested too deeply") from err
    finally:
        if loader is not None:
            loader.dispose()


def read_bounded(path: str | Path, max_bytes: int, error: type[RobidError] = ConfigError) -> bytes:
    """The bytes of a regular file, refused (one line naming it) when larger than max_bytes
    or not a regular file (opened without blocking: a FIFO never hangs the reader)."""
    p = Path(path)
    try:
        fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as err:
        raise error(f"{p}: cannot read: {err.strerror or err}") from err
    with os.fdopen(fd, "rb") as fh:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise error(f"{p}: {file_problem(p) or 'is not a regular file'}")
        try:
            data = fh.read(max_bytes + 1)
        except OSError as err:
            raise error(f"{p}: cannot read: {err.strerror or err}") from err
    if len(data) > max_bytes:
        raise error(f"{p}: larger than the {max_bytes} bytes allowed")
    return data


def load_yaml_file(path: str | Path, *, max_bytes: int = MAX_YAML_BYTES,
                   error: type[RobidError] = ConfigError) -> Any:
    """:func:`load_yaml` of a file, reading at most ``max_bytes`` of it."""
    return load_yaml(read_bounded(path, max_bytes, error), str(path), max_bytes=max_bytes,
                     error=error)
