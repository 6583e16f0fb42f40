"""Issue 14 items 3, 4, 7 and 11 in-process: motion nobody watches (non-finite timeouts,
cancel), checks before motion, a full state_dir degrading instead of crash-looping, and the
messages (frozen vs absent daemon, the cause of an internal error, one warning per event,
cleaned failed attempts)."""

from __future__ import annotations

import asyncio
import inspect
import logging
import os
import socket
import threading
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

from robid_link.cli.runs import _unreachable
from robid_link.config import load_daemon_config
from robid_link.exceptions import ConfigError, DaemonUnreachable, StoreFullError
from robid_link.link import campaign as cp
from robid_link.link.control import request
from robid_link.link.daemon import Daemon
from robid_link.link.store import SqliteStore, Store

from .conftest import QUICK, write_config

FRICTION = {"experiments": [{"kind": "friction", "speeds": [0.5], "joints": [1],
                             "rate_hz": 100}],
            "identify": False, "timeout_s": 30, "backoff_s": 0.05, "retries": 1}


def with_daemon(cfg_path: Path, body: Callable[[Daemon], Awaitable[Any]]) -> Any:
    async def go() -> Any:
        async with asyncio.timeout(150), Daemon(load_daemon_config(cfg_path), env={}) as d:
            return await body(d)

    return asyncio.run(go())


async def until(pred: Callable[[], Any], timeout_s: float = 60.0) -> None:
    """Wait for ``pred()`` (a bool, or an awaitable of one: a store read) to hold."""
    async with asyncio.timeout(timeout_s):
        while True:
            got = pred()
            if inspect.isawaitable(got):
                got = await got
            if got:
                return
            await asyncio.sleep(0.05)


async def state_is(d: Daemon, run_id: str, state: str) -> bool:
    assert d.store is not None
    return (await d.store.run(run_id))["state"] == state


def _ready(tmp: Path) -> list[str]:
    return [n for n in os.listdir(tmp / "share" / "sem") if n.endswith(".ready")]


# ------------------------------------------------------------------- 3: nobody watching
@pytest.mark.parametrize("key", ["timeout_s", "backoff_s"])
@pytest.mark.parametrize("value", [".inf", ".nan", "-.inf"])
def test_non_finite_timeouts_are_refused_at_load(tmp_path: Path, key: str, value: str) -> None:
    cfg = write_config(tmp_path, {"c": FRICTION})
    cfg.write_text(cfg.read_text().replace(f"{key}: {FRICTION[key]}", f"{key}: {value}"))
    with pytest.raises(ConfigError, match=f"campaigns.c.{key}"):
        load_daemon_config(cfg)


def test_cancel_withdraws_the_ready_of_a_running_run_and_drops_a_queued_one(
        tmp_path: Path) -> None:
    cfg = write_config(tmp_path, {"c": FRICTION})  # no controller: nobody answers

    async def body(d: Daemon) -> tuple[dict, dict, list]:
        first = (await d.handle({"cmd": "start", "campaign": "c"}))["run_id"]
        second = (await d.handle({"cmd": "start", "campaign": "c"}))["run_id"]
        await until(lambda: bool(_ready(tmp_path)))
        ans = await d.handle({"cmd": "cancel", "run_id": second})  # queued
        assert ans["state"] == "cancelled"
        ans = await d.handle({"cmd": "cancel", "run_id": first})  # running, 'ready' out
        assert ans["state"] == "cancelled" and _ready(tmp_path) == []
        with pytest.raises(ConfigError, match="is cancelled: nothing to cancel"):
            await d.handle({"cmd": "cancel", "run_id": first})
        await asyncio.sleep(0.3)
        assert d.store is not None
        status = await d.handle({"cmd": "status"})
        return (await d.store.run(first), await d.store.run(second),
                [s["state"] for s in status["runs"]])

    first, second, states = with_daemon(cfg, body)
    assert states == ["cancelled", "cancelled"]
    assert second["experiments"][0]["attempt"] == 0  # never given
    assert first["experiments"][0]["state"] == "withdrawn"
    assert _ready(tmp_path) == []


