"""The serial-line transcripts (``tests/golden/serial_line/``, from
docs/serial_line_protocol.md) against both sides: every frame's CRC-32 computed here with
zlib over the documented bytes; the driver sends exactly the daemon's frames (recorded at a
recording fake controller, or — for the compressed transfers — to a scripted controller that
plays the transcript's bytes); the fake controller, fed the daemon's frames on its pty, answers
exactly the controller's (a compressed block: the same header but for the payload's length and
CRC, and a payload that inflates to the same bytes — zlib builds may deflate differently)."""

from __future__ import annotations

import asyncio
import base64
import hashlib
import os
import select
import threading
import time
import tty
import zlib
from pathlib import Path
from typing import Any

import pytest

serial = pytest.importorskip("serial")

from robid_link.drivers.serial_zlog import decode_block  # noqa: E402
from robid_link.fakes.serial_peer import SerialPeer  # noqa: E402
from robid_link.ident.model.robot import Robot  # noqa: E402
from robid_link.jobs import RobotInfo  # noqa: E402
from robid_link.link import registry  # noqa: E402
from robid_link.link.driver import Done  # noqa: E402
from tests.drivers import golden  # noqa: E402


def _frames(name: str) -> list[tuple[str, str]]:
    """``(direction, frame)`` of a transcript: '>' daemon → controller, '<' back, '>!' a
    damaged daemon frame, '<+' the payload (hex) of the ZBLK before it, '<+!' one damaged on
    the line, '~' the line drops."""
    out = []
    for line in golden.text("serial_line", name).splitlines():
        if line and not line.startswith("#"):
            way, _, frame = line.partition(" ")
            out.append((way, frame))
    return out


def _crc_ok(frame: str) -> bool:
    body, _, crc = frame.rpartition("*")
    return crc == f"{zlib.crc32(body.encode('ascii')):08X}"


ZLOG = ["zlog.txt", "zlog_resume.txt", "zlog_answers.txt"]


@pytest.mark.parametrize("name", ["cycle.txt", "answers.txt", "caps_old.txt", *ZLOG])
def test_transcript_frames_carry_their_crc(name: str) -> None:
    for way, frame in _frames(name):
        if way in ("<", ">", ">!"):
            assert _crc_ok(frame) == (way != ">!"), frame


@pytest.mark.parametrize("name", ZLOG)
def test_transcript_blocks_carry_their_lengths_and_crcs(name: str) -> None:
    """Each payload against its ZBLK header (length, CRC; a damaged one fails its CRC), each
    decoded by the codec of the page to the log's bytes at its offset."""
    log = golden.common()["zlog_csv"]
    frames = _frames(name)
    for (way, frame), (pway, hexed) in zip(frames, frames[1:], strict=False):
        if way != "<" or not frame.startswith("ZBLK "):
            continue
        f = frame.rpartition("*")[0].split(" ")
        off, rawlen, payload = int(f[3]), int(f[4]), bytes.fromhex(hexed)
        assert pway in ("<+", "<+!") and int(f[7]) == len(payload)
        assert (f"{zlib.crc32(payload):08X}" == f[8]) == (pway == "<+")
        if pway == "<+":
            raw = decode_block(f[6], payload, rawlen)
            assert raw == log[off: off + rawlen] and f"{zlib.crc32(raw):08X}" == f[5]


def test_transcript_carries_the_program_and_the_log() -> None:
    names = golden.common()
    frames = [f.rpartition("*")[0].split(" ") for _, f in _frames("cycle.txt")]
    prog = {f[2]: f for f in frames if f[0] == "PROG"}
    put = {f[2]: f for f in frames if f[0] == "PUT"}
    for name, key in (("traj.csv", "traj_csv"), ("traj.yaml", "traj_yaml")):
        assert prog[name][3:] == [str(names[f"{key}_size"]), names[f"{key}_sha256"]]
        assert base64.b64decode(put[name][4]) == names[key]
    done = next(f for f in frames if f[0] == "DONE")
    log = base64.b64decode(next(f for f in frames if f[0] == "DATA")[4])
    assert log == names["log_csv"]
    assert done[3:] == [str(len(log)), hashlib.sha256(log).hexdigest()]


