"""The serial-line transcripts (``tests/golden/serial_line/``, from
docs/serial_line_protocol.md) against both sides: every frame's CRC-32 computed here with
zlib over the documented bytes; the driver sends exactly the daemon's frames (recorded at a
recording fake controller); the fake controller, fed the daemon's frames on its pty, answers
exactly the controller's."""

from __future__ import annotations

import asyncio
import base64
import hashlib
import threading
import time
import zlib
from pathlib import Path
from typing import Any

import pytest

serial = pytest.importorskip("serial")

from robid_link.fakes.serial_peer import SerialPeer  # noqa: E402
from robid_link.ident.model.robot import Robot  # noqa: E402
from robid_link.jobs import RobotInfo  # noqa: E402
from robid_link.link import registry  # noqa: E402
from tests.drivers import golden  # noqa: E402


def _frames(name: str) -> list[tuple[str, str]]:
    """``(direction, frame)`` of a transcript: '>' daemon → controller, '<' back, '>!' a
    damaged daemon frame."""
    out = []
    for line in golden.text("serial_line", name).splitlines():
        if line and not line.startswith("#"):
            way, _, frame = line.partition(" ")
            out.append((way, frame))
    return out


def _crc_ok(frame: str) -> bool:
    body, _, crc = frame.rpartition("*")
    return crc == f"{zlib.crc32(body.encode('ascii')):08X}"


@pytest.mark.parametrize("name", ["cycle.txt", "answers.txt"])
def test_transcript_frames_carry_their_crc(name: str) -> None:
    for way, frame in _frames(name):
        assert _crc_ok(frame) == (way != ">!"), frame


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

    async def cycle() -> None:
        opts = {**peer.driver_options(), "stat_period_s": 30, "io_timeout_s": 5}
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
