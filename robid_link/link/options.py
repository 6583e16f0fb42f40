"""Driver options declared once — type, bounds, default, per-joint vectors, paths, choices,
secrets — and checked at the edge: every error is one line naming the key
(``driver.<key>: expected …, got …``).

A driver lists its options as a class attribute::

    options = Options(
        share=Folder(hint="the shared folder"),
        observer=Choice("auto", "inotify", "polling", default="auto"),
        poll_interval_s=Number(0.1, low=0),
        counts_per_rad=Vector(Number(above=0), per_joint=True),
    )

``Options.parse`` turns the ``driver:`` mapping into ``Values`` (``values.share``), refusing an
unknown key, a missing required option and a value of the wrong type or range;
``Options.check_joints`` refuses a per-joint vector whose length is not the robot's.
"""

from __future__ import annotations

import math
import os
import re
import stat
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from robid_link.exceptions import ConfigError

__all__ = ["Options", "Values", "Option", "REQUIRED", "Integer", "Number", "Flag", "Text",
           "Choice", "Vector", "Table", "File", "Folder", "Secret", "Url", "Retired"]

_NAME = re.compile(r"^[a-z][a-z0-9_]*$")
_SHOWN = 60  # characters of a refused value shown in a message


class _Required:
    def __repr__(self) -> str:
        return "REQUIRED"


#: the default of an option that must be given
REQUIRED: Any = _Required()