class RecordingController(SerialPeer):
    """The fake controller, recording every frame either way; its answer to a STAT while the
    program runs (BUSY) opens ``gate``, so the DONE it pushes comes after that answer."""

    def __init__(self, *args: Any, gate: threading.Event, **kw: Any) -> None:
        super().__init__(*args, **kw)
        self.frames: list[tuple[str, str]] = []
        self.gate = gate

    def _handle(self, line: bytes) -> None:
        self.frames.append((">", line.decode("ascii", "replace").rstrip("\n")))
        super()._handle(line)

    def _send(self, data: bytes) -> None:
        self.frames.append(("<", data.decode("ascii").rstrip("\n")))
        super()._send(data)
        if data.startswith(b"BUSY "):
            self.gate.set()


def test_driver_sends_the_transcript(tmp_path: Path, robot: Robot) -> None:
    names = golden.common()
    gate = threading.Event()
    peer = RecordingController(golden.ScriptedCore(robot, names["log_csv"], gate), tmp_path,
                               gate=gate)
    nonce = "3f9a0c21"

    async def cycle() -> None:  # the plain protocol: the driver asks for no capability
        opts = {**peer.driver_options(), "stat_period_s": 30, "io_timeout_s": 5,
                "compress": False}
        driver = registry.make_driver(opts)
        driver.bind_robot(RobotInfo.of(robot))
        async with driver:
            await driver.put_program(golden.program(names))
            await driver.give_ready("exp1", nonce)
            done = await driver.take_done("exp1", nonce, timeout_s=20)
            assert await driver.fetch_logs(done) == names["log_csv"]
            await driver.acknowledge(done)

    with peer:
        asyncio.run(cycle())
    assert peer.frames == _frames("cycle.txt")


class _Line:
    """The daemon's end of the pty: whole frames out, whole lines in."""

    def __init__(self, port: str) -> None:
        self.port = serial.Serial(port, 921600, timeout=0.05)
        self.buf = b""

    def send(self, frame: str) -> None:
        self.port.write(frame.encode("ascii") + b"\n")

    def receive_bytes(self, n: int, timeout_s: float = 10.0) -> bytes:
        end = time.monotonic() + timeout_s
        while len(self.buf) < n:
            assert time.monotonic() < end, "no payload from the controller"
            self.buf += self.port.read(4096)
        out, self.buf = self.buf[:n], self.buf[n:]
        return out

    def receive(self, timeout_s: float = 10.0) -> str:
        end = time.monotonic() + timeout_s
        while b"\n" not in self.buf:
            assert time.monotonic() < end, "no answer from the controller"
            self.buf += self.port.read(4096)
        line, _, self.buf = self.buf.partition(b"\n")
        return line.decode("ascii")


def test_peer_answers_the_transcript(tmp_path: Path, robot: Robot) -> None:
    names = golden.common()
    gate = threading.Event()
    core = golden.ScriptedCore(robot, names["log_csv"], gate)
    with SerialPeer(core, tmp_path) as peer:
        line = _Line(str(peer.link))
        try:
            for way, frame in _frames("cycle.txt") + _frames("answers.txt"):
                if way.startswith(">"):
                    line.send(frame)
                    continue
                assert line.receive() == frame
                if frame.startswith("BUSY "):
                    gate.set()  # the motion ends now: DONE is pushed
        finally:
            line.port.close()
    assert core.runs == [("exp1", "3f9a0c21", names["traj_csv"], names["traj_yaml"])]


