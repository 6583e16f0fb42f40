"""The Modbus PLC driver against its fake PLC (a pymodbus server on 127.0.0.1): the PLC's own
faults are one clear line each, the register map is configurable and checked, experiment
numbers survive a daemon restart, a restarted daemon's second give does not run twice."""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path
from typing import Any

import pytest

from robid_link.drivers.modbus_plc import ModbusPlcDriver, nonce_tag, register_map
from robid_link.exceptions import ConfigError, DriverError, DriverTimeoutError
from robid_link.fakes.controller import default_truth, make_peer
from robid_link.ident.model.robot import Robot
from robid_link.jobs import MotionProgram, RobotInfo
from robid_link.link import registry
from robid_link.link.driver import Driver

from . import test_contract as contract

RATE_HZ = contract.RATE_HZ


def _peer(tmp_path: Path, robot: Robot, **kw: Any) -> Any:
    work = tmp_path / "plc"
    work.mkdir(exist_ok=True)
    return make_peer("modbus_plc", robot, default_truth(robot, rate_hz=RATE_HZ), work, **kw)


def _driver(peer: Any, robot: Robot, **over: Any) -> Driver:
    d = registry.make_driver({**peer.driver_options(), **over})
    d.bind_robot(RobotInfo.of(robot))
    return d


async def _give_take(driver: Driver, program: MotionProgram, nonce: str = "a1b2c3d4",
                     timeout_s: float = 20.0) -> bytes:
    await driver.put_program(program)
    await driver.give_ready("exp1", nonce)
    done = await driver.take_done("exp1", nonce, timeout_s=timeout_s)
    data = await driver.fetch_logs(done)
    await driver.acknowledge(done)
    return data


@pytest.mark.parametrize(("fault", "match"), [
    ("plc_gone", r"unreachable after \d+ connection attempts"),
    ("heartbeat_frozen", r"PLC heartbeat frozen at \d+ for"),
    ("error_code", r"experiment exp1 failed: error 4 \(emergency stop\)"),
    ("register_garbage", r"status register holds 48879.*register garbage"),
])
def test_plc_faults_are_one_line_not_a_timeout(tmp_path: Path, robot: Robot,
                                               program: MotionProgram, fault: str,
                                               match: str) -> None:
    with _peer(tmp_path, robot, fault=fault) as peer:
        driver = _driver(peer, robot, heartbeat_timeout_s=1.0, connect_retries=3)

        async def go() -> None:
            async with driver:
                await _give_take(driver, program, timeout_s=60)

        t0 = time.monotonic()
        with pytest.raises(DriverError, match=match) as err:
            asyncio.run(go())
    assert not isinstance(err.value, DriverTimeoutError)
    assert "\n" not in str(err.value) and time.monotonic() - t0 < 30
    assert peer.core.handled == []  # the PLC's faults run nothing


def test_a_moved_register_map_and_device_id(tmp_path: Path, robot: Robot,
                                            program: MotionProgram) -> None:
    regs = {"status": 120, "plc_heartbeat": 121, "command": 7}
    with _peer(tmp_path, robot, base_address=100, registers=regs, device_id=3) as peer:
        driver = _driver(peer, robot, base_address=100, registers=regs)

        async def go() -> bytes:
            async with driver:
                return await _give_take(driver, program)

        data = asyncio.run(go())
    assert data.startswith(b"t,q1,q2,q3,tau1") and len(peer.core.handled) == 1


def test_a_restarted_daemon_resumes_without_a_second_run(tmp_path: Path,
                                                         robot: Robot,
                                                         program: MotionProgram) -> None:
    with _peer(tmp_path, robot) as peer:
        async def first() -> None:  # give, then the daemon dies before taking
            async with _driver(peer, robot) as d:
                await d.put_program(program)
                await d.give_ready("exp1", "0badc0de")

        async def second() -> bytes:  # a new process: same share, same PLC
            async with _driver(peer, robot) as d:
                await d.put_program(program)
                await d.give_ready("exp1", "0badc0de")
                done = await d.take_done("exp1", "0badc0de", timeout_s=20)
                return await d.fetch_logs(done)

        asyncio.run(first())
        data = asyncio.run(second())
    assert data and len(peer.core.handled) == 1
    index = json.loads((tmp_path / "plc" / "inbox" / "experiments.json").read_text())
    assert index == {"exp1": 1}
    assert (tmp_path / "plc" / "outbox" / "1.0badc0de.log.csv").is_file()


def test_nonce_tags() -> None:
    assert nonce_tag("0badc0de") == 0x0BADC0DE and 0 <= nonce_tag("n1") < 2**32


@pytest.mark.parametrize(("over", "match"), [
    ({"host": None}, r"driver\.host: missing"),
    ({"share": None}, r"driver\.share: missing"),
    ({"port": 70000}, r"driver\.port: expected an integer in \[1, 65535\]"),
    ({"device_id": "x"}, r"driver\.device_id: expected an integer"),
    ({"registers": {"colour": 3}}, r"driver\.registers\.colour: unknown register"),
    ({"registers": {"status": -1}}, r"driver\.registers\.status: expected an address"),
    ({"registers": {"status": 0}}, r"driver\.registers\.status: address 0 is also command"),
    ({"registers": {"status": 500}}, r"driver\.registers: the map spans 501 registers"),
    ({"base_address": 65530}, r"driver\.base_address"),
    ({"poll_interval_s": 0}, r"driver\.poll_interval_s"),
    ({"heartbeat_timeout_s": 0.1}, r"driver\.heartbeat_timeout_s"),
    ({"rapid": "yes"}, r"driver\.rapid"),
])
def test_config_errors_name_the_key(over: dict[str, Any], match: str) -> None:
    opts = {"host": "127.0.0.1", "share": "/tmp", **over}
    with pytest.raises(ConfigError, match=match):
        ModbusPlcDriver(**{k: v for k, v in opts.items() if v is not None})


def test_default_register_map_is_contiguous() -> None:
    addr = register_map()
    assert sorted(addr.values()) == list(range(11)) and addr["command"] == 0


def test_an_unreachable_plc_is_one_line_at_open(tmp_path: Path) -> None:
    import socket

    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    driver = ModbusPlcDriver(host="127.0.0.1", port=port, share=str(tmp_path),
                             connect_retries=1)
    with pytest.raises(DriverError, match=rf"PLC 127.0.0.1:{port} unreachable after 2"):
        asyncio.run(driver.open())
