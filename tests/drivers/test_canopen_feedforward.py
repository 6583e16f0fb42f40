"""The CANopen driver's own feedforward (an uploaded parameter set → torque offset 0x60B2 of every
setpoint, kept across restarts; the torques come from the worker as a table), its socketcand
options, and the fake drives' reaction to a master that stops sending SYNC (quick stop on their
own)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from robid_link.drivers.canopen.drives import CanopenDrivesDriver
from robid_link.exceptions import ConfigError, DriverError
from robid_link.fakes.canopen.peer import EDS
from robid_link.fakes.controller import default_truth, make_peer
from robid_link.ident.entry import run
from robid_link.ident.fit.paramset import FORMAT, set_sha256
from robid_link.ident.model.robot import Robot
from robid_link.jobs import FeedforwardJob, FeedforwardTable, MotionProgram, ParameterSet, RobotInfo
from robid_link.link import registry
from robid_link.link.driver import Driver

from .conftest import bump_program

ARM3 = Path(__file__).resolve().parents[2] / "examples" / "robots" / "arm3.yaml"


@pytest.fixture(scope="module")
def program(robot: Robot) -> MotionProgram:
    return bump_program(robot, 1.5, 0.5)


def parameter_set(robot: Robot, viscous: float = 2.0) -> dict[str, Any]:
    """A set with the robot's nominal inertials and some friction (what an identification of
    a robot that matches its CAD would hand over)."""
    assert robot.nominal is not None
    doc: dict[str, Any] = {
        "format": FORMAT, "robot": robot.name, "joints": list(robot.joint_names),
        "run_id": "test", "effects": ["rigid_body", "viscous", "coulomb"],
        "base_parameters": [], "elasticity": [], "relative_error": 0.01,
        "friction": {"viscous": [viscous] * robot.n, "coulomb": [1.5] * robot.n,
                     "offset": [0.0] * robot.n},
        "standard_inertials": [float(x) for x in robot.nominal]}
    doc["sha256"] = set_sha256(doc)
    return doc


@contextlib.contextmanager
def drives(tmp_path: Path, robot: Robot, **peer_opts: Any) -> Iterator[tuple[Any, Any]]:
    peer = make_peer("canopen_drives", robot, default_truth(robot, rate_hz=200.0), tmp_path,
                     **peer_opts)
    with peer:
        yield peer, lambda: _driver(peer, robot)


def _driver(peer: Any, robot: Robot) -> Driver:
    driver = registry.make_driver(peer.driver_options())
    driver.bind_robot(RobotInfo.of(robot))
    driver.bind_feedforward(_worker)
    return driver


async def _worker(pset: ParameterSet, period_s: float, q: Any) -> FeedforwardTable:
    """What the daemon binds (a FeedforwardJob in a worker process), run here through the
    same door: the job's JSON into the worker's entry point, the table's JSON back."""
    job = FeedforwardJob(str(ARM3), (), pset, period_s, tuple(map(tuple, q)))
    return FeedforwardTable.from_json(await asyncio.to_thread(run, job.to_json()))


async def _cycle(driver: Driver, program: MotionProgram, nonce: str) -> bytes:
    await driver.put_program(program)
    await driver.give_ready("exp1", nonce)
    done = await driver.take_done("exp1", nonce, timeout_s=30)
    return await driver.fetch_logs(done)


def _received(peer: Any) -> tuple[np.ndarray, np.ndarray]:
    """Per SYNC every drive was enabled: targets (rad) and torque offsets (per mille)."""
    per = [{k: (tg, off) for k, tg, off in d.received} for d in peer.drives]
    ks = sorted(set.intersection(*(set(p) for p in per)))
    q = np.array([[per[j][k][0] / peer.cpr[j] for j in range(peer.n)] for k in ks])
    pm = np.array([[per[j][k][1] for j in range(peer.n)] for k in ks])
    assert np.all(np.diff(ks) == 1), "a SYNC without every drive's setpoint"
    return q, pm


def test_uploaded_set_reaches_every_drive_as_torque_offset(tmp_path: Path, robot: Robot,
                                                           program: MotionProgram) -> None:
    doc = parameter_set(robot)
    with drives(tmp_path, robot) as (peer, make):
        driver = make()

        async def go() -> None:
            async with driver:
                await _cycle(driver, program, "n0")  # no set yet: offsets are zero
                assert all(off == 0 for d in peer.drives for _, _, off in d.received)
                await driver.upload_parameters(doc, timeout_s=10)
                for d in peer.drives:
                    d.received.clear()
                await _cycle(driver, program, "n1")

        asyncio.run(go())
        q, pm = _received(peer)
    # the model torque of each setpoint, by Pinocchio's RNEA on the nominal model (the set's
    # inertials) plus the set's friction, from the setpoints the drives received
    h = peer.period
    moving = np.flatnonzero(np.any(pm != 0, axis=1))
    seg = slice(moving[0], len(q))
    qs = q[seg]
    qd = np.gradient(qs, h, axis=0)
    qdd = np.zeros_like(qs)
    qdd[1:-1] = (qs[2:] - 2 * qs[1:-1] + qs[:-2]) / h**2
    rigid = np.array([robot.rnea(*x) for x in zip(qs, qd, qdd, strict=True)])
    tau = rigid + 2.0 * qd + 1.5 * np.sign(qd) * (np.abs(qd) > 1e-6)
    want = tau / np.array(peer.rated) * 1000.0
    err = np.abs(pm[seg] - want)
    # inside the job: within the per-mille quantization; its first/last samples are at rest
    assert err[1:-1].max() <= 0.5 + 1e-6, err.max(axis=0)
    assert np.abs(pm[seg]).max() > 50  # gravity and inertia, not a trivial zero