class ScriptedController:
    """The controller's end of a pty (behind a stable symlink, like the fake's) playing a
    transcript in a thread: each daemon frame read and compared, each controller frame and
    payload written as the transcript has it, the line dropped and plugged again at '~'."""

    def __init__(self, workdir: Path, frames: list[tuple[str, str]]) -> None:
        self.link, self.frames = workdir / "tty", frames
        self.errors: list[str] = []
        self.played = 0
        self._plug()
        self._thread = threading.Thread(target=self._play, name="scripted-serial", daemon=True)

    def _plug(self) -> None:
        self.master, slave = os.openpty()
        tty.setraw(slave)
        self.slave = slave
        tmp = self.link.with_name(".tty.tmp")
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(os.ttyname(slave))
        os.replace(tmp, self.link)

    def _unplug(self) -> None:
        self.link.unlink(missing_ok=True)
        os.close(self.master)
        os.close(self.slave)

    def _read_line(self, buf: bytearray) -> bytes:
        end = time.monotonic() + 20
        while b"\n" not in buf:
            if time.monotonic() > end:
                raise TimeoutError("no frame from the daemon within 20 s")
            ready, _, _ = select.select([self.master], [], [], 0.05)
            if ready:
                buf += os.read(self.master, 65536)
        k = buf.index(b"\n")
        line = bytes(buf[:k])
        del buf[: k + 1]
        return line

    def _play(self) -> None:
        buf = bytearray()
        try:
            for way, frame in self.frames:
                if way == ">":
                    got = self._read_line(buf).decode("ascii", "replace")
                    if got != frame:
                        self.errors.append(f"daemon sent {got!r}, the transcript has {frame!r}")
                        return
                elif way == "<":
                    os.write(self.master, frame.encode("ascii") + b"\n")
                elif way.startswith("<+"):
                    os.write(self.master, bytes.fromhex(frame))
                elif way == "~":
                    self._unplug()
                    time.sleep(0.3)
                    self._plug()
                    buf.clear()
                self.played += 1
        except (OSError, TimeoutError) as err:
            self.errors.append(f"after {self.played} lines: {err}")

    def __enter__(self) -> ScriptedController:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._thread.join(30)
        self._unplug()


@pytest.mark.parametrize(("name", "log"), [("zlog.txt", "zlog_csv"),
                                           ("zlog_resume.txt", "zlog_csv"),
                                           ("caps_old.txt", "log_csv")])
def test_driver_follows_the_transcript(tmp_path: Path, name: str, log: str) -> None:
    """The driver against the transcript's own bytes: it asks exactly what the daemon asks
    (CAPS, ZGET from the end of what it holds, again after a damaged block or a dropped line)
    and stores the log byte for byte."""
    names = golden.common()
    done = Done("exp1", "3f9a0c21", names[f"{log}_sha256"], names[f"{log}_size"])

    async def fetch() -> bytes:
        driver = registry.make_driver({"name": "serial_line", "port": str(tmp_path / "tty"),
                                       "block_bytes": 1024, "io_timeout_s": 5})
        async with driver:
            data = await driver.fetch_logs(done)
            await driver.acknowledge(done)
        return data

    with ScriptedController(tmp_path, _frames(name)) as script:
        data = asyncio.run(fetch())
    assert script.errors == [] and script.played == len(_frames(name))
    assert data == names[log]


@pytest.mark.parametrize(("name", "zlog"), [("zlog.txt", True), ("zlog_resume.txt", True),
                                            ("zlog_answers.txt", True),
                                            ("caps_old.txt", False)])
def test_peer_answers_the_zlog_transcript(tmp_path: Path, robot: Robot, name: str,
                                          zlog: bool) -> None:
    """The fake controller (``zlog=False``: an older one) fed the daemon's frames answers the
    controller's; a payload is compared inflated. A payload damaged on the line and a dropped
    line are the line's doing: the controller sent an intact payload, and its answer to the
    request before the drop."""
    names = golden.common()
    log = names["zlog_csv" if zlog else "log_csv"]
    core = golden.ScriptedCore(robot, log)
    with SerialPeer(core, tmp_path, zlog=zlog) as peer:
        peer.offer_log("exp1", "3f9a0c21", log)
        line = _Line(str(peer.link))
        try:
            sent: bytes = b""
            for way, frame in _frames(name):
                if way.startswith(">"):
                    line.send(frame)
                elif way == "<" and frame.startswith("ZBLK "):
                    got = line.receive()
                    assert _fields(got)[:7] == _fields(frame)[:7], (got, frame)
                    sent = line.receive_bytes(int(_fields(got)[7]))
                    assert f"{zlib.crc32(sent):08X}" == _fields(got)[8]
                elif way == "<":
                    assert line.receive() == frame
                elif way == "<+":
                    assert zlib.decompress(sent) == zlib.decompress(bytes.fromhex(frame))
                elif way == "~":  # the answer the dropped line lost: this controller sent it
                    lost = _fields(line.receive())
                    assert lost[0] == "ZBLK"
                    line.receive_bytes(int(lost[7]))
        finally:
            line.port.close()


def _fields(frame: str) -> list[str]:
    return frame.rpartition("*")[0].split(" ")
