"""The SQLite store (WAL, synchronous=FULL) for runs, experiments, the step journal, results
and approvals; raw logs and programs as content-hashed files written and fsynced before their
row (``files.py``). One daemon per ``state_dir``, enforced with ``flock``.

``Store`` is the blocking implementation (one of each query), used as it is by the operator
commands that read while no daemon answers (``Store(state_dir, readonly=True)``);
``SqliteStore`` is the daemon's: the same ``Store`` behind the async interface, every query,
fsync and hash on one thread of its own, never on the event loop."""

from __future__ import annotations

import asyncio
import fcntl
import json
import os
import queue
import sqlite3
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any, TypeVar

from robid_link.exceptions import ConfigError, StoreFullError, StoreLockedError
from robid_link.jobs import MotionProgram
from robid_link.link.store.base import (
    RUN_STATES,
    STEP_FIELDS,
    AsyncStore,
    acknowledged_sets,
    pick_param_set,
)
from robid_link.link.store.files import CellFiles

__all__ = ["Store", "SqliteStore", "RESERVE_BYTES"]

T = TypeVar("T")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS runs (
    run_id TEXT PRIMARY KEY, campaign TEXT NOT NULL, trigger TEXT NOT NULL,
    state TEXT NOT NULL, created REAL NOT NULL, started REAL, finished REAL,
    spec TEXT NOT NULL, error TEXT, step TEXT);
CREATE TABLE IF NOT EXISTS experiments (
    run_id TEXT NOT NULL, exp_id TEXT NOT NULL, position INTEGER NOT NULL,
    kind TEXT NOT NULL, state TEXT NOT NULL, attempt INTEGER NOT NULL DEFAULT 0,
    nonce TEXT, program_sha TEXT, done_sha TEXT, done_size INTEGER, log_sha TEXT,
    error TEXT, updated REAL NOT NULL,
    PRIMARY KEY (run_id, exp_id));
