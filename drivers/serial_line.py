"""Small controllers on a serial line: the line protocol of ``docs/serial_line_protocol.md``
(CRC-checked text frames; programs up in chunks with ack and retransmit; logs down in
compressed, CRC-checked blocks when the controller offers ``zlog1``, in chunks otherwise).

The blocking pyserial port is read by one thread that hands whole frames to the event loop
(``call_soon_threadsafe``); writes go through ``asyncio.to_thread``. A port that vanishes
(USB adapter pulled, pty closed) is reopened within ``reopen_s``; a log fetch resumes from its
last good offset. Nothing a controller sends grows without bound: answers are kept only for
attempts this driver gave (a flood of unsolicited DONE frames is counted, not kept), a log
fetch stops at its announced size (and ``max_log_bytes``), a block inflates to its stated size
at most (``serial_zlog``), and a controller that answers no STAT twice in a row while a motion
runs fails the attempt.
"""

from __future__ import annotations

import asyncio
import base64
import binascii
import collections
import contextlib
import logging
import re
import threading
import time
import zlib
from collections.abc import Callable
from typing import Any

import serial  # type: ignore[import-untyped]

from robid_link.drivers.serial_frames import (
    ERROR_CODES,
    MAX_LINE,
    Pending,
    Splitter,
    block_at,
    chunk_at,
    decode_frame,
    encode_frame,
    number,
    starts,
)
from robid_link.drivers.serial_zlog import BlockError, block_length, decode_answer
from robid_link.exceptions import DriverError
from robid_link.jobs import MotionProgram
from robid_link.link.driver import Done, Driver
from robid_link.link.options import Flag, Integer, Number, Options, Text
from robid_link.link.retry import Backoff

__all__ = ["SerialLineDriver", "encode_frame", "decode_frame", "ERROR_CODES", "MAX_LINE"]

log = logging.getLogger("robid.driver.serial_line")

#: waits between attempts to reopen a vanished port (within ``reopen_s``)
REOPEN_BACKOFF = Backoff(0.05, 0.5)
#: the attempts whose answers are kept (given by this driver, newest last) and the answers
#: already taken that are remembered as such
MAX_KEPT = 64
#: STAT requests in a row without a valid answer while waiting: the controller is gone
MAX_SILENT_STATS = 2
#: the capabilities this driver speaks (``CAPS``), and how many NAKs to them mean an old
#: controller that speaks none
CAPABILITIES = ("zlog1",)
CAPS_NAKS = 3
#: the largest block a ZGET may ask for, and how much longer than it its payload may be
MAX_BLOCK = 1 << 20
MAX_PAYLOAD_OVER = 1024


class _Renegotiate(Exception):
    """A block request met a reopened port: ask CAPS again before the next ZGET."""


class _BlockLost(Exception):
    """No intact answer to a ZGET after ``retries`` + 1 tries (the reason as its text)."""


