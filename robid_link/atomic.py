"""Crash-safe file writes shared by the store, the drivers, the fakes and the worker's reports:
a whole file replaced atomically (a JSON document too), or a line appended durably (the
error-ladder history)."""

from __future__ import annotations

import json
import os
import secrets
from pathlib import Path
from typing import Any

__all__ = ["atomic_write", "write_json", "append_durable", "fsync_dir"]


def atomic_write(path: Path, data: bytes, mode: int = 0o644) -> None:
    """Temp file in the same folder, fsync, rename over ``path``, fsync of the folder: a reader
    sees the old file or the whole new one, and a power cut keeps one of them."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    fsync_dir(path.parent)


def write_json(path: str | Path, doc: dict[str, Any]) -> None:
    """``doc`` as indented JSON (no NaN), written atomically; the folder is made if missing.
    Here, not beside the figures, so that the link's commands (``status --json``) need none of
    the worker's imports."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(p, json.dumps(doc, indent=2, allow_nan=False).encode())


def append_durable(path: Path, data: bytes, mode: int = 0o644) -> None:
    """Append ``data`` with one write and fsync it (and the folder, for a new file).

    An append log is not rewritten through a temp file: with O_APPEND two writers (the CLI
    and the daemon on one model's history) cannot lose each other's lines."""
    created = not path.exists()
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, mode)
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view):]
        os.fsync(fd)
    finally:
        os.close(fd)
    if created:
        fsync_dir(path.parent)


def fsync_dir(folder: Path) -> None:
    """Make a rename or a new file in ``folder`` durable."""
    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
