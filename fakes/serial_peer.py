"""The controller end of the serial line protocol (``docs/serial_line_protocol.md``, written
from that page) on the master side of a pseudo-terminal pair; the daemon opens the slave
through a stable symlink ``<workdir>/tty`` (a pulled cable comes back as a new pty behind the
same name).

Own faults: ``flip_bytes`` (a bit flipped in ``flip_rate`` of the frames either way: CRCs
catch them, frames are resent), ``cable_pulled`` (mid-log the line is gone for ``pull_s`` and
returns as a new device: the driver reopens it and resumes), ``device_gone`` (the device
vanishes for good after GO), ``corrupt_block`` (a log block damaged on the line
``corrupt_times`` times). ``pace_baud`` paces both directions at 10 bits per byte, since a
pty ignores the baud rate. Logs go down in compressed blocks (``zlog1``, ``serial_zlog``; the
next block is compressed while one is on the line); ``zlog=False`` plays an older controller
that knows neither CAPS nor ZGET.
"""

from __future__ import annotations

import base64
import binascii
import concurrent.futures
import hashlib
import logging
import os
import queue
import random
import select
import threading
import time
import tty
import zlib
from pathlib import Path
from typing import Any

from robid_link.fakes.controller import ControllerCore, Peer, RunResult
from robid_link.fakes.serial_zlog import MAX_BLOCK, block_length, encode_block

__all__ = ["SerialPeer", "frame", "frame_fields"]

log = logging.getLogger("robid.fake_controller")
PROGRAM_FILES = ("traj.csv", "traj.yaml")
#: the longest line either side accepts (page: "Frames")
MAX_LINE = 24_000
#: the capabilities this controller speaks (page: "Negotiation")
CAPABILITIES = ("zlog1",)
#: a compressed block: bytes covered, their CRC-32, codec, payload
Block = tuple[int, int, str, bytes]


def frame(*fields: object) -> bytes:
    """One frame (page: "Frames"): ASCII fields joined by single spaces, ``*``, the CRC-32
    (IEEE 802.3) of everything before the ``*`` as 8 upper-case hex digits, ``\n``."""
    body = " ".join(str(f) for f in fields).encode("ascii", "replace")  # free text: ASCII
    return body + b"*" + f"{zlib.crc32(body):08X}".encode() + b"\n"


def frame_fields(line: bytes) -> list[str] | None:
    """The fields of a received line; None when it is no frame or its CRC does not match
    (upper-case hex exactly: a flipped case bit is damage too)."""
    body, star, crc = line.rstrip(b"\n").rpartition(b"*")
    if not star or crc != f"{zlib.crc32(body):08X}".encode():
        return None
    try:
        return body.decode("ascii").split(" ")
    except UnicodeDecodeError:
        return None


class _Pacer:
    """Holds a byte stream to ``baud`` bits per second (10 bits per byte: start, 8, stop)."""

    def __init__(self, baud: int) -> None:
        self.baud, self.free_at = baud, 0.0

    def take(self, n: int) -> None:
        if self.baud <= 0:
            return
        now = time.monotonic()
        self.free_at = max(self.free_at, now) + 10 * n / self.baud
        if self.free_at > now:
            time.sleep(self.free_at - now)