def test_a_run_cancelled_while_the_runner_takes_it_from_the_queue_never_moves(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The runner reads a queued run's state from the store (an await) before it starts it;
    a cancel arriving then must win: the run ends cancelled, nothing of it left out."""
    cfg = write_config(tmp_path, {"c": FRICTION})  # no controller: nobody answers
    real_run = Store.run
    target: dict[str, str] = {}
    held, release = threading.Event(), threading.Event()

    def run(store: Store, run_id: str) -> dict[str, Any]:  # on the store's thread
        if run_id == target.get("second") and not held.is_set():
            held.set()  # the runner's read of the queued run: hold it there
            release.wait(30)
        return real_run(store, run_id)

    monkeypatch.setattr(Store, "run", run)

    async def body(d: Daemon) -> tuple[dict, list[str], str | None]:
        first = (await d.handle({"cmd": "start", "campaign": "c"}))["run_id"]
        await until(lambda: bool(_ready(tmp_path)))
        target["second"] = (await d.handle({"cmd": "start", "campaign": "c"}))["run_id"]
        # the runner takes the second once the first ends (its answer waits behind the hold)
        cancel_first = asyncio.create_task(d.handle({"cmd": "cancel", "run_id": first}))
        await until(held.is_set)
        cancel = asyncio.create_task(d.handle({"cmd": "cancel",
                                               "run_id": target["second"]}))
        for _ in range(20):
            await asyncio.sleep(0)  # the cancel is under way while the runner is held
        release.set()
        await cancel_first
        await cancel
        await asyncio.sleep(0.5)  # room for a wrongly started run to show itself
        assert d.store is not None
        return (await d.store.run(target["second"]), _ready(tmp_path), d._current)

    second, ready, current = with_daemon(cfg, body)
    assert second["state"] == "cancelled" and ready == [] and current is None


def test_a_ready_left_by_a_cancel_interrupted_by_a_kill_is_withdrawn_at_start(
        tmp_path: Path) -> None:
    cfg = write_config(tmp_path, {"c": FRICTION})
    (tmp_path / "share" / "sem").mkdir(parents=True)
    with Store(tmp_path / "state") as store:
        run_id = store.create_run("c", "operator", {}, [("friction", "friction")])
        store.step(run_id, "friction", "given", attempt=1, nonce="n1")
        store.set_run(run_id, "cancelled")
    (tmp_path / "share" / "sem" / "friction.n1.ready").write_text("{}\n")

    async def body(d: Daemon) -> None:
        return None

    with_daemon(cfg, body)
    assert _ready(tmp_path) == []


# ------------------------------------------------------------------- 4: checks before motion
@pytest.mark.parametrize("option, value", [
    ("harmonics", 0), ("harmonics", 10_000), ("restarts", 0), ("seed", -1),
    ("evaluations", 0), ("evaluations", 10**9), ("duration_s", 1e9), ("harmonics", 2.5)])
def test_absurd_rigid_body_options_are_refused_at_load(tmp_path: Path, option: str,
                                                       value: Any) -> None:
    exp = {"kind": "rigid_body", "duration_s": 10, option: value}
    cfg = write_config(tmp_path, {"c": {"experiments": [exp]}})
    with pytest.raises(ConfigError, match=rf"campaigns\.c\.experiments\[0\]\.{option}"):
        load_daemon_config(cfg)


@pytest.mark.parametrize("joints", [[0], [1, 1], [99]])
def test_bad_friction_joints_are_refused_at_load(tmp_path: Path, joints: list[int]) -> None:
    exp = {"kind": "friction", "joints": joints}
    cfg = write_config(tmp_path, {"c": {"experiments": [exp]}})
    with pytest.raises(ConfigError, match="joints"):
        load_daemon_config(cfg)


@pytest.mark.parametrize("change, message", [
    ({"model": "missing.yaml"}, "missing.yaml: model file not found"),
    ({"add": ["no_such_effect@2"]}, "no_such_effect"),
    ({"experiments": [{"kind": "friction", "joints": [7]}]}, "joints: 7"),
])
def test_start_refuses_before_anything_is_given(tmp_path: Path, change: dict,
                                                message: str) -> None:
    camp = {**FRICTION, **change}
    if "model" in change:
        camp["model"] = str(tmp_path / change["model"])
    cfg = write_config(tmp_path, {"c": camp})

    async def body(d: Daemon) -> str:
        with pytest.raises(Exception) as info:
            await d.handle({"cmd": "start", "campaign": "c"})
        assert d.store is not None and await d.store.runs() == []
        return str(info.value)

    assert message in with_daemon(cfg, body)
    assert os.listdir(tmp_path / "share" / "inbox") == []


# ------------------------------------------------------------------- 7: full state_dir
class _Disk:
    """``Store.free_bytes`` under the test's control (no tiny file system needed)."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.free = 0
        monkeypatch.setattr(Store, "free_bytes", lambda store: self.free)
        monkeypatch.setattr(Daemon, "space_poll_s", 0.1)


def test_full_state_dir_pauses_refuses_serves_status_and_resumes(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, controller: Any,
        caplog: pytest.LogCaptureFixture) -> None:
    disk = _Disk(monkeypatch)
    disk.free = 1 << 40
    cfg = write_config(tmp_path, {"c": FRICTION})
    async def left_over() -> str:  # a run left over, resumed by the operator on a full disk
        async with SqliteStore(tmp_path / "state") as store:
            return await cp.create_run(load_daemon_config(cfg), store, "c", "operator")

    run_id = asyncio.run(left_over())
    disk.free = 0

    async def body(d: Daemon) -> tuple[dict, str, dict]:
        assert d.store is not None
        await until(lambda: state_is(d, run_id, "interrupted"))  # never moves on its own
        await d.handle({"cmd": "resume", "run_id": run_id})
        await until(lambda: d._full is not None and run_id in d._paused)
        with pytest.raises(StoreFullError, match="MiB free"):
            await d.handle({"cmd": "start", "campaign": "c"})
        status = await d.handle({"cmd": "status"})
        paused = await d.store.run(run_id)
        disk.free = 1 << 40
        await until(lambda: state_is(d, run_id, "completed"))
        return paused, status["status"], await d.store.run(run_id)

    with caplog.at_level(logging.INFO, logger="robid"), controller():
        paused, line, done = with_daemon(cfg, body)
    assert paused["state"] == "running"  # unfinished, journaled as it is; nothing failed
    assert paused["experiments"][0]["attempt"] == 0  # nothing was given on a full disk
    assert "MiB free" in line and "1 run(s) paused" in line
    assert done["state"] == "completed"
    full_lines = [r for r in caplog.records if "new runs refused" in r.getMessage()]
    assert len(full_lines) == 1


def test_full_disk_while_recording_a_failure_does_not_crash_the_daemon(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = write_config(tmp_path, {"c": FRICTION})
    real = Store.set_run
    attempted: list[str] = []

    def set_run(store: Store, run_id: str, state: str, **kw: Any) -> None:
        attempted.append(state)
        if state == "failed":
            raise StoreFullError("state_dir: disk full while writing: waiting for space")
        real(store, run_id, state, **kw)

    async def boom(*args: Any, **kw: Any) -> None:
        raise RuntimeError("boom")

    monkeypatch.setattr(Store, "set_run", set_run)
    monkeypatch.setattr(cp, "execute_run", boom)

    async def body(d: Daemon) -> dict:
        ans = await d.handle({"cmd": "start", "campaign": "c"})
        await asyncio.sleep(0.5)
        return await d.handle({"cmd": "status", "run_id": ans["run_id"]})

    status = with_daemon(cfg, body)  # the daemon lived on to answer
    assert "failed" in attempted  # the failure was recorded, and that write hit the full disk
    assert status["ok"]
    (run,) = status["runs"]
    # nothing claims the run failed (the write did not land): it stays unfinished, to resume
    assert run["state"] in ("queued", "running"), run["state"]


# ------------------------------------------------------------------- 11: messages
def test_internal_error_line_carries_its_cause(tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch,
                                               caplog: pytest.LogCaptureFixture) -> None:
    from robid_link.link.notify import _LineFormatter

    async def boom(*args: Any, **kw: Any) -> None:
        raise RuntimeError("boom at step 3")

    monkeypatch.setattr(cp, "execute_run", boom)
    cfg = write_config(tmp_path, {"c": FRICTION})

    async def body(d: Daemon) -> dict:
        ans = await d.handle({"cmd": "start", "campaign": "c"})
        await until(lambda: state_is(d, ans["run_id"], "failed"))
        return await d.store.run(ans["run_id"])  # type: ignore[union-attr]

    with caplog.at_level(logging.ERROR, logger="robid.daemon"):
        run = with_daemon(cfg, body)
    assert run["error"] == "internal error: RuntimeError: boom at step 3"
    [rec] = [r for r in caplog.records if "internal error" in r.getMessage()]
    line = _LineFormatter(journald=False).format(rec)
    assert "internal error: RuntimeError: boom at step 3" in line and "\n" not in line


def test_status_tells_a_frozen_daemon_from_an_absent_one(tmp_path: Path) -> None:
    path = tmp_path / "ctl.sock"
    with pytest.raises(DaemonUnreachable) as absent:
        request(path, {"cmd": "status"}, timeout_s=0.5)
    assert _unreachable(absent.value) == "daemon not running"
    with socket.socket(socket.AF_UNIX) as srv:  # accepts, never answers: a frozen loop
        srv.bind(str(path))
        srv.listen(1)
        with pytest.raises(DaemonUnreachable) as frozen:
            request(path, {"cmd": "status"}, timeout_s=0.5)
    assert _unreachable(frozen.value).startswith("daemon not answering")


def _share_driver(tmp_path: Path) -> Any:
    from robid_link.drivers.file_share import FileShareDriver

    (tmp_path / "share").mkdir(exist_ok=True)
    return FileShareDriver(share=tmp_path / "share", canary_interval_s=0,
                           observer="polling", poll_interval_s=0.02)


def test_one_warning_per_stale_file_and_none_for_the_done_being_taken(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    import hashlib

    from robid_link.atomic import atomic_write

    driver = _share_driver(tmp_path)
    sem = tmp_path / "share" / "sem"
    sem.mkdir(parents=True, exist_ok=True)
    (tmp_path / "share" / "outbox").mkdir(exist_ok=True)
    data = b"t,q1\n0,1\n"
    # the answer of the attempt a resumed run is about to take, written while it was down
    (sem / "exp1.cur.done").write_text(f"{hashlib.sha256(data).hexdigest()} size=9\n")

    async def go() -> None:
        async with driver:
            await driver.take_done("exp1", "cur", timeout_s=5)
            waiter = asyncio.create_task(driver.take_done("exp2", "new", timeout_s=5))
            await asyncio.sleep(0.1)
            stale = sem / "exp2.old.done"
            atomic_write(stale, b"0" * 64 + b"\n")
            with open(stale, "ab") as f:  # created, modified, closed: three events
                f.write(b" ")
            await asyncio.sleep(0.5)
            waiter.cancel()
            await asyncio.gather(waiter, return_exceptions=True)

    with caplog.at_level(logging.INFO, logger="robid.driver.file_share"):
        asyncio.run(go())
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert not any("exp1.cur" in w for w in warnings), warnings
    assert len([w for w in warnings if "exp2.old.done" in w]) == 1, warnings


def test_failed_attempt_files_are_cleaned_from_the_share(tmp_path: Path) -> None:
    driver = _share_driver(tmp_path)

    async def go() -> None:
        async with driver:
            await driver.give_ready("exp1", "n1")
            (tmp_path / "share" / "outbox" / "exp1.n1.log.csv").write_bytes(b"junk")
            (tmp_path / "share" / "sem" / "exp1.n1.done").write_bytes(b"junk")
            (tmp_path / "share" / "sem" / "exp1.n1.failed").write_bytes(b"stop")
            await driver.withdraw("exp1", "n1")

    asyncio.run(go())
    assert os.listdir(tmp_path / "share" / "sem") == []
    assert os.listdir(tmp_path / "share" / "outbox") == []


def test_start_json_without_wait_writes_the_run_id(tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    import json

    from robid_link import cli
    from robid_link.cli import campaign as commands

    cfg = write_config(tmp_path, {"c": FRICTION})
    monkeypatch.setattr(commands, "request", lambda *a, **k: {"ok": True, "run_id": "r1"})
    assert cli.main(["campaign", "start", "c", "--config", str(cfg), "--json",
                     str(tmp_path / "s.json")]) == 0
    assert json.loads((tmp_path / "s.json").read_text())["run_id"] == "r1"


def test_quick_campaign_still_valid() -> None:  # the bounds keep the shipped examples valid
    for path in Path(__file__).resolve().parents[2].glob("examples/link/*.yaml"):
        doc = yaml.safe_load(path.read_text())
        if isinstance(doc, dict) and "campaigns" in doc:
            load_daemon_config(path)
    assert QUICK["experiments"]
