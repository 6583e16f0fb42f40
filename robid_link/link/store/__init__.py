"""The daemon's store: the async interface (``base.py``) every backend implements, the one
implementation of each query (``sql.py``: SQLAlchemy Core, one schema in ``schema.py``) over
SQLite (``sqlite.py``) or a plant's PostgreSQL (``postgres.py``), run for the daemon on a thread
of its own (``threaded.py``), and the cell's content-addressed files (``files.py``)."""

from robid_link.link.store.base import RUN_STATES, AsyncStore
from robid_link.link.store.sql import RESERVE_BYTES, Store
from robid_link.link.store.threaded import PostgresStore, SqliteStore, ThreadedStore, open_store

__all__ = ["AsyncStore", "SqliteStore", "PostgresStore", "ThreadedStore", "Store", "open_store",
           "RUN_STATES", "RESERVE_BYTES"]
