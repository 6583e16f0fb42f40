"""The store's queries, one implementation of each, in SQLAlchemy Core over either backend:
SQLite under a state dir (``sqlite.py``) or a plant's PostgreSQL (``postgres.py``). Raw logs and
programs are content-hashed files written and fsynced before their row (``files.py``).

``Store`` is blocking: the daemon runs it on a thread of its own (``threaded.py``), operator
commands and the fleet read it directly (``Store(state_dir, readonly=True)``,
``Store(url=URL, readonly=True)``). A store opened for a robot (the daemon's) is that robot's
view of a shared database: its runs, logs, programs and approvals, and what it writes is kept
under its name."""

from __future__ import annotations

import json
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from sqlalchemy import Connection, and_, case, delete, func, insert, or_, select, true, update
from sqlalchemy.exc import DBAPIError
from sqlalchemy.sql import ColumnElement

from robid_link.exceptions import (
    ConfigError,
    RobidError,
    StoreFullError,
    StoreLockedError,
    StoreLockLostError,
    StoreUnavailableError,
)
from robid_link.jobs import MotionProgram
from robid_link.link.store import schema as sc
from robid_link.link.store.base import (
    RUN_STATES,
    STEP_FIELDS,
    acknowledged_sets,
    log_url,
    pick_param_set,
)
from robid_link.link.store.files import CellFiles
from robid_link.link.store.postgres import PostgresBackend, claim_row
from robid_link.link.store.sqlite import SqliteBackend, lock_state_dir

__all__ = ["Store", "RESERVE_BYTES", "IDENTIFY_KINDS_SKIPPED"]

#: free bytes the store keeps in reserve: below it no new motion starts
RESERVE_BYTES = 64 << 20
#: experiment kinds whose logs an identification does not use
IDENTIFY_KINDS_SKIPPED = ("verify", "elasticity")


def _row(r: Any) -> dict[str, Any]:
    return dict(r._mapping)


