"""Compressed log blocks (docs/serial_line_protocol.md, "Compressed logs"): the controller's
encoder (``fakes/serial_zlog.py``) and the daemon's decoder (``drivers/serial_zlog.py``),
written apart from the page, agree on any text; the page's worked example is what the encoder
writes and what the decoder reads; every malformed payload is refused with a reason, and none
inflates past its bound."""

from __future__ import annotations

import re
import zlib
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robid_link.drivers.serial_zlog import BlockError, decode_block
from robid_link.fakes.serial_zlog import block_length, columns, encode_block

DOC = Path(__file__).resolve().parents[2] / "docs" / "serial_line_protocol.md"
LOG = (b"t,q1,q2,q3,tau1,tau2,tau3\n0,0,0,0,0.5,-12.25,3.5\n"
       b"0.01,0.0001,-0.0001,0.00005,0.52,-12.24,3.51\n"
       b"0.02,0.0004,-0.0004,0.0002,0.49,-12.26,3.49\n")

_number = st.builds(lambda sign, whole, frac: sign + whole + frac,
                    st.sampled_from(["", "-"]),
                    st.one_of(st.just("0"), st.integers(1, 10**12).map(str)),
                    st.one_of(st.just(""), st.text("0123456789", min_size=1, max_size=12)
                              .map(lambda f: "." + f)))
_field = st.one_of(_number, _number, st.sampled_from(["", "t", "nan", "1.5e-05", "-0", "007",
                                                      "-0.000", "1234567890123456789"]))
_text = st.lists(st.lists(_field, min_size=1, max_size=8).map(",".join), min_size=1,
                 max_size=40).map(lambda lines: "\n".join(lines).encode())


@settings(max_examples=150, deadline=None)
@given(_text)
def test_any_text_comes_back_byte_for_byte(raw: bytes) -> None:
    codec, payload = encode_block(raw)
    assert decode_block(codec, payload, len(raw)) == raw
    assert decode_block("d", zlib.compress(columns(raw)), len(raw)) == raw


@settings(max_examples=50, deadline=None)
@given(st.binary(min_size=1, max_size=300))
def test_any_bytes_come_back(raw: bytes) -> None:
    codec, payload = encode_block(raw)
    assert decode_block(codec, payload, len(raw)) == raw


def test_a_block_ends_at_a_line_end_or_at_max() -> None:
    assert block_length(LOG, 0, 1024) == len(LOG)
    assert block_length(LOG, 0, 40) == 26  # the header line
    assert block_length(LOG, 0, 16) == 16  # no line end within 16 bytes
    assert block_length(LOG, 130, 1024) == len(LOG) - 130


def test_the_pages_example_is_what_the_encoder_writes() -> None:
    text = DOC.read_text()
    rows = re.findall(r"^column (\d)\s+([0-9A-F ]+)$", text, re.M)
    assert [int(j) for j, _ in rows] == list(range(7))
    example = bytes.fromhex("05 07 07 07 07 01" + "".join(h for _, h in rows))
    assert columns(LOG) == example
    assert decode_block("d", zlib.compress(example), len(LOG)) == LOG
    codec, payload = encode_block(LOG)  # the page: this short a block goes as z
    assert codec == "z" and len(zlib.compress(example, 9)) > len(payload)


def _d(stream: bytes, rawlen: int = 64) -> None:
    decode_block("d", zlib.compress(stream), rawlen)


@pytest.mark.parametrize(("stream", "rawlen", "reason"), [
    (bytes([0x80] * 11), 64, "a varint over 10 bytes"),
    (b"\x01\x01\x03\x00\x00\x00\x00\x00", 1, "column header out of range"),  # order 3
    (b"\x01\x01\x00\x13\x00\x00\x00\x00", 1, "column header out of range"),  # smax 19
    (b"\x01\x01\x00\x01\x02\x00\x00\x00", 1, "column header out of range"),  # dflt > smax
    (b"\x01\x01\x00\x00\x00\x09\x00\x00", 1, "column header out of range"),  # W 9
    (b"\x01\x01\x00\x00\x00\x00\x01\x01\x00", 1, "an exception past its column"),
    (b"\x01\x01\x00\x00\x00\x00\x01\x00\x05", 1, "an exception past its column or its scale"),
    (b"\x01\x01\x00\x00\x00\x00\x00" + b"\xff" * 9 + b"\x03", 20, "a value outside 64 bits"),
    (b"\x01\x01\x00\x00\x00\x00\x00\x02\x00", 1, "1 bytes after the last column"),
    (b"\x01\x01\x00\x00\x00\x00\x00\x02", 2, "1 bytes where the header says 2"),
    (b"\x01\x03\x00\x00\x00\x00\x00\x02", 1, "3 fields for 1 bytes"),
    (b"\x01", 64, "columns end inside a number"),
    (b"\x00", 64, "0 lines"),
])
def test_malformed_columns_are_refused(stream: bytes, rawlen: int, reason: str) -> None:
    with pytest.raises(BlockError, match=re.escape(reason)):
        _d(stream, rawlen)


def test_a_value_just_inside_64_bits_decodes() -> None:
    big = (1 << 63) - 1  # zigzag 2^64 - 2: ten varint bytes
    first = bytearray()
    z = 2 * big
    while z >= 0x80:
        first.append(z & 0x7F | 0x80)
        z >>= 7
    first.append(z)
    stream = b"\x01\x01\x00\x00\x00\x00\x00" + bytes(first)
    assert decode_block("d", zlib.compress(stream), 19) == str(big).encode()


@pytest.mark.parametrize(("codec", "payload", "rawlen", "reason"), [
    ("z", zlib.compress(bytes(1 << 20)), 65536, "inflates beyond 65536 bytes"),
    ("d", zlib.compress(bytes(1 << 20)), 1000, "inflates beyond 6096 bytes"),
    ("z", zlib.compress(b"abc")[:-3], 3, "zlib stream ends early"),
    ("z", zlib.compress(b"abc") + b"x", 3, "bytes after the zlib stream"),
    ("z", b"\x78\xda\xff\xff", 3, "damaged zlib stream"),
    ("z", zlib.compress(b"abcd"), 3, "inflates beyond 3 bytes"),
    ("z", zlib.compress(b"ab"), 3, "2 bytes where the header says 3"),
    ("x", zlib.compress(b"abc"), 3, "unknown codec 'x'"),
])
def test_malformed_payloads_are_refused(codec: str, payload: bytes, rawlen: int,
                                        reason: str) -> None:
    with pytest.raises(BlockError, match=re.escape(reason)):
        decode_block(codec, payload, rawlen)
