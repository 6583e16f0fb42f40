"""Issue 14 item 5: the share is an attack surface. Share files are read without following
links, only when regular, up to a size limit, off the event loop; a malformed 'done' of the
current nonce is a failed attempt reported to the operator, never a silent second motion."""

from __future__ import annotations

import asyncio
import hashlib
import os
from pathlib import Path

import pytest

from robid_link.drivers.file_share import FileShareDriver
from robid_link.exceptions import ConfigError, CycleError, DriverError, ProtocolError
from robid_link.jobs import MotionProgram
from robid_link.link import cycle
from robid_link.link.cycle import CyclePolicy, run_cycle
from robid_link.link.driver import Done
from robid_link.link.store import SqliteStore
from robid_link.safeopen import NotRegularError, TooLargeError, read_regular


def _program() -> MotionProgram:
    import yaml

    header = {"robot": "arm3", "rate_hz": 100.0, "kind": "custom",
              "joint_types": ["revolute"] * 3}
    return MotionProgram("exp1", {"traj.csv": b"t,q1,q2,q3\n0,0,0,0\n0.01,0.001,0,0\n",
                                  "traj.yaml": yaml.safe_dump(header).encode()}, 0.01)


def _driver(tmp_path: Path, **kw: object) -> FileShareDriver:
    share = tmp_path / "share"
    share.mkdir(exist_ok=True)
    return FileShareDriver(share=share, canary_interval_s=0, **kw)  # type: ignore[arg-type]


def test_read_regular_refuses_links_fifos_and_large_files(tmp_path: Path) -> None:
    (tmp_path / "f").write_bytes(b"abc")
    assert read_regular(tmp_path / "f", 3) == b"abc"
    os.symlink(tmp_path / "f", tmp_path / "link")
    with pytest.raises(NotRegularError, match="symbolic link"):
        read_regular(tmp_path / "link", 100)
    os.mkfifo(tmp_path / "fifo")
    with pytest.raises(NotRegularError):  # returns at once: O_NONBLOCK, nobody writes
        read_regular(tmp_path / "fifo", 100)
    with pytest.raises(TooLargeError):
        read_regular(tmp_path / "f", 2)


def test_symlinked_log_of_a_secret_is_not_fetched(tmp_path: Path) -> None:
    secret = tmp_path / "secret"
    secret.write_bytes(b"t,q1,tau1\n0,0,0\n")
    secret.chmod(0o600)
    driver = _driver(tmp_path)

    async def go() -> bytes:
        async with driver:
            os.symlink(secret, driver.outbox / "exp1.n1.log.csv")
            data = secret.read_bytes()
            return await driver.fetch_logs(Done("exp1", "n1", hashlib.sha256(data).hexdigest(),
                                                len(data)))

    with pytest.raises(DriverError, match="symbolic link"):
        asyncio.run(go())


@pytest.mark.parametrize("which", ["done", "failed", "log"])
def test_a_fifo_on_the_share_does_not_freeze_the_loop(tmp_path: Path, which: str) -> None:
    driver = _driver(tmp_path)

    async def go() -> None:
        async with driver:
            if which == "log":
                os.mkfifo(driver.outbox / "exp1.n1.log.csv")
                await driver.fetch_logs(Done("exp1", "n1", "0" * 64, 1))
            else:
                os.mkfifo(driver.sem / f"exp1.n1.{which}")
                await driver.take_done("exp1", "n1", timeout_s=5)

    async def bounded() -> None:
        async with asyncio.timeout(20):  # the whole test: a frozen loop would never get here
            await go()

    with pytest.raises(DriverError):
        asyncio.run(bounded())


def test_a_huge_sparse_log_is_refused_unread(tmp_path: Path) -> None:
    driver = _driver(tmp_path, max_log_bytes=1 << 20)

    async def go() -> None:
        async with driver:
            with open(driver.outbox / "exp1.n1.log.csv", "wb") as f:
                f.truncate(2 << 30)  # 2 GiB of holes: costs no disk, would cost 2 GiB of RAM
            await driver.fetch_logs(Done("exp1", "n1", "0" * 64, 2 << 30))

    with pytest.raises(DriverError, match="more than the 1048576 allowed"):
        asyncio.run(go())


def test_max_log_bytes_is_validated(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="driver.max_log_bytes"):
        _driver(tmp_path, max_log_bytes=0)


@pytest.mark.parametrize("garbage", [b"\xff\xfe garbage\n", b"xyz size=3\n",
                                     b"0" * 64 + b" size=-4\n"])
def test_malformed_done_is_one_failed_attempt_never_a_second_motion(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, garbage: bytes) -> None:
    monkeypatch.setattr(cycle, "new_nonce", lambda: "n1")
    driver = _driver(tmp_path)
    program = _program()

    async def check(path: str) -> dict[str, int]:
        return {}

    async def go() -> tuple[list[dict], dict]:
        async with SqliteStore(tmp_path / "state", reserve_bytes=0) as store, driver:
            run_id = await store.create_run("c", "operator", {}, [("exp1", "custom")])
            (driver.sem / "exp1.n1.done").write_bytes(garbage)  # the current nonce's answer
            with pytest.raises(CycleError, match="not retried") as info:
                await run_cycle(store, driver, run_id, "exp1", program,
                                CyclePolicy(timeout_s=5, retries=3, backoff_s=0.01), check)
            assert isinstance(info.value.__cause__, ProtocolError)
            return await store.journal(run_id), await store.experiment(run_id, "exp1")

    journal, row = asyncio.run(go())
    givings = [j for j in journal if j["step"] == "giving"]
    assert len(givings) == 1  # one motion, no re-run
    assert row["state"] == "failed"
    assert os.listdir(driver.sem) == []  # withdrawn and cleaned
