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

from robid_link.exceptions import ConfigError, DriverError
from robid_link.link.driver import Done, Driver, MotionProgram
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


def test_upload_parameters_lands_in_params_atomically(tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """The identified parameters go to ``share/params/`` as one whole JSON file per upload,
    written through the atomic write (temp + rename), never half a file."""
    import json

    import robid_link.atomic as atomic

    doc = {"robot": "arm3", "run_id": "r-1", "parameters": [
        {"name": "zz_1", "value": 0.25, "std": 0.01, "expression": "zz_1"}]}
    renames: list[tuple[str, str]] = []
    real_replace = os.replace

    def spy(src: Any, dst: Any) -> None:
        renames.append((Path(src).name, Path(dst).name))
        real_replace(src, dst)

    monkeypatch.setattr(atomic.os, "replace", spy)

    async def go() -> list[Path]:
        driver, _ = _file_share(tmp_path)
        async with driver:
            await driver.upload_parameters(doc)
            await driver.upload_parameters({**doc, "parameters": []})  # same second: kept too
        return sorted((tmp_path / "share" / "params").iterdir())

    files = asyncio.run(go())
    assert [f.suffix for f in files] == [".json", ".json"]
    assert all(f.name.startswith("arm3.") and ".r-1" in f.name for f in files)
    contents = [json.loads(f.read_text()) for f in files]
    assert doc in contents and {**doc, "parameters": []} in contents
    assert {dst for _, dst in renames} == {f.name for f in files}
    assert all(src.startswith(".") and src.endswith(".tmp") for src, _ in renames)


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
