"""The store's one schema (SQLAlchemy Core tables, the same on SQLite and PostgreSQL) and its
versioned migrations, run by the project when a daemon opens the store.

Version 1 is the schema of the SQLite-only store (no version table); version 2 adds the plant:
a robot on every run, log, program and approval (one store, many robots), where each raw log
lives, the ``robots`` directory, and a model version on results; version 3 the time a run
entered its state (``state_since``: since when an interrupted run waits for its operator).
``migrate`` brings a store to ``SCHEMA_VERSION`` in one transaction, under a lock against a
second daemon migrating at once.

Why not Alembic: the schema is nine tables and each step a few lines of Core DDL, tested on
both backends by the store's suite; the runner is ~50 lines with no script folder, ini file or
template engine to ship inside the wheel of the embedded (SQLite) default.
"""

from __future__ import annotations

from collections.abc import Callable

from sqlalchemy import (
    Column,
    Connection,
    Float,
    Integer,
    LargeBinary,
    MetaData,
    PrimaryKeyConstraint,
    Table,
    Text,
    inspect,
    select,
    text,
)

from robid_link.exceptions import ConfigError

__all__ = ["SCHEMA_VERSION", "metadata", "robots", "runs", "experiments", "journal", "logs",
           "programs", "approvals", "results", "param_sets", "param_uploads", "migrate",
           "schema_version"]

#: the schema this code reads and writes
SCHEMA_VERSION = 3

metadata = MetaData()

version_table = Table("robid_schema", metadata, Column("version", Integer, nullable=False))

#: the plant's directory of robots: who holds each (host, pid), its type and description
robots = Table(
    "robots", metadata,
    Column("robot", Text, primary_key=True),
    Column("type", Text), Column("description_name", Text), Column("description", LargeBinary),
    Column("lock", Text), Column("host", Text), Column("pid", Integer),
    Column("state_dir", Text), Column("log_location", Text), Column("seen", Float))

runs = Table(
    "runs", metadata,
    Column("run_id", Text, primary_key=True), Column("robot", Text),
    Column("campaign", Text, nullable=False), Column("trigger", Text, nullable=False),
    Column("state", Text, nullable=False), Column("created", Float, nullable=False),
    Column("started", Float), Column("finished", Float), Column("spec", Text, nullable=False),
    Column("error", Text), Column("step", Text), Column("state_since", Float))

experiments = Table(
    "experiments", metadata,
    Column("run_id", Text, nullable=False), Column("exp_id", Text, nullable=False),
    Column("position", Integer, nullable=False), Column("kind", Text, nullable=False),
    Column("state", Text, nullable=False),
    Column("attempt", Integer, nullable=False, server_default=text("0")),
    Column("nonce", Text), Column("program_sha", Text), Column("done_sha", Text),
    Column("done_size", Integer), Column("log_sha", Text), Column("error", Text),
    Column("updated", Float, nullable=False),
    PrimaryKeyConstraint("run_id", "exp_id"))

journal = Table(
    "journal", metadata,
    Column("seq", Integer, primary_key=True, autoincrement=True),
    Column("time", Float, nullable=False), Column("run_id", Text, nullable=False),
    Column("exp_id", Text), Column("step", Text, nullable=False),
    Column("detail", Text, nullable=False),
    sqlite_autoincrement=True)

logs = Table(
    "logs", metadata,
    Column("robot", Text, nullable=False, server_default=text("''")),
    Column("sha256", Text, nullable=False), Column("size", Integer, nullable=False),
    Column("stored", Float, nullable=False), Column("location", Text),
    PrimaryKeyConstraint("robot", "sha256"))

programs = Table(
    "programs", metadata,
    Column("robot", Text, nullable=False, server_default=text("''")),
    Column("key", Text, nullable=False), Column("sha256", Text, nullable=False),
    Column("created", Float, nullable=False),
    PrimaryKeyConstraint("robot", "key"))

approvals = Table(
    "approvals", metadata,
    Column("robot", Text, nullable=False, server_default=text("''")),
    Column("sha256", Text, nullable=False), Column("campaign", Text, nullable=False),
    Column("exp_id", Text, nullable=False), Column("approved", Float, nullable=False),
    Column("by", Text, nullable=False),
    PrimaryKeyConstraint("robot", "sha256"))

results = Table(
    "results", metadata,
    Column("id", Integer, primary_key=True, autoincrement=True),
    Column("run_id", Text, nullable=False), Column("robot", Text, nullable=False),
    Column("kind", Text, nullable=False),
    Column("model_version", Text, nullable=False, server_default=text("''")),
    Column("time", Float, nullable=False), Column("record", Text, nullable=False),
    sqlite_autoincrement=True)

param_sets = Table(
    "param_sets", metadata,
    Column("robot", Text, nullable=False), Column("sha256", Text, nullable=False),
    Column("version", Integer, nullable=False), Column("run_id", Text, nullable=False),
    Column("created", Float, nullable=False), Column("body", LargeBinary, nullable=False),
    Column("approved", Float), Column("approved_by", Text),
    PrimaryKeyConstraint("robot", "sha256"))

