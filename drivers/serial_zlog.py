"""The daemon's decoder of compressed log blocks (``docs/serial_line_protocol.md``, capability
``zlog1``): a block's payload back to the log's bytes, inflating never past its bound.

Every way a payload can be wrong (a damaged zlib stream, one that inflates beyond the block, a
column that does not decode, bytes of another length) is a ``BlockError`` with a short reason:
the driver asks for the block again, a bounded number of times.
"""

from __future__ import annotations

import zlib
from collections.abc import Iterator

import numpy as np

__all__ = ["BlockError", "block_length", "decode_answer", "decode_block", "inflate_limit"]

_MAX_SCALE = 18
_INT64_LOW, _INT64_HIGH = -(1 << 63), (1 << 63) - 1
_POW10 = [10 ** k for k in range(_MAX_SCALE + 1)]


class BlockError(ValueError):
    """A block payload that does not decode to its bytes (the reason in one short line)."""


def block_length(header: list[str], size: int) -> int:
    """The log bytes a ZBLK ``header`` says its block covers, checked against the ``size``
    asked for."""
    rawlen = header[4]
    if not rawlen.isdigit() or not 1 <= int(rawlen) <= size:
        raise BlockError(f"a block of {rawlen} bytes where at most {size} were asked")
    return int(rawlen)


def decode_answer(header: list[str], payload: bytes, size: int) -> bytes:
    """The log bytes a ZBLK answer (``header``, and ``payload`` whose CRC was checked)
    carries, their CRC-32 checked."""
    raw = decode_block(header[6], payload, block_length(header, size))
    if f"{zlib.crc32(raw):08X}" != header[5]:
        raise BlockError("its bytes fail their CRC")
    return raw


def inflate_limit(codec: str, rawlen: int) -> int:
    """The most bytes a payload of ``codec`` may inflate to (page: "What the daemon does")."""
    return rawlen if codec == "z" else 2 * rawlen + 4096


def decode_block(codec: str, payload: bytes, rawlen: int) -> bytes:
    """The ``rawlen`` bytes of the log a block's payload carries."""
    if codec not in ("z", "d"):
        raise BlockError(f"unknown codec {codec!r}")
    inflated = _inflate(payload, inflate_limit(codec, rawlen))
    raw = inflated if codec == "z" else _Columns(inflated, rawlen).text()
    if len(raw) != rawlen:
        raise BlockError(f"{len(raw)} bytes where the header says {rawlen}")
    return raw


def _inflate(payload: bytes, limit: int) -> bytes:
    inflater = zlib.decompressobj()
    try:
        out = inflater.decompress(payload, limit + 1)  # one more tells a bomb
    except zlib.error as err:
        raise BlockError(f"damaged zlib stream ({err})") from None
    if len(out) > limit:
        raise BlockError(f"inflates beyond {limit} bytes")
    if not inflater.eof:
        raise BlockError("zlib stream ends early")
    if inflater.unused_data:
        raise BlockError("bytes after the zlib stream")
    return out


