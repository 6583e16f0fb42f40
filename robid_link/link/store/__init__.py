"""The daemon's store: the async interface (``base.py``) every backend implements, the one
implementation of each query (``sql.py``: SQLAlchemy Core, one schema in ``schema.py``) over
SQLite (``sqlite.py``) or a plant's PostgreSQL (``postgres.py``), run for the daemon on a thread
of its own (``threaded.py``), and the cell's content-addressed files (``files.py``)."""

from typing import Any

from robid_link.link.store.base import RUN_STATES, AsyncStore
from robid_link.link.store.sql import RESERVE_BYTES, Store
from robid_link.link.store.threaded import PostgresStore, SqliteStore, ThreadedStore, open_store

__all__ = ["AsyncStore", "SqliteStore", "PostgresStore", "ThreadedStore", "Store", "open_store",
           "open_reader", "RUN_STATES", "RESERVE_BYTES"]


def open_reader(cfg: Any, robot: str) -> Store:
    """The store of a daemon config, read-only (the operator's commands and page, with or
    without a daemon): its SQLite file under state_dir, or ``robot``'s view of the plant's
    store (``store:``)."""
    if cfg.store:
        return Store(cfg.state_dir, url=cfg.store, robot=robot, readonly=True)
    return Store(cfg.state_dir, readonly=True)
