"""The daemon's store: SQLite (WAL, synchronous=FULL) for runs, experiments, the step journal,
results and approvals; raw logs and programs as content-hashed files written and fsynced
before their row. One daemon per ``state_dir``, enforced with ``flock``."""

from __future__ import annotations

import errno
import fcntl
import hashlib
import json
import os
import sqlite3
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

from robid_link.atomic import atomic_write, fsync_dir
from robid_link.exceptions import ConfigError, RobidError, StoreFullError, StoreLockedError
from robid_link.jobs import MotionProgram

__all__ = ["Store", "RUN_STATES"]

RUN_STATES = ("queued", "running", "completed", "failed", "cancelled")

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
_FULL_ERRNOS = {errno.ENOSPC, errno.EDQUOT}


class Store:
    """Open with ``Store(state_dir)`` (exclusive, for the daemon) or
    ``Store(state_dir, readonly=True)`` (operator commands while no daemon answers)."""

    def __init__(self, state_dir: str | Path, *, readonly: bool = False,
                 reserve_bytes: int = RESERVE_BYTES) -> None:
        self.dir = Path(state_dir)
        self.reserve_bytes = reserve_bytes
        self.readonly = readonly
        self._lock_fd: int | None = None
        db = self.dir / "robid.sqlite"
        if readonly:
            if not db.is_file():
                raise ConfigError(f"state_dir: {self.dir} holds no store yet")
            self.db = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=10.0)
        else:
            try:
                self.dir.mkdir(parents=True, exist_ok=True)
                for sub in ("logs", "programs", "reports"):
                    (self.dir / sub).mkdir(exist_ok=True)
            except OSError as err:
                raise ConfigError(f"state_dir: {self.dir}: {err.strerror}") from err
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
        st = os.statvfs(self.dir)
        return st.f_bavail * st.f_frsize

    def require_space(self, need_bytes: int = 0, what: str = "a new run") -> None:
        """Refuse ``what`` (before any motion) unless ``need_bytes`` fit above the reserve."""
        free = self.free_bytes()
        if free < need_bytes + self.reserve_bytes:
            raise StoreFullError(f"state_dir: {self.dir} has {free >> 20} MiB free, "
                                 f"{(need_bytes + self.reserve_bytes) >> 20} MiB needed for "
                                 f"{what}: waiting for space")

    def _full(self, err: BaseException) -> StoreFullError:
        return StoreFullError(f"state_dir: {self.dir}: disk full while writing "
                              f"({str(err).splitlines()[0]}): waiting for space")

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
                raise self._full(err) from err
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

    def set_step(self, run_id: str, step: str) -> None:
        with self._tx() as db:
            db.execute("UPDATE runs SET step = ? WHERE run_id = ?", (step, run_id))

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
        allowed = {"attempt", "nonce", "program_sha", "done_sha", "done_size", "log_sha", "error"}
        bad = set(fields) - allowed
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
        return self.dir / "logs" / sha[:2] / f"{sha}.csv"

    def put_log(self, data: bytes) -> str:
        """Store a raw log under its SHA-256 (file fsynced before its row); idempotent."""
        sha = hashlib.sha256(data).hexdigest()
        path = self.log_path(sha)
        try:
            if not (path.is_file() and path.stat().st_size == len(data)):
                if not path.parent.is_dir():  # a new fan-out folder must survive a power cut
                    path.parent.mkdir()
                    fsync_dir(path.parent.parent)
                atomic_write(path, data, 0o444)
        except OSError as err:
            if err.errno in _FULL_ERRNOS:
                raise self._full(err) from err
            raise
        with self._tx() as db:
            db.execute("INSERT OR IGNORE INTO logs (sha256, size, stored) VALUES (?, ?, ?)",
                       (sha, len(data), time.time()))
        return sha

    def check_log(self, sha: str) -> Path:
        """The stored log's path after re-hashing it (a damaged file is an error)."""
        path = self.log_path(sha)
        try:
            got = hashlib.sha256(path.read_bytes()).hexdigest()
        except FileNotFoundError as err:
            raise RobidError(f"{path}: stored log missing") from err
        if got != sha:
            raise RobidError(f"{path}: stored log damaged (sha256 {got[:12]}…)")
        return path

    def log_count(self) -> int:
        return int(self.db.execute("SELECT COUNT(*) FROM logs").fetchone()[0])

    # ----------------------------------------------------------------- programs
    def program_for(self, key: str) -> str | None:
        row = self.db.execute("SELECT sha256 FROM programs WHERE key = ?", (key,)).fetchone()
        return row[0] if row and (self.dir / "programs" / row[0]).is_dir() else None

    def put_program(self, key: str, program: MotionProgram) -> str:
        sha = program.sha256
        folder = self.dir / "programs" / sha
        if not folder.is_dir():
            tmp = self.dir / "programs" / f".{sha}.{os.getpid()}.tmp"
            try:
                tmp.mkdir(exist_ok=True)
                for suffix, data in program.files.items():
                    atomic_write(tmp / suffix, data)
                meta = {"exp_id": program.exp_id, "duration_s": program.duration_s,
                        "meta": dict(program.meta)}
                atomic_write(tmp / "program.json", json.dumps(meta).encode())
                os.replace(tmp, folder)
                fsync_dir(folder.parent)
            except OSError as err:
                if err.errno in _FULL_ERRNOS:
                    raise self._full(err) from err
                raise
        with self._tx() as db:
            db.execute("INSERT OR REPLACE INTO programs (key, sha256, created) VALUES (?, ?, ?)",
                       (key, sha, time.time()))
        return sha

    def load_program(self, sha: str) -> MotionProgram:
        folder = self.dir / "programs" / sha
        try:
            meta = json.loads((folder / "program.json").read_text())
            files = {p.name: p.read_bytes() for p in folder.iterdir() if p.name != "program.json"}
        except (OSError, ValueError) as err:
            raise RobidError(f"{folder}: stored program unreadable ({err})") from err
        prog = MotionProgram(meta["exp_id"], files, meta["duration_s"], meta["meta"])
        if prog.sha256 != sha:
            raise RobidError(f"{folder}: stored program damaged (hash differs)")
        return prog

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
        sets = self.param_sets(robot)
        hits = [s for s in sets if str(s["version"]) == ref or s["sha256"].startswith(ref)]
        if len(hits) != 1:
            raise ConfigError(f"robot {robot}: {'no' if not hits else 'more than one'} "
                              f"parameter set matches {ref!r}")
        return hits[0]

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
        acked = [u["sha256"] for u in self.uploads(robot) if u["state"] == "acknowledged"]
        out: list[str] = []
        for sha in acked:
            if not out or out[-1] != sha:
                out.append(sha)
        return out
