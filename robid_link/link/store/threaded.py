"""The daemon's store: a blocking ``Store`` (``sql.py``) behind the async interface, every
query, commit, fsync and hash on one thread of its own, never on the event loop; calls run in
the order they were made. ``SqliteStore`` (a cell's own file) and ``PostgresStore`` (a robot's
view of a plant's database) differ only in how the ``Store`` is opened."""

from __future__ import annotations

import asyncio
import queue
import threading
from collections.abc import Callable
from contextlib import suppress
from pathlib import Path
from typing import Any, TypeVar

from robid_link.jobs import MotionProgram
from robid_link.link.store.base import AsyncStore
from robid_link.link.store.files import CellFiles
from robid_link.link.store.sql import RESERVE_BYTES, Store

__all__ = ["ThreadedStore", "SqliteStore", "PostgresStore", "open_store"]

T = TypeVar("T")


class _StoreThread:
    """One thread that runs a store's calls in the order they were made. A call once made
    runs to its end even when its caller is cancelled (the journal never half-knows a step,
    and a later call sees its effect); the caller's future is settled from the loop."""

    def __init__(self, name: str) -> None:
        self._calls: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._serve, name=name, daemon=True)

    def start(self) -> None:
        self._thread.start()

    async def call(self, fn: Callable[..., T], *args: Any, **kw: Any) -> T:
        loop = asyncio.get_running_loop()
        future: asyncio.Future[T] = loop.create_future()
        self._calls.put((fn, args, kw, loop, future))
        return await future

    def _serve(self) -> None:
        while (item := self._calls.get()) is not None:
            fn, args, kw, loop, future = item
            try:
                result, error = fn(*args, **kw), None
            except BaseException as err:  # noqa: BLE001 - handed to the caller
                result, error = None, err
            with suppress(RuntimeError):  # the caller's loop has closed: nobody waits
                loop.call_soon_threadsafe(_settle, future, result, error)

    def stop(self) -> None:
        """Run every call already made, then end the thread (blocking)."""
        self._calls.put(None)
        self._thread.join()


def _settle(future: asyncio.Future[Any], result: Any, error: BaseException | None) -> None:
    if future.done():  # the caller was cancelled; the call itself has run
        return
    if error is not None:
        future.set_exception(error)
    else:
        future.set_result(result)


