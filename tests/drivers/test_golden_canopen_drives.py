"""The CANopen transcript (``tests/golden/canopen_drives/startup.txt``, from CiA 301 and CiA
402-2) against both sides: the driver puts exactly its frames on the bus to bring node 1 up
and runs one experiment with SYNCs that count and one RPDO per drive and SYNC (recorded by a
listener on the virtual bus); the fake drives, sent the transcript's frames by a plain
python-can bus, answer exactly as it says (".." where a byte is a process value)."""

from __future__ import annotations

import asyncio
import math
import time
from pathlib import Path
from typing import Any

import pytest

can = pytest.importorskip("can")
pytest.importorskip("canopen")

from robid_link.fakes.controller import default_truth, make_peer  # noqa: E402
from robid_link.ident.model.robot import Robot  # noqa: E402
from robid_link.jobs import RobotInfo  # noqa: E402
from robid_link.link import registry  # noqa: E402
from tests.drivers import golden  # noqa: E402
from tests.drivers.conftest import bump_program  # noqa: E402

NODE = 1
#: node 1's COB-IDs and the broadcast ones (CiA 301 §7.3.3)
MINE = {0x000, 0x080, 0x080 + NODE, 0x180 + NODE, 0x200 + NODE, 0x280 + NODE, 0x580 + NODE,
        0x600 + NODE, 0x700 + NODE}


def _transcript() -> list[tuple[str, int, list[int | None]]]:
    """``(direction, COB-ID, data)``; a None byte is any value."""
    out = []
    for line in golden.text("canopen_drives", "startup.txt").splitlines():
        line = line.split("#", 1)[0].split()
        if line:
            data = [None if b == ".." else int(b, 16) for b in line[2:]]
            out.append((line[0], int(line[1], 16), data))
    return out


def _mine(msg: Any) -> bool:
    """Node 1's frames and the broadcast ones, without its heartbeats (only the boot-up)."""
    if msg.arbitration_id not in MINE:
        return False
    return msg.arbitration_id != 0x700 + NODE or bytes(msg.data) == b"\x00"


def _same(frame: tuple[str, int, list[int | None]], msg: Any) -> bool:
    _, cob, data = frame
    return msg.arbitration_id == cob and len(msg.data) == len(data) and all(
        b is None or b == got for b, got in zip(data, msg.data, strict=True))


def test_transcript_sdo_frames_are_well_formed() -> None:
    """Every SDO frame is 8 bytes; an expedited command byte says how many bytes it carries
    (CiA 301 §7.2.4.3: n = bits 3-2 count the bytes without data)."""
    for way, cob, data in _transcript():
        if cob in (0x580 + NODE, 0x600 + NODE):
            assert len(data) == 8
            cmd = data[0]
            if cmd in (0x23, 0x27, 0x2B, 0x2F, 0x43, 0x47, 0x4B, 0x4F):
                carried = 4 - ((cmd >> 2) & 3)
                assert all(b is None or b == 0 for b in data[4 + carried:]) or way == ">"


def _peer(tmp_path: Path, robot: Robot) -> Any:
    return make_peer("canopen_drives", robot, default_truth(robot, rate_hz=200.0), tmp_path,
                     sync_period_s=0.005, counts_per_rad=2**20 / (2 * math.pi))


def test_driver_sends_the_transcript(tmp_path: Path, robot: Robot) -> None:
    frames = _transcript()
    nmt_start = frames.index((">", 0x000, [0x01, 0x00]))
    startup, cycle = frames[: nmt_start + 1], frames[nmt_start + 1:]
    peer = _peer(tmp_path, robot)
    with peer:
        listener = can.Bus(interface="virtual", channel=peer.channel)
        reader = can.BufferedReader()
        notifier = can.Notifier(listener, [reader])
        try:
            async def run() -> None:
                driver = registry.make_driver(peer.driver_options())
                driver.bind_robot(RobotInfo.of(robot))
                async with driver:
                    await driver.put_program(bump_program(robot, 0.3, 0.02))
                    await driver.give_ready("exp1", "3f9a0c21")
                    done = await driver.take_done("exp1", "3f9a0c21", timeout_s=30)
                    await driver.fetch_logs(done)

            asyncio.run(run())
            time.sleep(0.1)
        finally:
            notifier.stop()
            listener.shutdown()
    got = []
    while (msg := reader.get_message(0)) is not None:
        if _mine(msg):
            got.append(msg)
    for k, frame in enumerate(startup):
        assert _same(frame, got[k]), f"frame {k}: {got[k]} is not {frame}"
    after = got[len(startup):]
    for frame in cycle:  # the first of each kind after NMT start
        first = next(m for m in after if m.arbitration_id == frame[1])
        assert _same(frame, first), f"{first} is not {frame}"
    _check_streaming(after)


def _check_streaming(frames: list[Any]) -> None:
    """The SYNCs count 1, 2, … 240, 1, …; one RPDO1 (8 bytes: controlword 000Fh while it
    streams, 0006h shutdown at the end) before each; TPDOs carry a counter that was sent."""
    syncs = [m.data[0] for m in frames if m.arbitration_id == 0x080]
    assert len(syncs) > 60 and syncs[0] == 1
    assert all(b == a % 240 + 1 for a, b in zip(syncs, syncs[1:], strict=False))
    rpdo = [m for m in frames if m.arbitration_id == 0x200 + NODE]
    assert all(len(m.data) == 8 for m in rpdo)
    words = [int.from_bytes(m.data[:2], "little") for m in rpdo]
    assert set(words) <= {0x000F, 0x0006} and words[-1] == 0x0006
    kinds = [m.arbitration_id for m in frames if m.arbitration_id in (0x080, 0x200 + NODE)]
    assert all(a != b for a, b in zip(kinds, kinds[1:], strict=False))  # alternate
    for cob, size in ((0x180 + NODE, 7), (0x280 + NODE, 5)):
        tpdo = [m for m in frames if m.arbitration_id == cob]
        assert tpdo and all(len(m.data) == size and m.data[-1] in syncs for m in tpdo)


def test_peer_answers_the_transcript(tmp_path: Path, robot: Robot) -> None:
    frames = _transcript()
    peer = _peer(tmp_path, robot)
    with peer:
        master = can.Bus(interface="virtual", channel=peer.channel)
        try:
            for k, (way, cob, data) in enumerate(frames):
                if way == ">":
                    master.send(can.Message(arbitration_id=cob, data=bytes(data),
                                            is_extended_id=False))
                    continue
                end = time.monotonic() + 5
                while True:
                    msg = master.recv(max(0.0, end - time.monotonic()))
                    assert msg is not None, f"frame {k}: no answer, expected {way} {cob:03X}"
                    if _mine(msg):
                        break
                assert _same((way, cob, data), msg), f"frame {k}: {msg} is not {cob:03X} {data}"
        finally:
            master.shutdown()
    assert peer.states()[NODE] == "Operation enabled"
