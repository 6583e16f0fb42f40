"""The serial line driver against its fake controller on a pty pair: flipped bits are caught
by the frame CRCs and resent, a cable pulled mid-log is reopened and the log resumes intact
(plain chunks and compressed blocks alike), a damaged block is asked again and one damaged
for good is one line, an older controller gets plain GET, a zip bomb is refused, a device
that vanishes is one line, config errors name the key, frames round-trip."""

from __future__ import annotations

import asyncio
import hashlib
import re
import time
from pathlib import Path
from typing import Any

import pytest

from robid_link.drivers.serial_frames import Splitter
from robid_link.drivers.serial_line import SerialLineDriver, decode_frame, encode_frame
from robid_link.exceptions import ConfigError, DriverError, DriverTimeoutError
from robid_link.fakes.controller import default_truth, make_peer
from robid_link.ident.model.robot import Robot
from robid_link.jobs import MotionProgram, RobotInfo
from robid_link.link import registry
from robid_link.link.driver import Driver

from .conftest import bump_program
from .test_contract import RATE_HZ


@pytest.fixture(scope="module")
def program(robot: Robot) -> MotionProgram:
    return bump_program(robot, 2.0, 0.05)


def _peer(tmp_path: Path, robot: Robot, **kw: Any) -> Any:
    work = tmp_path / "ctl"
    work.mkdir(parents=True, exist_ok=True)
    return make_peer("serial_line", robot, default_truth(robot, rate_hz=RATE_HZ), work, **kw)


def _driver(peer: Any, robot: Robot, **over: Any) -> Driver:
    d = registry.make_driver({**peer.driver_options(), **over})
    d.bind_robot(RobotInfo.of(robot))
    return d


async def _cycle(driver: Driver, program: MotionProgram) -> bytes:
    async with driver:
        await driver.put_program(program)
        await driver.give_ready("exp1", "c0ffee01")
        done = await driver.take_done("exp1", "c0ffee01", timeout_s=60)
        data = await driver.fetch_logs(done)
        await driver.acknowledge(done)
        return data


#: the log in small pieces either way: plain chunks, or compressed blocks
MODES = {"plain": {"compress": False, "chunk_bytes": 512}, "zlog": {"block_bytes": 1024}}


@pytest.mark.parametrize("mode", MODES)
def test_flipped_bits_are_resent_and_the_log_arrives_intact(tmp_path: Path, robot: Robot,
                                                            program: MotionProgram,
                                                            mode: str) -> None:
    with _peer(tmp_path, robot, fault="flip_bytes", flip_rate=0.2) as peer:
        driver = _driver(peer, robot, io_timeout_s=0.3, retries=30, **MODES[mode])
        data = asyncio.run(_cycle(driver, program))
        assert peer.frames_bad > 0 and driver.bad_frames > 0  # both ways
        assert (peer.blocks_sent > 0) == (mode == "zlog")
    run = peer.core.handled
    assert len(run) == 1 and data.startswith(b"t,q1,q2,q3,tau1")


@pytest.mark.parametrize("mode", MODES)
def test_cable_pulled_mid_log_reopens_and_resumes(tmp_path: Path, robot: Robot,
                                                  program: MotionProgram, mode: str) -> None:
    with _peer(tmp_path, robot, fault="cable_pulled", pull_s=0.8) as peer:
        driver = _driver(peer, robot, io_timeout_s=0.3, reopen_s=5, **MODES[mode])
        data = asyncio.run(_cycle(driver, program))
    assert driver.reopened == 1  # type: ignore[attr-defined]
    # intact: the base checked size and SHA-256 against DONE; a clean run gives the same log
    with _peer(tmp_path / "again", robot) as clean:
        again = asyncio.run(_cycle(_driver(clean, robot), program))
    assert hashlib.sha256(data).digest() == hashlib.sha256(again).digest()


def test_a_vanished_device_is_one_line(tmp_path: Path, robot: Robot,
                                       program: MotionProgram) -> None:
    with _peer(tmp_path, robot, fault="device_gone") as peer:
        driver = _driver(peer, robot, reopen_s=1.0, io_timeout_s=0.3)
        t0 = time.monotonic()
        with pytest.raises(DriverError, match=r"serial device .*tty gone: not back within 1 s"
                           ) as err:
            asyncio.run(_cycle(driver, program))
    assert not isinstance(err.value, DriverTimeoutError) and "\n" not in str(err.value)
    assert time.monotonic() - t0 < 30 and peer.core.handled == []


def test_a_missing_port_is_one_line(tmp_path: Path) -> None:
    driver = SerialLineDriver(port=str(tmp_path / "nope"))
    with pytest.raises(DriverError, match=r"serial port .*nope: cannot open \(.*No such file"):
        asyncio.run(driver.open())


@pytest.mark.parametrize(("over", "match"), [
    ({"port": None}, r"driver\.port: missing"),
    ({"baudrate": "fast"}, r"driver\.baudrate: expected an integer"),
    ({"chunk_bytes": 10**6}, r"driver\.chunk_bytes: expected an integer in \[16, 16384\]"),
    ({"retries": -1}, r"driver\.retries"),
    ({"io_timeout_s": 0}, r"driver\.io_timeout_s: expected a number > 0"),
    ({"reopen_s": "x"}, r"driver\.reopen_s"),
])
def test_config_errors_name_the_key(over: dict[str, Any], match: str) -> None:
    opts = {"port": "/dev/ttyUSB0", **over}
    with pytest.raises(ConfigError, match=match):
        SerialLineDriver(**{k: v for k, v in opts.items() if v is not None})


