"""The daemon's store: the async interface (``base.py``) every backend implements, the SQLite
backend (``sqlite.py``: ``SqliteStore`` for the daemon, ``Store`` for blocking readers) and the
cell's content-addressed files (``files.py``)."""

from robid_link.link.store.base import RUN_STATES, AsyncStore
from robid_link.link.store.sqlite import RESERVE_BYTES, SqliteStore, Store

__all__ = ["AsyncStore", "SqliteStore", "Store", "RUN_STATES", "RESERVE_BYTES"]
