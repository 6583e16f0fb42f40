"""The client side of Universal Robots' Real-Time Data Exchange (RTDE guide, protocol version 2):
package framing, the requests a client sends, the answers and data packages it reads.

A package is ``uint16 size`` (header included) + ``uint8 type`` + payload, big-endian. Every
malformed answer is a DriverError of one line naming what was wrong; the peer in
``fakes/ur/peer.py`` is written apart from this module (no shared code).
"""

from __future__ import annotations

import asyncio
import struct
from dataclasses import dataclass

from robid_link.exceptions import DriverError, ProtocolError

__all__ = ["REQUEST_PROTOCOL_VERSION", "GET_URCONTROL_VERSION", "TEXT_MESSAGE", "DATA_PACKAGE",
           "SETUP_OUTPUTS", "SETUP_INPUTS", "START", "PAUSE", "PACKAGE_NAMES", "TYPE_FORMATS",
           "MissingFields", "Recipe", "package", "request_protocol_version",
           "get_urcontrol_version", "setup_outputs", "start", "pause", "parse_accepted",
           "parse_urcontrol_version", "parse_setup_outputs", "parse_text_message",
           "read_package"]

HEADER = struct.Struct(">HB")
REQUEST_PROTOCOL_VERSION = 86  # 'V'
GET_URCONTROL_VERSION = 118  # 'v'
TEXT_MESSAGE = 77  # 'M'
DATA_PACKAGE = 85  # 'U'
SETUP_OUTPUTS = 79  # 'O'
SETUP_INPUTS = 73  # 'I'
START = 83  # 'S'
PAUSE = 80  # 'P'
PACKAGE_NAMES = {REQUEST_PROTOCOL_VERSION: "REQUEST_PROTOCOL_VERSION",
                 GET_URCONTROL_VERSION: "GET_URCONTROL_VERSION", TEXT_MESSAGE: "TEXT_MESSAGE",
                 DATA_PACKAGE: "DATA_PACKAGE", SETUP_OUTPUTS: "CONTROL_PACKAGE_SETUP_OUTPUTS",
                 SETUP_INPUTS: "CONTROL_PACKAGE_SETUP_INPUTS", START: "CONTROL_PACKAGE_START",
                 PAUSE: "CONTROL_PACKAGE_PAUSE"}
#: the guide's data types → struct formats (all big-endian)
TYPE_FORMATS = {"BOOL": "?", "UINT8": "B", "UINT32": "I", "UINT64": "Q", "INT32": "i",
                "DOUBLE": "d", "VECTOR3D": "3d", "VECTOR6D": "6d", "VECTOR6INT32": "6i",
                "VECTOR6UINT32": "6I"}
TEXT_LEVELS = {0: "exception", 1: "error", 2: "warning", 3: "info"}


class MissingFields(DriverError):
    """The controller answered NOT_FOUND for output fields (``.names``)."""

    def __init__(self, message: str, names: tuple[str, ...]) -> None:
        super().__init__(message)
        self.names = names


@dataclass(frozen=True)
class Recipe:
    """An output recipe the controller accepted: its id, field names and types; ``unpack``
    turns one data package's payload into one flat tuple of values (recipe id first)."""

    id: int
    names: tuple[str, ...]
    types: tuple[str, ...]

    @property
    def layout(self) -> struct.Struct:
        return struct.Struct(">B" + "".join(TYPE_FORMATS[t] for t in self.types))

    def slices(self) -> dict[str, slice]:
        """Field name → its place in the unpacked tuple (after the recipe id)."""
        out, k = {}, 1
        for name, typ in zip(self.names, self.types, strict=True):
            width = struct.calcsize(">" + TYPE_FORMATS[typ])
            count = width // struct.calcsize(">" + TYPE_FORMATS[typ][-1])
            out[name] = slice(k, k + count)
            k += count
        return out


def package(kind: int, payload: bytes = b"") -> bytes:
    if len(payload) + HEADER.size > 0xFFFF:
        raise DriverError(f"RTDE package of {len(payload)} bytes is too big for its uint16 size")
    return HEADER.pack(HEADER.size + len(payload), kind) + payload