CREATE TABLE IF NOT EXISTS journal (
    seq INTEGER PRIMARY KEY AUTOINCREMENT, time REAL NOT NULL, run_id TEXT NOT NULL,
    exp_id TEXT, step TEXT NOT NULL, detail TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS logs (
    sha256 TEXT PRIMARY KEY, size INTEGER NOT NULL, stored REAL NOT NULL);
CREATE TABLE IF NOT EXISTS programs (
    key TEXT PRIMARY KEY, sha256 TEXT NOT NULL, created REAL NOT NULL);
CREATE TABLE IF NOT EXISTS approvals (
    sha256 TEXT PRIMARY KEY, campaign TEXT NOT NULL, exp_id TEXT NOT NULL,
    approved REAL NOT NULL, by TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS results (
    id INTEGER PRIMARY KEY AUTOINCREMENT, run_id TEXT NOT NULL, robot TEXT NOT NULL,
    kind TEXT NOT NULL, time REAL NOT NULL, record TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS param_sets (
    sha256 TEXT PRIMARY KEY, robot TEXT NOT NULL, version INTEGER NOT NULL,
    run_id TEXT NOT NULL, created REAL NOT NULL, body BLOB NOT NULL,
    approved REAL, approved_by TEXT);
CREATE TABLE IF NOT EXISTS param_uploads (
    seq INTEGER PRIMARY KEY AUTOINCREMENT, robot TEXT NOT NULL, sha256 TEXT NOT NULL,
    time REAL NOT NULL, run_id TEXT, state TEXT NOT NULL, error TEXT);
"""


#: free bytes the store keeps in reserve: below it no new motion starts
RESERVE_BYTES = 64 << 20


class Store:
    """Open with ``Store(state_dir)`` (exclusive, for the daemon) or
    ``Store(state_dir, readonly=True)`` (operator commands while no daemon answers)."""

    def __init__(self, state_dir: str | Path, *, readonly: bool = False,
                 reserve_bytes: int = RESERVE_BYTES) -> None:
        self.dir = Path(state_dir)
        self.files = CellFiles(self.dir)
        self.reserve_bytes = reserve_bytes
        self.readonly = readonly
        self._lock_fd: int | None = None
        db = self.dir / "robid.sqlite"
        if readonly:
            if not db.is_file():
                raise ConfigError(f"state_dir: {self.dir} holds no store yet")
            self.db = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=10.0)
        else:
            self.files.prepare()
            self._lock()
            self.db = sqlite3.connect(db, timeout=10.0, isolation_level=None)
            self.db.execute("PRAGMA journal_mode=WAL")
            self.db.execute("PRAGMA synchronous=FULL")
            self.db.executescript(_SCHEMA)
        self.db.row_factory = sqlite3.Row

    def _lock(self) -> None:
        path = self.dir / "lock"
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError as err:
            holder = os.read(fd, 32).decode(errors="replace").strip() or "?"
            os.close(fd)
            raise StoreLockedError(f"state_dir: {self.dir} is in use by another daemon "
                                   f"(pid {holder})") from err
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._lock_fd = fd

    def close(self) -> None:
        db = getattr(self, "db", None)
        if db is not None:
            db.close()
            self.db = None  # type: ignore[assignment]
        if self._lock_fd is not None:
            os.close(self._lock_fd)  # releases the flock
            self._lock_fd = None

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ----------------------------------------------------------------- space
    def free_bytes(self) -> int:
        return self.files.free_bytes()

    def require_space(self, need_bytes: int = 0, what: str = "a new run") -> None:
        """Refuse ``what`` (before any motion) unless ``need_bytes`` fit above the reserve."""
        free = self.free_bytes()
        if free < need_bytes + self.reserve_bytes:
            raise StoreFullError(f"state_dir: {self.dir} has {free >> 20} MiB free, "
                                 f"{(need_bytes + self.reserve_bytes) >> 20} MiB needed for "
                                 f"{what}: waiting for space")

    @contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        try:
            self.db.execute("BEGIN IMMEDIATE")
            try:
                yield self.db
            except BaseException:
                with suppress(sqlite3.Error):  # SQLite rolls back by itself on SQLITE_FULL
                    self.db.execute("ROLLBACK")
                raise
            self.db.execute("COMMIT")
        except sqlite3.OperationalError as err:
            if "full" in str(err) or "disk" in str(err):
                with suppress(sqlite3.Error):
                    self.db.execute("ROLLBACK")
                raise self.files.full(err) from err
            raise

    # ----------------------------------------------------------------- runs
    def create_run(self, campaign: str, trigger: str, spec: dict[str, Any],
                   experiments: list[tuple[str, str]]) -> str:
        """A new queued run with its experiments (``(exp_id, kind)`` in order)."""
        run_id = time.strftime("%Y%m%d-%H%M%S-") + uuid.uuid4().hex[:6]
        now = time.time()
        with self._tx() as db:
            db.execute("INSERT INTO runs (run_id, campaign, trigger, state, created, spec) "
                       "VALUES (?, ?, ?, 'queued', ?, ?)",
                       (run_id, campaign, trigger, now, json.dumps(spec)))
            for pos, (exp_id, kind) in enumerate(experiments):
                db.execute("INSERT INTO experiments (run_id, exp_id, position, kind, state, "
                           "updated) VALUES (?, ?, ?, ?, 'pending', ?)",
                           (run_id, exp_id, pos, kind, now))
            self._journal(db, run_id, None, "queued", {"campaign": campaign, "trigger": trigger})
        return run_id

    def set_run(self, run_id: str, state: str, *, error: str | None = None,
                step: str | None = None) -> None:
        if state not in RUN_STATES:
            raise ValueError(state)
        now = time.time()
        with self._tx() as db:
            db.execute("UPDATE runs SET state = ?, error = COALESCE(?, error), step = ?, "
                       "started = CASE WHEN ? = 'running' THEN COALESCE(started, ?) "
                       "ELSE started END, "
                       "finished = CASE WHEN ? IN ('completed', 'failed', 'cancelled') THEN ? "
                       "ELSE NULL END "
                       "WHERE run_id = ?",
                       (state, error, step, state, now, state, now, run_id))
            self._journal(db, run_id, None, state, {"error": error} if error else {})

    def run(self, run_id: str) -> dict[str, Any]:
        row = self.db.execute("SELECT * FROM runs WHERE run_id = ?", (run_id,)).fetchone()
        if row is None:
            raise ConfigError(f"run {run_id}: not in the store")
        return self._run_dict(row)

    def runs(self, limit: int = 50) -> list[dict[str, Any]]:
        rows = self.db.execute("SELECT * FROM runs ORDER BY created DESC, rowid DESC LIMIT ?",
                               (limit,)).fetchall()
        return [self._run_dict(r) for r in rows]

    def unfinished_runs(self) -> list[str]:
        rows = self.db.execute("SELECT run_id FROM runs WHERE state IN ('queued', 'running') "
                               "ORDER BY created, rowid").fetchall()
        return [r[0] for r in rows]

    def given_without_run(self) -> list[dict[str, Any]]:
        """Experiments whose 'ready' may still be out although their run no longer runs (a
        cancel or a failure interrupted by a kill): the daemon withdraws them at start."""
        rows = self.db.execute(
            "SELECT e.* FROM experiments e JOIN runs r ON r.run_id = e.run_id "
            "WHERE e.state IN ('giving', 'given', 'taken') AND e.nonce IS NOT NULL "
            "AND r.state NOT IN ('queued', 'running')").fetchall()
        return [dict(r) for r in rows]

    def _run_dict(self, row: sqlite3.Row) -> dict[str, Any]:
        d = dict(row)
        d["spec"] = json.loads(d["spec"])
        exps = self.experiments(d["run_id"])
        d["experiments"] = exps
        d["progress"] = {"stored": sum(e["log_sha"] is not None for e in exps),
                         "total": len(exps)}
        return d

    # ----------------------------------------------------------------- experiments
    def experiments(self, run_id: str) -> list[dict[str, Any]]:
        rows = self.db.execute("SELECT * FROM experiments WHERE run_id = ? ORDER BY position",
                               (run_id,)).fetchall()
        return [dict(r) for r in rows]

    def experiment(self, run_id: str, exp_id: str) -> dict[str, Any]:
        row = self.db.execute("SELECT * FROM experiments WHERE run_id = ? AND exp_id = ?",
                              (run_id, exp_id)).fetchone()
        if row is None:
            raise ConfigError(f"run {run_id}: no experiment {exp_id}")
        return dict(row)

    def step(self, run_id: str, exp_id: str, state: str, **fields: Any) -> None:
        """Journal one step of an experiment and update its row, in one transaction."""
        bad = set(fields) - STEP_FIELDS
        if bad:
            raise ValueError(bad)
        sets = ", ".join(f"{k} = ?" for k in fields)
        with self._tx() as db:
            db.execute(f"UPDATE experiments SET state = ?, updated = ?{', ' if sets else ''}"
                       f"{sets} WHERE run_id = ? AND exp_id = ?",
                       (state, time.time(), *fields.values(), run_id, exp_id))
            self._journal(db, run_id, exp_id, state, fields)

    def note(self, run_id: str, exp_id: str | None, step: str, **detail: Any) -> None:
        """A journal line that changes no state (a retry, an ignored answer, a warning)."""
        with self._tx() as db:
            self._journal(db, run_id, exp_id, step, detail)

    @staticmethod
    def _journal(db: sqlite3.Connection, run_id: str, exp_id: str | None, step: str,
                 detail: dict[str, Any]) -> None:
        db.execute("INSERT INTO journal (time, run_id, exp_id, step, detail) "
                   "VALUES (?, ?, ?, ?, ?)", (time.time(), run_id, exp_id, step,
                                               json.dumps(detail, default=str)))

    def journal(self, run_id: str | None = None) -> list[dict[str, Any]]:
        q = "SELECT * FROM journal" + (" WHERE run_id = ?" if run_id else "") + " ORDER BY seq"
        rows = self.db.execute(q, (run_id,) if run_id else ()).fetchall()
        return [{**dict(r), "detail": json.loads(r["detail"])} for r in rows]

    # ----------------------------------------------------------------- raw logs
    def log_path(self, sha: str) -> Path:
        return self.files.log_path(sha)

    def put_log(self, data: bytes, *, run_id: str | None = None, exp_id: str | None = None
                ) -> str:
        """Store a raw log under its SHA-256 (file fsynced before its row); idempotent. With
        ``run_id`` its 'raw_stored' journal line goes in the same transaction."""
        sha = self.files.write_log(data)
        with self._tx() as db:
            db.execute("INSERT OR IGNORE INTO logs (sha256, size, stored) VALUES (?, ?, ?)",
                       (sha, len(data), time.time()))
            if run_id is not None:
                self._journal(db, run_id, exp_id, "raw_stored",
                              {"log_sha": sha, "size": len(data)})
        return sha

    def check_log(self, sha: str) -> Path:
        """The stored log's path after re-hashing it (a damaged file is an error)."""
        return self.files.check_log(sha)

    def log_count(self) -> int:
        return int(self.db.execute("SELECT COUNT(*) FROM logs").fetchone()[0])

    # ----------------------------------------------------------------- programs
    def program_for(self, key: str) -> str | None:
        row = self.db.execute("SELECT sha256 FROM programs WHERE key = ?", (key,)).fetchone()
        return row[0] if row and self.files.has_program(row[0]) else None

    def put_program(self, key: str, program: MotionProgram) -> str:
        sha = self.files.write_program(program)
        with self._tx() as db:
            db.execute("INSERT OR REPLACE INTO programs (key, sha256, created) VALUES (?, ?, ?)",
                       (key, sha, time.time()))
        return sha

    def load_program(self, sha: str) -> MotionProgram:
        return self.files.load_program(sha)

    # ----------------------------------------------------------------- approvals
    def approve(self, sha: str, campaign: str, exp_id: str, by: str) -> None:
        with self._tx() as db:
            db.execute("INSERT OR REPLACE INTO approvals (sha256, campaign, exp_id, approved, "
                       "by) VALUES (?, ?, ?, ?, ?)", (sha, campaign, exp_id, time.time(), by))

    def approved(self, sha: str) -> bool:
        return self.db.execute("SELECT 1 FROM approvals WHERE sha256 = ?",
                               (sha,)).fetchone() is not None

    # ----------------------------------------------------------------- results
    def add_result(self, run_id: str, robot: str, kind: str, record: dict[str, Any]) -> None:
        with self._tx() as db:
            db.execute("DELETE FROM results WHERE run_id = ? AND kind = ?", (run_id, kind))
            db.execute("INSERT INTO results (run_id, robot, kind, time, record) "
                       "VALUES (?, ?, ?, ?, ?)",
                       (run_id, robot, kind, time.time(), json.dumps(record)))
            self._journal(db, run_id, None, f"result_{kind}", {"robot": robot})

    def results(self, robot: str | None = None, run_id: str | None = None
                ) -> list[dict[str, Any]]:
        q, args = "SELECT * FROM results WHERE 1 = 1", list[str]()
        if robot:
            q, args = q + " AND robot = ?", [*args, robot]
        if run_id:
            q, args = q + " AND run_id = ?", [*args, run_id]
        rows = self.db.execute(q + " ORDER BY time, id", args).fetchall()
        return [{**dict(r), "record": json.loads(r["record"])} for r in rows]

    # ----------------------------------------------------------------- parameter sets
    def add_param_set(self, doc: dict[str, Any], body: bytes) -> int:
        """Keep a parameter set (its exact bytes); returns its version for the robot."""
        with self._tx() as db:
            row = db.execute("SELECT version FROM param_sets WHERE sha256 = ?",
                             (doc["sha256"],)).fetchone()
            if row:
                return int(row[0])
            version = 1 + int(db.execute("SELECT COALESCE(MAX(version), 0) FROM param_sets "
                                         "WHERE robot = ?", (doc["robot"],)).fetchone()[0])
            db.execute("INSERT INTO param_sets (sha256, robot, version, run_id, created, body) "
                       "VALUES (?, ?, ?, ?, ?, ?)", (doc["sha256"], doc["robot"], version,
                                                     doc["run_id"], time.time(), body))
            self._journal(db, doc["run_id"], None, "param_set",
                          {"robot": doc["robot"], "version": version, "sha256": doc["sha256"]})
        return version

    def param_sets(self, robot: str) -> list[dict[str, Any]]:
        rows = self.db.execute("SELECT * FROM param_sets WHERE robot = ? ORDER BY version",
                               (robot,)).fetchall()
        return [{**dict(r), "body": bytes(r["body"])} for r in rows]

    def param_set(self, robot: str, ref: str) -> dict[str, Any]:
        """A set by version number or (a prefix of) its sha256."""
        return pick_param_set(self.param_sets(robot), robot, ref)

    def approve_param_set(self, sha: str, by: str) -> None:
        with self._tx() as db:
            db.execute("UPDATE param_sets SET approved = ?, approved_by = ? WHERE sha256 = ?",
                       (time.time(), by, sha))

    def record_upload(self, robot: str, sha: str, run_id: str | None, state: str,
                      error: str | None = None) -> None:
        """An upload attempt: ``sent``, then ``acknowledged`` or ``failed``."""
        with self._tx() as db:
            db.execute("INSERT INTO param_uploads (robot, sha256, time, run_id, state, error) "
                       "VALUES (?, ?, ?, ?, ?, ?)",
                       (robot, sha, time.time(), run_id, state, error))

    def uploads(self, robot: str) -> list[dict[str, Any]]:
        rows = self.db.execute("SELECT * FROM param_uploads WHERE robot = ? ORDER BY seq",
                               (robot,)).fetchall()
        return [dict(r) for r in rows]

    def active_param_sets(self, robot: str) -> list[str]:
        """The sets the controller acknowledged, oldest first: the last one is in use, the
        one before it is what a rollback restores."""
        return acknowledged_sets(self.uploads(robot))


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


class SqliteStore(AsyncStore):
    """The daemon's SQLite store: ``Store`` behind the async interface, every call on one
    dedicated thread (queries, commits with synchronous=FULL, fsyncs, hashing), so the event
    loop never waits on the disk. ``async with SqliteStore(state_dir) as store: ...``"""

    def __init__(self, state_dir: str | Path, *, reserve_bytes: int = RESERVE_BYTES) -> None:
        self.dir = Path(state_dir)
        self._reserve_bytes = reserve_bytes
        self._store: Store | None = None
        self._thread: _StoreThread | None = None

    @property
    def reserve_bytes(self) -> int:  # type: ignore[override]
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
            self._store = await thread.call(Store, self.dir, reserve_bytes=self._reserve_bytes)
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
                         record: dict[str, Any]) -> None:
        await self._call("add_result", run_id, robot, kind, record)

    async def results(self, robot: str | None = None, run_id: str | None = None
                      ) -> list[dict[str, Any]]:
        return list(await self._call("results", robot, run_id))

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
