"""The door's wire format: ``Record``, the base of every job and result record (``jobs.py``),
and its JSON both ways with one-line errors.

A record is one JSON object: ``{"schema": "robid-job/1", "type": "identify-job", <field>: …}``;
``from_json`` refuses an unknown schema, an unknown record type, and a missing or unknown key,
in one line naming the record and the key (``RecordError``). Bytes go as base64; NaN and ±inf
(unknown limits) as Python's json writes them. Imports nothing numerical.
"""

from __future__ import annotations

import base64
import binascii
import dataclasses
import json
import types
import typing
from collections.abc import Mapping
from typing import Any, ClassVar, Self

from robid_link.exceptions import RecordError

__all__ = ["SCHEMA", "RECORDS", "Record", "Job"]

#: the wire format's name and version; a record of another version is refused
SCHEMA = "robid-job/1"

#: record type name → record class (every record, jobs, results and their parts)
RECORDS: dict[str, type[Record]] = {}


class Record:
    """Base of every record: a frozen dataclass with a ``TYPE`` name, JSON both ways."""

    TYPE: ClassVar[str] = ""

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        name = cls.__dict__.get("TYPE")
        if name:
            if name in RECORDS:
                raise ValueError(f"record type {name!r} is defined twice")
            RECORDS[name] = cls

    def to_dict(self) -> dict[str, Any]:
        return {"schema": SCHEMA, "type": self.TYPE, **_encode(self)}

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), separators=(",", ":"), default=_plain)

    @classmethod
    def from_json(cls, text: str | bytes) -> Self:
        """The record in ``text``; RecordError names what is wrong (one line)."""
        try:
            doc = json.loads(text)
        except ValueError as err:
            raise RecordError(f"record: not JSON ({err})") from err
        return cls.from_dict(doc)

    @classmethod
    def from_dict(cls, doc: Any) -> Self:
        if not isinstance(doc, dict):
            raise RecordError(f"record: expected a JSON object, got {_what(doc)}")
        if "schema" not in doc:
            raise RecordError("record: key 'schema' missing")
        if doc["schema"] != SCHEMA:
            raise RecordError(f"record: schema {doc['schema']!r} unknown (this side reads "
                              f"{SCHEMA})")
        name = doc.get("type")
        target = RECORDS.get(name) if isinstance(name, str) else None
        if target is None or not isinstance(name, str):
            raise RecordError(f"record: type {name!r} unknown")
        if not issubclass(target, cls):
            raise RecordError(f"{name}: expected a {cls.TYPE or cls.__name__} record")
        body = {k: v for k, v in doc.items() if k not in ("schema", "type")}
        return typing.cast(Self, _decode_record(target, body, name, ""))


class Job(Record):
    """A job for the worker; ``RESULT`` is the record type it answers with."""

    RESULT: ClassVar[type[Record]] = Record


def _plain(value: Any) -> Any:
    """numpy scalars and arrays that slipped into a free-form mapping: as JSON numbers."""
    if hasattr(value, "tolist"):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON")


def _encode(value: Any) -> Any:
    if isinstance(value, Record):
        return {f.name: _encode(getattr(value, f.name)) for f in dataclasses.fields(value)}  # type: ignore[arg-type]
    if isinstance(value, bytes):
        return base64.b64encode(value).decode("ascii")
    if isinstance(value, Mapping):
        return {str(k): _encode(v) for k, v in value.items()}
    if isinstance(value, tuple | list):
        if all(type(v) in _PLAIN for v in value):  # a row of numbers: no walk per element
            return list(value)
        return [_encode(v) for v in value]
    return value


_PLAIN = (int, float, str, bool, type(None))
#: element types of tuples decoded in one pass (a bad element falls back to the walk that
#: names it); bool is not an int here
_FAST: dict[Any, tuple[type, ...]] = {float: (int, float), int: (int,), str: (str,)}


def _what(value: Any) -> str:
    if isinstance(value, bool | int | float | str) or value is None:
        text = repr(value)
        return text if len(text) <= 40 else f"{text[:37]}…"
    names: dict[type, str] = {dict: "an object", list: "a list"}
    return names.get(type(value), type(value).__name__)


_HINTS: dict[type, dict[str, Any]] = {}


def _decode_record(cls: type[Record], body: Any, rec: str, path: str) -> Record:
    if not isinstance(body, dict):
        raise RecordError(f"{rec}: key '{path}': expected an object, got {_what(body)}")
    hints = _HINTS.get(cls)
    if hints is None:
        hints = _HINTS[cls] = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]  # type: ignore[arg-type]
    for key in body:
        if key not in names:
            raise RecordError(f"{rec}: unknown key '{path}{key}' (known: {', '.join(names)})")
    for key in names:
        if key not in body:
            raise RecordError(f"{rec}: key '{path}{key}' missing")
    values = {k: _decode(body[k], hints[k], rec, f"{path}{k}") for k in names}
    try:
        return cls(**values)
    except (TypeError, ValueError) as err:
        raise RecordError(f"{rec}: {err}") from err


def _decode(value: Any, hint: Any, rec: str, path: str) -> Any:
    """``value`` (parsed JSON) as the field type ``hint``; RecordError names the key."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)

    def bad(expected: str) -> RecordError:
        return RecordError(f"{rec}: key '{path}': expected {expected}, got {_what(value)}")

    if hint is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        return _decode(value, next(a for a in args if a is not type(None)), rec, path)
    if isinstance(hint, type) and issubclass(hint, Record):
        return _decode_record(hint, value, rec, f"{path}.")
    if origin is tuple:
        if not isinstance(value, list):
            raise bad("a list")
        fast = _FAST.get(args[0])
        if fast is not None and all(type(v) in fast for v in value):
            return tuple(map(args[0], value))
        return tuple(_decode(v, args[0], rec, f"{path}[{i}]") for i, v in enumerate(value))
    if origin in (dict, Mapping):
        if not isinstance(value, dict):
            raise bad("an object")
        return {k: _decode(v, args[1], rec, f"{path}.{k}") for k, v in value.items()}
    if hint is bytes:
        try:
            return base64.b64decode(value, validate=True)
        except (TypeError, ValueError, binascii.Error):
            raise bad("base64 text") from None
    if hint is bool:
        if not isinstance(value, bool):
            raise bad("true or false")
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad("an integer")
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise bad("a number")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise bad("a string")
        return value
    raise TypeError(f"{rec}.{path}: no JSON form for {hint!r}")