def test_a_set_in_use_without_a_fitting_table_is_refused_before_motion(
        tmp_path: Path, robot: Robot, program: MotionProgram) -> None:
    """The driver computes no dynamics: with a set in use it streams only a table the worker
    made for exactly its setpoints (rows, joints, set), else the give fails before motion."""
    doc = parameter_set(robot)

    async def short(pset: ParameterSet, period_s: float, q: Any) -> FeedforwardTable:
        return FeedforwardTable(pset.sha256, period_s, tuple((0.0,) * robot.n for _ in q[1:]))

    with drives(tmp_path, robot) as (peer, _):
        async def go() -> None:
            driver = registry.make_driver(peer.driver_options())
            driver.bind_robot(RobotInfo.of(robot))
            async with driver:
                await driver.upload_parameters(doc, timeout_s=10)
                await driver.put_program(program)
                with pytest.raises(DriverError, match="no worker bound to compute it"):
                    await driver.give_ready("exp1", "n1")
                driver.bind_feedforward(short)
                with pytest.raises(DriverError, match="the table answered does not fit"):
                    await driver.give_ready("exp1", "n2")
                driver.bind_feedforward(_worker)
                await driver.give_ready("exp1", "n3")  # nothing was left half-given
                await driver.take_done("exp1", "n3", timeout_s=30)

        asyncio.run(go())


def test_set_kept_by_a_restarted_driver_and_refused_set_changes_nothing(
        tmp_path: Path, robot: Robot) -> None:
    doc = parameter_set(robot)
    bad = {**parameter_set(robot, viscous=9.0), "sha256": doc["sha256"]}  # content ≠ hash
    other = {**parameter_set(robot), "robot": "another"}
    other["sha256"] = set_sha256(other)
    with drives(tmp_path, robot) as (peer, make):
        async def first() -> None:
            async with make() as driver:
                await driver.upload_parameters(doc, timeout_s=10)
                for wrong, why in ((bad, r"damaged \(sha256 mismatch\)"),
                                   (other, "for robot another")):
                    with pytest.raises(DriverError, match=f"parameter set refused: .*{why}"):
                        await driver.upload_parameters(wrong, timeout_s=10)
                assert driver.parameters.sha256 == doc["sha256"]

        async def second() -> str | None:
            async with make() as driver:
                return str(driver.parameters.sha256)

        asyncio.run(first())
        saved = Path(peer.driver_options()["record_dir"]) / "parameters.json"
        assert json.loads(saved.read_bytes())["sha256"] == doc["sha256"]
        assert asyncio.run(second()) == doc["sha256"]


def test_drives_quick_stop_when_the_master_stops_sending_sync(
        tmp_path: Path, robot: Robot, program: MotionProgram) -> None:
    with drives(tmp_path, robot, sync_timeout_s=0.3) as (peer, make):
        driver = make()

        async def go() -> np.ndarray:
            async with driver:
                await driver.put_program(program)
                await driver.give_ready("exp1", "n1")
                await asyncio.sleep(0.6)  # the approach and the program: moving
                v = peer.velocity()
                # the master dies with the daemon (SIGKILL): no SYNC, no setpoint, no ramp
                master, driver.master = driver.master, None
                master.stop()
                end = time.monotonic() + 20
                while set(peer.states().values()) != {"Switch on disabled"}:
                    assert time.monotonic() < end, peer.states()
                    await asyncio.sleep(0.05)
                return v

        v = asyncio.run(go())
        assert np.abs(v).max() > 0.05, v  # it was moving when the SYNC stopped
        assert peer.master_lost == 1
        assert np.all(peer.velocity() == 0.0)


def test_program_over_socketcand_in_process(tmp_path: Path, robot: Robot,
                                            program: MotionProgram) -> None:
    with drives(tmp_path, robot, interface="socketcand") as (peer, make):
        opts = peer.driver_options()
        assert (opts["interface"], opts["host"], opts["channel"]) == ("socketcand",
                                                                      "127.0.0.1", "can0")
        driver = make()

        async def go() -> bytes:
            async with driver:
                return await _cycle(driver, program, "n1")

        data = asyncio.run(go())
        assert peer.server is not None and peer.server.port == opts["port"]
    rows = np.loadtxt(data.decode().splitlines(), delimiter=",", skiprows=1)
    assert rows.shape[1] == 1 + 2 * robot.n and len(rows) > 100


@pytest.mark.parametrize("opts, key", [
    ({"host": "127.0.0.1"}, "driver.host: only for interface socketcand"),
    ({"interface": "socketcand", "port": 29536}, "driver.host"),
    ({"interface": "socketcand", "host": "127.0.0.1"}, "driver.port"),
    ({"interface": "socketcand", "host": "127.0.0.1", "port": 70000}, "driver.port"),
    ({"robot_file": "/nonexistent/arm.yaml"}, "driver.robot_file"),
    # an existing file too: the option is refused, not silently ignored
    ({"robot_file": str(EDS)}, r"driver\.robot_file: no longer used \(.*\); remove it"),
])
def test_socketcand_and_robot_file_options_name_the_key(opts: dict[str, Any], key: str) -> None:
    base = {"nodes": [1, 2, 3], "counts_per_rad": [1e5] * 3, "eds": str(EDS)}
    with pytest.raises(ConfigError, match=key):
        CanopenDrivesDriver(**{**base, **opts})
