"""The driver contract, run against every registered driver with its fake peer; the file-share
protocol's details (early answers, stale and duplicate semaphores, checksums, observers)."""

from __future__ import annotations

import asyncio
import hashlib
import os
from pathlib import Path
from typing import Any

import pytest
from robid_link.drivers.file_share import FileShareDriver, parse_sem

from robid_link.exceptions import ConfigError, DriverError, DriverTimeoutError
from robid_link.link.driver import Done, Driver, MotionProgram
from robid_link.link.registry import available_drivers, driver_class, make_driver

PROGRAM_CSV = b"t,q1,q2,q3\n0,0,0,0\n0.01,0.001,0,0\n"


def _program(exp_id: str = "exp1") -> MotionProgram:
    import yaml

    files = {"traj.csv": PROGRAM_CSV,
             "traj.yaml": yaml.safe_dump({"robot": "arm3", "rate_hz": 100.0,
                                          "kind": "custom"}).encode()}
    return MotionProgram(exp_id, files, 0.01)


class _Peer:
    """Controller side written by hand (no plant): answers one experiment on demand."""

    def __init__(self, share: Path) -> None:
        self.share = share

    def answer(self, exp_id: str, nonce: str, data: bytes = b"t,q1\n0,1\n",
               sha: str | None = None) -> None:
        from robid_link.link.atomic import atomic_write

        atomic_write(self.share / "outbox" / f"{exp_id}.{nonce}.log.csv", data)
        sha = sha or hashlib.sha256(data).hexdigest()
        atomic_write(self.share / "sem" / f"{exp_id}.{nonce}.done",
                     f"{sha} size={len(data)}\n".encode())


def _file_share(tmp_path: Path, **kw: Any) -> tuple[Driver, _Peer]:
    share = tmp_path / "share"
    share.mkdir(exist_ok=True)
    kw.setdefault("canary_interval_s", 0)
    return FileShareDriver(share=share, **kw), _Peer(share)


DRIVERS = {"file_share": _file_share}


@pytest.fixture(params=sorted(DRIVERS))
def pair(request: pytest.FixtureRequest, tmp_path: Path) -> tuple[Driver, _Peer]:
    return DRIVERS[request.param](tmp_path)


def test_every_registered_driver_has_a_contract_fake() -> None:
    assert set(available_drivers()) <= set(DRIVERS) | {"fake"}


@pytest.mark.parametrize("name", sorted(available_drivers()))
def test_registry_drivers_open_and_close_cleanly(name: str, tmp_path: Path) -> None:
    driver, _ = DRIVERS[name](tmp_path)
    assert isinstance(driver, driver_class(name))

    async def go() -> None:
        async with driver:
            pass
        await driver.close()  # twice is safe
        with pytest.raises(DriverError, match="closed"):
            await driver.open()

    asyncio.run(go())


class TestContract:
    def test_full_cycle(self, pair: tuple[Driver, _Peer]) -> None:
        driver, peer = pair
        data = b"t,q1,q2,q3,tau1,tau2,tau3\n0,0,0,0,1,2,3\n"

        async def go() -> bytes:
            async with driver:
                await driver.put_program(_program())
                await driver.give_ready("exp1", "n1")
                await driver.give_ready("exp1", "n1")  # idempotent after a restart
                loop = asyncio.get_running_loop()
                loop.call_later(0.05, peer.answer, "exp1", "n1", data)
                done = await driver.take_done("exp1", "n1", timeout_s=10)
                out = await driver.fetch_logs(done)
                await driver.acknowledge(done)
                return out

        assert asyncio.run(go()) == data

    def test_take_times_out_with_a_clear_error(self, pair: tuple[Driver, _Peer]) -> None:
        driver, _ = pair

        async def go() -> None:
            async with driver:
                await driver.give_ready("exp1", "n1")
                await driver.take_done("exp1", "n1", timeout_s=0.2)

        with pytest.raises(DriverTimeoutError, match=r"no 'done' for experiment exp1.*0\.2 s"):
            asyncio.run(go())

    def test_answer_before_take_is_not_missed(self, pair: tuple[Driver, _Peer]) -> None:
        driver, peer = pair

        async def go() -> Done:
            async with driver:
                await driver.give_ready("exp1", "n1")
                peer.answer("exp1", "n1")
                return await driver.take_done("exp1", "n1", timeout_s=2)

        assert asyncio.run(go()).nonce == "n1"

    @pytest.mark.parametrize("damage", ["truncated", "corrupt"])
    def test_checksum_catches_a_damaged_log(self, pair: tuple[Driver, _Peer],
                                            damage: str) -> None:
        driver, peer = pair
        data = b"t,q1\n0,1\n1,2\n"

        async def go() -> None:
            async with driver:
                good = hashlib.sha256(data).hexdigest()
                bad = data[:5] if damage == "truncated" else data.replace(b"2", b"3")
                peer.answer("exp1", "n1", bad, sha=good)
                done = await driver.take_done("exp1", "n1", timeout_s=2)
                await driver.fetch_logs(done)

        with pytest.raises(DriverError, match="checksum|truncated"):
            asyncio.run(go())

    @pytest.mark.parametrize("bad", ["../etc", "a.b", "", "x" * 65, "a/b"])
    def test_names_that_could_escape_are_refused(self, pair: tuple[Driver, _Peer],
                                                 bad: str) -> None:
        driver, _ = pair

        async def go() -> None:
            async with driver:
                await driver.give_ready(bad, "n1")

        with pytest.raises(DriverError, match="expected 1-64 letters"):
            asyncio.run(go())

    def test_methods_need_an_open_driver(self, pair: tuple[Driver, _Peer]) -> None:
        driver, _ = pair
        with pytest.raises(DriverError, match="not open"):
            asyncio.run(driver.give_ready("exp1", "n1"))


