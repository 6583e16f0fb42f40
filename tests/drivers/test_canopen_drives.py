"""The CANopen driver over its fake CiA 402 drives (python-can's virtual bus, in-process):
every fault stops every drive (quick stop / disabled / fault), fails the experiment with one
line naming node, joint and cause, and keeps the log captured so far; bad config names the key;
closing while streaming ramps to rest."""

from __future__ import annotations

import asyncio
import collections
import contextlib
import gc
import os
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest

from robid_link.drivers.canopen.drives import CanopenDrivesDriver
from robid_link.drivers.canopen.realtime import ProcessHold
from robid_link.exceptions import ConfigError, DriverError
from robid_link.fakes.canopen.peer import EDS
from robid_link.fakes.controller import default_truth, make_peer
from robid_link.ident.excite import excitation as ex
from robid_link.ident.excite import program as pg
from robid_link.ident.model.robot import Robot
from robid_link.jobs import MotionProgram, RobotInfo
from robid_link.link import registry
from robid_link.link.driver import Driver

from .conftest import bump_program

ARM3 = Path(__file__).resolve().parents[2] / "examples" / "robots" / "arm3.yaml"
STOPPED = {"Quick stop active", "Switch on disabled", "Fault", "Ready to switch on"}


@pytest.fixture(scope="module")
def program(robot: Robot) -> MotionProgram:
    """1.5 s, up to 0.5 rad: long and wide enough for every fault to strike mid-motion."""
    return bump_program(robot, 1.5, 0.5)


@contextlib.contextmanager
def drives(tmp_path: Path, robot: Robot, fault: str | None = None,
           peer_opts: dict[str, Any] | None = None, **opts: Any
           ) -> Iterator[tuple[Driver, Any]]:
    peer = make_peer("canopen_drives", robot, default_truth(robot, rate_hz=200.0), tmp_path,
                     fault=fault, **(peer_opts or {}))
    with peer:
        driver = registry.make_driver({**peer.driver_options(), **opts})
        driver.bind_robot(RobotInfo.of(robot))
        try:
            yield driver, peer
        finally:
            asyncio.run(driver.close())


def _run(driver: Driver, program: MotionProgram, before_take: Any = None) -> bytes:
    async def go() -> bytes:
        async with driver:
            await driver.put_program(program)
            await driver.give_ready("exp1", "n1")
            if before_take is not None:
                before_take(driver)
            done = await driver.take_done("exp1", "n1", timeout_s=30)
            return await driver.fetch_logs(done)

    return asyncio.run(go())


def _partial(err: pytest.ExceptionInfo[DriverError]) -> np.ndarray:
    path = Path(str(err.value).split("kept as ")[1].split(" (")[0])
    assert path.name == "exp1.n1.partial.csv" and path.with_suffix(".blf").exists()
    return np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)


