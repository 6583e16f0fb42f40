"""The controller's end of compressed logs (``docs/serial_line_protocol.md``, "Compressed logs
(capability zlog1)"), written from that page: which bytes a block covers, and its payload —
codec ``d`` (the block in columns of residuals, then zlib) or ``z`` (zlib of the bytes)."""

from __future__ import annotations

import re
import zlib
from collections import Counter

__all__ = ["block_length", "encode_block", "columns", "MAX_BLOCK"]

#: the largest ``max`` a ZGET may ask for (page: "Requests")
MAX_BLOCK = 1 << 20
_NUMBER = re.compile(rb"-?(?:0|[1-9][0-9]*)(?:\.([0-9]+))?")
_INT64 = 1 << 63


def block_length(log: bytes, offset: int, max_bytes: int) -> int:
    """How many bytes the block at ``offset`` covers: up to the last line end within ``max``
    bytes, or ``max`` bytes (fewer at the log's end) when there is none."""
    end = log.rfind(b"\n", offset, offset + max_bytes) + 1
    if end <= offset:
        end = min(offset + max_bytes, len(log))
    return end - offset


def encode_block(raw: bytes) -> tuple[str, bytes]:
    """``(codec, payload)``: ``d`` when its payload is the shorter one, else ``z``."""
    plain = zlib.compress(raw, 9)
    cols = columns(raw)
    if len(cols) <= 2 * len(raw) + 4096:
        packed = zlib.compress(cols, 9)
        if len(packed) < len(plain):
            return "d", packed
    return "z", plain


def columns(raw: bytes) -> bytes:
    """The block in columns, before deflate (page: "Layout")."""
    lines = [line.split(b",") for line in raw.split(b"\n")]
    out = bytearray()
    _varint(out, len(lines))
    for fields in lines:
        _varint(out, len(fields))
    for j in range(max(len(fields) for fields in lines)):
        _column(out, [fields[j] for fields in lines if len(fields) > j])
    return bytes(out)


def _number(field: bytes) -> tuple[int, int] | None:
    """(value, scale) of a number field, None for a literal."""
    match = _NUMBER.fullmatch(field)
    if match is None:
        return None
    digits = field.lstrip(b"-").replace(b".", b"")
    if len(digits) > 18:
        return None
    value = int(digits)
    if field.startswith(b"-"):
        if value == 0:
            return None  # a negative zero would come back without its sign
        value = -value
    return value, len(match.group(1) or b"")


def _column(out: bytearray, cells: list[bytes]) -> None:
    parsed = [_number(c) for c in cells]
    scales = [p[1] for p in parsed if p is not None]
    smax = max(scales, default=0)
    # a number whose grid value leaves int64 travels as a literal (smax may stay larger)
    parsed = [p if p is not None and -_INT64 <= p[0] * 10 ** (smax - p[1]) < _INT64 else None
              for p in parsed]
    counts = Counter(p[1] for p in parsed if p is not None)
    dflt = min(counts, key=lambda s: (-counts[s], s)) if counts else 0
    best: tuple[int, int, int, list[int]] | None = None
    for order in (0, 1, 2):
        res = _residuals(parsed, smax, order)
        width = (max(res, default=0).bit_length() + 7) // 8
        key = (width, sum(r.bit_length() for r in res), order, res)
        if width <= 8 and (best is None or key[:3] < best[:3]):
            best = key
    assert best is not None  # order 0 always fits: |m| < 10^18
    width, _, order, res = best
    out.append(order)
    _varint(out, smax)
    _varint(out, dflt)
    out.append(width)
    exceptions = [(i, 0 if p is None else p[1] + 1) for i, p in enumerate(parsed)
                  if p is None or p[1] != dflt]
    _varint(out, len(exceptions))
    last = -1
    for i, tag in exceptions:
        _varint(out, i - last - 1)
        _varint(out, tag)
        last = i
    first = next((p for p in parsed if p is not None), None)
    if first is not None:
        _varint(out, _zigzag(first[0]))
    for k in range(width):
        out += bytes((r >> (8 * k)) & 0xFF for r in res)
    for cell, p in zip(cells, parsed, strict=True):
        if p is None:
            _varint(out, len(cell))
            out += cell


def _residuals(parsed: list[tuple[int, int] | None], smax: int, order: int) -> list[int]:
    """zigzag(m − ⌊p / 10^(smax − s)⌋) per field; 0 for a literal and the first number."""
    out = []
    g1 = g2 = None
    for p in parsed:
        if p is None:
            out.append(0)
            continue
        m, s = p
        step = 10 ** (smax - s)
        if g1 is None:
            out.append(0)
        else:
            pred = 0 if order == 0 else g1 if order == 1 or g2 is None else 2 * g1 - g2
            out.append(_zigzag(m - pred // step))
        g1, g2 = m * step, g1
    return out


def _zigzag(v: int) -> int:
    return 2 * v if v >= 0 else -2 * v - 1


def _varint(out: bytearray, v: int) -> None:
    while v >= 0x80:
        out.append(v & 0x7F | 0x80)
        v >>= 7
    out.append(v)