def test_stale_and_duplicate_semaphores_are_ignored(tmp_path: Path,
                                                    caplog: pytest.LogCaptureFixture) -> None:
    driver, peer = _file_share(tmp_path)

    async def go() -> Done:
        async with driver:
            await driver.give_ready("exp1", "new")
            waiter = asyncio.create_task(driver.take_done("exp1", "new", timeout_s=5))
            await asyncio.sleep(0.1)
            peer.answer("exp1", "old", b"stale\n")  # another attempt's late answer
            await asyncio.sleep(0.2)
            assert not waiter.done()
            peer.answer("exp1", "new", b"fresh\n")
            done = await waiter
            peer.answer("exp1", "new", b"fresh\n")  # answered twice
            await asyncio.sleep(0.2)
            return done

    with caplog.at_level("WARNING", logger="robid.driver.file_share"):
        done = asyncio.run(go())
    assert done.sha256 == hashlib.sha256(b"fresh\n").hexdigest()
    assert "stale_semaphore=exp1.old.done" in caplog.text
    assert "duplicate_semaphore=exp1.new.done" in caplog.text


@pytest.mark.parametrize("semaphore, text, message", [
    ("exp1.n1.failed", "joint 2 collision stop\n",
     "experiment exp1 failed: joint 2 collision stop"),  # the controller reports a failure
    ("exp1.n1.done", "not a checksum\n", "does not start with the log's SHA-256"),
])
def test_failed_or_malformed_answer_is_an_error(tmp_path: Path, semaphore: str, text: str,
                                                message: str) -> None:
    driver, peer = _file_share(tmp_path)

    async def go() -> None:
        async with driver:
            (peer.share / "sem" / semaphore).write_text(text)
            await driver.take_done("exp1", "n1", timeout_s=2)

    with pytest.raises(DriverError, match=message):
        asyncio.run(go())


def test_program_files_are_written_atomically(tmp_path: Path) -> None:
    driver, peer = _file_share(tmp_path)

    async def go() -> None:
        async with driver:
            await driver.put_program(_program())
            await driver.give_ready("exp1", "n1")

    asyncio.run(go())
    inbox = sorted(os.listdir(peer.share / "inbox"))
    assert inbox == ["exp1.traj.csv", "exp1.traj.yaml"]  # no temp file left behind
    assert (peer.share / "inbox" / "exp1.traj.csv").read_bytes() == PROGRAM_CSV
    assert parse_sem(os.listdir(peer.share / "sem")[0]) == ("exp1", "n1", "ready")


@pytest.mark.parametrize("observer", ["polling", "inotify"])
def test_both_observers_deliver(tmp_path: Path, observer: str) -> None:
    driver, peer = _file_share(tmp_path, observer=observer, poll_interval_s=0.02)

    async def go() -> str:
        async with driver:
            asyncio.get_running_loop().call_later(0.1, peer.answer, "exp1", "n1")
            await driver.take_done("exp1", "n1", timeout_s=5)
            return driver.observer_kind  # type: ignore[attr-defined]

    assert asyncio.run(go()) == observer


def test_network_share_picks_polling(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import robid_link.drivers.file_share as fs

    monkeypatch.setattr(fs, "network_fs", lambda path: "nfs4")
    driver, _ = _file_share(tmp_path)

    async def go() -> str:
        async with driver:
            return driver.observer_kind  # type: ignore[attr-defined]

    assert asyncio.run(go()) == "polling"


def test_canary_falls_back_to_polling_when_events_stop(tmp_path: Path) -> None:
    driver, peer = _file_share(tmp_path, observer="inotify", canary_interval_s=0.1,
                               canary_timeout_s=0.3, poll_interval_s=0.02)

    async def go() -> str:
        async with driver:
            assert driver.observer_kind == "inotify"  # type: ignore[attr-defined]
            driver._observer.unschedule_all()  # type: ignore[attr-defined]  # inotify goes deaf
            await asyncio.sleep(0.8)
            peer.answer("exp1", "n1")
            await driver.take_done("exp1", "n1", timeout_s=3)
            return driver.observer_kind  # type: ignore[attr-defined]

    assert asyncio.run(go()) == "polling"


def test_missing_share_and_bad_options(tmp_path: Path) -> None:
    with pytest.raises(DriverError, match="shared folder not found"):
        asyncio.run(FileShareDriver(share=tmp_path / "nope").open())
    with pytest.raises(ConfigError, match="driver.share: missing"):
        make_driver({"name": "file_share"})
    with pytest.raises(ConfigError, match="driver.colour: unknown option"):
        make_driver({"name": "file_share", "share": str(tmp_path), "colour": 1})
    with pytest.raises(ConfigError, match="driver.name: unknown driver 'ethercat'"):
        make_driver({"name": "ethercat"})
    with pytest.raises(ConfigError, match="driver.observer"):
        make_driver({"name": "file_share", "share": str(tmp_path), "observer": "magic"})


def test_third_party_driver_through_entry_points(monkeypatch: pytest.MonkeyPatch) -> None:
    import importlib.metadata as md

    from robid_link.link import registry

    target = "robid_link.drivers.file_share:FileShareDriver"
    ep = md.EntryPoint("acme", target, "robid_link.drivers")
    monkeypatch.setattr(registry, "entry_points", lambda group: [ep])
    assert registry.available_drivers()["acme"] == target
    assert registry.driver_class("acme") is FileShareDriver
    bad = md.EntryPoint("broken", "no_such_module:X", "robid_link.drivers")
    monkeypatch.setattr(registry, "entry_points", lambda group: [bad])
    with pytest.raises(ConfigError, match="driver 'broken' cannot be imported"):
        registry.driver_class("broken")