@pytest.mark.parametrize("fault, cause", [
    ("drive_fault", r"node 2 \(joint 2 j2\): drive fault \(EMCY 0x2310 continuous "
                    r"over-current\), error code 0x603F = 0x2310 continuous over-current"),
    # the EMCY lost: 0x603F, read by SDO after the stop, still names the cause
    ("drive_fault_quiet", r"node 2 \(joint 2 j2\): drive fault \(no EMCY received\), error "
                          r"code 0x603F = 0x2310 continuous over-current"),
    # a hostile bus: another sender on node 3's TPDO1 COB-ID, a TPDO mapped otherwise
    ("foreign_tpdo", r"node 3 \(joint 3 j3\): two different TPDO1 for SYNC \d+ .*not this "
                     r"drive's answer \(another node on its COB-ID"),
    ("bad_length", r"node 2 \(joint 2 j2\): TPDO2 of \d bytes, \d mapped: not this drive's "
                   r"answer"),
    ("heartbeat_loss", r"node 2 \(joint 2 j2\): lost heartbeat"),
    ("following_error", r"node 2 \(joint 2 j2\): following error .* rad beyond the window"),
    ("dropped_frames", r"node 2 \(joint 2 j2\): no TPDO for \d+ SYNC periods"),
    ("die", r"node \d \(joint \d j\d\): no TPDO for \d+ SYNC periods"),
])
def test_a_fault_mid_motion_stops_every_drive_and_keeps_the_log(
        tmp_path: Path, robot: Robot, program: MotionProgram, fault: str, cause: str) -> None:
    opts = {"heartbeat_timeout_s": 0.5} if fault == "heartbeat_loss" else {}
    if fault in ("dropped_frames", "die"):
        opts = {"max_missed": 10, "heartbeat_timeout_s": 5.0}
    with drives(tmp_path, robot, fault, **opts) as (driver, peer):
        with pytest.raises(DriverError, match=rf"experiment exp1: {cause}.*quick stop on every "
                                               r"drive; log captured so far kept as .*incomplete"
                           ) as err:
            _run(driver, program)
        time.sleep(0.3)  # the quick stop ramp of the fake axes
        states = peer.states()
    rows = _partial(err)
    assert len(rows) > 20 and np.all(np.isfinite(rows))  # what was captured before the stop
    if fault != "die":
        assert set(states.values()) <= STOPPED, states


def test_late_answers_are_logged_at_their_own_sync(tmp_path: Path, robot: Robot,
                                                   program: MotionProgram,
                                                   caplog: pytest.LogCaptureFixture) -> None:
    """TPDOs up to 12 periods late and bunched (a loaded socketcand host): the log is the one a
    prompt bus gives, row for row. The answers carry their SYNC's counter; when they arrive
    counts for nothing (it once paired positions and torques of different SYNCs)."""
    logs = {}
    for lag in (0, 12):
        (tmp_path / f"lag{lag}").mkdir()
        with drives(tmp_path / f"lag{lag}", robot, peer_opts={"answer_lag_periods": lag}
                    ) as (driver, _):
            logs[lag] = np.loadtxt(_run(driver, program).decode().splitlines(), delimiter=",",
                                   skiprows=1, ndmin=2)
    prompt, late = logs[0], logs[12]
    n = robot.n
    assert "without every drive's answer" not in caplog.text  # no gaps
    # the end too: standstill is counted per answered SYNC (batched answers once never gave
    # three fresh ticks in a row: a quick stop at rest) and the job ends with every row that
    # came in (a batch may bring a few more rows at rest)
    assert np.all(np.diff(late[:, 0]) > 0) and len(prompt) <= len(late) <= len(prompt) + 12
    common = len(prompt)
    np.testing.assert_array_equal(late[:common, : 1 + n], prompt[:common, : 1 + n])
    # the torques differ by the noise only (same seed, drawn per SYNC since the drives started)
    spread = np.std(late[:common, 1 + n:] - prompt[:common, 1 + n:], axis=0)
    assert np.all(spread < 3.0 * np.sqrt(2.0) * 0.2 + 1e-9), spread


def test_a_node_that_never_boots_is_named_at_open(tmp_path: Path, robot: Robot) -> None:
    with drives(tmp_path, robot, "no_boot", boot_timeout_s=0.5) as (driver, peer):
        with pytest.raises(DriverError, match=r"node 2 \(joint 2 j2\): no boot-up or heartbeat "
                                              r"within 0.5 s"):
            asyncio.run(driver.open())
        assert peer.states()[1] == "Switch on disabled"  # nothing was enabled


