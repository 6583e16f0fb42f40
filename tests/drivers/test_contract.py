"""The driver contract, run over every registered driver with its real fake peer (a share, an
HTTP + websocket server, a virtual CAN bus, a Modbus server, a pty pair — each started and
stopped here): the full cycle, timeouts, early, stale and duplicate answers, damaged logs, a
controller that reports failure, unsafe names, the open/close life cycle, config errors."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import hashlib
import importlib.metadata as md
import io
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from robid_link.exceptions import ConfigError, DriverError, DriverTimeoutError
from robid_link.fakes.controller import default_truth, make_peer
from robid_link.ident.model.robot import Robot, load_robot
from robid_link.jobs import MotionProgram, RobotInfo
from robid_link.link import registry
from robid_link.link.driver import Done, Driver

from .conftest import bump_program

ROBOTS = Path(__file__).resolve().parents[2] / "examples" / "robots"
NAMES = sorted(set(registry.available_drivers()) & set(registry.available_peers()))
RATE_HZ = 200.0


@functools.cache
def _robot_of(name: str | None) -> Robot:
    """The contract's robot: arm3, or the one a peer's protocol needs (``contract_robot``:
    a UR controller moves six joints)."""
    cls = registry.peer_class(name) if name else None
    return load_robot(ROBOTS / getattr(cls, "contract_robot", "arm3.yaml"))


def _param(request: pytest.FixtureRequest) -> str | None:
    callspec = getattr(request.node, "callspec", None)
    return callspec.params.get("name") if callspec else None


@pytest.fixture
def robot(request: pytest.FixtureRequest) -> Robot:
    return _robot_of(_param(request))


@pytest.fixture
def program(robot: Robot) -> MotionProgram:
    """The contract suite's program (0.6 s, 5 cm peaks) for the driver's robot."""
    return bump_program(robot, 0.6, 0.05)


def _variants() -> list[Any]:
    """Every driver with its peer, once per protocol variant the peer declares
    (``contract_variants``, e.g. RWS 1.0 and 2.0)."""
    out = []
    for name in NAMES:
        for opts in getattr(registry.peer_class(name), "contract_variants", ({},)):
            tag = "-".join(f"{k}{v}" for k, v in opts.items())
            out.append(pytest.param(name, dict(opts), id=f"{name}-{tag}" if tag else name))
    return out


@contextlib.contextmanager
def cell(name: str, tmp_path: Path, robot: Robot, variant: dict[str, Any] | None = None,
         **kw: Any) -> Iterator[tuple[Driver, Any]]:
    """The driver ``name`` connected to its fake peer (options ``variant``) over arm3."""
    cls = registry.peer_class(name)
    fault = kw.get("fault")
    if fault in getattr(cls, "unsupported", {}):
        pytest.skip(f"{name}: {cls.unsupported[fault]}")
    work = tmp_path / "cell"
    work.mkdir(exist_ok=True)
    peer = make_peer(name, robot, default_truth(robot, rate_hz=RATE_HZ), work,
                     **(variant or {}), **kw)
    with peer:
        driver = registry.make_driver(peer.driver_options())
        driver.bind_robot(RobotInfo.of(robot))
        try:
            yield driver, peer
        finally:
            asyncio.run(driver.close())


def _cycle(driver: Driver, program: MotionProgram, timeout_s: float = 30.0) -> bytes:
    async def go() -> bytes:
        async with driver:
            await driver.put_program(program)
            await driver.give_ready("exp1", "n1")
            await driver.give_ready("exp1", "n1")  # idempotent after a restart
            done = await driver.take_done("exp1", "n1", timeout_s=timeout_s)
            data = await driver.fetch_logs(done)
            await driver.acknowledge(done)
            return data

    return asyncio.run(go())


def _parse(data: bytes) -> np.ndarray:
    """t, q…, τ… of a log in the house layout (speeds, when a link logs them, dropped)."""
    head = data.split(b"\n", 1)[0].decode().split(",")
    n = sum(1 for h in head if h.startswith("tau"))
    q, qd, tau = ([f"{k}{j}" for j in range(1, n + 1)] for k in ("q", "qd", "tau"))
    assert head in (["t", *q, *tau], ["t", *q, *qd, *tau]), head
    arr = np.loadtxt(io.BytesIO(data), delimiter=",", skiprows=1, ndmin=2)
    return np.hstack([arr[:, : 1 + n], arr[:, -n:]])


@pytest.mark.parametrize("name, variant", _variants())
class TestContract:
    def test_full_cycle_brings_back_the_plant_log(self, name: str, variant: dict[str, Any],
                                                  tmp_path: Path,
                                                  robot: Robot, program: MotionProgram) -> None:
        with cell(name, tmp_path, robot, variant) as (driver, peer):
            arr = _parse(_cycle(driver, program))
        assert np.all(np.isfinite(arr))
        # the log spans the 0.6 s program; a link may leave holes (a CAN sample whose TPDO came
        # late under load is dropped, not invented), but not most of it
        span = arr[-1, 0] - arr[0, 0]
        assert span >= 0.5 and arr.shape[0] >= 0.5 * span * RATE_HZ
        assert np.abs(arr[:, 1:4]).max() == pytest.approx(0.05, abs=0.01)  # the program's path
        assert len(peer.core.handled) == 1  # one give, one run

    def test_no_answer_times_out_with_a_clear_error(self, name: str, variant: dict[str, Any],
                                                    tmp_path: Path,
                                                    robot: Robot, program: MotionProgram
                                                    ) -> None:
        with cell(name, tmp_path, robot, variant, fault="never_answer") as (driver, _):
            async def go() -> None:
                async with driver:
                    await driver.put_program(program)
                    await driver.give_ready("exp1", "n1")
                    try:
                        await driver.take_done("exp1", "n1", timeout_s=1.0)
                    finally:
                        await driver.withdraw("exp1", "n1")

            with pytest.raises(DriverTimeoutError, match=r"experiment exp1.*1 s"):
                asyncio.run(go())

    def test_answer_before_take_is_not_missed(self, name: str, variant: dict[str, Any],
                                              tmp_path: Path, robot: Robot,
                                              program: MotionProgram) -> None:
        with cell(name, tmp_path, robot, variant) as (driver, peer):
            async def go() -> Done:
                async with driver:
                    await driver.put_program(program)
                    await driver.give_ready("exp1", "n1")
                    end = time.monotonic() + 30
                    while not peer.core.handled and time.monotonic() < end:
                        await asyncio.sleep(0.02)
                    await asyncio.sleep(1.5)  # the answer is there before anyone waits
                    return await driver.take_done("exp1", "n1", timeout_s=5)

            assert asyncio.run(go()).nonce == "n1"

    @pytest.mark.parametrize("fault", ["stale_semaphore", "answer_twice"])
    def test_stale_and_duplicate_answers_are_ignored(self, name: str, variant: dict[str, Any],
                                                     tmp_path: Path,
                                                     robot: Robot, program: MotionProgram,
                                                     fault: str) -> None:
        """A stale answer (another nonce) shows first, or the answer comes twice: the take
        returns this attempt's own answer, and a duplicate is never taken as the answer of
        the next attempt (a retry under a new nonce runs the program again)."""
        with cell(name, tmp_path, robot, variant, fault=fault) as (driver, peer):
            async def go() -> tuple[Done, bytes, Done, bytes]:
                async with driver:
                    await driver.put_program(program)
                    out: list[Any] = []
                    for nonce in ("n1", "n2"):
                        await driver.give_ready("exp1", nonce)
                        done = await driver.take_done("exp1", nonce, timeout_s=30)
                        out += [done, await driver.fetch_logs(done)]
                        await driver.acknowledge(done)
                    return out[0], out[1], out[2], out[3]

            first, log1, second, log2 = asyncio.run(go())
        assert (first.exp_id, first.nonce, second.nonce) == ("exp1", "n1", "n2")
        for data in (log1, log2):
            arr = _parse(data)
            assert np.all(np.isfinite(arr))
            assert np.abs(arr[:, 1:4]).max() == pytest.approx(0.05, abs=0.01)
        assert len(peer.core.handled) == 2  # the second take waited for the second run

    @pytest.mark.parametrize("fault", ["truncated_log", "corrupt_log"])
    def test_checksum_catches_a_damaged_log(self, name: str, variant: dict[str, Any],
                                            tmp_path: Path, robot: Robot,
                                            program: MotionProgram, fault: str) -> None:
        with cell(name, tmp_path, robot, variant, fault=fault) as (driver, _):
            with pytest.raises(DriverError, match="checksum|truncated|CRC|corrupt"):
                _cycle(driver, program)

    def test_a_reported_failure_is_an_error_not_a_timeout(self, name: str, variant: dict[str, Any],
                                                          tmp_path: Path,
                                                          robot: Robot, program: MotionProgram
                                                          ) -> None:
        with cell(name, tmp_path, robot, variant, fault="fail") as (driver, _):
            t0 = time.monotonic()
            with pytest.raises(DriverError, match="exp1") as err:
                _cycle(driver, program, timeout_s=30)
        assert not isinstance(err.value, DriverTimeoutError)
        assert time.monotonic() - t0 < 25

    @pytest.mark.parametrize("bad", ["../etc", "a.b", "", "x" * 65, "a/b"])
    def test_names_that_could_escape_are_refused(self, name: str, variant: dict[str, Any],
                                                 tmp_path: Path,
                                                 robot: Robot, bad: str) -> None:
        with cell(name, tmp_path, robot, variant) as (driver, _):
            async def go() -> None:
                async with driver:
                    await driver.give_ready(bad, "n1")

            with pytest.raises(DriverError, match="expected 1-64 letters"):
                asyncio.run(go())

    def test_life_cycle(self, name: str, variant: dict[str, Any],
                        tmp_path: Path, robot: Robot) -> None:
        with cell(name, tmp_path, robot, variant) as (driver, _):
            with pytest.raises(DriverError, match="not open"):
                asyncio.run(driver.give_ready("exp1", "n1"))

            async def go() -> None:
                async with driver:
                    pass
                await driver.close()  # twice is safe
                with pytest.raises(DriverError, match="closed"):
                    await driver.open()

            asyncio.run(go())

    def test_unknown_option_names_the_key(self, name: str, variant: dict[str, Any], tmp_path: Path,
                                          robot: Robot) -> None:
        with cell(name, tmp_path, robot, variant) as (_, peer):
            with pytest.raises(ConfigError, match=rf"driver\.colour: unknown option for "
                                                  rf"driver '{name}'"):
                registry.make_driver({**peer.driver_options(), "colour": 1})


def test_every_registered_driver_has_a_fake_peer() -> None:
    assert NAMES and set(registry.available_drivers()) == set(NAMES)


def test_third_party_driver_and_peer_through_entry_points(monkeypatch: pytest.MonkeyPatch
                                                          ) -> None:
    from robid_link.drivers.file_share import FileShareDriver
    from robid_link.fakes.file_share_peer import FileSharePeer

    eps = {registry.ENTRY_POINT_GROUP: [md.EntryPoint(
               "acme", "robid_link.drivers.file_share:FileShareDriver", "robid_link.drivers")],
           registry.PEER_ENTRY_POINT_GROUP: [md.EntryPoint(
               "acme", "robid_link.fakes.file_share_peer:FileSharePeer",
               "robid_link.fake_peers")]}
    monkeypatch.setattr(registry, "entry_points", lambda group: eps[group])
    assert registry.driver_class("acme") is FileShareDriver
    assert registry.peer_class("acme") is FileSharePeer
    bad = md.EntryPoint("broken", "no_such_module:X", "robid_link.drivers")
    monkeypatch.setattr(registry, "entry_points", lambda group: [bad])
    with pytest.raises(ConfigError, match="driver 'broken' cannot be imported"):
        registry.driver_class("broken")


def test_a_missing_library_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    import importlib

    real = importlib.import_module

    def fake_import(name: str, *a: Any) -> Any:
        if name == "robid_link.drivers.file_share":
            raise ModuleNotFoundError("No module named 'can'", name="can")
        return real(name, *a)

    monkeypatch.setattr(registry.importlib, "import_module", fake_import)
    monkeypatch.setitem(registry.BUILTIN_DRIVERS, "file_share",
                        ("robid_link.drivers.file_share:FileShareDriver", "can"))
    with pytest.raises(ConfigError, match=r"driver 'file_share' cannot be imported \(can\); "
                                          r"install it with: pip install 'robid_link\[can\]'"):
        registry.driver_class("file_share")


def test_log_checksum_of_the_core_is_the_true_log(robot: Robot, program: MotionProgram,
                                                  tmp_path: Path) -> None:
    peer = make_peer("file_share", robot, default_truth(robot, rate_hz=RATE_HZ), tmp_path,
                     fault="corrupt_log")
    res = peer.core.run("exp1", "n1", program.files["traj.csv"], program.files["traj.yaml"])
    assert res.sha256 == hashlib.sha256(res.log).hexdigest() and res.delivered != res.log
