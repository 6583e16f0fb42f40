"""The PostgreSQL backend of the store: one database for a plant's robots, reached by a URL
whose password comes from PGPASSWORD or a PGPASSFILE (never the URL, never printed); one daemon
per robot, held by a session advisory lock keyed by the robot's name. The queries are the
store's own (``sql.py``); this module checks the URL, connects, and holds the lock."""

from __future__ import annotations

import os
import socket
import time
from typing import Any

from sqlalchemy import Connection, Engine, create_engine, event, select, text
from sqlalchemy.engine import URL, make_url
from sqlalchemy.exc import ArgumentError, DBAPIError, InterfaceError, OperationalError

from robid_link.config import check_store_url as config_store_url
from robid_link.exceptions import (
    ConfigError,
    StoreFullError,
    StoreLockedError,
    StoreUnavailableError,
)
from robid_link.link.store import schema as sc

__all__ = ["PostgresBackend", "check_store_url", "is_store_url"]

#: the advisory locks of robid: a robot's is the 64-bit hash of its name seeded with this;
#: a migration takes this one
LOCK_CLASS = 0x726F6264  # 'robd'
#: a dead cell host releases its robot in about idle + interval × count seconds
KEEPALIVE = {"tcp_keepalives_idle": 10, "tcp_keepalives_interval": 5,
             "tcp_keepalives_count": 3}
#: how long a re-lock waits for this daemon's own stale session to end once told to
STALE_WAIT_S = 5.0


def is_store_url(text: str) -> bool:
    """A PostgreSQL URL rather than a state dir (what ``--store`` takes both of)."""
    return text.startswith(("postgresql:", "postgresql+", "postgres:"))


def check_store_url(value: Any, key: str = "store") -> URL:
    """The URL of a PostgreSQL store, for psycopg 3. A password in it is refused (one line
    that does not print it: ``config.check_store_url``)."""
    checked = config_store_url(value, key)
    try:
        url = make_url(checked)
    except (ArgumentError, ValueError) as err:
        raise ConfigError(f"{key}: not a valid URL ({type(err).__name__})") from None
    return url.set(drivername="postgresql+psycopg")


def shown(url: URL) -> str:
    """The URL as messages print it (it holds no password: ``check_store_url``)."""
    return url.set(drivername="postgresql").render_as_string(hide_password=True)


def _try_lock(conn: Connection, key: int) -> bool:
    return bool(conn.execute(text("SELECT pg_try_advisory_lock(:k)"), {"k": key}).scalar_one())


class PostgresBackend:
    """A plant's database; ``robot`` is what the advisory lock is keyed by."""

    shared = True  # many robots: every row names its robot

    def __init__(self, url: str | URL) -> None:
        self.url = check_store_url(url if isinstance(url, str) else url.render_as_string(
            hide_password=False))
        self.where = f"store {shown(self.url)}"
        #: the server's pid of the session that holds this store's robot (None before)
        self.session_pid: int | None = None

    def engine(self, readonly: bool) -> Engine:
        try:
            import psycopg  # noqa: F401
        except ImportError as err:
            raise ConfigError("store: a PostgreSQL store needs the extra 'fleet' (pip install "
                              "'robid_link[fleet]')") from err
        engine = create_engine(self.url, pool_pre_ping=True,
                               connect_args={"application_name": "robid",
                                             "connect_timeout": 10})

        @event.listens_for(engine, "connect")
        def _connect(dbapi: Any, record: Any) -> None:
            with dbapi.cursor() as cur:
                cur.execute("SET synchronous_commit = on")  # a commit is on the server's disk
                for k, v in KEEPALIVE.items():
                    cur.execute(f"SET {k} = {int(v)}")
                if readonly:
                    cur.execute("SET default_transaction_read_only = on")
            dbapi.commit()

        return engine

    def lock(self, conn: Connection, robot: str | None) -> None:
        """The robot's advisory lock on this session (held until it ends: a killed daemon's
        connection closes and frees it); StoreLockedError names the holder. Taken again after
        a lost connection, the holder may be this daemon's own previous session, which the
        server keeps until its keepalive gives up (~25 s): that session is ended and the lock
        taken, or StoreUnavailableError says the server has not let it go yet."""
        if robot is None:
            raise ValueError("a daemon's PostgreSQL store needs the robot's name")
        with conn.begin():
            key = conn.execute(text("SELECT hashtextextended(:r, :c)"),
                               {"c": LOCK_CLASS, "r": robot}).scalar_one()
            got = _try_lock(conn, key)
            stale = None if got or self.session_pid is None else self._own_stale(conn, key,
                                                                                robot)
            if stale is not None:
                conn.execute(text("SELECT pg_terminate_backend(:p)"), {"p": stale})
                end = time.monotonic() + STALE_WAIT_S
                while not (got := _try_lock(conn, key)) and time.monotonic() < end:
                    time.sleep(0.05)
                if not got:
                    raise StoreUnavailableError(
                        f"{self.where}: robot {robot} is still held by this daemon's previous "
                        f"session (server pid {stale}), which the server has not ended yet: "
                        "waiting for it")
            holder = conn.execute(select(sc.robots.c.host, sc.robots.c.pid).where(
                sc.robots.c.robot == robot)).first() if not got else None
            if got:
                self.session_pid = conn.execute(text("SELECT pg_backend_pid()")).scalar_one()
        if not got:
            who = f"pid {holder.pid} on {holder.host}" if holder else "another host"
            raise StoreLockedError(f"{self.where}: robot {robot} is in use by another daemon "
                                   f"({who}); give each cell its own robot_name")

    def _own_stale(self, conn: Connection, key: int, robot: str) -> int | None:
        """The server pid of the session holding the robot's lock when it is this store's
        previous one (the pid it held the lock from, and the robot's row still names this
        process on this host as its daemon); None when anyone else holds it."""
        holder = conn.execute(text(
            "SELECT pid FROM pg_locks WHERE locktype = 'advisory' AND granted "
            "AND classid::bigint = :hi AND objid::bigint = :lo AND objsubid = 1"),
            {"hi": (key >> 32) & 0xFFFFFFFF, "lo": key & 0xFFFFFFFF}).scalar()
        if holder is None or holder != self.session_pid:
            return None
        row = conn.execute(select(sc.robots.c.host, sc.robots.c.pid).where(
            sc.robots.c.robot == robot)).first()
        if row is None or (row.host, row.pid) != (socket.gethostname(), os.getpid()):
            return None
        return int(holder)

    def migration_lock(self, conn: Connection) -> None:
        """Two daemons starting at once on an empty or older database: one migrates, the
        other waits for it inside its own transaction and then finds the schema current."""
        conn.execute(text("SELECT pg_advisory_xact_lock(:c)"), {"c": LOCK_CLASS})

    @staticmethod
    def lost(err: DBAPIError) -> bool:
        """The server went away or does not answer (a connection lost, refused, reset)."""
        return bool(err.connection_invalidated) or isinstance(err, (OperationalError,
                                                                    InterfaceError))

    def full(self, err: DBAPIError) -> StoreFullError | None:
        if getattr(err.orig, "sqlstate", None) == "53100":  # disk_full
            return StoreFullError(f"{self.where}: the database server's disk is full: "
                                  "waiting for space")
        return None


def claim_row(robot: str, state_dir: str | None, log_location: str | None) -> dict[str, Any]:
    """The robots row a daemon writes when it takes its robot."""
    return {"robot": robot, "host": socket.gethostname(), "pid": os.getpid(),
            "state_dir": state_dir, "log_location": log_location, "seen": time.time()}
