"""Moved to :mod:`robid_link.atomic` (the one atomic write); kept while callers switch."""

from __future__ import annotations

from robid_link.atomic import atomic_write, fsync_dir

__all__ = ["atomic_write", "fsync_dir"]
