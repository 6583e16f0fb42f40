"""The SQLite backend of the store: one file under the state dir (WAL, synchronous=FULL, write
transactions that take the lock at BEGIN), one daemon per state dir (``flock``). The queries
are the store's own (``sql.py``); this module only opens the file and holds the lock."""

from __future__ import annotations

import fcntl
import os
from pathlib import Path
from typing import Any

from sqlalchemy import Connection, Engine, create_engine, event
from sqlalchemy.exc import DBAPIError
from sqlalchemy.pool import NullPool

from robid_link.exceptions import ConfigError, StoreFullError, StoreLockedError
from robid_link.link.store.files import CellFiles

__all__ = ["SqliteBackend", "DB_NAME", "lock_state_dir"]

DB_NAME = "robid.sqlite"


def lock_state_dir(folder: Path) -> int:
    """The daemon's lock on its state dir (its cell files, its SQLite file): an open file
    descriptor holding ``flock``; StoreLockedError names the holder's pid."""
    fd = os.open(folder / "lock", os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError as err:
        holder = os.read(fd, 32).decode(errors="replace").strip() or "?"
        os.close(fd)
        raise StoreLockedError(f"state_dir: {folder} is in use by another daemon "
                               f"(pid {holder})") from err
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    return fd


class SqliteBackend:
    """``robid.sqlite`` under ``folder``."""

    shared = False  # one robot per file: rows without a robot are this robot's

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.where = f"state_dir: {folder}"
        self.files = CellFiles(folder)

    def engine(self, readonly: bool) -> Engine:
        db = self.folder / DB_NAME
        if readonly:
            if not db.is_file():
                raise ConfigError(f"state_dir: {self.folder} holds no store yet")
            url = f"sqlite:///file:{db}?mode=ro&uri=true"
        else:
            url = f"sqlite:///{db}"
        engine = create_engine(url, poolclass=NullPool, connect_args={"timeout": 10.0})

        @event.listens_for(engine, "connect")
        def _connect(dbapi: Any, record: Any) -> None:
            dbapi.isolation_level = None  # transactions are begun below, not by the driver
            if not readonly:
                dbapi.execute("PRAGMA journal_mode=WAL")
                dbapi.execute("PRAGMA synchronous=FULL")

        @event.listens_for(engine, "begin")
        def _begin(conn: Connection) -> None:
            # a writer takes the write lock at BEGIN: no deadlock upgrading a read later
            conn.exec_driver_sql("BEGIN IMMEDIATE" if conn.info.pop("write", False)
                                 else "BEGIN")

        return engine

    def lock(self, conn: Connection, robot: str | None) -> None:
        """Nothing beyond the state dir's flock (taken by the store first)."""

    def migration_lock(self, conn: Connection) -> None:
        """BEGIN IMMEDIATE already holds the file's write lock."""

    @staticmethod
    def lost(err: DBAPIError) -> bool:
        """The file cannot be reached for now (held by another writer past the timeout,
        its folder unreadable); a query that is wrong is not that."""
        text = str(err.orig).lower()
        return bool(err.connection_invalidated) or any(
            w in text for w in ("locked", "busy", "unable to open"))

    def full(self, err: DBAPIError) -> StoreFullError | None:
        text = str(err.orig)
        if "full" in text or "disk" in text:
            return self.files.full(err.orig or err)
        return None