def test_sync_overrun_streak_quick_stops(tmp_path: Path, robot: Robot,
                                         program: MotionProgram,
                                         caplog: pytest.LogCaptureFixture) -> None:
    """Every overrun is counted and the first ones logged; a streak stops every drive."""
    masters = []
    with drives(tmp_path, robot, overrun_streak=3) as (driver, peer):
        def slow_host(d: Driver) -> None:
            assert isinstance(d, CanopenDrivesDriver) and d.master is not None
            masters.append(d.master)
            d.master.tick_hook = lambda: time.sleep(0.02)

        with pytest.raises(DriverError, match=r"experiment exp1: bus: SYNC overrun: 3 periods "
                                              r"in a row late.*kept as"):
            _run(driver, program, slow_host)
    assert masters[0].overruns >= 3 and masters[0].worst_late_s > 0.01
    assert any(r.getMessage().startswith("SYNC overrun: ") and "(1 overruns so far"
               in r.getMessage() for r in caplog.records)


def test_sync_priority_puts_the_motion_path_under_sched_fifo(
        tmp_path: Path, robot: Robot, program: MotionProgram,
        caplog: pytest.LogCaptureFixture) -> None:
    """``sync_priority``: the SYNC thread and the CAN receive thread run under SCHED_FIFO at
    it, the BLF recorder and the log writer one below; the fake drives' threads (SYNC
    handling, heartbeat producers, SYNC supervision) at their ``rt_priority``. Where the
    process may not, each motion path thread says so in one warning line and runs as before."""
    allowed: list[bool] = []

    def probe() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
            allowed.append(True)
        except OSError:
            allowed.append(False)

    t = threading.Thread(target=probe)
    t.start()
    t.join()
    with drives(tmp_path, robot, peer_opts={"rt_priority": 3}, sync_priority=2) as (driver, _):
        async def go() -> tuple[str, collections.Counter[tuple[str, int]]]:
            async with driver:
                await driver.put_program(program)
                await driver.give_ready("exp1", "n1")
                await driver.take_done("exp1", "n1", timeout_s=30)  # the writer wrote its log
                assert isinstance(driver, CanopenDrivesDriver) and driver.master is not None
                return driver.master.scheduling, _fifo_threads()

        scheduling, fifo = asyncio.run(go())
    if allowed[0]:
        assert scheduling == "SCHED_FIFO 2"
        assert fifo["canopen-sync-master", 2] == fifo["canopen-blf", 1] == 1
        assert fifo["ThreadPoolExecutor-canopen_0", 1] == 1  # the log writer
        assert fifo["Notifier", 2] == fifo["Notifier", 3] == 1  # ours, the drives'
        assert fifo["Cyclic send task", 3] >= robot.n  # each drive's heartbeat producer
        assert fifo["cia402-sync-watch", 3] == 1
    else:
        assert scheduling == "normal" and not fifo
        assert any("driver.sync_priority: SCHED_FIFO 2 refused" in r.getMessage()
                   for r in caplog.records)


def test_process_hold_freezes_the_heap_shortens_the_switch_interval_and_restores() -> None:
    """A ProcessHold freezes the heap (gc.freeze) and lowers the GIL switch interval to its
    own; holds nest (the shortest interval wins, the last release unfreezes and restores the
    interval from before); a second hold or release of the same one changes nothing."""
    gc.unfreeze()  # a clean slate: a CLI run in this process may have frozen the heap
    before = sys.getswitchinterval()
    first, second = ProcessHold(0.001), ProcessHold(0.00025)
    try:
        first.hold()
        first.hold()
        frozen = gc.get_freeze_count()
        assert frozen > 1000 and sys.getswitchinterval() == pytest.approx(0.001)
        second.hold()
        assert sys.getswitchinterval() == pytest.approx(0.00025)
        first.release()
        first.release()
        # the second still holds (a frozen object that dies leaves the count: not an exact one)
        assert gc.get_freeze_count() > frozen // 2
        assert sys.getswitchinterval() == pytest.approx(0.00025)
        second.release()
        assert gc.get_freeze_count() == 0 and sys.getswitchinterval() == before
        second.release()
        assert gc.get_freeze_count() == 0 and sys.getswitchinterval() == before
    finally:  # a failure above must not leave the process held for the tests after it
        first.release()
        second.release()


