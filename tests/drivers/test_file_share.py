"""The file-share protocol's details on the share itself (stale and duplicate semaphores,
malformed answers, atomic program files, observers, the canary); the contract over every
driver with its real peer is in ``test_contract.py``."""

from __future__ import annotations

import asyncio
import hashlib
import os
from pathlib import Path
from typing import Any

import pytest

from robid_link.drivers.file_share import FileShareDriver, parse_sem
from robid_link.exceptions import ConfigError, DriverError, DriverTimeoutError
from robid_link.jobs import MotionProgram
from robid_link.link.driver import Done, Driver
from robid_link.link.registry import make_driver

PROGRAM_CSV = b"t,q1,q2,q3\n0,0,0,0\n0.01,0.001,0,0\n"


def _program(exp_id: str = "exp1") -> MotionProgram:
    import yaml

    files = {"traj.csv": PROGRAM_CSV,
             "traj.yaml": yaml.safe_dump({"robot": "arm3", "rate_hz": 100.0, "kind": "custom",
                                          "joint_types": ["revolute"] * 3}).encode()}
    return MotionProgram(exp_id, files, 0.01)


class _Peer:
    """Controller side written by hand (no plant): answers one experiment on demand."""

    def __init__(self, share: Path) -> None:
        self.share = share

    def answer(self, exp_id: str, nonce: str, data: bytes = b"t,q1\n0,1\n",
               sha: str | None = None) -> None:
        from robid_link.atomic import atomic_write

        atomic_write(self.share / "outbox" / f"{exp_id}.{nonce}.log.csv", data)
        sha = sha or hashlib.sha256(data).hexdigest()
        atomic_write(self.share / "sem" / f"{exp_id}.{nonce}.done",
                     f"{sha} size={len(data)}\n".encode())


def _file_share(tmp_path: Path, **kw: Any) -> tuple[Driver, _Peer]:
    share = tmp_path / "share"
    share.mkdir(exist_ok=True)
    kw.setdefault("canary_interval_s", 0)
    return FileShareDriver(share=share, **kw), _Peer(share)


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
    # no temp file left behind; RAPID rendered by the driver beside the neutral trajectory
    assert inbox == ["exp1.mod", "exp1.traj.csv", "exp1.traj.yaml"]
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


def _param_cell(tmp_path: Path, **kw: Any) -> tuple[FileShareDriver, Any, dict[str, Any]]:
    from robid_link.fakes.controller import default_truth, make_peer
    from robid_link.ident.fit.paramset import make_parameter_set
    from robid_link.ident.model.robot import load_robot

    robot = load_robot(Path(__file__).resolve().parents[2] / "examples/robots/arm3.yaml")
    share = tmp_path / "share"
    share.mkdir()
    peer = make_peer("file_share", robot, default_truth(robot), share, poll_s=0.005, **kw)
    names = [f"{p}_{j}" for p in ("fv", "fc") for j in (1, 2, 3)]
    doc = make_parameter_set(robot, {"effects": ["viscous", "coulomb"], "parameters": [
        {"name": n, "value": 1.0 + k, "std": 0.1, "expression": n}
        for k, n in enumerate(names)]}, run_id="run1")
    return FileShareDriver(share=share, canary_interval_s=0), peer, doc


def test_upload_parameters_is_loaded_and_acknowledged(tmp_path: Path) -> None:
    from robid_link.link.driver import parameter_bytes

    driver, peer, doc = _param_cell(tmp_path)

    async def go() -> None:
        async with driver:
            await driver.upload_parameters(doc, timeout_s=10)

    with peer:
        asyncio.run(go())
    assert peer.core.feedforward.sha256 == doc["sha256"]
    assert list(peer.core.feedforward.viscous) == [1.0, 2.0, 3.0]
    files = list((peer.share / "params").iterdir())
    assert [f.read_bytes() for f in files] == [parameter_bytes(doc)]  # atomically, exactly
    assert os.listdir(peer.share / "sem") == []  # acknowledged: semaphores cleaned


def test_an_unacknowledged_upload_times_out_and_is_withdrawn(tmp_path: Path) -> None:
    driver, peer, doc = _param_cell(tmp_path, fault="no_param_ack")

    async def go() -> None:
        async with driver:
            await driver.upload_parameters(doc, timeout_s=0.5)

    with peer, pytest.raises(DriverTimeoutError, match=r"did not acknowledge parameter set "
                                                       r"\w{12} within 0\.5 s; withdrawn, it "
                                                       r"keeps its previous set"):
        asyncio.run(go())
    assert peer.core.feedforward is None  # the controller kept what it had
    assert os.listdir(peer.share / "sem") == [] and os.listdir(peer.share / "params") == []


def test_a_parameter_set_the_controller_refuses_is_an_error(tmp_path: Path) -> None:
    driver, peer, doc = _param_cell(tmp_path)
    bad = {**doc, "friction": {"viscous": [1.0]}}  # damaged: its hash no longer fits

    async def go() -> None:
        async with driver:
            await driver.upload_parameters(bad, timeout_s=10)

    with peer, pytest.raises(DriverError, match=r"damaged \(sha256 mismatch\)"):
        asyncio.run(go())
    assert peer.core.feedforward is None


def test_upload_needs_the_capability(tmp_path: Path) -> None:
    class NoUpload(FileShareDriver):
        capabilities = frozenset()

    async def go() -> None:
        share = tmp_path / "share"
        share.mkdir()
        async with NoUpload(share=share, canary_interval_s=0) as driver:
            with pytest.raises(DriverError, match="cannot upload parameters"):
                await driver.upload_parameters({"robot": "arm3"})
        assert not (share / "params").exists()

    asyncio.run(go())