class _Columns:
    """A reader of codec d's layout (lines, fields, columns) over the inflated bytes."""

    def __init__(self, data: bytes, rawlen: int) -> None:
        self.data, self.pos, self.rawlen = data, 0, rawlen

    def varint(self) -> int:
        value = shift = 0
        for _ in range(10):
            if self.pos >= len(self.data):
                raise BlockError("columns end inside a number")
            byte = self.data[self.pos]
            self.pos += 1
            value |= (byte & 0x7F) << shift
            if byte < 0x80:
                return value
            shift += 7
        raise BlockError("a varint over 10 bytes")

    def byte(self) -> int:
        if self.pos >= len(self.data):
            raise BlockError("columns end inside a column header")
        self.pos += 1
        return self.data[self.pos - 1]

    def take(self, n: int) -> bytes:
        if self.pos + n > len(self.data):
            raise BlockError("columns end inside a column")
        self.pos += n
        return self.data[self.pos - n: self.pos]

    def text(self) -> bytes:
        n_lines = self.varint()
        if not 1 <= n_lines <= len(self.data):  # each line costs a byte of the layout
            raise BlockError(f"{n_lines} lines in {len(self.data)} bytes")
        widths = [self.varint() for _ in range(n_lines)]
        # n fields make at least n - 1 bytes (the commas and line ends between them)
        if min(widths) < 1 or sum(widths) > self.rawlen + 1:
            raise BlockError(f"{sum(widths)} fields for {self.rawlen} bytes")
        longer = [0] * (max(widths) + 1)  # longer[j]: the lines of more than j fields
        for w in widths:
            longer[w - 1] += 1
        for j in range(len(longer) - 2, -1, -1):
            longer[j] += longer[j + 1]
        cols = [self.column(longer[j]) for j in range(max(widths))]
        if self.pos != len(self.data):
            raise BlockError(f"{len(self.data) - self.pos} bytes after the last column")
        at = [0] * len(cols)
        lines = []
        for w in widths:
            fields = []
            for j in range(w):
                fields.append(cols[j][at[j]])
                at[j] += 1
            lines.append(b",".join(fields))
        return b"\n".join(lines)

    def column(self, n: int) -> list[bytes]:
        order, smax, dflt, width = self.byte(), self.varint(), self.varint(), self.byte()
        if order > 2 or smax > _MAX_SCALE or dflt > smax or width > 8:
            raise BlockError(f"column header out of range (order {order}, scale {smax}, "
                             f"default {dflt}, {width} bytes per residual)")
        scales: list[int | None] = [dflt] * n  # None: a literal
        i = -1
        for _ in range(self.varint()):
            i += self.varint() + 1
            tag = self.varint()
            if i >= n or tag > smax + 1:
                raise BlockError("an exception past its column or its scale")
            scales[i] = tag - 1 if tag else None
        numbered = any(s is not None for s in scales)
        first = _unzigzag(self.varint()) if numbered else 0
        residuals = _planes(self.take(width * n), width, n)
        literals = iter([self.take(self.varint()) for s in scales if s is None])
        return _cells(scales, residuals, order, smax, first, literals)


def _planes(buf: bytes, width: int, n: int) -> list[int]:
    """The residuals (zigzag undone) of ``width`` planes of ``n`` bytes, least significant
    plane first."""
    if width == 0:
        return [0] * n
    planes = np.frombuffer(buf, np.uint8).reshape(width, n).astype(np.uint64)
    z = np.zeros(n, np.uint64)
    for k in range(width):
        z |= planes[k] << np.uint64(8 * k)
    return ((z >> np.uint64(1)).astype(np.int64) ^ -(z & np.uint64(1)).astype(np.int64)).tolist()


def _cells(scales: list[int | None], residuals: list[int], order: int, smax: int, first: int,
           literals: Iterator[bytes]) -> list[bytes]:
    """Each field's bytes: the literals as they came, the numbers predicted and corrected."""
    out: list[bytes] = []
    g1 = g2 = None
    for s, r in zip(scales, residuals, strict=True):
        if s is None:
            out.append(next(literals))
            continue
        step = _POW10[smax - s]
        if g1 is None:
            m = first
        elif order == 0:
            m = r
        else:
            pred = g1 if order == 1 or g2 is None else 2 * g1 - g2
            m = pred // step + r
        g = m * step
        if not _INT64_LOW <= g <= _INT64_HIGH:
            raise BlockError("a value outside 64 bits")
        g1, g2 = g, g1
        out.append(_text(m, s))
    return out


def _text(m: int, s: int) -> bytes:
    digits = str(-m if m < 0 else m)
    if s:
        digits = digits.rjust(s + 1, "0")
        digits = f"{digits[:-s]}.{digits[-s:]}"
    return (f"-{digits}" if m < 0 else digits).encode()


def _unzigzag(z: int) -> int:
    return (z >> 1) ^ -(z & 1)
