"""The cell's own files beside any store backend: raw logs and programs, content-addressed,
each written and fsynced before the row that names it. A plant may keep the raw logs centrally
(``log_store``: a mounted folder, written in place, or an fsspec URL, written beside the cell's
own copy); the store's row says where. Blocking: a store calls these on its own thread, never
on the event loop."""

from __future__ import annotations

import errno
import hashlib
import json
import os
from pathlib import Path

from robid_link.atomic import atomic_write, fsync_dir
from robid_link.exceptions import ConfigError, RobidError, StoreFullError
from robid_link.jobs import MotionProgram
from robid_link.link.store.base import is_url, log_file, log_url

__all__ = ["CellFiles", "FULL_ERRNOS"]

#: the errors of a full disk (or quota)
FULL_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT})


class CellFiles:
    """``logs/<sha[:2]>/<sha>.csv`` and ``programs/<sha>/`` under ``folder``; ``reports/``
    for the worker's report files. ``log_store``: a folder that holds the logs instead, or an
    fsspec URL that gets a copy of each before its row (``location`` says which)."""

    def __init__(self, folder: Path, log_store: str | None = None) -> None:
        self.dir = folder
        self.remote = log_store if log_store and is_url(log_store) else None
        self.log_dir = Path(log_store) if log_store and not self.remote else folder
        #: where the store says this cell's logs are
        self.location = self.remote or str(self.log_dir)

    def prepare(self) -> None:
        """The folder and its sub-folders, made when missing (ConfigError names the folder)."""
        try:
            self.dir.mkdir(parents=True, exist_ok=True)
            for sub in ("logs", "programs", "reports"):
                (self.dir / sub).mkdir(exist_ok=True)
        except OSError as err:
            raise ConfigError(f"state_dir: {self.dir}: {err.strerror}") from err
        try:
            (self.log_dir / "logs").mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise ConfigError(f"log_store: {self.log_dir}: {err.strerror}") from err

    def free_bytes(self) -> int:
        """Free bytes where the raw logs are written (the lesser of the two folders)."""
        st = os.statvfs(self.dir)
        free = st.f_bavail * st.f_frsize
        if self.log_dir != self.dir:
            lg = os.statvfs(self.log_dir)
            free = min(free, lg.f_bavail * lg.f_frsize)
        return free

    def full(self, err: BaseException) -> StoreFullError:
        return StoreFullError(f"state_dir: {self.dir}: disk full while writing "
                              f"({str(err).splitlines()[0]}): waiting for space")

    # ----------------------------------------------------------------- raw logs
    def log_path(self, sha: str) -> Path:
        return log_file(self.log_dir, sha)

    def write_log(self, data: bytes) -> str:
        """The log's file under its SHA-256, durable (a new fan-out folder too), and its copy
        in the remote log store; idempotent."""
        sha = hashlib.sha256(data).hexdigest()
        path = self.log_path(sha)
        try:
            if not (path.is_file() and path.stat().st_size == len(data)):
                if not path.parent.is_dir():  # a new fan-out folder must survive a power cut
                    path.parent.mkdir()
                    fsync_dir(path.parent.parent)
                atomic_write(path, data, 0o444)
        except OSError as err:
            if err.errno in FULL_ERRNOS:
                raise self.full(err) from err
            raise
        if self.remote:
            self._upload(sha, data)
        return sha

    def _upload(self, sha: str, data: bytes) -> None:
        """The log's copy at the remote log store (an object store's PUT is durable when it
        returns); an existing copy of the same size is kept."""
        import fsspec  # type: ignore[import-untyped]

        assert self.remote is not None
        url = log_url(self.remote, sha)
        try:
            fs, path = fsspec.core.url_to_fs(url)
            if not (fs.exists(path) and fs.size(path) == len(data)):
                fs.makedirs(path.rsplit("/", 1)[0], exist_ok=True)
                fs.pipe_file(path, data)
        except (OSError, ValueError, ImportError) as err:
            raise RobidError(f"log_store: {self.remote}: cannot write log {sha[:12]} "
                             f"({type(err).__name__}: {err})") from err

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

    # ----------------------------------------------------------------- programs
    def has_program(self, sha: str) -> bool:
        return (self.dir / "programs" / sha).is_dir()

    def write_program(self, program: MotionProgram) -> str:
        """The program's files in ``programs/<sha>/`` (a folder renamed into place, durable);
        its hash."""
        sha = program.sha256
        folder = self.dir / "programs" / sha
        if folder.is_dir():
            return sha
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
            if err.errno in FULL_ERRNOS:
                raise self.full(err) from err
            raise
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