class Store:
    """``Store(state_dir)``: the SQLite store of one cell, exclusive (a daemon's);
    ``Store(state_dir, url=URL, robot=NAME)``: a robot's view of a plant's PostgreSQL store,
    exclusive for that robot, its raw logs under ``state_dir`` (or ``log_store``);
    ``readonly=True``: an operator's reader; ``exclusive=False``: a writer of results that is
    no daemon (the fleet's re-identification), of an existing store unless ``create``."""

    def __init__(self, state_dir: str | Path | None = None, *, url: str | None = None,
                 robot: str | None = None, readonly: bool = False,
                 exclusive: bool | None = None, reserve_bytes: int = RESERVE_BYTES,
                 log_store: str | None = None, create: bool = False) -> None:
        self.dir = Path(state_dir) if state_dir is not None else None
        self.robot = robot
        self.readonly = readonly
        self.exclusive = (not readonly) if exclusive is None else exclusive
        self.reserve_bytes = reserve_bytes
        self.conn: Connection | None = None
        self._lock_fd: int | None = None
        self._create = create
        #: the one line once a lost connection's robot lock could not be taken again
        self.lock_lost: str | None = None
        if url is None and self.dir is None:
            raise ValueError("a store needs a state dir or a URL")
        self.backend: SqliteBackend | PostgresBackend = (
            PostgresBackend(url) if url is not None else SqliteBackend(self.dir))  # type: ignore[arg-type]
        self.where = self.backend.where
        self.files = CellFiles(self.dir, log_store) if self.dir is not None else None
        try:
            self._open()
        except BaseException:
            self.close()
            raise

    def _open(self) -> None:
        if self.exclusive:
            assert self.files is not None and self.dir is not None and not self.readonly
            self.files.prepare()
            self._lock_fd = lock_state_dir(self.dir)
        self.engine = self.backend.engine(self.readonly)
        try:
            self.conn = self.engine.connect()
        except DBAPIError as err:
            raise StoreUnavailableError(f"{self.where}: cannot connect "
                                        f"({_first_line(err)})") from err
        if self.exclusive:
            self.backend.lock(self.conn, self.robot)
        try:
            self._schema()
        except DBAPIError as err:  # a damaged file, or a database that is not robid's
            raise RobidError(f"{self.where}: cannot read its store ({_first_line(err)})"
                             ) from err

    def _schema(self) -> None:
        """A reader checks the schema's version; a writer creates or migrates it."""
        if self.readonly:
            with self._read() as c:
                sc.check_readable(c, self.where)
            return
        with self._tx() as c:
            self.backend.migration_lock(c)
            if not (self.exclusive or self._create) and sc.schema_version(c) is None:
                raise ConfigError(f"{self.where} holds no store yet")
            sc.migrate(c, self.where)
            if self.exclusive and self.robot is not None:
                self._claim(c)

    def _claim(self, c: Connection) -> None:
        """The robots row of the daemon that holds the robot; in a one-robot (SQLite) store
        the rows written before robots had names become this robot's."""
        assert self.robot is not None
        row = claim_row(self.robot, str(self.dir), self.files.location if self.files else None)
        if not c.execute(update(sc.robots).where(sc.robots.c.robot == self.robot)
                         .values(**row)).rowcount:
            c.execute(insert(sc.robots).values(**row))
        if not self.backend.shared:
            c.execute(update(sc.runs).where(sc.runs.c.robot.is_(None))
                      .values(robot=self.robot))
            for t in (sc.logs, sc.programs, sc.approvals):
                c.execute(update(t).where(t.c.robot == "").values(robot=self.robot))
            c.execute(update(sc.logs).where(sc.logs.c.location.is_(None))
                      .values(location=row["log_location"]))

    def close(self) -> None:
        conn, self.conn = self.conn, None
        if conn is not None:
            conn.close()  # a PostgreSQL session ends: its advisory lock is released
            self.engine.dispose()
        if self._lock_fd is not None:
            import os

            os.close(self._lock_fd)  # releases the flock
            self._lock_fd = None

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ----------------------------------------------------------------- transactions
    def _connection(self) -> Connection:
        if self.conn is None:
            raise RuntimeError(f"{self.where}: the store is closed")
        if self.lock_lost:
            raise StoreLockLostError(self.lock_lost)
        if self.conn.invalidated and self.exclusive:
            # the session was lost (server restart): a new one must take the robot again
            try:
                self.backend.lock(self.conn, self.robot)
            except StoreLockedError as err:  # another daemon took the robot meanwhile
                self.lock_lost = (f"{self.where}: lock on robot {self.robot} lost with the "
                                  f"connection, another daemon holds it now: no further "
                                  f"motion from this daemon; stop it")
                self.conn.invalidate()  # this session holds nothing: never write through it
                raise StoreLockLostError(self.lock_lost) from err
            except StoreUnavailableError:
                self.conn.invalidate()  # holds no lock: the next call takes it again
                raise
            except DBAPIError as err:
                if not self.conn.invalidated:
                    self.conn.invalidate()
                raise StoreUnavailableError(f"{self.where}: cannot reconnect "
                                            f"({_first_line(err)})") from err
        return self.conn

    @contextmanager
    def _tx(self) -> Iterator[Connection]:
        """One write transaction (SQLite: BEGIN IMMEDIATE); a full disk is StoreFullError,
        a lost connection one line naming the store."""
        conn = self._connection()
        conn.info["write"] = True
        try:
            with conn.begin():
                yield conn
        except DBAPIError as err:
            full = self.backend.full(err)
            if full is not None:
                raise full from err
            self._unavailable(err)
            raise

    @contextmanager
    def _read(self) -> Iterator[Connection]:
        conn = self._connection()
        conn.info["write"] = False
        try:
            with conn.begin():
                yield conn
        except DBAPIError as err:
            self._unavailable(err)
            raise

    def _unavailable(self, err: DBAPIError) -> None:
        """A lost connection or a server that does not answer: StoreUnavailableError, one
        line naming the store (a password is never in it)."""
        if self.backend.lost(err):
            raise StoreUnavailableError(f"{self.where}: connection lost "
                                        f"({_first_line(err)})") from err

    def _mine(self, column: Any) -> ColumnElement[bool]:
        """Rows of this store's robot (all rows for a store opened for no robot)."""
        if self.robot is None:
            return true()
        return column == self.robot

    def _key(self) -> str:
        """The robot column of programs, approvals and logs ('' before robots had names)."""
        return self.robot or ""

    # ----------------------------------------------------------------- space
    def _cell(self) -> CellFiles:
        if self.files is None:
            raise ConfigError(f"{self.where}: opened without a state dir (no cell files here)")
        return self.files

    def free_bytes(self) -> int:
        return self._cell().free_bytes()

    def require_space(self, need_bytes: int = 0, what: str = "a new run") -> None:
        """Refuse ``what`` (before any motion) unless ``need_bytes`` fit above the reserve."""
        free = self.free_bytes()
        if free < need_bytes + self.reserve_bytes:
            raise StoreFullError(f"state_dir: {self.dir} has {free >> 20} MiB free, "
                                 f"{(need_bytes + self.reserve_bytes) >> 20} MiB needed for "
                                 f"{what}: waiting for space")

    # ----------------------------------------------------------------- robots
    def register_robot(self, robot_type: str, description_name: str, description: bytes,
                       lock: list[str] | tuple[str, ...] = ()) -> None:
        """What this store's robot is: its type (the description's name) and description
        (what the fleet re-identifies with)."""
        if self.robot is None:
            raise ValueError("register_robot: the store was opened for no robot")
        with self._tx() as c:
            c.execute(update(sc.robots).where(sc.robots.c.robot == self.robot).values(
                type=robot_type, description_name=description_name, description=description,
                lock=json.dumps(list(lock)), seen=time.time()))

    def robots(self) -> list[dict[str, Any]]:
        """Every robot the store knows (its directory, and robots with results only: a store
        of the SQLite days), by name; without the description bytes."""
        r = sc.robots
        with self._read() as c:
            rows = {x.robot: _row(x) for x in c.execute(
                select(r.c.robot, r.c.type, r.c.description_name, r.c.lock, r.c.host, r.c.pid,
                       r.c.state_dir, r.c.log_location, r.c.seen))}
            for name in c.execute(select(sc.results.c.robot).distinct()).scalars():
                rows.setdefault(name, {"robot": name, "type": None, "description_name": None,
                                       "lock": None, "host": None, "pid": None,
                                       "state_dir": None, "log_location": None, "seen": None})
        for d in rows.values():
            d["lock"] = json.loads(d["lock"]) if d["lock"] else []
        return [rows[k] for k in sorted(rows)]

    def robot_description(self, robot: str) -> tuple[str, bytes, list[str]]:
        """(file name, bytes, locked joints) of a robot's description as its daemon gave it."""
        r = sc.robots
        with self._read() as c:
            row = c.execute(select(r.c.description_name, r.c.description, r.c.lock)
                            .where(r.c.robot == robot)).first()
        if row is None or row.description is None:
            raise ConfigError(f"robot {robot}: the store holds no description of it (its "
                              "daemon has not started since the store became a plant's)")
        return row.description_name, bytes(row.description), json.loads(row.lock or "[]")

    # ----------------------------------------------------------------- runs
    def create_run(self, campaign: str, trigger: str, spec: dict[str, Any],
                   experiments: list[tuple[str, str]]) -> str:
        """A new queued run with its experiments (``(exp_id, kind)`` in order)."""
        run_id = time.strftime("%Y%m%d-%H%M%S-") + uuid.uuid4().hex[:6]
        now = time.time()
        with self._tx() as c:
            c.execute(insert(sc.runs).values(run_id=run_id, robot=self.robot, campaign=campaign,
                                             trigger=trigger, state="queued", created=now,
                                             spec=json.dumps(spec), state_since=now))
            if experiments:
                c.execute(insert(sc.experiments), [
                    {"run_id": run_id, "exp_id": exp_id, "position": pos, "kind": kind,
                     "state": "pending", "attempt": 0, "updated": now}
                    for pos, (exp_id, kind) in enumerate(experiments)])
            self._journal(c, run_id, None, "queued", {"campaign": campaign, "trigger": trigger})
        return run_id

    def set_run(self, run_id: str, state: str, *, error: str | None = None,
                step: str | None = None) -> None:
        if state not in RUN_STATES:
            raise ValueError(state)
        now = time.time()
        r = sc.runs
        values: dict[str, Any] = {"state": state, "step": step,
                                  "finished": now if state in ("completed", "failed",
                                                               "cancelled") else None}
        if error is not None:
            values["error"] = error
        if state == "running":
            values["started"] = func.coalesce(r.c.started, now)
        # since when the run is in its state: kept by an update that does not change it
        values["state_since"] = case((r.c.state == state,
                                      func.coalesce(r.c.state_since, r.c.created)), else_=now)
        with self._tx() as c:
            c.execute(update(r).where(r.c.run_id == run_id).values(**values))
            self._journal(c, run_id, None, state, {"error": error} if error else {})

    def run(self, run_id: str) -> dict[str, Any]:
        with self._read() as c:
            row = c.execute(select(sc.runs).where(sc.runs.c.run_id == run_id,
                                                  self._mine(sc.runs.c.robot))).first()
            if row is None:
                raise ConfigError(f"run {run_id}: not in the store")
            return self._run_dict(c, row)

    def runs(self, limit: int = 50) -> list[dict[str, Any]]:
        r = sc.runs
        with self._read() as c:
            rows = c.execute(select(r).where(self._mine(r.c.robot))
                             .order_by(r.c.created.desc(), r.c.run_id.desc()).limit(limit))
            return [self._run_dict(c, x) for x in rows.all()]

    def unfinished_runs(self) -> list[str]:
        r = sc.runs
        with self._read() as c:
            return list(c.execute(select(r.c.run_id).where(
                r.c.state.in_(("queued", "running")), self._mine(r.c.robot))
                .order_by(r.c.created, r.c.run_id)).scalars())

    def given_without_run(self) -> list[dict[str, Any]]:
        """Experiments whose 'ready' may still be out although their run no longer runs (a
        cancel or a failure interrupted by a kill): the daemon withdraws them at start."""
        e, r = sc.experiments, sc.runs
        with self._read() as c:
            rows = c.execute(select(e).join(r, r.c.run_id == e.c.run_id).where(
                e.c.state.in_(("giving", "given", "taken")), e.c.nonce.is_not(None),
                r.c.state.not_in(("queued", "running")), self._mine(r.c.robot)))
            return [_row(x) for x in rows]

    def _run_dict(self, c: Connection, row: Any) -> dict[str, Any]:
        d = _row(row)
        d["spec"] = json.loads(d["spec"])
        if d.get("state_since") is None:  # a run of an older store, untouched since
            d["state_since"] = d["created"]
        exps = self._experiments(c, d["run_id"])
        d["experiments"] = exps
        d["progress"] = {"stored": sum(e["log_sha"] is not None for e in exps),
                         "total": len(exps)}
        return d

    # ----------------------------------------------------------------- experiments
    @staticmethod
    def _experiments(c: Connection, run_id: str) -> list[dict[str, Any]]:
        e = sc.experiments
        return [_row(x) for x in c.execute(select(e).where(e.c.run_id == run_id)
                                           .order_by(e.c.position))]

    def experiments(self, run_id: str) -> list[dict[str, Any]]:
        with self._read() as c:
            return self._experiments(c, run_id)

    def experiment(self, run_id: str, exp_id: str) -> dict[str, Any]:
        e = sc.experiments
        with self._read() as c:
            row = c.execute(select(e).where(e.c.run_id == run_id, e.c.exp_id == exp_id)).first()
        if row is None:
            raise ConfigError(f"run {run_id}: no experiment {exp_id}")
        return _row(row)

    def step(self, run_id: str, exp_id: str, state: str, **fields: Any) -> None:
        """Journal one step of an experiment and update its row, in one transaction."""
        bad = set(fields) - STEP_FIELDS
        if bad:
            raise ValueError(bad)
        e = sc.experiments
        with self._tx() as c:
            c.execute(update(e).where(e.c.run_id == run_id, e.c.exp_id == exp_id)
                      .values(state=state, updated=time.time(), **fields))
            self._journal(c, run_id, exp_id, state, fields)

    def note(self, run_id: str, exp_id: str | None, step: str, **detail: Any) -> None:
        """A journal line that changes no state (a retry, an ignored answer, a warning)."""
        with self._tx() as c:
            self._journal(c, run_id, exp_id, step, detail)

    @staticmethod
    def _journal(c: Connection, run_id: str, exp_id: str | None, step: str,
                 detail: dict[str, Any]) -> None:
        c.execute(insert(sc.journal).values(time=time.time(), run_id=run_id, exp_id=exp_id,
                                            step=step, detail=json.dumps(detail, default=str)))

    def journal(self, run_id: str | None = None) -> list[dict[str, Any]]:
        j = sc.journal
        q = select(j)
        if run_id:
            q = q.where(j.c.run_id == run_id)
        elif self.robot is not None:
            q = q.where(j.c.run_id.in_(select(sc.runs.c.run_id).where(
                self._mine(sc.runs.c.robot))))
        with self._read() as c:
            return [{**_row(x), "detail": json.loads(x.detail)}
                    for x in c.execute(q.order_by(j.c.seq))]

    # ----------------------------------------------------------------- raw logs
    def log_path(self, sha: str) -> Path:
        return self._cell().log_path(sha)

    def put_log(self, data: bytes, *, run_id: str | None = None, exp_id: str | None = None
                ) -> str:
        """Store a raw log under its SHA-256 (file fsynced before its row); idempotent. With
        ``run_id`` its 'raw_stored' journal line goes in the same transaction."""
        cell = self._cell()
        sha = cell.write_log(data)
        lg = sc.logs
        with self._tx() as c:
            known = c.execute(select(lg.c.sha256).where(lg.c.robot == self._key(),
                                                        lg.c.sha256 == sha)).first()
            if known is None:
                c.execute(insert(lg).values(robot=self._key(), sha256=sha, size=len(data),
                                            stored=time.time(), location=cell.location))
            if run_id is not None:
                self._journal(c, run_id, exp_id, "raw_stored",
                              {"log_sha": sha, "size": len(data)})
        return sha

    def check_log(self, sha: str) -> Path:
        """The stored log's path after re-hashing it (a damaged file is an error)."""
        return self._cell().check_log(sha)

    def log_count(self) -> int:
        lg = sc.logs
        q = select(func.count()).select_from(lg)
        if self.robot is not None:
            q = q.where(lg.c.robot == self.robot)
        with self._read() as c:
            return int(c.execute(q).scalar_one())

    def identify_inputs(self, robot: str, since: float | None = None
                        ) -> list[dict[str, Any]]:
        """The completed runs of ``robot`` (created at or after ``since``) with the raw logs
        their identification used: ``run_id``, ``created``, ``spec``, ``logs`` (``sha256``,
        ``url``: where the log is, from its row's location)."""
        r, e, lg = sc.runs, sc.experiments, sc.logs
        q = select(r.c.run_id, r.c.created, r.c.spec).where(
            r.c.robot == robot, r.c.state == "completed")
        if since is not None:
            q = q.where(r.c.created >= since)
        out = []
        with self._read() as c:
            for run in c.execute(q.order_by(r.c.created, r.c.run_id)).all():
                rows = c.execute(
                    select(e.c.log_sha, lg.c.location).join(lg, and_(
                        lg.c.sha256 == e.c.log_sha, or_(lg.c.robot == robot, lg.c.robot == "")))
                    .where(e.c.run_id == run.run_id, e.c.log_sha.is_not(None),
                           e.c.kind.not_in(IDENTIFY_KINDS_SKIPPED))
                    .order_by(e.c.position)).all()
                logs = [{"sha256": x.log_sha, "url": log_url(x.location, x.log_sha)}
                        for x in rows if x.location]
                if logs:
                    out.append({"run_id": run.run_id, "created": run.created,
                                "spec": json.loads(run.spec), "logs": logs})
        return out

    # ----------------------------------------------------------------- programs
    def program_for(self, key: str) -> str | None:
        p = sc.programs
        with self._read() as c:
            sha = c.execute(select(p.c.sha256).where(p.c.robot == self._key(),
                                                     p.c.key == key)).scalar()
        return sha if sha and self._cell().has_program(sha) else None

    def put_program(self, key: str, program: MotionProgram) -> str:
        sha = self._cell().write_program(program)
        p = sc.programs
        with self._tx() as c:
            c.execute(delete(p).where(p.c.robot == self._key(), p.c.key == key))
            c.execute(insert(p).values(robot=self._key(), key=key, sha256=sha,
                                       created=time.time()))
        return sha

    def load_program(self, sha: str) -> MotionProgram:
        return self._cell().load_program(sha)

    # ----------------------------------------------------------------- approvals
    def approve(self, sha: str, campaign: str, exp_id: str, by: str) -> None:
        a = sc.approvals
        with self._tx() as c:
            c.execute(delete(a).where(a.c.robot == self._key(), a.c.sha256 == sha))
            c.execute(insert(a).values(robot=self._key(), sha256=sha, campaign=campaign,
                                       exp_id=exp_id, approved=time.time(), by=by))

    def approved(self, sha: str) -> bool:
        a = sc.approvals
        with self._read() as c:
            return c.execute(select(a.c.sha256).where(a.c.robot == self._key(),
                                                      a.c.sha256 == sha)).first() is not None

    # ----------------------------------------------------------------- results
    def add_result(self, run_id: str, robot: str, kind: str, record: dict[str, Any],
                   *, model_version: str = "") -> None:
        """A run's result of ``kind`` (replacing an earlier one of the same run, kind and
        model version; ``''``: the run's own model, another: a fleet re-identification)."""
        res = sc.results
        with self._tx() as c:
            c.execute(delete(res).where(res.c.run_id == run_id, res.c.kind == kind,
                                        res.c.model_version == model_version))
            c.execute(insert(res).values(run_id=run_id, robot=robot, kind=kind,
                                         model_version=model_version, time=time.time(),
                                         record=json.dumps(record)))
            detail = {"robot": robot, **({"model_version": model_version}
                                         if model_version else {})}
            self._journal(c, run_id, None, f"result_{kind}", detail)

    def results(self, robot: str | None = None, run_id: str | None = None,
                model_version: str | None = "") -> list[dict[str, Any]]:
        """Results (of a robot, of a run) in the order they were stored; of the runs' own
        model (``model_version=''``), of another version, or of all (None)."""
        res = sc.results
        q = select(res)
        if robot:
            q = q.where(res.c.robot == robot)
        if run_id:
            q = q.where(res.c.run_id == run_id)
        if model_version is not None:
            q = q.where(res.c.model_version == model_version)
        with self._read() as c:
            return [{**_row(x), "record": json.loads(x.record)}
                    for x in c.execute(q.order_by(res.c.time, res.c.id))]

    # ----------------------------------------------------------------- parameter sets
    def add_param_set(self, doc: dict[str, Any], body: bytes) -> int:
        """Keep a parameter set (its exact bytes) under this store's robot (else the set's);
        returns its version for the robot."""
        robot = self.robot or doc["robot"]
        ps = sc.param_sets
        with self._tx() as c:
            version = c.execute(select(ps.c.version).where(
                ps.c.robot == robot, ps.c.sha256 == doc["sha256"])).scalar()
            if version is not None:
                return int(version)
            version = 1 + int(c.execute(select(func.coalesce(func.max(ps.c.version), 0))
                                        .where(ps.c.robot == robot)).scalar_one())
            c.execute(insert(ps).values(sha256=doc["sha256"], robot=robot, version=version,
                                        run_id=doc["run_id"], created=time.time(), body=body))
            self._journal(c, doc["run_id"], None, "param_set",
                          {"robot": robot, "version": version, "sha256": doc["sha256"]})
        return int(version)

    def param_sets(self, robot: str) -> list[dict[str, Any]]:
        ps = sc.param_sets
        with self._read() as c:
            return [{**_row(x), "body": bytes(x.body)} for x in c.execute(
                select(ps).where(ps.c.robot == robot).order_by(ps.c.version))]

    def param_set(self, robot: str, ref: str) -> dict[str, Any]:
        """A set by version number or (a prefix of) its sha256."""
        return pick_param_set(self.param_sets(robot), robot, ref)

    def approve_param_set(self, sha: str, by: str) -> None:
        """Approve this robot's set ``sha``; another robot's is refused naming both."""
        ps = sc.param_sets
        with self._tx() as c:
            done = c.execute(update(ps).where(ps.c.sha256 == sha, self._mine(ps.c.robot))
                             .values(approved=time.time(), approved_by=by)).rowcount
            if not done:
                other = c.execute(select(ps.c.robot, ps.c.version)
                                  .where(ps.c.sha256 == sha)).first()
                if other is None:
                    raise ConfigError(f"parameter set {sha[:12]}: not in the store")
                raise ConfigError(f"parameter set {other.version} of robot {other.robot} "
                                  f"({sha[:12]}): this store is robot {self.robot}'s; approve "
                                  f"it with robot {other.robot}'s daemon")

    def record_upload(self, robot: str, sha: str, run_id: str | None, state: str,
                      error: str | None = None) -> None:
        """An upload attempt: ``sent``, then ``acknowledged`` or ``failed``."""
        with self._tx() as c:
            c.execute(insert(sc.param_uploads).values(robot=robot, sha256=sha, time=time.time(),
                                                      run_id=run_id, state=state, error=error))

    def uploads(self, robot: str) -> list[dict[str, Any]]:
        u = sc.param_uploads
        with self._read() as c:
            return [_row(x) for x in c.execute(select(u).where(u.c.robot == robot)
                                               .order_by(u.c.seq))]

    def active_param_sets(self, robot: str) -> list[str]:
        """The sets the controller acknowledged, oldest first: the last one is in use, the
        one before it is what a rollback restores."""
        return acknowledged_sets(self.uploads(robot))


def _first_line(err: DBAPIError) -> str:
    text = str(err.orig or err).strip()
    return text.splitlines()[0] if text else type(err).__name__