def test_process_hold_leaves_an_interval_set_by_someone_else() -> None:
    """An interval another part of the process set while the hold was in force stands."""
    before = sys.getswitchinterval()
    hold = ProcessHold(0.001)
    hold.hold()
    sys.setswitchinterval(0.002)
    try:
        hold.release()
        assert sys.getswitchinterval() == pytest.approx(0.002)
    finally:
        sys.setswitchinterval(before)


def test_process_held_while_the_master_runs(tmp_path: Path, robot: Robot) -> None:
    """While the driver is open what was alive when the SYNC started is out of the collector's
    reach (a full collection would walk it all, holding the GIL for 40–100 ms) and the switch
    interval is a quarter SYNC period; once closed, closing twice included, both are back."""
    gc.unfreeze()  # a clean slate: a CLI run in this process may have frozen the heap
    before = sys.getswitchinterval()
    with drives(tmp_path, robot) as (driver, peer):
        async def go() -> tuple[int, float]:
            async with driver:
                held = gc.get_freeze_count(), sys.getswitchinterval()
            await driver.close()
            return held

        frozen, interval = asyncio.run(go())
    assert frozen > 1000 and interval == pytest.approx(peer.period / 4)
    assert gc.get_freeze_count() == 0 and sys.getswitchinterval() == before


def _fifo_threads() -> collections.Counter[tuple[str, int]]:
    """How many SCHED_FIFO threads per (name up to ' for', priority)."""
    out: collections.Counter[tuple[str, int]] = collections.Counter()
    for th in threading.enumerate():
        if th.native_id is not None and _policy(str(th.native_id)) == os.SCHED_FIFO:
            with contextlib.suppress(OSError):  # the thread ended meanwhile
                out[th.name.split(" for ")[0],
                    os.sched_getparam(th.native_id).sched_priority] += 1
    return out


def _policy(tid: str) -> int:
    try:
        return os.sched_getscheduler(int(tid))
    except OSError:  # the thread ended meanwhile
        return -1


def test_bus_error_quick_stops(tmp_path: Path, robot: Robot, program: MotionProgram,
                               monkeypatch: pytest.MonkeyPatch) -> None:
    with drives(tmp_path, robot) as (driver, _):
        def bus_off(d: Driver) -> None:
            assert isinstance(d, CanopenDrivesDriver) and d.network is not None
            bus = d.network.bus
            real = bus.send
            calls = {"n": 0}

            def send(msg: can.Message, timeout: float | None = None) -> None:
                calls["n"] += 1
                if 200 < calls["n"] < 260:
                    raise can.CanOperationError("Network is down (bus-off)")
                real(msg, timeout)

            monkeypatch.setattr(bus, "send", send)

        with pytest.raises(DriverError, match=r"bus: CAN bus error .*bus-off"):
            _run(driver, program, bus_off)


def test_full_run_and_idempotent_give(tmp_path: Path, robot: Robot,
                                      program: MotionProgram) -> None:
    with drives(tmp_path, robot) as (driver, peer):
        data = _run(driver, program)
        records = sorted(p.name for p in (tmp_path / "records").iterdir())
    arr = np.loadtxt(data.decode().splitlines()[1:], delimiter=",")
    assert np.abs(arr[:, 1]).max() == pytest.approx(0.5, abs=0.01)
    assert abs(arr[-1, 1]) < 1e-3  # ends at rest where the program ends
    assert records == ["exp1.n1.blf", "exp1.n1.log.csv"] and len(peer.core.handled) == 1
    frames = list(can.BLFReader(str(tmp_path / "records" / "exp1.n1.blf")))
    assert {0x80, 0x201, 0x181, 0x281} <= {f.arbitration_id for f in frames}


