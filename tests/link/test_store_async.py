"""The daemon's store off the event loop (``link/store/``): a slow fsync or commit runs on the
store's own thread while the loop keeps ticking; calls run in the order made, to their end even
when their caller is cancelled; the blocking readers of the operator commands see the same
rows through the same queries. On both backends (a cell's SQLite, a plant's PostgreSQL)."""

from __future__ import annotations

import asyncio
import inspect
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from robid_link.exceptions import StoreLockedError
from robid_link.link.store import AsyncStore, SqliteStore, Store, ThreadedStore
from robid_link.link.store import files as files_mod
from robid_link.link.store import sql as sql_mod

from .conftest import Backend

#: ticks the loop must make while the store is held up
TICKS = 25


class Gate:
    """Holds a blocking call until the loop has ticked ``TICKS`` times. Had the call run on
    the loop, nothing would tick: the gate gives up after a generous bound and says so."""

    def __init__(self) -> None:
        self.open = threading.Event()
        self.entered = threading.Event()
        self.gave_up = False
        self.thread: str | None = None

    def wrap(self, fn: Callable[..., Any]) -> Callable[..., Any]:
        def held(*args: Any, **kw: Any) -> Any:
            self.thread = threading.current_thread().name
            self.entered.set()
            if not self.open.wait(30):
                self.gave_up = True
            return fn(*args, **kw)
        return held


async def _ticking(gate: Gate, work: Any) -> tuple[Any, int, int]:
    """Run ``work`` while a task ticks; returns its result, the ticks at its end, and the
    ticks counted while the gate was closed."""
    ticks = 0
    while_held = 0

    async def tick() -> None:
        nonlocal ticks, while_held
        while True:
            ticks += 1
            if gate.entered.is_set() and not gate.open.is_set():
                while_held += 1
                if while_held >= TICKS:
                    gate.open.set()
            await asyncio.sleep(0)

    ticker = asyncio.create_task(tick())
    try:
        result = await work
    finally:
        ticker.cancel()
        await asyncio.gather(ticker, return_exceptions=True)
    return result, ticks, while_held


def test_a_slow_fsync_of_a_raw_log_leaves_the_loop_ticking(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, backend: Backend) -> None:
    gate = Gate()
    monkeypatch.setattr(files_mod, "atomic_write", gate.wrap(files_mod.atomic_write))

    async def go() -> tuple[Any, int, int]:
        async with backend.async_store(tmp_path / "s") as store:
            out = await _ticking(gate, store.put_log(b"t,q1,tau1\n0,0,0\n"))
            assert await store.log_count() == 1
            return out

    sha, ticks, held = asyncio.run(go())
    assert not gate.gave_up and held >= TICKS and ticks >= held
    assert len(sha) == 64 and gate.thread is not None and gate.thread.startswith("robid-store")


def test_a_slow_commit_leaves_the_loop_ticking(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                               backend: Backend) -> None:
    """The journal line is written inside the transaction: holding it holds the commit."""
    gate = Gate()

    async def go() -> tuple[Any, int, int, list[str]]:
        async with backend.async_store(tmp_path / "s") as store:
            run_id = await store.create_run("c", "operator", {}, [("a", "friction")])
            monkeypatch.setattr(sql_mod.Store, "_journal",
                                staticmethod(gate.wrap(sql_mod.Store._journal)))
            out = await _ticking(gate, store.step(run_id, "a", "giving", attempt=1, nonce="n1"))
            steps = [j["step"] for j in await store.journal(run_id)]
            return (*out, steps)

    _, ticks, held, steps = asyncio.run(go())
    assert not gate.gave_up and held >= TICKS and steps == ["queued", "giving"]


def test_a_call_runs_to_its_end_and_in_order_when_its_caller_is_cancelled(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, backend: Backend) -> None:
    gate = Gate()

    async def go() -> tuple[bool, dict[str, Any]]:
        async with backend.async_store(tmp_path / "s") as store:
            run_id = await store.create_run("c", "operator", {}, [("a", "friction")])
            monkeypatch.setattr(sql_mod.Store, "_journal",
                                staticmethod(gate.wrap(sql_mod.Store._journal)))
            caller = asyncio.create_task(store.step(run_id, "a", "giving", attempt=1,
                                                    nonce="n1"))
            while not gate.entered.is_set():
                await asyncio.sleep(0.01)
            caller.cancel()
            later = asyncio.create_task(store.experiment(run_id, "a"))  # queued behind it
            gate.open.set()
            cancelled = False
            try:
                await caller
            except asyncio.CancelledError:
                cancelled = True
            return cancelled, await later

    cancelled, row = asyncio.run(go())
    assert cancelled and row["state"] == "giving" and row["nonce"] == "n1"