class SerialPeer(Peer):
    """A serial controller on a pty: ``start`` serves in a thread (plus a worker thread that
    runs programs), ``stop`` joins both and closes the pty."""

    driver = "serial_line"
    #: beyond the core's: a noisy line, a pulled cable, a device gone for good; hostile ones:
    #: ``endless_log`` (DONE announces 2^40 bytes and GET answers forever), ``done_flood``
    #: (100 000 unsolicited DONE frames while a program runs), ``stalled_put`` (PUT is never
    #: acknowledged past 0), ``silent_run`` (no STAT answered while the program runs until an
    #: ABORT), ``zip_bomb`` (every log block inflates to a thousand times its size). Every
    #: ABORT is kept in ``aborts`` (its wall-clock time).
    faults = ("flip_bytes", "cable_pulled", "device_gone", "corrupt_block", "endless_log",
              "done_flood", "stalled_put", "silent_run", "zip_bomb")

    def __init__(self, core: ControllerCore, workdir: Path, *, baudrate: int = 921600,
                 pace_baud: int = 0, flip_rate: float = 0.05, pull_s: float = 1.0,
                 seed: int = 0, zlog: bool = True, corrupt_times: int = 2) -> None:
        super().__init__(core, workdir)
        self.link = Path(workdir) / "tty"
        self.baudrate, self.flip_rate, self.pull_s = baudrate, flip_rate, pull_s
        self.zlog, self._corrupt_left = zlog, corrupt_times
        self._corrupt_at: int | None = None
        self._blocks: dict[tuple[str, str, int, int], concurrent.futures.Future[Block]] = {}
        self._pool: concurrent.futures.ThreadPoolExecutor | None = None
        self.blocks_sent = 0
        self.blocks_asked: list[int] = []  # the offset of every ZGET, in order
        self._tx, self._rx = _Pacer(pace_baud), _Pacer(pace_baud)
        self._rng = random.Random(seed)
        self._fd_lock, self._write_lock = threading.Lock(), threading.Lock()
        self._master = self._slave = -1
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._jobs: queue.Queue[tuple[str, str] | None] = queue.Queue()
        self._files: dict[tuple[str, str], tuple[int, str, bytearray]] = {}
        self._state: dict[tuple[str, str], str] = {}  # BUSY / DONE / ERR
        self._results: dict[tuple[str, str], RunResult] = {}  # logs not cleared yet
        self._done: dict[tuple[str, str], tuple[int, str]] = {}  # length, SHA-256
        self._errors: dict[tuple[str, str], tuple[int, str]] = {}
        self._programs: dict[str, dict[str, bytes]] = {}
        self._pulled = False
        self.frames_in = self.frames_bad = 0
        self.aborts: list[float] = []
        self._silent: tuple[str, str] | None = None  # silent_run: the program nobody hears
        #: nonce → time.perf_counter() when its DONE was first sent (benchmarks)
        self.answer_times: dict[str, float] = {}

    def driver_options(self) -> dict[str, Any]:
        return {"name": "serial_line", "port": str(self.link), "baudrate": self.baudrate}

    # -- the pty
    def _plug(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)
        tmp = self.link.with_name(f".{self.link.name}.tmp")
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(os.ttyname(slave))
        os.replace(tmp, self.link)
        with self._fd_lock:
            self._master, self._slave = master, slave

    def _unplug(self) -> None:
        self.link.unlink(missing_ok=True)
        with self._fd_lock:
            for fd in (self._master, self._slave):
                if fd >= 0:
                    os.close(fd)
            self._master = self._slave = -1

    def start(self) -> None:
        if self._threads:
            return
        self._plug()
        self._pool = concurrent.futures.ThreadPoolExecutor(1, "fake-serial-zlog")
        for target, name in ((self._serve, "fake-serial"), (self._work, "fake-serial-job")):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)

    def stop(self) -> None:
        self._stop.set()
        self._jobs.put(None)
        for t in self._threads:
            t.join(30)
        self._threads.clear()
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        self._unplug()

    # -- bytes
    def _write(self, *fields: object) -> None:
        self._send(frame(*fields))

    def _send(self, data: bytes) -> None:
        """One frame onto the line (damaged at random under ``flip_bytes``)."""
        out = bytearray(data)
        if self.core.fault == "flip_bytes" and self._rng.random() < self.flip_rate:
            out[self._rng.randrange(len(out) - 1)] ^= 1 << self._rng.randrange(7)
        with self._write_lock:
            self._tx.take(len(out))
            view = memoryview(out)
            while view:
                with self._fd_lock:
                    fd = self._master
                if fd < 0:
                    return  # the cable is out: the frame is lost
                try:
                    view = view[os.write(fd, view):]
                except OSError:
                    return

    def _serve(self) -> None:
        buf = bytearray()
        while not self._stop.is_set():
            with self._fd_lock:
                fd = self._master
            if fd < 0:
                time.sleep(0.02)
                continue
            try:
                ready, _, _ = select.select([fd], [], [], 0.05)
                data = os.read(fd, 65536) if ready else b""
            except OSError:
                time.sleep(0.02)
                continue
            self._rx.take(len(data))
            buf += data
            while (k := buf.find(b"\n")) >= 0:
                line, buf = bytearray(buf[: k + 1]), buf[k + 1:]
                if self.core.fault == "flip_bytes" and self._rng.random() < self.flip_rate:
                    line[self._rng.randrange(len(line) - 1)] ^= 1 << self._rng.randrange(7)
                self._handle(bytes(line))
            if len(buf) > MAX_LINE:
                buf.clear()

    # -- frames
    def _handle(self, line: bytes) -> None:
        self.frames_in += 1
        f = frame_fields(line)
        if f is None:
            self.frames_bad += 1
            self._write("NAK")
            return
        handler = getattr(self, f"_on_{f[0].lower()}", None)
        try:
            if handler is None:
                raise ValueError(f[0])
            handler(*f[1:])
        except (TypeError, ValueError, binascii.Error):
            self._write("NAK")

    def _on_ping(self, n: str) -> None:
        self._write("PONG", n)

    def _on_prog(self, exp_id: str, name: str, size: str, sha: str) -> None:
        self._files[(exp_id, name)] = (int(size), sha, bytearray())
        self._write("OK", "PROG", exp_id, name)

    def _on_put(self, exp_id: str, name: str, offset: str, b64: str) -> None:
        if self.core.fault == "stalled_put":
            self._write("ACK", "PUT", exp_id, name, 0)
            return
        size, sha, buf = self._files[(exp_id, name)]
        if int(offset) == len(buf) and len(buf) < size:
            buf += base64.b64decode(b64, validate=True)
            if len(buf) >= size and hashlib.sha256(buf).hexdigest() != sha:
                buf.clear()  # whole file wrong after all: ask for it again from 0
            elif len(buf) == size:
                self._programs.setdefault(exp_id, {})[name] = bytes(buf)
        self._write("ACK", "PUT", exp_id, name, len(buf))

    def _on_go(self, exp_id: str, nonce: str) -> None:
        key = (exp_id, nonce)
        if key in self._state:  # given again after a restart: never a second run
            self._write("OK", "GO", exp_id, nonce)
            return
        files = self._programs.get(exp_id, {})
        if any(n not in files for n in PROGRAM_FILES):
            self._write("ERR", exp_id, nonce, 1, "program incomplete")
            return
        self._state[key] = "BUSY"
        self._write("OK", "GO", exp_id, nonce)
        if self.core.fault == "device_gone" and self.core.take_fault():
            log.info("serial device gone for good")
            self._unplug()
            self.died.set()
            return
        self._jobs.put(key)

    def _on_stat(self, exp_id: str, nonce: str) -> None:
        key = (exp_id, nonce)
        if key == self._silent:
            return
        state = self._state.get(key, "IDLE")
        if state in ("DONE", "ERR"):
            self._answer(key)
        else:
            self._write(state, exp_id, nonce)

    def _on_get(self, exp_id: str, nonce: str, offset: str, size: str) -> None:
        res, off = self._results.get((exp_id, nonce)), int(offset)
        if res is None:
            self._write("ERR", exp_id, nonce, 9, "no log")
            return
        if self._cable_pulled_at(off):
            return
        chunk = res.delivered[off: off + min(int(size), 16384)]
        if res.fault == "endless_log":  # a logger that never stops writing
            chunk = (b"0.001,0.1,0.2,0.3,1.5,2.5,3.5\n" * 600)[: min(int(size), 16384)]
        if chunk:
            self._write("DATA", exp_id, nonce, off, base64.b64encode(chunk).decode())
        else:
            self._write("EOF", exp_id, nonce, off)

    def _cable_pulled_at(self, off: int) -> bool:
        """``cable_pulled``: mid-log the line is gone for a while, then a new device."""
        if off > 0 and self.core.fault == "cable_pulled" and not self._pulled:
            self._pulled = True
            log.info("serial cable pulled at offset %d for %g s", off, self.pull_s)
            self._unplug()
            time.sleep(self.pull_s)
            self._plug()
            return True
        return False

    def _on_caps(self, *names: str) -> None:
        if not self.zlog:
            raise ValueError("CAPS")  # an older controller: an unknown frame
        self._write("CAPS", *[n for n in names if n in CAPABILITIES])

    def _on_zget(self, exp_id: str, nonce: str, offset: str, size: str) -> None:
        off, most = int(offset), int(size)
        if not self.zlog or off < 0 or not 1 <= most <= MAX_BLOCK:
            raise ValueError("ZGET")
        self.blocks_asked.append(off)
        res = self._results.get((exp_id, nonce))
        if res is None:
            self._write("ERR", exp_id, nonce, 9, "no log")
            return
        if self._cable_pulled_at(off):
            return
        data = res.delivered
        if res.fault == "endless_log":  # a logger that never stops writing
            endless = b"0.001,0.1,0.2,0.3,1.5,2.5,3.5\n" * (most // 30 + 1)
            rawlen, rawcrc, codec, payload = _compress(endless, 0, most)
        elif off >= len(data):
            self._write("EOF", exp_id, nonce, off)
            return
        else:
            rawlen, rawcrc, codec, payload = self._block(exp_id, nonce, data, off, most)
        zcrc = f"{zlib.crc32(payload):08X}"
        if self.core.fault == "zip_bomb":  # a thousand times the block's size of zeros
            codec, payload = "z", zlib.compress(bytes(1000 * most), 9)[: most + 1024]
            zcrc = f"{zlib.crc32(payload):08X}"
        elif self.core.fault == "corrupt_block" and off > 0 and self._corrupt_left > 0 \
                and self._corrupt_at in (None, off):
            self._corrupt_at, self._corrupt_left = off, self._corrupt_left - 1
            payload = bytes([payload[0] ^ 0x10]) + payload[1:]  # damaged after its CRC
        if res.fault != "endless_log" and off + rawlen < len(data):  # the next one meanwhile
            self._prefetch(exp_id, nonce, data, off + rawlen, most)
        self.blocks_sent += 1
        self._send(frame("ZBLK", exp_id, nonce, offset, rawlen, f"{rawcrc:08X}", codec,
                         len(payload), zcrc) + payload)

    def _block(self, exp_id: str, nonce: str, data: bytes, off: int, most: int) -> Block:
        future = self._blocks.pop((exp_id, nonce, off, most), None)
        return _compress(data, off, most) if future is None else future.result()

    def _prefetch(self, exp_id: str, nonce: str, data: bytes, off: int, most: int) -> None:
        key = (exp_id, nonce, off, most)
        if key in self._blocks or self._pool is None:
            return
        while len(self._blocks) >= 4:  # the daemon asked elsewhere: forget the oldest
            self._blocks.pop(next(iter(self._blocks))).cancel()
        self._blocks[key] = self._pool.submit(_compress, data, off, most)

    def _on_clear(self, exp_id: str, nonce: str) -> None:
        self._results.pop((exp_id, nonce), None)
        self._write("OK", "CLEAR", exp_id, nonce)

    def _on_abort(self, exp_id: str, nonce: str) -> None:
        self.aborts.append(time.time())
        if self._silent == (exp_id, nonce):
            self._silent = None
        if self._state.get((exp_id, nonce)) == "BUSY":
            self._state[(exp_id, nonce)] = "ABORTED"
        self._write("OK", "ABORT", exp_id, nonce)

    def _answer(self, key: tuple[str, str]) -> None:
        if self._state.get(key) == "ERR":
            code, text = self._errors[key]
            self._write("ERR", *key, code, text)
        elif key in self._done:  # also after CLEAR: STAT always has an answer
            self.answer_times.setdefault(key[1], time.perf_counter())
            size, sha = self._done[key]
            if key in self._results and self._results[key].fault == "endless_log":
                size = 1 << 40
            self._write("DONE", *key, size, sha)

    def offer_log(self, exp_id: str, nonce: str, data: bytes) -> None:
        """A finished program's log, as if it had run (benchmarks of the log transfer)."""
        self._state[(exp_id, nonce)] = "DONE"
        self._results[(exp_id, nonce)] = res = RunResult(exp_id, nonce, None, data, data)
        self._done[(exp_id, nonce)] = (len(res.log), res.sha256)

    # -- the worker
    def _work(self) -> None:
        while (key := self._jobs.get()) is not None:
            files = self._programs[key[0]]
            res = self.core.run(*key, files["traj.csv"], files["traj.yaml"])
            if res.fault == "done_flood":
                for k in range(100_000):  # answers to attempts nobody gave
                    self._write("DONE", f"x{k}", f"n{k}", 1, "0" * 64)
            if res.fault == "silent_run":
                self._silent = key
                while self._silent == key and not self._stop.wait(0.05):
                    pass
                continue
            if self._state.get(key) == "ABORTED" or res.fault == "never_answer":
                continue
            if res.fault == "die":
                self.core.die()
                self._unplug()
                self.died.set()
                return
            if res.error is not None:
                self._errors[key] = (2 if res.fault == "fail" else 1,
                                     res.error.replace("\n", " "))
                self._state[key] = "ERR"
                self._answer(key)
                continue
            self._results[key] = res
            self._done[key] = (len(res.log), res.sha256)
            if res.fault == "stale_semaphore":  # an older attempt's answer shows first
                self._write("DONE", key[0], "0stale0", 1, "0" * 64)
                time.sleep(0.2)
            self._state[key] = "DONE"
            self._answer(key)
            if res.fault == "answer_twice":
                time.sleep(0.05)
                self._answer(key)


def _compress(data: bytes, off: int, most: int) -> Block:
    """The block of ``data`` at ``off`` of at most ``most`` bytes, compressed."""
    raw = data[off: off + block_length(data, off, most)]
    codec, payload = encode_block(raw)
    return len(raw), zlib.crc32(raw), codec, payload