class ThreadedStore(AsyncStore):
    """A ``Store`` behind the async interface, every call on one dedicated thread (queries,
    commits, fsyncs, hashing), so the event loop never waits on the disk or the network.
    ``async with ThreadedStore(state_dir, **store_options) as store: ...``"""

    def __init__(self, state_dir: str | Path, *, reserve_bytes: int = RESERVE_BYTES,
                 **options: Any) -> None:
        self.dir = Path(state_dir)
        self._reserve_bytes = reserve_bytes
        self._options = options
        # where the logs are, by the blocking store's own rule (no I/O: usable while closed)
        self._files = CellFiles(self.dir, options.get("log_store"))
        self._store: Store | None = None
        self._thread: _StoreThread | None = None

    @property
    def reserve_bytes(self) -> int:
        return self._reserve_bytes

    @reserve_bytes.setter
    def reserve_bytes(self, value: int) -> None:
        self._reserve_bytes = value
        if self._store is not None:
            self._store.reserve_bytes = value

    async def open(self) -> None:
        if self._thread is not None:
            return
        thread = _StoreThread(f"robid-store-{self.dir.name}")
        thread.start()
        try:
            self._store = await thread.call(Store, self.dir, reserve_bytes=self._reserve_bytes,
                                            **self._options)
        except BaseException:
            await asyncio.to_thread(thread.stop)
            raise
        self._thread = thread

    async def close(self) -> None:
        thread, store = self._thread, self._store
        self._thread = self._store = None
        if thread is None:
            return
        try:
            if store is not None:
                await thread.call(store.close)
        finally:  # shielded: a cancelled close still ends the thread
            await asyncio.shield(asyncio.to_thread(thread.stop))

    async def _call(self, name: str, *args: Any, **kw: Any) -> Any:
        if self._thread is None or self._store is None:
            raise RuntimeError(f"store {self.dir} is not open")
        return await self._thread.call(getattr(self._store, name), *args, **kw)

    # ----------------------------------------------------------------- space
    async def free_bytes(self) -> int:
        return int(await self._call("free_bytes"))

    async def require_space(self, need_bytes: int = 0, what: str = "a new run") -> None:
        await self._call("require_space", need_bytes, what)

    # ----------------------------------------------------------------- robots
    async def register_robot(self, robot_type: str, description_name: str, description: bytes,
                             lock: tuple[str, ...] = ()) -> None:
        await self._call("register_robot", robot_type, description_name, description, lock)

    # ----------------------------------------------------------------- runs
    async def create_run(self, campaign: str, trigger: str, spec: dict[str, Any],
                         experiments: list[tuple[str, str]]) -> str:
        return str(await self._call("create_run", campaign, trigger, spec, experiments))

    async def set_run(self, run_id: str, state: str, *, error: str | None = None,
                      step: str | None = None) -> None:
        await self._call("set_run", run_id, state, error=error, step=step)

    async def run(self, run_id: str) -> dict[str, Any]:
        return dict(await self._call("run", run_id))

    async def runs(self, limit: int = 50) -> list[dict[str, Any]]:
        return list(await self._call("runs", limit))

    async def unfinished_runs(self) -> list[str]:
        return list(await self._call("unfinished_runs"))

    async def given_without_run(self) -> list[dict[str, Any]]:
        return list(await self._call("given_without_run"))

    # ----------------------------------------------------------------- experiments, journal
    async def experiments(self, run_id: str) -> list[dict[str, Any]]:
        return list(await self._call("experiments", run_id))

    async def experiment(self, run_id: str, exp_id: str) -> dict[str, Any]:
        return dict(await self._call("experiment", run_id, exp_id))

    async def step(self, run_id: str, exp_id: str, state: str, **fields: Any) -> None:
        await self._call("step", run_id, exp_id, state, **fields)

    async def note(self, run_id: str, exp_id: str | None, step: str, **detail: Any) -> None:
        await self._call("note", run_id, exp_id, step, **detail)

    async def journal(self, run_id: str | None = None) -> list[dict[str, Any]]:
        return list(await self._call("journal", run_id))

    # ----------------------------------------------------------------- raw logs
    def log_path(self, sha: str) -> Path:
        return self._files.log_path(sha)

    async def put_log(self, data: bytes, *, run_id: str | None = None,
                      exp_id: str | None = None) -> str:
        return str(await self._call("put_log", data, run_id=run_id, exp_id=exp_id))

    async def check_log(self, sha: str) -> Path:
        return Path(await self._call("check_log", sha))

    async def log_count(self) -> int:
        return int(await self._call("log_count"))

    # ----------------------------------------------------------------- programs, approvals
    async def program_for(self, key: str) -> str | None:
        sha = await self._call("program_for", key)
        return None if sha is None else str(sha)

    async def put_program(self, key: str, program: MotionProgram) -> str:
        return str(await self._call("put_program", key, program))

    async def load_program(self, sha: str) -> MotionProgram:
        prog: MotionProgram = await self._call("load_program", sha)
        return prog

    async def approve(self, sha: str, campaign: str, exp_id: str, by: str) -> None:
        await self._call("approve", sha, campaign, exp_id, by)

    async def approved(self, sha: str) -> bool:
        return bool(await self._call("approved", sha))

    # ----------------------------------------------------------------- results
    async def add_result(self, run_id: str, robot: str, kind: str,
                         record: dict[str, Any], *, model_version: str = "") -> None:
        await self._call("add_result", run_id, robot, kind, record, model_version=model_version)

    async def results(self, robot: str | None = None, run_id: str | None = None,
                      model_version: str | None = "") -> list[dict[str, Any]]:
        return list(await self._call("results", robot, run_id, model_version))

    # ----------------------------------------------------------------- parameter sets
    async def add_param_set(self, doc: dict[str, Any], body: bytes) -> int:
        return int(await self._call("add_param_set", doc, body))

    async def param_sets(self, robot: str) -> list[dict[str, Any]]:
        return list(await self._call("param_sets", robot))

    async def approve_param_set(self, sha: str, by: str) -> None:
        await self._call("approve_param_set", sha, by)

    async def record_upload(self, robot: str, sha: str, run_id: str | None, state: str,
                            error: str | None = None) -> None:
        await self._call("record_upload", robot, sha, run_id, state, error)

    async def uploads(self, robot: str) -> list[dict[str, Any]]:
        return list(await self._call("uploads", robot))


class SqliteStore(ThreadedStore):
    """The cell's own SQLite store under ``state_dir`` (one daemon per state dir)."""

    def __init__(self, state_dir: str | Path, *, reserve_bytes: int = RESERVE_BYTES,
                 robot: str | None = None, log_store: str | None = None) -> None:
        super().__init__(state_dir, reserve_bytes=reserve_bytes, robot=robot,
                         log_store=log_store)


class PostgresStore(ThreadedStore):
    """``robot``'s view of a plant's PostgreSQL store at ``url`` (one daemon per robot), its
    raw logs under ``state_dir`` (or ``log_store``)."""

    def __init__(self, url: str, state_dir: str | Path, *, robot: str,
                 reserve_bytes: int = RESERVE_BYTES, log_store: str | None = None) -> None:
        super().__init__(state_dir, reserve_bytes=reserve_bytes, url=url, robot=robot,
                         log_store=log_store)


def open_store(state_dir: str | Path, *, url: str | None = None, robot: str | None = None,
               log_store: str | None = None) -> ThreadedStore:
    """The daemon's store (not yet opened): the plant's at ``url``, else the cell's SQLite."""
    if url:
        assert robot is not None
        return PostgresStore(url, state_dir, robot=robot, log_store=log_store)
    return SqliteStore(state_dir, robot=robot, log_store=log_store)