def test_a_raw_log_and_its_journal_line_are_one_transaction(tmp_path: Path,
                                                            backend: Backend) -> None:
    async def go() -> tuple[str, list[dict[str, Any]]]:
        async with backend.async_store(tmp_path / "s") as store:
            run_id = await store.create_run("c", "operator", {}, [("a", "friction")])
            sha = await store.put_log(b"t,q1\n0,1\n", run_id=run_id, exp_id="a")
            return sha, await store.journal(run_id)

    sha, journal = asyncio.run(go())
    assert journal[-1]["step"] == "raw_stored" and journal[-1]["exp_id"] == "a"
    assert journal[-1]["detail"] == {"log_sha": sha, "size": 9}


def test_the_blocking_reader_sees_what_the_daemon_stored(tmp_path: Path, backend: Backend) -> None:
    async def go() -> str:
        async with backend.async_store(tmp_path / "s") as store:
            run_id = await store.create_run("c", "operator", {}, [("a", "friction")])
            await store.set_run(run_id, "running", step="experiment 1/1 a")
            await store.add_result(run_id, "arm3", "identify", {"rmse": [1.0]})
            return run_id

    run_id = asyncio.run(go())
    with backend.reader(tmp_path / "s") as ro:
        assert ro.runs()[0]["run_id"] == run_id and ro.run(run_id)["step"] == "experiment 1/1 a"
        assert ro.results("arm3")[0]["record"] == {"rmse": [1.0]}


def test_a_second_daemon_is_refused_and_nothing_is_left_running(tmp_path: Path,
                                                                backend: Backend) -> None:
    async def go() -> str:
        async with backend.async_store(tmp_path / "s"):
            with pytest.raises(StoreLockedError, match="in use by another daemon") as err:
                await backend.async_store(tmp_path / "s").open()
        return str(err.value)

    assert "\n" not in asyncio.run(go())  # and the leak check sees no store thread left


def test_close_is_safe_twice_and_a_closed_store_says_so(tmp_path: Path, backend: Backend) -> None:
    async def go() -> None:
        store = backend.async_store(tmp_path / "s")
        await store.open()
        await store.close()
        await store.close()
        with pytest.raises(RuntimeError, match="is not open"):
            await store.runs()

    asyncio.run(go())


def test_every_operation_of_the_interface_has_one_blocking_implementation() -> None:
    """SqliteStore forwards each operation of the interface to Store's query of the same
    name (the one the operator commands use); the dead ``set_step`` is gone."""
    ops = {name for name, fn in inspect.getmembers(AsyncStore, inspect.iscoroutinefunction)
           if not name.startswith("_") and name not in ("open", "close")}
    assert {"run", "runs", "step", "put_log", "results", "param_set"} <= ops
    assert not SqliteStore.__abstractmethods__ and not ThreadedStore.__abstractmethods__
    missing = sorted(op for op in ops if not callable(getattr(Store, op, None)))
    assert missing == []
    assert not hasattr(Store, "set_step")


@pytest.mark.parametrize("where", ["state_dir", "folder", "url"])
def test_the_daemon_finds_a_log_where_log_store_put_it(tmp_path: Path, where: str) -> None:
    """``log_path`` of the daemon's store is where ``put_log`` wrote the log: the state dir,
    the ``log_store`` folder instead, or the state dir beside an fsspec URL's copy (the cycle
    checks the log at this path before it counts as stored)."""
    log_store = {"state_dir": None, "folder": str(tmp_path / "central"),
                 "url": "memory://robid-plant-logs"}[where]

    async def go() -> tuple[Path, Path]:
        async with SqliteStore(tmp_path / "s", robot="arm3", log_store=log_store) as store:
            sha = await store.put_log(b"t,q1\n0,1\n")
            return store.log_path(sha), await store.check_log(sha)

    path, checked = asyncio.run(go())
    assert path == checked and path.read_bytes() == b"t,q1\n0,1\n"
    assert path.is_relative_to(tmp_path / ("central" if where == "folder" else "s"))
