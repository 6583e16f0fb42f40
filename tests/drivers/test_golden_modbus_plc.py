"""The Modbus PLC transcript (``tests/golden/modbus_plc/cycle.yaml``, from
docs/modbus_plc_protocol.md) against both sides: the driver sends exactly its function codes,
addresses and values (recorded at a recording fake PLC); the fake PLC, driven by the
transcript's requests from a plain pymodbus client, answers its registers and files."""

from __future__ import annotations

import asyncio
import json
import threading
import time
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("pymodbus")

from pymodbus.client import AsyncModbusTcpClient  # noqa: E402

from robid_link.fakes.modbus_peer import ModbusPeer  # noqa: E402
from robid_link.ident.model.robot import Robot  # noqa: E402
from robid_link.jobs import RobotInfo  # noqa: E402
from robid_link.link import registry  # noqa: E402
from tests.drivers import golden  # noqa: E402


class RecordingPlc(ModbusPeer):
    """The fake PLC, recording every request it serves: (function code, address, count,
    values written or the registers read). pymodbus reads a written register back for its
    answer to function 6: that read-back is not a request."""

    def __init__(self, *args: Any, **kw: Any) -> None:
        super().__init__(*args, **kw)
        self.requests: list[tuple[int, int, int, list[int]]] = []

    async def _action(self, fc: int, start: int, address: int, count: int, regs: list[int],
                      values: Any) -> Any:
        result = await super()._action(fc, start, address, count, regs, values)
        if values is not None:
            self.requests.append((fc, address, count, [int(v) for v in values]))
        elif fc in (3, 4):
            self.requests.append((fc, address, count,
                                  list(regs[address - start: address - start + count])))
        return result


def _names() -> dict[str, Any]:
    return golden.common()


def _content_ok(spec: Any, data: bytes) -> bool:
    if isinstance(spec, dict):
        return bool(json.loads(data) == spec["json"])
    return data == (spec.encode() if isinstance(spec, str) else spec)


def _regs_ok(spec: list[Any], regs: list[int]) -> bool:
    return len(spec) == len(regs) and all(s == "*" or s == r for s, r in zip(spec, regs,
                                                                              strict=True))


def test_driver_sends_the_transcript(tmp_path: Path, robot: Robot) -> None:
    doc = golden.load("modbus_plc", "cycle.yaml")
    names = _names()
    core = golden.ScriptedCore(robot, names["log_csv"])
    plc = RecordingPlc(core, tmp_path / "share")
    nonce, share = doc["nonce"], tmp_path / "share"

    async def cycle() -> None:
        driver = registry.make_driver(plc.driver_options())
        driver.bind_robot(RobotInfo.of(robot))
        async with driver:
            await driver.put_program(golden.program(names))
            for path, spec in golden.fill(doc["steps"][1]["share"], names).items():
                assert _content_ok(spec, (share / path).read_bytes()), path
            await driver.give_ready("exp1", nonce)
            done = await driver.take_done("exp1", nonce, timeout_s=20)
            assert await driver.fetch_logs(done) == names["log_csv"]
            await driver.acknowledge(done)

    with plc:
        asyncio.run(cycle())
    want = [(w["fc"], w["address"], len(w["values"]), w["values"])
            for step in doc["steps"] for w in step.get("writes", [])]
    hb, reads, writes = (doc["heartbeat"], doc["map"], [])
    beats = []
    for fc, address, count, values in plc.requests:
        if (fc, address) == (hb["fc"], hb["address"]):
            beats.append(values[0])
        elif fc == 3:
            assert (address, count) == (reads["address"], reads["count"])
        else:
            writes.append((fc, address, count, values))
    assert writes == want
    assert beats and all((b - a) % 65536 == 1 for a, b in zip(beats, beats[1:], strict=False))
    for path in golden.fill(doc["steps"][5]["delete"], names):
        assert not (share / path).exists()


async def _poll(client: AsyncModbusTcpClient, spec: list[Any], timeout_s: float = 10.0
                ) -> list[int]:
    """Read the map (function 3) until it shows ``spec``."""
    end = time.monotonic() + timeout_s
    while True:
        res = await client.read_holding_registers(0, count=11, device_id=1)
        assert not res.isError(), res
        if _regs_ok(spec, list(res.registers)):
            return list(res.registers)
        assert time.monotonic() < end, f"registers {list(res.registers)}, waiting for {spec}"
        await asyncio.sleep(0.01)


def test_peer_answers_the_transcript(tmp_path: Path, robot: Robot) -> None:
    doc = golden.load("modbus_plc", "cycle.yaml")
    names = _names()
    gate = threading.Event()
    core = golden.ScriptedCore(robot, names["log_csv"], gate)
    share = tmp_path / "share"
    steps = {s["step"]: s for s in doc["steps"]}

    async def replay(port: int) -> None:
        client = AsyncModbusTcpClient("127.0.0.1", port=port)
        assert await client.connect()
        try:
            await _poll(client, steps["open"]["read"])
            for path, spec in golden.fill(steps["put"]["share"], names).items():
                data = json.dumps(spec["json"]) if isinstance(spec, dict) else spec
                (share / path).write_bytes(data.encode() if isinstance(data, str) else data)
            await _poll(client, steps["give"]["read"])
            for w in steps["give"]["writes"]:
                assert w["fc"] == 16
                assert not (await client.write_registers(w["address"], w["values"],
                                                         device_id=1)).isError()
            await _poll(client, steps["run"]["read"])
            end = time.monotonic() + 10.0  # BUSY shows before the core's thread is handed it
            while not core.runs and time.monotonic() < end:
                await asyncio.sleep(0.01)
            assert core.runs == [("1", doc["nonce"], names["traj_csv"], names["traj_yaml"])]
            gate.set()
            await _poll(client, steps["done"]["read"])
            for path, spec in golden.fill(steps["done"]["share"], names).items():
                assert _content_ok(spec, (share / path).read_bytes()), path
            await _poll(client, steps["acknowledge"]["read"])
            for w in steps["acknowledge"]["writes"]:
                assert not (await client.write_registers(w["address"], w["values"],
                                                         device_id=1)).isError()
            for path in steps["acknowledge"]["delete"]:
                (share / path).unlink()
            last = await _poll(client, steps["idle"]["read"])
            await asyncio.sleep(0.25)  # the PLC's heartbeat counts at least every 100 ms
            later = await _poll(client, steps["idle"]["read"])
            assert (later[10] - last[10]) % 65536 >= 2
            assert not (await client.write_register(4, 7, device_id=1)).isError()  # FC 6
        finally:
            client.close()

    with ModbusPeer(core, share) as plc:
        asyncio.run(replay(plc.port))