param_uploads = Table(
    "param_uploads", metadata,
    Column("seq", Integer, primary_key=True, autoincrement=True),
    Column("robot", Text, nullable=False), Column("sha256", Text, nullable=False),
    Column("time", Float, nullable=False), Column("run_id", Text),
    Column("state", Text, nullable=False), Column("error", Text),
    sqlite_autoincrement=True)

# the queries' paths: a robot's runs by state, a run's journal, a robot's results
_INDEXES = (
    "CREATE INDEX IF NOT EXISTS runs_robot_state ON runs (robot, state)",
    "CREATE INDEX IF NOT EXISTS journal_run ON journal (run_id, seq)",
    "CREATE INDEX IF NOT EXISTS results_robot ON results (robot, model_version, time)",
    "CREATE INDEX IF NOT EXISTS results_run ON results (run_id, kind)",
    "CREATE INDEX IF NOT EXISTS uploads_robot ON param_uploads (robot, seq)",
)


def schema_version(conn: Connection) -> int | None:
    """The store's schema version; 1 for a store of the SQLite-only days (tables, no
    version), None for an empty database."""
    names = set(inspect(conn).get_table_names())
    if "robid_schema" in names:
        return int(conn.execute(select(version_table.c.version)).scalar_one())
    return 1 if "runs" in names else None


def _rebuild(conn: Connection, table: Table, columns: str, source: str) -> None:
    """Give ``table`` its version-2 shape (a new primary key): create it under a temporary
    name, copy ``columns`` from ``source`` (a SELECT list over the old table), swap."""
    old = f"{table.name}_v1"
    conn.execute(text(f"ALTER TABLE {table.name} RENAME TO {old}"))
    table.create(conn)
    conn.execute(text(f"INSERT INTO {table.name} ({columns}) SELECT {source} FROM {old}"))
    conn.execute(text(f"DROP TABLE {old}"))


def _v1_to_v2(conn: Connection) -> None:
    """Robots on rows (NULL: the one robot of a single-robot store, adopted when its daemon
    opens it), log locations, model versions, the robots directory."""
    conn.execute(text("ALTER TABLE runs ADD COLUMN robot TEXT"))
    conn.execute(text("ALTER TABLE results ADD COLUMN model_version TEXT NOT NULL DEFAULT ''"))
    _rebuild(conn, logs, "robot, sha256, size, stored, location",
             "'', sha256, size, stored, NULL")
    _rebuild(conn, programs, "robot, key, sha256, created", "'', key, sha256, created")
    _rebuild(conn, approvals, "robot, sha256, campaign, exp_id, approved, by",
             "'', sha256, campaign, exp_id, approved, by")
    _rebuild(conn, param_sets, "robot, sha256, version, run_id, created, body, approved, "
             "approved_by", "robot, sha256, version, run_id, created, body, approved, "
             "approved_by")
    robots.create(conn)


def _v2_to_v3(conn: Connection) -> None:
    """When each run entered its state (NULL for the runs before: read as their creation)."""
    if "state_since" not in {c["name"] for c in inspect(conn).get_columns("runs")}:
        conn.execute(text("ALTER TABLE runs ADD COLUMN state_since FLOAT"))


#: version k → the step from k to k + 1
MIGRATIONS: dict[int, Callable[[Connection], None]] = {1: _v1_to_v2, 2: _v2_to_v3}


def migrate(conn: Connection, where: str) -> int:
    """Create the schema in an empty database or step it up to ``SCHEMA_VERSION`` (inside
    the caller's transaction, which holds the lock); the version found. A store newer than
    this code is refused (``where`` names it)."""
    found = schema_version(conn)
    if found is None:
        metadata.create_all(conn)
    elif found > SCHEMA_VERSION:
        raise ConfigError(f"{where}: store schema version {found} is newer than this robid "
                          f"reads ({SCHEMA_VERSION}); upgrade robid_link")
    else:
        for k in range(found, SCHEMA_VERSION):
            MIGRATIONS[k](conn)
        if found == 1:
            version_table.create(conn)
    for ddl in _INDEXES:
        conn.execute(text(ddl))
    if found != SCHEMA_VERSION:
        conn.execute(version_table.delete())
        conn.execute(version_table.insert().values(version=SCHEMA_VERSION))
    return found or 0


def check_readable(conn: Connection, where: str) -> None:
    """A reader's check: the store exists and is at this code's version."""
    found = schema_version(conn)
    if found is None:
        raise ConfigError(f"{where} holds no store yet")
    if found != SCHEMA_VERSION:
        newer = found > SCHEMA_VERSION
        raise ConfigError(f"{where}: store schema version {found}, this robid reads "
                          f"{SCHEMA_VERSION}; " + ("upgrade robid_link" if newer else
                                                   "start its daemon once to migrate it"))