def test_frames_round_trip_and_any_flipped_bit_is_caught() -> None:
    frame = encode_frame("DONE", "exp1", "ab12", 42, "f" * 64)
    assert decode_frame(frame) == ["DONE", "exp1", "ab12", "42", "f" * 64]
    for k in range(len(frame) - 1):
        for bit in range(8):
            bad = bytearray(frame)
            bad[k] ^= 1 << bit
            assert decode_frame(bytes(bad)) is None, (k, bit)


def test_a_damaged_block_is_asked_again(tmp_path: Path, robot: Robot,
                                        program: MotionProgram) -> None:
    with _peer(tmp_path, robot, fault="corrupt_block", corrupt_times=2) as peer:
        driver = _driver(peer, robot, block_bytes=1024)
        data = asyncio.run(_cycle(driver, program))
    assert driver.bad_blocks == 2 and driver.zlog  # type: ignore[attr-defined]
    with _peer(tmp_path / "again", robot) as clean:
        assert asyncio.run(_cycle(_driver(clean, robot), program)) == data


def test_a_block_damaged_every_time_is_one_line_and_the_fetch_resumes(
        tmp_path: Path, robot: Robot, program: MotionProgram) -> None:
    """``retries`` + 1 damaged copies of one block stop the fetch with one line naming the
    log and the block; the bytes before it are kept, and the next fetch starts there (never
    from 0), so the stored log is whole."""
    with _peer(tmp_path, robot, fault="corrupt_block", corrupt_times=4) as peer:
        driver = _driver(peer, robot, block_bytes=1024, retries=2)

        async def go() -> tuple[str, bytes, list[int]]:
            async with driver:
                await driver.put_program(program)
                await driver.give_ready("exp1", "c0ffee01")
                done = await driver.take_done("exp1", "c0ffee01", timeout_s=60)
                with pytest.raises(DriverError) as err:
                    await driver.fetch_logs(done)
                before = len(peer.blocks_asked)
                data = await driver.fetch_logs(done)
                return str(err.value), data, peer.blocks_asked[before:]

        line, data, again = asyncio.run(go())
    stopped = re.fullmatch(r"serial port \S+: log of experiment exp1 \(nonce c0ffee01\): "
                           r"block at offset (\d+) not received intact \(.*payload CRC.*\); "
                           r"fetch stopped, \1 bytes kept for a resume", line)
    assert stopped, line
    assert again[0] == min(again) == int(stopped.group(1)) > 0  # resumed there, never from 0
    with _peer(tmp_path / "again", robot) as clean:
        assert asyncio.run(_cycle(_driver(clean, robot), program)) == data


def test_an_older_controller_without_compression_gets_plain_get(
        tmp_path: Path, robot: Robot, program: MotionProgram) -> None:
    with _peer(tmp_path, robot, zlog=False) as peer:
        driver = _driver(peer, robot)
        data = asyncio.run(_cycle(driver, program))
        assert peer.blocks_sent == 0 and driver.zlog is False  # type: ignore[attr-defined]
    with _peer(tmp_path / "again", robot) as clean:
        assert asyncio.run(_cycle(_driver(clean, robot), program)) == data


def test_a_zip_bomb_is_refused_without_inflating_it(tmp_path: Path, robot: Robot,
                                                    program: MotionProgram) -> None:
    with _peer(tmp_path, robot, fault="zip_bomb") as peer:
        driver = _driver(peer, robot, retries=1)
        with pytest.raises(DriverError, match=r"block at offset 0 not decoded after 2 tries "
                                              r"\(inflates beyond \d+ bytes\)") as err:
            asyncio.run(_cycle(driver, program))
    assert "\n" not in str(err.value)


def test_the_splitter_hands_each_block_its_payload_whatever_the_reads() -> None:
    """A ZBLK header's payload (newlines and all) is taken by its length, in any slicing of
    the reads; a damaged header leaves its payload to be line noise; a payload that stops
    coming is dropped whole."""
    payload = b"\x00\n\xffZBLK \n" * 5
    header = encode_frame("ZBLK", "exp1", "n1", 0, 9, "0" * 8, "z", len(payload), "0" * 8)
    stream = encode_frame("PONG", 0) + header + payload + encode_frame("EOF", "exp1", "n1", 9)
    for step in (1, 3, 7, len(stream)):
        split = Splitter(1024)
        got = [item for k in range(0, len(stream), step) for item in split.feed(
            stream[k: k + step])]
        assert got == [(encode_frame("PONG", 0), None), (header, payload),
                       (encode_frame("EOF", "exp1", "n1", 9), None)], step
    damaged = header.replace(b"exp1", b"exq1")
    got = Splitter(1024).feed(damaged + payload)
    assert got[0] == (damaged, None) and all(p is None for _, p in got)
    assert Splitter(16).feed(header + payload)[0] == (header, None)  # over the payload cap
    split = Splitter(1024)
    assert split.feed(header + payload[:10]) == [] and split.waiting
    split.cut()
    assert not split.waiting and split.feed(encode_frame("PONG", 1)) == [
        (encode_frame("PONG", 1), None)]