def _show(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= _SHOWN else text[: _SHOWN - 1] + "…"


def _num(x: float) -> str:
    """A bound as a person writes it: 50000000, not 5e+07; 0.001, 1e-06."""
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else f"{x:g}"


def _bounds(low: float | None, high: float | None, above: float | None) -> str:
    if above is not None:
        return f" in ({_num(above)}, {_num(high)}]" if high is not None else f" > {_num(above)}"
    if low is not None and high is not None:
        return f" in [{_num(low)}, {_num(high)}]"
    if low is not None:
        return f" >= {_num(low)}"
    return f" <= {_num(high)}" if high is not None else ""


class Option:
    """One option: ``default`` (``REQUIRED``: it must be given), ``hint`` (what to give, in the
    'missing' line), ``per_joint`` (a vector with one value per joint of the robot) and
    ``secret`` (its value never appears in a message or a repr). Subclasses define
    ``expect`` (the words after 'expected') and ``convert``."""

    expect = "a value"

    def __init__(self, default: Any = REQUIRED, *, hint: str = "", secret: bool = False
                 ) -> None:
        self.default, self.hint, self.secret = default, hint, secret
        self.per_joint = False

    @property
    def required(self) -> bool:
        return self.default is REQUIRED

    def refuse(self, key: str, value: Any, expect: str | None = None) -> ConfigError:
        got = (f"a value of type {type(value).__name__} (not shown: secret)" if self.secret
               else _show(value))
        return ConfigError(f"{key}: expected {expect or self.expect}, got {got}")

    def convert(self, key: str, value: Any) -> Any:
        """The checked value (normalised: ``float`` for numbers, ``Path`` for paths)."""
        return value


class Integer(Option):
    """A whole number (not a bool), optionally within ``[low, high]``; ``expect`` may name
    it better ('a node id in 1..127')."""

    def __init__(self, default: Any = REQUIRED, *, low: int | None = None,
                 high: int | None = None, expect: str = "", hint: str = "") -> None:
        super().__init__(default, hint=hint)
        self.low, self.high = low, high
        self.expect = expect or "an integer" + _bounds(low, high, None)

    def convert(self, key: str, value: Any) -> int:
        if (isinstance(value, bool) or not isinstance(value, int)
                or (self.low is not None and value < self.low)
                or (self.high is not None and value > self.high)):
            raise self.refuse(key, value)
        return value


class Number(Option):
    """A finite number (int or float, not a bool) within ``[low, high]``, or above ``above``
    (exclusive)."""

    def __init__(self, default: Any = REQUIRED, *, low: float | None = None,
                 high: float | None = None, above: float | None = None, hint: str = ""
                 ) -> None:
        super().__init__(default, hint=hint)
        self.low, self.high, self.above = low, high, above
        self.expect = "a number" + _bounds(low, high, above)

    def convert(self, key: str, value: Any) -> float:
        if (isinstance(value, bool) or not isinstance(value, int | float)
                or abs(value) > 1e300 or not math.isfinite(value)  # 10**400: no float
                or (self.low is not None and value < self.low)
                or (self.above is not None and not value > self.above)
                or (self.high is not None and value > self.high)):
            raise self.refuse(key, value)
        return float(value)


class Flag(Option):
    """``true`` or ``false``."""

    expect = "true or false"

    def convert(self, key: str, value: Any) -> bool:
        if not isinstance(value, bool):
            raise self.refuse(key, value)
        return value


class Text(Option):
    """A non-empty string, optionally matching ``pattern`` (then ``expect`` names it)."""

    def __init__(self, default: Any = REQUIRED, *, pattern: str | None = None,
                 expect: str = "a non-empty string", hint: str = "") -> None:
        super().__init__(default, hint=hint)
        self.pattern = re.compile(pattern) if pattern else None
        self.expect = expect

    def convert(self, key: str, value: Any) -> str:
        if not isinstance(value, str) or not value or (
                self.pattern is not None and not self.pattern.fullmatch(value)):
            raise self.refuse(key, value)
        return value


class Secret(Text):
    """A string that is never shown (a password or token given in the config)."""

    def __init__(self, default: Any = REQUIRED, *, hint: str = "") -> None:
        super().__init__(default, hint=hint)
        self.secret = True


class Url(Option):
    """A URL of one of ``schemes`` with a host, and nothing but ``/`` after it: returned
    without a trailing path. Credentials never travel in a URL: one written with
    ``user:password@`` is refused in a line that shows neither (they belong in the driver's
    credentials file or the environment), and a refused URL is shown without them."""

    def __init__(self, default: Any = REQUIRED, *, schemes: tuple[str, ...] = ("http", "https"),
                 hint: str = "") -> None:
        super().__init__(default, hint=hint)
        self.schemes = schemes
        self.expect = f"{'|'.join(schemes)}://host[:port]"

    def convert(self, key: str, value: Any) -> str:
        from urllib.parse import urlsplit

        if not isinstance(value, str) or not value:
            raise self.refuse(key, value)
        try:
            u = urlsplit(value)
            port = u.port
        except ValueError:
            u, port = None, None
        if u is not None and (u.username is not None or u.password is not None):
            raise ConfigError(f"{key}: credentials in the URL are refused (not shown); give "
                              "them in the driver's credentials file or the environment")
        if (u is None or u.scheme not in self.schemes or not u.hostname
                or u.path not in ("", "/") or u.query or u.fragment):
            raise self.refuse(key, value.split("@")[-1] if "@" in value else value)
        host = f"[{u.hostname}]" if ":" in u.hostname else u.hostname
        return f"{u.scheme}://{host}" + (f":{port}" if port is not None else "")


class Choice(Option):
    """One of ``values`` (compared with their type: ``true`` is not ``1``)."""

    def __init__(self, *values: Any, default: Any = REQUIRED, expect: str = "",
                 hint: str = "") -> None:
        super().__init__(default, hint=hint)
        self.values = values
        names = [str(v) for v in values]
        self.expect = expect or "one of " + ", ".join(names)

    def convert(self, key: str, value: Any) -> Any:
        if not any(type(value) is type(v) and value == v for v in self.values):
            raise self.refuse(key, value)
        return value


class Vector(Option):
    """A non-empty list of ``item`` values, returned as a tuple; ``per_joint``: one per joint
    of the robot (checked when the robot is bound); ``unique``: no value twice."""

    def __init__(self, item: Option, default: Any = REQUIRED, *, per_joint: bool = False,
                 unique: bool = False, hint: str = "") -> None:
        super().__init__(default, hint=hint)
        self.item, self.per_joint, self.unique = item, per_joint, unique
        self.expect = (f"a list{' with one value per joint' if per_joint else ''}, "
                       f"each {item.expect}")

    def convert(self, key: str, value: Any) -> tuple[Any, ...]:
        if not isinstance(value, list | tuple) or not value:
            raise self.refuse(key, value)
        out = tuple(self.item.convert(f"{key}[{i}]", v) for i, v in enumerate(value))
        if self.unique and len(set(out)) != len(out):
            raise self.refuse(key, list(value), "a list without repeated values")
        return out


class Table(Option):
    """A mapping of names to values (checked further by the driver)."""

    expect = "a mapping"

    def convert(self, key: str, value: Any) -> dict[str, Any]:
        if not isinstance(value, Mapping):
            raise self.refuse(key, value)
        return dict(value)


class Retired(Option):
    """An option a driver no longer reads: given, it is refused in one line saying ``why``
    (never accepted and ignored, which would hide that the config says something untrue)."""

    def __init__(self, why: str) -> None:
        super().__init__(None)
        self.why = why

    def convert(self, key: str, value: Any) -> Any:
        raise ConfigError(f"{key}: no longer used ({self.why}); remove it from the config")


class _PathOption(Option):
    kind = "path"

    def __init__(self, default: Any = REQUIRED, *, exists: bool = False, hint: str = ""
                 ) -> None:
        super().__init__(default, hint=hint)
        self.exists = exists
        self.expect = f"a {self.kind} path"

    def convert(self, key: str, value: Any) -> Path:
        if isinstance(value, bytes) or not isinstance(value, str | os.PathLike) or not str(
                value):
            raise self.refuse(key, value)
        path = Path(value)
        if self.exists and not self._found(path):
            raise ConfigError(f"{key}: {path}: {self.kind} not found")
        return path

    def _found(self, path: Path) -> bool:
        return path.exists()


class File(_PathOption):
    """A file path; ``exists``: the file must be there; ``private``: only the daemon's user
    may read it (a credentials file)."""

    kind = "file"

    def __init__(self, default: Any = REQUIRED, *, exists: bool = False, private: bool = False,
                 hint: str = "") -> None:
        super().__init__(default, exists=exists or private, hint=hint)
        self.private = private

    def _found(self, path: Path) -> bool:
        return path.is_file()

    def convert(self, key: str, value: Any) -> Path:
        path = super().convert(key, value)
        if self.private:
            st = path.stat()
            if st.st_mode & 0o077:
                raise ConfigError(f"{key}: {path} is readable by others (mode "
                                  f"{stat.S_IMODE(st.st_mode):04o}); chmod 600 {path}")
            if hasattr(os, "getuid") and st.st_uid != os.getuid():
                raise ConfigError(f"{key}: {path} belongs to uid {st.st_uid}, not to the "
                                  f"daemon's user (uid {os.getuid()})")
        return path


class Folder(_PathOption):
    """A folder path; ``exists``: the folder must be there when the config is read;
    ``created``: the driver makes it when missing (else it must be there when the driver opens:
    ``robid config check`` and the daemon's start say so first)."""

    kind = "folder"

    def __init__(self, default: Any = REQUIRED, *, exists: bool = False, created: bool = False,
                 hint: str = "") -> None:
        super().__init__(default, exists=exists, hint=hint)
        self.created = created

    def _found(self, path: Path) -> bool:
        return path.is_dir()


class Values:
    """Checked option values as attributes (``values.share``); ``repr`` hides secrets."""

    _hidden: frozenset[str]

    def __init__(self, items: Mapping[str, Any], secret: frozenset[str] = frozenset()) -> None:
        self.__dict__.update(items)
        self.__dict__["_hidden"] = secret

    def __getattr__(self, name: str) -> Any:  # only for names not set: a typo in a driver
        raise AttributeError(f"no option {name!r}")

    def __repr__(self) -> str:
        shown = ", ".join(f"{k}={'***' if k in self._hidden else repr(v)}"
                          for k, v in self.__dict__.items() if k != "_hidden")
        return f"Values({shown})"

    def as_dict(self) -> dict[str, Any]:
        return {k: v for k, v in self.__dict__.items() if k != "_hidden"}


class Options(Mapping[str, Option]):
    """A driver's options by name (iterating gives the names)."""

    def __init__(self, **specs: Option) -> None:
        for name in specs:
            if not _NAME.match(name):
                raise ValueError(f"option name {name!r}: lower-case letters, digits and '_'")
        self._specs = dict(specs)

    def __getitem__(self, name: str) -> Option:
        return self._specs[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._specs)

    def __len__(self) -> int:
        return len(self._specs)

    def merged(self, other: Options) -> Options:
        """These options with ``other``'s added; a name in both takes ``other``'s spec (a
        driver declares its own default for an option every driver has)."""
        return Options(**{**self._specs, **other._specs})

    def parse(self, given: Mapping[str, Any], *, owner: str = "", prefix: str = "driver"
              ) -> Values:
        """Every option checked: given ones converted, the rest at their default. ``None``
        counts as not given (YAML ``key: null``)."""
        for key in given:
            if key not in self._specs:
                known = ", ".join(sorted(self._specs)) or "none"
                raise ConfigError(f"{prefix}.{key}: unknown option for driver {owner!r} "
                                  f"(known: {known})")
        out: dict[str, Any] = {}
        for name, spec in self._specs.items():
            key, value = f"{prefix}.{name}", given.get(name)
            if value is None:
                if spec.required:
                    raise ConfigError(f"{key}: missing" + (f" ({spec.hint})" if spec.hint
                                                           else ""))
                out[name] = spec.default
            else:
                out[name] = spec.convert(key, value)
        return Values(out, frozenset(n for n, s in self._specs.items() if s.secret))

    def check_joints(self, values: Values, n: int, robot: str, *, prefix: str = "driver"
                     ) -> None:
        """Every per-joint vector given holds ``n`` values (robot ``robot`` has ``n`` joints)."""
        for name, spec in self._specs.items():
            vec = getattr(values, name, None)
            if spec.per_joint and vec is not None and len(vec) != n:
                raise ConfigError(f"{prefix}.{name}: {len(vec)} values, robot {robot} has {n} "
                                  "joints")