def request_protocol_version(version: int = 2) -> bytes:
    return package(REQUEST_PROTOCOL_VERSION, struct.pack(">H", version))


def get_urcontrol_version() -> bytes:
    return package(GET_URCONTROL_VERSION)


def setup_outputs(frequency_hz: float, names: tuple[str, ...]) -> bytes:
    """Protocol 2: ``double`` output frequency, then the field names joined by commas."""
    return package(SETUP_OUTPUTS, struct.pack(">d", frequency_hz) + ",".join(names).encode())


def start() -> bytes:
    return package(START)


def pause() -> bytes:
    return package(PAUSE)


def parse_accepted(kind: int, payload: bytes) -> bool:
    """The one-byte answer to a version request, start or pause (1 accepted, 0 refused)."""
    if len(payload) != 1 or payload[0] not in (0, 1):
        raise ProtocolError(f"RTDE {PACKAGE_NAMES.get(kind, kind)} answer: expected one byte "
                            f"0 or 1, got {payload[:8].hex() or 'nothing'}")
    return payload[0] == 1


def parse_urcontrol_version(payload: bytes) -> tuple[int, int, int, int]:
    if len(payload) != 16:
        raise ProtocolError(f"RTDE GET_URCONTROL_VERSION answer: expected 16 bytes (4 uint32), "
                            f"got {len(payload)}")
    major, minor, bugfix, build = struct.unpack(">IIII", payload)
    return major, minor, bugfix, build


def parse_setup_outputs(payload: bytes, names: tuple[str, ...]) -> Recipe:
    """The answer to a setup of ``names``: recipe id and one type per name. NOT_FOUND is a
    MissingFields error naming the fields; a type this client cannot read is refused."""
    if len(payload) < 2:
        raise ProtocolError("RTDE CONTROL_PACKAGE_SETUP_OUTPUTS answer: no recipe id and types")
    try:
        types = tuple(payload[1:].decode("ascii").split(","))
    except UnicodeDecodeError as err:
        raise ProtocolError("RTDE CONTROL_PACKAGE_SETUP_OUTPUTS answer: types are not ASCII"
                            ) from err
    if len(types) != len(names):
        raise ProtocolError(f"RTDE CONTROL_PACKAGE_SETUP_OUTPUTS answer: {len(types)} types for "
                            f"{len(names)} fields")
    missing = tuple(n for n, t in zip(names, types, strict=True) if t == "NOT_FOUND")
    if missing:
        raise MissingFields(f"RTDE output field{'s' if len(missing) > 1 else ''} "
                            f"{', '.join(missing)} answered NOT_FOUND", missing)
    for name, typ in zip(names, types, strict=True):
        if typ not in TYPE_FORMATS:
            raise ProtocolError(f"RTDE output field {name}: unknown type {typ[:32]!r}")
    if payload[0] == 0:
        raise DriverError("RTDE refused the output recipe (recipe id 0)")
    return Recipe(payload[0], names, types)


def parse_text_message(payload: bytes) -> tuple[str, str, str]:
    """Protocol 2 text message: (level, source, message); damaged ones read as far as they go."""
    try:
        n = payload[0]
        message = payload[1: 1 + n].decode("utf-8", "replace")
        m = payload[1 + n]
        source = payload[2 + n: 2 + n + m].decode("utf-8", "replace")
        level = TEXT_LEVELS.get(payload[2 + n + m], "info")
    except IndexError:
        return "warning", "?", payload.decode("utf-8", "replace")
    return level, source, message


async def read_package(reader: asyncio.StreamReader) -> tuple[int, bytes]:
    """One package from the stream: (type, payload). EOF mid-package is IncompleteReadError."""
    size, kind = HEADER.unpack(await reader.readexactly(HEADER.size))
    if size < HEADER.size:
        raise ProtocolError(f"RTDE package header says {size} bytes (less than its own 3): "
                            "corrupt stream")
    return kind, await reader.readexactly(size - HEADER.size)
