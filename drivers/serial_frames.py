"""The serial line's frames (``docs/serial_line_protocol.md``, "Frames"): their CRC-32 and
fields, which answer belongs to which request, and the one request in flight."""

from __future__ import annotations

import asyncio
import zlib
from collections.abc import Callable

from robid_link.exceptions import DriverError

__all__ = ["ERROR_CODES", "MAX_LINE", "Pending", "Splitter", "block_at", "block_header",
           "chunk_at", "decode_frame", "encode_frame", "number", "starts"]

#: what a controller's ERR code means (docs/serial_line_protocol.md)
ERROR_CODES = {1: "program missing or incomplete", 2: "motion supervision triggered",
               3: "joint limit reached", 4: "emergency stop", 5: "not in automatic mode",
               6: "log storage full", 7: "aborted by the daemon", 8: "busy with another program",
               9: "no log for this experiment and nonce"}
#: the longest frame either side accepts (a 16 KiB chunk in base64 plus its header)
MAX_LINE = 24_000

def encode_frame(*fields: object) -> bytes:
    """One frame: the fields joined by spaces, ``*`` and the body's CRC-32 in 8 hex digits."""
    body = " ".join(str(f) for f in fields).encode("ascii", "replace")
    return body + b"*%08X\n" % zlib.crc32(body)


def decode_frame(line: bytes) -> list[str] | None:
    """The fields of a frame, None when its CRC fails or it is not a frame (line noise)."""
    body, star, crc = line.rstrip(b"\r\n").rpartition(b"*")
    if not star or crc != b"%08X" % zlib.crc32(body):  # exact: a flipped case bit counts too
        return None
    try:
        return body.decode("ascii").split(" ")
    except UnicodeDecodeError:
        return None


class Pending:
    """The one request in flight: a predicate on answer frames and the future it resolves;
    ``payload``: the block that came with a ZBLK answer. With ``quiet`` (a ZGET: binary bytes
    may follow a damaged header) a damaged frame is resent only once the line is quiet."""

    def __init__(self, match: Callable[[list[str]], bool], quiet: bool = False) -> None:
        self.match, self.quiet = match, quiet
        self.future: asyncio.Future[list[str]] = asyncio.get_running_loop().create_future()
        self.resend = asyncio.Event()
        self.damaged = False
        self.payload = b""
        self.why = "no answer"


class Splitter:
    """Bytes read from the line into whole frames, each with the payload that follows it when
    it is an intact ZBLK header (at most ``max_payload`` bytes); noise without a line end is
    dropped past ``MAX_LINE``."""

    def __init__(self, max_payload: int) -> None:
        self.max_payload = max_payload
        self.buf = bytearray()
        self.block: tuple[bytes, int] | None = None  # a header waiting for its payload

    @property
    def waiting(self) -> bool:
        return self.block is not None

    def feed(self, data: bytes) -> list[tuple[bytes, bytes | None]]:
        self.buf += data
        out: list[tuple[bytes, bytes | None]] = []
        while True:
            if self.block is not None:
                line, n = self.block
                if len(self.buf) < n:
                    break
                out.append((line, bytes(self.buf[:n])))
                del self.buf[:n]
                self.block = None
            elif (k := self.buf.find(b"\n")) >= 0:
                line = bytes(self.buf[: k + 1])
                del self.buf[: k + 1]
                self.block = block_header(line, self.max_payload)
                if self.block is None:
                    out.append((line, None))
            else:
                break
        if self.block is None and len(self.buf) > MAX_LINE:
            self.buf.clear()
        return out

    def cut(self) -> None:
        """Forget a payload that stopped coming (and what came of it)."""
        self.block = None
        self.buf.clear()


def block_header(line: bytes, max_payload: int) -> tuple[bytes, int] | None:
    """``(line, zlen)`` when ``line`` is an intact ZBLK header whose payload (at most
    ``max_payload`` bytes) follows it on the line."""
    if not line.startswith(b"ZBLK "):
        return None
    fields = decode_frame(line)
    if fields is None or len(fields) != 9 or not fields[7].isdigit():
        return None
    zlen = int(fields[7])
    return (line, zlen) if 0 < zlen <= max_payload else None


def starts(*prefix: str, size: int | None = None) -> Callable[[list[str]], bool]:
    """Accepts the frames that begin with ``prefix`` (and have ``size`` fields, if given)."""
    want = list(prefix)
    return lambda f: f[: len(want)] == want and (size is None or len(f) == size)


def chunk_at(exp_id: str, nonce: str, offset: int) -> Callable[[list[str]], bool]:
    """Accepts the answer to ``GET`` at ``offset``: its DATA or EOF, or an ERR."""
    return lambda f: len(f) >= 4 and f[1:3] == [exp_id, nonce] and (
        f[0] == "ERR" or (f[0] in ("DATA", "EOF") and f[3] == str(offset)))


def block_at(exp_id: str, nonce: str, offset: int) -> Callable[[list[str]], bool]:
    """Accepts the answer to ``ZGET`` at ``offset``: its ZBLK or EOF, or an ERR."""
    return lambda f: len(f) >= 4 and f[1:3] == [exp_id, nonce] and (
        f[0] == "ERR" or (f[0] == "EOF" and f[3] == str(offset))
        or (f[0] == "ZBLK" and len(f) == 9 and f[3] == str(offset)))


def number(text: str, what: str) -> int:
    try:
        return int(text)
    except ValueError as err:
        raise DriverError(f"{what} frame: {text!r} is not a number") from err