class SerialLineDriver(Driver):
    """Daemon side of the serial line protocol.

    Options: ``port`` (device path), ``baudrate`` (115200), ``chunk_bytes`` (2048: payload per
    data frame), ``io_timeout_s`` (1: per frame, on top of its transmission time at the baud
    rate), ``retries`` (8 per frame, and per log block), ``reopen_s`` (5: how long a vanished
    port is retried), ``stat_period_s`` (0.5: status polls while waiting for 'done'),
    ``compress`` (true: logs in compressed blocks when the controller offers ``zlog1``),
    ``block_bytes`` (65536: the log bytes one block covers at most).
    """

    name = "serial_line"
    options = Options(
        port=Text(hint="the serial device, e.g. /dev/ttyUSB0"),
        baudrate=Integer(115200, low=50, high=10_000_000),
        chunk_bytes=Integer(2048, low=16, high=16384), io_timeout_s=Number(1.0, above=0),
        retries=Integer(8, low=0, high=100), reopen_s=Number(5.0, above=0),
        stat_period_s=Number(0.5, above=0), compress=Flag(True),
        block_bytes=Integer(65536, low=16, high=MAX_BLOCK))

    def __init__(self, **options: Any) -> None:
        super().__init__(**options)
        o = self.config
        self.port, self.baudrate, self.chunk = o.port, o.baudrate, o.chunk_bytes
        self.io_timeout_s, self.retries = o.io_timeout_s, o.retries
        self.reopen_s, self.stat_period_s = o.reopen_s, o.stat_period_s
        self.block_bytes = o.block_bytes
        #: whether logs come in zlog1 blocks: None until the controller was asked (at open and
        #: after every reopened port)
        self.zlog: bool | None = None if o.compress else False
        self._serial: Any = None
        self._reader: threading.Thread | None = None
        self._stop_reader = threading.Event()
        self._up = asyncio.Event()
        self._lost = asyncio.Event()
        self._lost_reason = ""
        self._fault: DriverError | None = None
        self._lock = asyncio.Lock()
        self._pending: Pending | None = None
        self._answers: dict[tuple[str, str], list[str]] = {}
        self._waiting: set[tuple[str, str]] = set()
        # bounded memories: the attempts given (answers kept only for these), the taken ones
        self._given: collections.deque[tuple[str, str]] = collections.deque(maxlen=MAX_KEPT)
        self._taken: collections.deque[tuple[str, str]] = collections.deque(maxlen=MAX_KEPT)
        self.unsolicited = 0  # answers to attempts this driver did not give (dropped)
        self._tick = asyncio.Event()
        self._partial: dict[tuple[str, str], bytearray] = {}
        self._tasks: list[asyncio.Task[None]] = []
        self.bad_frames = 0
        self.bad_blocks = 0  # blocks asked again: damaged on the line or not decoding
        self._why = ""  # why the last request went unanswered
        self._rx_at = 0.0  # time.monotonic() of the last bytes read (the loop's clock)
        self.reopened = 0

    # -- the port and its reader thread
    async def _open(self) -> None:
        await self._open_port()
        self._tasks.append(asyncio.create_task(self._link_loop(), name="serial_line-link"))
        await self._request(["PING", "0"], lambda f: f[:2] == ["PONG", "0"], what="PING")
        self.zlog = None if self.config.compress else False  # this controller's, asked now
        await self._negotiate()

    async def _negotiate(self) -> None:
        """CAPS: which capabilities the controller speaks. An old one answers NAK (as to any
        unknown frame): after ``CAPS_NAKS`` of them, or ``retries`` + 1 tries, plain GET."""
        if self.zlog is False:
            return
        got, naks = ["CAPS"], 0
        for _ in range(self.retries + 1):
            try:
                got = await self._request(["CAPS", *CAPABILITIES], lambda f: f[0] == "CAPS",
                                          what="CAPS", tries=1)
                break
            except DriverError:
                if self._fault is not None:
                    raise
                naks += self._why == "NAK"
                if naks >= CAPS_NAKS:
                    break
        self.zlog = "zlog1" in got[1:]
        log.info("serial port %s: %s", self.port, "logs in compressed blocks (zlog1)"
                 if self.zlog else "the controller offers no compressed logs; plain GET")

    async def _open_port(self) -> None:
        try:
            self._serial = await asyncio.to_thread(
                serial.Serial, self.port, self.baudrate, timeout=0.05, write_timeout=30)
        except (serial.SerialException, OSError, ValueError) as err:
            raise DriverError(f"serial port {self.port}: cannot open ({_reason(err)})") from err
        self._stop_reader.clear()
        self._reader = threading.Thread(target=self._read_thread, args=(self._serial,),
                                        name=f"serial-reader-{self.port}", daemon=True)
        self._reader.start()
        self._up.set()

    def _read_thread(self, port: Any) -> None:
        """Blocking reads, split into frames (and a ZBLK header's payload), each handed to the
        loop through the bridge (it waits for room when the loop is behind); a dead port is
        reported."""
        split = Splitter(self.block_bytes + MAX_PAYLOAD_OVER)
        try:
            while not self._stop_reader.is_set():
                data = port.read(max(1, min(port.in_waiting, 65536)))
                if not data:
                    if split.waiting and time.monotonic() - self._rx_at > self.io_timeout_s:
                        split.cut()  # a payload cut short: a damaged frame
                        self.bridge.call(self._on_line, b"")
                    continue
                self._rx_at = time.monotonic()
                for line, payload in split.feed(data):
                    self.bridge.call(self._on_line, line, payload)
        except (serial.SerialException, OSError, TypeError) as err:
            if not self._stop_reader.is_set():
                self.bridge.call(self._on_lost, _reason(err))

    async def _close_port(self) -> None:
        self._up.clear()
        self._stop_reader.set()
        if self._reader is not None:
            await asyncio.to_thread(self._reader.join, 5)
            self._reader = None
        if self._serial is not None:
            port, self._serial = self._serial, None
            with contextlib.suppress(serial.SerialException, OSError):
                await asyncio.to_thread(port.close)

    def _on_lost(self, reason: str) -> None:
        log.warning("serial port %s lost (%s); reopening", self.port, reason)
        self._up.clear()
        self._lost_reason = reason
        if self.config.compress:
            self.zlog = None  # ask again: another controller may answer behind the port
        if self._pending is not None:  # its answer is lost: ask again once the port is back
            self._pending.why = "line dropped"
            self._pending.resend.set()
        self._lost.set()
        self._tick.set()

    async def _link_loop(self) -> None:
        """Reopen a vanished port with growing, jittered delays for at most ``reopen_s``."""
        while True:
            await self._lost.wait()
            self._lost.clear()
            reason = self._lost_reason
            await self._close_port()
            loop = asyncio.get_running_loop()
            end, tries = loop.time() + self.reopen_s, 0
            while not self._up.is_set():
                try:
                    await self._open_port()
                    self.reopened += 1
                    self._fault = None
                    log.info("serial port %s reopened", self.port)
                except DriverError as err:
                    reason = str(err).rsplit("(", 1)[-1].rstrip(")")
                    if loop.time() >= end:
                        self._fault = DriverError(
                            f"serial device {self.port} gone: not back within "
                            f"{self.reopen_s:g} s ({reason})")
                        self._tick.set()
                        if self._pending and not self._pending.future.done():
                            self._pending.future.set_exception(self._fault)
                        await asyncio.sleep(1.0)  # keep trying, slowly: a cable comes back
                        continue
                    tries += 1
                    await REOPEN_BACKOFF.sleep(tries)

    async def _close(self) -> None:
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        self._tasks.clear()
        await self._close_port()

    # -- frames
    def _on_line(self, line: bytes, payload: bytes | None = None) -> None:
        fields = decode_frame(line)
        if fields is None:
            self.bad_frames += 1
            if self._pending is not None:
                self._pending.why = "damaged answer"
                if self._pending.quiet:
                    self._pending.damaged = True  # resent once the line is quiet
                else:
                    self._pending.resend.set()
            return
        if payload is not None and f"{zlib.crc32(payload):08X}" != fields[8]:
            self.bad_frames += 1
            self.bad_blocks += 1
            if self._pending is not None:
                self._pending.why = "payload CRC"
                self._pending.resend.set()
            return
        kind = fields[0]
        if kind == "NAK":
            if self._pending is not None:
                self._pending.why = "NAK"
                self._pending.resend.set()
            return
        reply = self._pending is not None and not self._pending.future.done() and \
            self._pending.match(fields)
        if kind in ("DONE", "ERR") and len(fields) >= 3:
            self._on_answer(fields, quiet=reply)  # a STAT's reply repeats a pushed answer
        if reply:
            self._pending.payload = payload or b""  # type: ignore[union-attr]
            self._pending.future.set_result(fields)  # type: ignore[union-attr]

    def _on_answer(self, fields: list[str], quiet: bool = False) -> None:
        key = (fields[1], fields[2])
        if key in self._taken and (quiet or self._answers.get(key) == fields):
            log.debug("serial %s repeated answer %s %s %s", self.port, *fields[:3])
        elif key in self._taken:
            log.warning("serial %s duplicate answer %s %s %s (already taken; ignored)",
                        self.port, *fields[:3])
        elif key not in self._waiting and any(k[0] == key[0] for k in self._waiting):
            log.warning("serial %s stale answer %s %s %s (another nonce; ignored)",
                        self.port, *fields[:3])
        elif key not in self._waiting and key not in self._given:
            self.unsolicited += 1  # never kept: a controller cannot fill the memory
            if self.unsolicited in (1, 10) or self.unsolicited % 10_000 == 0:
                log.warning("serial %s %d answer(s) to attempts this daemon did not give "
                            "(latest %s %s %s; dropped)", self.port, self.unsolicited,
                            *fields[:3])
        else:
            self._answers[key] = fields
        self._tick.set()
        self._tick = asyncio.Event()

    async def _send(self, line: bytes) -> None:
        if not self._up.is_set():
            try:
                async with asyncio.timeout(self.reopen_s + 1):
                    await self._up.wait()
            except TimeoutError:
                pass
        if self._fault is not None:
            raise self._fault
        port = self._serial
        try:
            await asyncio.to_thread(port.write, line)
        except (serial.SerialException, OSError, AttributeError, TypeError) as err:
            # a port closed under the write (a pulled cable's reopen): pyserial's abort pipe is
            # gone mid-call and its select() raises TypeError — the line dropped, as the reader
            # takes it
            self._on_lost(_reason(err))

    async def _request(self, fields: list[object], match: Callable[[list[str]], bool],
                       what: str, reply_bytes: int = 64, tries: int | None = None) -> list[str]:
        """Send one frame and wait for the answer ``match`` accepts, resending on a NAK, a
        damaged answer or silence, at most ``retries`` times (``tries`` in all, if given)."""
        pending = await self._exchange(fields, match, what, reply_bytes, tries)
        return pending.future.result()

    async def _exchange(self, fields: list[object], match: Callable[[list[str]], bool],
                        what: str, reply_bytes: int = 64, tries: int | None = None,
                        block: bool = False) -> Pending:
        """``_request``, giving the answered request (``block``: a ZGET, whose answer's
        payload is in ``payload``)."""
        line = encode_frame(*fields)
        wire_s = 10 * (len(line) + reply_bytes) / self.baudrate
        tries = self.retries + 1 if tries is None else tries
        why = "no answer"
        async with self._lock:
            for _ in range(tries):
                if block and self.zlog is None:
                    raise _Renegotiate
                self._pending = pending = Pending(match, quiet=block)
                try:
                    await self._send(line)
                    if await self._reply(pending, self.io_timeout_s + wire_s):
                        return pending
                    why = pending.why
                finally:
                    self._pending = None
            if self._fault is not None:
                raise self._fault
            self._why = why
            raise DriverError(f"serial port {self.port}: no valid answer to {what} after "
                              f"{tries} tries ({why}: line noise or no controller)")

    async def _reply(self, pending: Pending, timeout_s: float) -> bool:
        """True once the answer came, False on a NAK, a damaged frame or silence. Bytes still
        arriving (earlier answers queued on a slow line) are not silence: resending then would
        only lengthen the queue."""
        loop = asyncio.get_running_loop()
        deadline, limit = loop.time() + timeout_s, loop.time() + timeout_s * (self.retries + 1)
        resend: asyncio.Future[Any] = asyncio.ensure_future(pending.resend.wait())
        either: set[asyncio.Future[Any]] = {pending.future, resend}
        quiet_s = max(0.05, 200 / self.baudrate)  # 20 characters
        try:
            while True:
                left = deadline - loop.time()
                if pending.damaged:  # after a damaged ZBLK header: once the line is quiet
                    if loop.time() - self._rx_at >= quiet_s:
                        return False
                    left = min(left, quiet_s)
                if left > 0:
                    done, _ = await asyncio.wait(either, timeout=left,
                                                 return_when=asyncio.FIRST_COMPLETED)
                    if done:
                        return pending.future.done()
                    if pending.damaged:
                        continue
                busy = loop.time() - self._rx_at < min(self.io_timeout_s, 0.2)
                if not busy or loop.time() >= limit:
                    return False
                deadline = loop.time() + 0.05
        finally:
            resend.cancel()

    # -- the cycle
    async def _put_program(self, program: MotionProgram) -> None:
        for name in sorted(program.files):
            data = program.files[name]
            sha = _sha256(data)
            pid = program.exp_id
            await self._request(["PROG", pid, name, len(data), sha],
                                starts("OK", "PROG", pid, name), what=f"PROG {name}")
            offset, stalls = 0, 0
            while offset < len(data):
                chunk = data[offset: offset + self.chunk]
                got = await self._request(
                    ["PUT", pid, name, offset, base64.b64encode(chunk).decode()],
                    starts("ACK", "PUT", pid, name, size=5), what=f"PUT {name} at {offset}")
                acked = number(got[4], f"PUT {name}")
                if acked > len(data):
                    raise DriverError(f"serial port {self.port}: controller acknowledged "
                                      f"{acked} bytes of {name}, {len(data)} were sent")
                stalls = stalls + 1 if acked <= offset else 0
                if stalls > self.retries:
                    raise DriverError(f"serial port {self.port}: {name} makes no progress "
                                      f"(the controller acknowledges {acked} of {len(data)} "
                                      f"bytes, {stalls} times in a row)")
                offset = acked

    async def _give_ready(self, exp_id: str, nonce: str) -> None:
        self._remember_given((exp_id, nonce))
        got = await self._request(["GO", exp_id, nonce],
                                  lambda f: f[:4] == ["OK", "GO", exp_id, nonce]
                                  or (f[0] == "ERR" and f[1:3] == [exp_id, nonce]), what="GO")
        if got[0] == "ERR":
            raise self._error(exp_id, got)

    def _remember_given(self, key: tuple[str, str]) -> None:
        if key not in self._given:
            if len(self._given) == self._given.maxlen:
                self._answers.pop(self._given[0], None)  # the oldest falls out with its answer
            self._given.append(key)

    async def _wait_done(self, exp_id: str, nonce: str) -> Done:
        key = (exp_id, nonce)
        self._waiting.add(key)
        silent = 0
        try:
            while True:
                fields = self._answers.get(key)
                if fields is not None:
                    self._taken.append(key)
                    if fields[0] == "ERR":
                        raise self._error(exp_id, fields)
                    if len(fields) != 5 or not _HEX64.fullmatch(fields[4].lower()):
                        raise DriverError(f"serial port {self.port}: malformed DONE frame")
                    return Done(exp_id, nonce, fields[4].lower(), number(fields[3], "DONE"))
                if self._fault is not None:
                    raise self._fault
                tick = self._tick
                try:
                    await self._request(["STAT", exp_id, nonce],
                                        lambda f: f[0] in ("BUSY", "IDLE", "DONE", "ERR")
                                        and f[1:3] == [exp_id, nonce], what="STAT")
                    silent = 0
                except DriverError:  # a lost STAT: the next one asks again, once
                    silent += 1
                    if silent >= MAX_SILENT_STATS:
                        raise DriverError(f"serial port {self.port}: controller silent while "
                                          f"experiment {exp_id} runs: no answer to "
                                          f"{silent} STAT requests in a row") from None
                if key not in self._answers:
                    with contextlib.suppress(TimeoutError):
                        async with asyncio.timeout(self.stat_period_s):
                            await tick.wait()
        finally:
            self._waiting.discard(key)
            if key not in self._given:  # an attempt of an earlier daemon: nothing kept
                self._answers.pop(key, None)

    def _error(self, exp_id: str, fields: list[str]) -> DriverError:
        code = number(fields[3], "ERR") if len(fields) > 3 else 0
        text = " ".join(fields[4:])
        return DriverError(f"controller on {self.port} reports experiment {exp_id} failed: "
                           f"error {code} ({ERROR_CODES.get(code, 'unknown error code')})"
                           + (f": {text}" if text else ""))

    async def _fetch_logs(self, done: Done) -> bytes:
        """The log from the end of what is held (kept across a reopened port and a failed
        fetch): in compressed blocks when the controller offers them, else in chunks."""
        key = (done.exp_id, done.nonce)
        data = self._partial.setdefault(key, bytearray())
        if self.zlog is None:
            await self._negotiate()
        if not (self.zlog and done.size is not None
                and await self._fetch_blocks(done, data, done.size)):
            await self._fetch_chunks(done, data)
        self._partial.pop(key, None)
        return bytes(data)

    async def _fetch_blocks(self, done: Done, data: bytearray, total: int) -> bool:
        """ZGET block after block, each decoded in a thread while the next one travels and
        appended only when it decodes to its bytes at the end of ``data``; a block that does
        not is asked again, ``retries`` times. False when the capability is gone after a
        reopened port (plain GET goes on from there)."""
        failures: dict[int, int] = {}
        ahead: tuple[int, int, asyncio.Task[bytes]] | None = None  # offset, length, decoding
        try:
            while True:
                off = len(data) if ahead is None else ahead[0] + ahead[1]
                try:
                    answer = (await self._ask_block(done, off, total) if off < total
                              else (["EOF"], b""))
                except _BlockLost as lost:  # what was decoded before it is kept
                    if ahead is not None:
                        with contextlib.suppress(BlockError):
                            data += await ahead[2]
                        ahead = None
                    why = str(lost).removeprefix(f"serial port {self.port}: ")  # said once
                    raise DriverError(f"{self._block_name(done, off)} not received intact "
                                      f"({why}); fetch stopped, {len(data)} bytes kept for "
                                      "a resume") from None
                if ahead is not None:
                    decoding, ahead = ahead[2], None
                    try:
                        data += await decoding
                    except BlockError as err:  # what came after it is dropped
                        self._block_failed(done, len(data), failures, err)
                        continue
                if answer is None or answer[0][0] == "EOF":
                    return answer is not None  # EOF: the base checks size and SHA-256
                size = min(self.block_bytes, total - off)
                try:
                    rawlen = block_length(answer[0], size)
                except BlockError as err:
                    self._block_failed(done, off, failures, err)
                    continue
                ahead = (off, rawlen, asyncio.create_task(asyncio.to_thread(
                    decode_answer, answer[0], answer[1], size)))
        finally:
            if ahead is not None:
                ahead[2].cancel()

    async def _ask_block(self, done: Done, off: int, total: int
                         ) -> tuple[list[str], bytes] | None:
        """The answer to ``ZGET`` at ``off`` (a ZBLK and its payload, whose CRC is checked, or
        EOF); None when the controller no longer speaks zlog1 (a reopened port)."""
        while True:
            if self.zlog is None:  # at open, or after a reopened port
                await self._negotiate()
            if not self.zlog:
                return None
            size = min(self.block_bytes, total - off)
            try:
                answer = await self._exchange(
                    ["ZGET", done.exp_id, done.nonce, off, size],
                    block_at(done.exp_id, done.nonce, off), what=f"ZGET at {off}",
                    reply_bytes=size + MAX_PAYLOAD_OVER, block=True)
            except _Renegotiate:
                continue
            except DriverError as err:
                if self._fault is not None:
                    raise
                raise _BlockLost(str(err)) from None
            got = answer.future.result()
            if got[0] == "ERR":
                raise self._error(done.exp_id, got)
            return got, answer.payload

    def _block_failed(self, done: Done, off: int, failures: dict[int, int],
                      err: BlockError) -> None:
        failures[off] = failures.get(off, 0) + 1
        self.bad_blocks += 1
        if failures[off] > self.retries:
            raise DriverError(f"{self._block_name(done, off)} not decoded after "
                              f"{failures[off]} tries ({err}); fetch stopped, {off} bytes "
                              "kept for a resume")
        log.warning("%s asked again: %s", self._block_name(done, off), err)

    def _block_name(self, done: Done, off: int) -> str:
        return (f"serial port {self.port}: log of experiment {done.exp_id} (nonce "
                f"{done.nonce}): block at offset {off}")

    async def _fetch_chunks(self, done: Done, data: bytearray) -> None:
        """GET chunk after chunk from the end of ``data``."""
        cap = self.config.max_log_bytes
        total, stalls = done.size, 0
        key = (done.exp_id, done.nonce)
        while total is None or len(data) < total:
            if len(data) > cap:  # no announced size to stop at: the cap does
                self._partial.pop(key, None)
                raise DriverError(f"serial port {self.port}: log of experiment {done.exp_id} "
                                  f"over driver.max_log_bytes ({cap}); fetch stopped")
            off = len(data)
            got = await self._request(
                ["GET", done.exp_id, done.nonce, off, self.chunk],
                chunk_at(done.exp_id, done.nonce, off), what=f"GET at {off}",
                reply_bytes=4 * self.chunk // 3 + 64)
            if got[0] == "ERR":
                raise self._error(done.exp_id, got)
            if got[0] == "EOF" or len(got) < 5:
                break  # the controller has no more: the base checks size and SHA-256
            try:
                chunk = base64.b64decode(got[4], validate=True)
            except binascii.Error as err:
                raise DriverError(f"serial port {self.port}: bad base64 in DATA at {off}"
                                  ) from err
            stalls = 0 if chunk else stalls + 1
            if stalls > self.retries:
                raise DriverError(f"serial port {self.port}: log of experiment "
                                  f"{done.exp_id} makes no progress (empty DATA at {off}, "
                                  f"{stalls} times in a row)")
            data += chunk

    async def _acknowledge(self, done: Done) -> None:
        await self._request(["CLEAR", done.exp_id, done.nonce],
                            lambda f: f[:4] == ["OK", "CLEAR", done.exp_id, done.nonce],
                            what="CLEAR")

    async def _withdraw(self, exp_id: str, nonce: str) -> None:
        self._partial.pop((exp_id, nonce), None)
        await self._request(["ABORT", exp_id, nonce],
                            lambda f: f[:4] == ["OK", "ABORT", exp_id, nonce], what="ABORT")


_HEX64 = re.compile(r"[0-9a-f]{64}")


def _sha256(data: bytes) -> str:
    import hashlib

    return hashlib.sha256(data).hexdigest()


def _reason(err: BaseException) -> str:
    return (str(err).splitlines() or [type(err).__name__])[0][:160] or type(err).__name__