def test_close_while_streaming_ramps_to_rest(tmp_path: Path, robot: Robot,
                                             program: MotionProgram) -> None:
    with drives(tmp_path, robot) as (driver, peer):
        async def go() -> None:
            async with driver:
                await driver.put_program(program)
                await driver.give_ready("exp1", "n1")
                await asyncio.sleep(0.6)  # mid-motion: SIGTERM closes the driver

        asyncio.run(go())
        states = peer.states()
        hist = peer.hist.copy()
    assert set(states.values()) == {"Ready to switch on"}, states  # disabled after the ramp
    assert np.allclose(hist[-1], hist[-2])  # at rest
    assert (tmp_path / "records" / "exp1.n1.partial.csv").exists()


def test_unsafe_program_refused_before_motion(tmp_path: Path, robot: Robot) -> None:
    t = np.arange(0.0, 1.0, 0.01)
    q = np.zeros((t.size, 3))
    q[:, 0] = 3.0 * t  # starts moving at 3 rad/s
    prog = MotionProgram("exp1", pg.trajectory_files(
        ex.Trajectory(t, q, 100.0, "custom", robot.name)), 1.0)
    with drives(tmp_path, robot) as (driver, peer):
        async def go() -> None:
            async with driver:
                await driver.put_program(prog)

        with pytest.raises(DriverError, match=r"unsafe program refused: experiment exp1: joint 1 "
                                              r"starts moving"):
            asyncio.run(go())
        assert not peer.core.handled


def _options(**over: Any) -> dict[str, Any]:
    base = {"name": "canopen_drives", "interface": "virtual", "channel": "x", "nodes": [1, 2, 3],
            "counts_per_rad": [1000.0] * 3, "rated_torque_nm": [10.0] * 3, "eds": str(EDS)}
    return {**base, **over}


@pytest.mark.parametrize("over, key", [
    ({"nodes": [1, 200, 3]}, r"driver\.nodes\[1\]: expected a node id in 1\.\.127"),
    ({"nodes": [1, 1, 3]}, r"driver\.nodes: expected a list without repeated values"),
    ({"eds": "/nonexistent/drives.eds"}, r"driver\.eds: .*file not found"),
    ({"eds": None}, r"driver\.eds: missing"),
    ({"sync_period_s": 0.0005}, r"driver\.sync_period_s: expected a number in \[0\.001"),
    ({"counts_per_rad": [1000.0, -1.0, 3.0]}, r"driver\.counts_per_rad\[1\]"),
    ({"bitrate": "fast"}, r"driver\.bitrate"),
    ({"sync_echo": "0x6041:0"}, r"driver\.sync_echo: expected a manufacturer-specific object"),
    ({"sync_echo": "echo"}, r"driver\.sync_echo: expected .*'echo'"),
    ({"max_missed": 500}, r"driver\.max_missed: expected an integer in \[1, 200\]"),
    ({"sync_priority": 100}, r"driver\.sync_priority: expected an integer in \[0, 99\]"),
])
def test_bad_config_names_the_key(over: dict[str, Any], key: str) -> None:
    with pytest.raises(ConfigError, match=key):
        registry.make_driver(_options(**over))


@pytest.mark.parametrize("over, key", [
    ({"nodes": [1, 2]}, r"driver\.nodes: 2 values, robot arm3 has 3 joints"),
    ({"counts_per_rad": [1000.0] * 4}, r"driver\.counts_per_rad: 4 values, robot arm3 has 3"),
    ({"rated_torque_nm": [1.0] * 2}, r"driver\.rated_torque_nm: 2 values"),
    ({"counts_per_rad": [1e12] * 3}, r"driver\.counts_per_rad\[0\]: joint 1 .* 32-bit"),
])
def test_unit_vectors_are_checked_against_the_robot(robot: Robot, over: dict[str, Any],
                                                    key: str) -> None:
    driver = registry.make_driver(_options(**over))
    with pytest.raises(ConfigError, match=key):
        driver.bind_robot(RobotInfo.of(robot))
