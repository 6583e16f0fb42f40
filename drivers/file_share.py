"""The seed tool's protocol on a shared folder: programs in ``inbox/``, logs in ``outbox/``,
semaphores ``<id>.<nonce>.ready|done|failed`` in ``sem/`` (DESIGN.md, "File-share protocol").

'done' is taken through watchdog: the inotify observer on local disks, a polling observer on
network shares (SMB/NFS deliver no remote inotify events), and a canary file that proves
events still arrive, else the driver falls back to polling.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import json
import logging
import os
import re
import secrets
import stat
import time
from pathlib import Path
from typing import Any

from watchdog.events import FileSystemEventHandler

from robid_link.atomic import atomic_write
from robid_link.drivers.rapid import MAX_AXES, render_rapid
from robid_link.exceptions import ConfigError, DriverError, ProtocolError
from robid_link.jobs import MotionProgram
from robid_link.link.driver import CAP_RAPID, CAP_UPLOAD, Done, Driver, ThreadBridge
from robid_link.link.options import Choice, Flag, Folder, Integer, Number, Options
from robid_link.safeopen import read_regular

__all__ = ["FileShareDriver", "ShareTransfer", "sem_name", "parse_sem", "network_fs",
           "done_text", "read_done", "log_name"]

log = logging.getLogger("robid.driver.file_share")

#: file systems whose remote changes raise no local inotify event
NETWORK_FS = {"nfs", "nfs4", "cifs", "smb3", "smbfs", "ncpfs", "afs", "9p", "fuse.sshfs",
              "fuse.glusterfs", "ceph", "glusterfs", "lustre", "davfs"}
_SEM = re.compile(r"^([A-Za-z0-9][A-Za-z0-9_\-]*)\.([A-Za-z0-9][A-Za-z0-9_\-]*)"
                  r"\.(ready|done|failed)$")
_HEX64 = re.compile(r"^[0-9a-f]{64}$")
#: a semaphore holds one short line; anything longer is not one
MAX_SEM_BYTES = 4096
#: stale or duplicate files looked at concurrently, and remembered (one warning each), at most:
#: a share flooded with semaphores costs neither tasks nor memory without bound
MAX_CHECKS = 32
MAX_REMEMBERED = 1024
MAX_LOG_BYTES = 256 * 1024 * 1024


def sem_name(exp_id: str, nonce: str, kind: str) -> str:
    return f"{exp_id}.{nonce}.{kind}"


def log_name(exp_id: str, nonce: str) -> str:
    """The log a controller writes into ``outbox/`` for one experiment and nonce."""
    return f"{exp_id}.{nonce}.log.csv"


def parse_sem(name: str) -> tuple[str, str, str] | None:
    """``(exp_id, nonce, kind)`` of a semaphore file name, None for anything else."""
    m = _SEM.match(name)
    return (m.group(1), m.group(2), m.group(3)) if m else None


def network_fs(path: Path) -> str | None:
    """The file-system type of ``path`` when it is a network share, else None."""
    try:
        mounts = Path("/proc/self/mounts").read_text().splitlines()  # ProcSubset=pid
    except OSError:
        return None
    real = str(path.resolve())
    best, fstype = "", ""
    for line in mounts:
        parts = line.split()
        if len(parts) < 3:
            continue
        mnt = parts[1].replace("\\040", " ")
        if (real == mnt or real.startswith(mnt.rstrip("/") + "/")) and len(mnt) >= len(best):
            best, fstype = mnt, parts[2]
    return fstype if fstype in NETWORK_FS else None


def done_text(sha256: str, size: int) -> bytes:
    """What a controller writes into a 'done' semaphore."""
    return f"{sha256} size={size}\n".encode()


def read_done(path: Path, exp_id: str, nonce: str) -> Done | None:
    """Parse a 'done' semaphore: the log's SHA-256 (hex), optionally ``size=N`` after it.
    None while the file is absent or still empty (a non-atomic writer); ProtocolError when
    it is malformed, not a regular file or too large (the controller has answered: the motion
    may have run, so this is a failed attempt for the operator, never a silent re-run).
    Blocking: call it through ``asyncio.to_thread``."""
    try:
        raw = read_regular(path, MAX_SEM_BYTES)
    except FileNotFoundError:
        return None
    except OSError as err:
        raise ProtocolError(f"{path}: unreadable 'done' semaphore ({err.strerror or err})"
                            ) from err
    try:
        text = raw.decode("ascii").strip()
    except UnicodeDecodeError as err:
        raise ProtocolError(f"{path}: 'done' semaphore is not ASCII text") from err
    if not text:
        return None
    tokens = text.split()
    sha = tokens[0].lower()
    if not _HEX64.match(sha):
        raise ProtocolError(f"{path}: 'done' semaphore does not start with the log's SHA-256")
    size = None
    for tok in tokens[1:]:
        if tok.startswith("size="):
            try:
                size = int(tok[5:])
            except ValueError as err:
                raise ProtocolError(f"{path}: bad size field {tok[:40]!r}") from err
            if size < 0:
                raise ProtocolError(f"{path}: bad size field {tok[:40]!r}")
    return Done(exp_id, nonce, sha, size)


def read_failed(path: Path) -> str | None:
    """The reason in a 'failed' semaphore (None when there is none); blocking."""
    try:
        raw = read_regular(path, MAX_SEM_BYTES)
    except FileNotFoundError:
        return None
    except OSError as err:
        return f"unreadable 'failed' semaphore ({err.strerror or err})"
    return raw.decode("utf-8", errors="replace").strip()[:200]


def _identity(path: Path) -> tuple[int, int] | None:
    """Which file ``path`` is now (inode, change time), None when there is none."""
    try:
        st = os.lstat(path)
    except OSError:
        return None
    return (st.st_ino, st.st_ctime_ns)


class ShareTransfer:
    """The transfer half of the file-share protocol, shared by every driver that moves programs
    and logs over a folder (``file_share``; ``modbus_plc`` with its handshake in registers).

    Files are keyed by ``key`` (the name a controller sees: the experiment id, or the PLC's
    experiment number) and ``nkey`` (the nonce as the controller sees it): programs
    ``inbox/<key>.<suffix>``, logs ``outbox/<key>.<nkey>.log.csv``, semaphores
    ``sem/<key>.<nkey>.ready|done|failed``. Blocking file work runs in a thread.
    """

    def __init__(self, share: Path, *, rapid: bool, max_log_bytes: int = MAX_LOG_BYTES
                 ) -> None:
        self.share, self.rapid, self.max_log_bytes = share, rapid, max_log_bytes
        self.inbox, self.outbox, self.sem = (share / d for d in ("inbox", "outbox", "sem"))

    def prepare(self) -> None:
        """The share must exist; its three folders are made when missing and must be real
        folders (a symbolic link put there would redirect the daemon's writes)."""
        if not self.share.is_dir():
            raise DriverError(f"{self.share}: shared folder not found")
        for d in (self.inbox, self.outbox, self.sem):
            with contextlib.suppress(FileExistsError):
                d.mkdir()
            self.folder(d)

    @staticmethod
    def folder(path: Path) -> Path:
        """``path`` if it is a folder of its own, not a symbolic link (checked before every
        write into it: the other side of the share may replace it); blocking."""
        try:
            st = os.lstat(path)
        except OSError as err:
            raise DriverError(f"{path}: share folder unreadable ({err.strerror or err})"
                              ) from err
        if stat.S_ISLNK(st.st_mode) or not stat.S_ISDIR(st.st_mode):
            kind = "a symbolic link" if stat.S_ISLNK(st.st_mode) else "not a folder"
            raise DriverError(f"{path}: {kind}; refusing to write through it (the share's "
                              "inbox/, outbox/ and sem/ must be real folders)")
        return path

    async def put_program(self, program: MotionProgram, key: str | None = None) -> None:
        """Each program file written atomically as ``inbox/<key>.<suffix>`` (+ RAPID ``.mod``)."""
        key = key or program.exp_id
        files = dict(program.files)
        if self.rapid:
            files["mod"] = render_rapid(program)

        def write() -> None:
            inbox = self.folder(self.inbox)
            for suffix, data in files.items():
                if not re.fullmatch(r"[a-z]+(\.[a-z]+)?", suffix):
                    raise DriverError(f"program file suffix {suffix!r} is not allowed")
                atomic_write(inbox / f"{key}.{suffix}", data)

        await asyncio.to_thread(write)

    def sem_path(self, key: str, nkey: str, kind: str) -> Path:
        return self.sem / sem_name(key, nkey, kind)

    def done(self, key: str, nkey: str, exp_id: str, nonce: str) -> Done | None:
        """The 'done' of ``key``/``nkey`` as the daemon's ``Done`` of ``exp_id``/``nonce``."""
        return read_done(self.sem_path(key, nkey, "done"), exp_id, nonce)

    def failed(self, key: str, nkey: str) -> str | None:
        """The reason in a 'failed' semaphore ('' when it gives none), None without one."""
        return read_failed(self.sem_path(key, nkey, "failed"))

    def identity(self, key: str, nkey: str, kind: str) -> tuple[int, int] | None:
        return _identity(self.sem_path(key, nkey, kind))

    async def fetch_log(self, key: str, nkey: str, limit: int | None = None) -> bytes:
        """The log through the safe open: no links, regular files, at most ``max_log_bytes``
        and ``limit`` (the size its 'done' announced: a longer file is refused unread)."""
        path = self.outbox / log_name(key, nkey)
        cap = self.max_log_bytes if limit is None else min(limit, self.max_log_bytes)
        try:
            return await asyncio.to_thread(read_regular, path, cap)
        except FileNotFoundError as err:
            raise DriverError(f"{path}: log missing although 'done' was given") from err
        except OSError as err:
            raise DriverError(f"{path}: log refused ({err.strerror or err})") from err

    async def remove(self, key: str, nkey: str, *kinds: str) -> None:
        await asyncio.to_thread(self.folder, self.sem)  # never deletes through a link
        for kind in kinds:
            await asyncio.to_thread(self.sem_path(key, nkey, kind).unlink, True)

    async def clear(self, key: str, nkey: str) -> None:
        """A given-up attempt leaves nothing: 'ready' first (nothing may start it later),
        then its answers and log."""
        await self.remove(key, nkey, "ready", "done", "failed")
        await asyncio.to_thread(self.folder, self.outbox)
        await asyncio.to_thread((self.outbox / log_name(key, nkey)).unlink, True)



class _Events(FileSystemEventHandler):
    """watchdog handler: hands file names from the observer thread to the event loop through
    the driver's bridge."""

    def __init__(self, bridge: ThreadBridge, callback: Any) -> None:
        super().__init__()
        self._bridge, self._callback = bridge, callback

    def dispatch(self, event: Any) -> None:
        if event.is_directory or event.event_type not in ("created", "moved", "modified",
                                                            "closed"):
            return
        raw = event.dest_path if event.event_type == "moved" else event.src_path
        self._bridge.call(self._callback, os.path.basename(os.fsdecode(raw)))


class FileShareDriver(Driver):
    """Daemon side of the file-share protocol.

    Options: ``share`` (folder), ``observer`` (auto | inotify | polling; auto picks polling on
    network file systems), ``poll_interval_s`` (polling observer), ``canary_interval_s`` (0 to
    disable the liveness check), ``canary_timeout_s``, ``rapid`` (true: render each program
    as an ABB RAPID module ``inbox/<id>.mod`` beside the neutral trajectory; false for
    controllers that read only the trajectory file), ``max_log_bytes`` (a larger log, or
    anything but a regular file, is refused unread).
    """

    name = "file_share"
    capabilities = frozenset({CAP_RAPID, CAP_UPLOAD})
    options = Options(
        share=Folder(hint="the shared folder"),
        observer=Choice("auto", "inotify", "polling", default="auto"),
        poll_interval_s=Number(0.1, low=0), canary_interval_s=Number(30.0, low=0),
        canary_timeout_s=Number(2.0, low=0), rapid=Flag(True),
        max_log_bytes=Integer(MAX_LOG_BYTES, low=1))

    def __init__(self, **options: Any) -> None:
        super().__init__(**options)
        o = self.config
        self.max_log_bytes, self.rapid = o.max_log_bytes, o.rapid
        if not self.rapid:
            self.capabilities = frozenset({CAP_UPLOAD})
        self.share = o.share
        self.transfer = ShareTransfer(self.share, rapid=self.rapid,
                                      max_log_bytes=self.max_log_bytes)
        self.inbox, self.outbox, self.sem = (self.transfer.inbox, self.transfer.outbox,
                                             self.transfer.sem)
        self._observer_choice = o.observer
        self._poll_s = o.poll_interval_s or 0.1
        self._canary_s = o.canary_interval_s
        self._canary_timeout_s = o.canary_timeout_s or 2.0
        self._observer: Any = None
        self.observer_kind = ""
        self._waiters: dict[tuple[str, str], asyncio.Event] = {}
        self._taken: dict[tuple[str, str], tuple[int, int] | None] = {}
        self._warned: set[tuple[str, tuple[int, int] | None]] = set()
        self._checks: set[asyncio.Task[None]] = set()
        self._canary_seen: asyncio.Event | None = None
        self._canary_name = ""
        self._tasks: list[asyncio.Task[None]] = []
        self._param_attempts: dict[str, tuple[str, str]] = {}

    # -- lifecycle
    async def _open(self) -> None:
        self.transfer.prepare()
        kind = self._observer_choice
        if kind == "auto":
            fs = network_fs(self.share)
            kind = "polling" if fs else "inotify"
            if fs:
                log.info("share=%s fs=%s observer=polling (network file system)", self.share, fs)
        await self._start_observer(kind)
        # answers already there may be the very ones a resumed run takes next: not stale yet
        left = [n for n in os.listdir(self.sem) if parse_sem(n) and not n.endswith(".ready")]
        if left:
            log.info("share=%s answers=%d already in sem/ (taken if a resumed run wants them)",
                     self.share, len(left))
        if self.observer_kind == "inotify" and self._canary_s > 0:
            self._tasks.append(asyncio.create_task(self._liveness_loop(),
                                                   name="file_share-liveness"))

    async def _start_observer(self, kind: str) -> None:
        from watchdog.observers import Observer
        from watchdog.observers.polling import PollingObserver

        if self._observer is not None:
            await self._stop_observer()
        obs = PollingObserver(timeout=self._poll_s) if kind == "polling" else Observer()
        obs.schedule(_Events(self.bridge, self._on_file), str(self.sem), recursive=False)
        try:
            await asyncio.to_thread(obs.start)
        except OSError as err:  # e.g. inotify watch limit reached
            if kind == "polling":
                raise DriverError(f"{self.sem}: cannot watch the folder ({err})") from err
            log.warning("share=%s inotify unavailable (%s); polling instead", self.share, err)
            await self._start_observer("polling")
            return
        self._observer, self.observer_kind = obs, kind
        # anything that arrived while no observer ran is picked up by a scan
        for name in os.listdir(self.sem):
            self._on_file(name)

    async def _stop_observer(self) -> None:
        obs, self._observer = self._observer, None
        if obs is not None:
            # stop() waits for the observer's lock, which its thread holds while it hands an
            # event over: off the loop, or a full bridge would never drain
            await asyncio.to_thread(obs.stop)
            await asyncio.to_thread(obs.join, 5.0)

    async def _close(self) -> None:
        for task in [*self._tasks, *self._checks]:
            task.cancel()
        await asyncio.gather(*self._tasks, *self._checks, return_exceptions=True)
        self._tasks.clear()
        await self._stop_observer()

    # -- events
    def _on_file(self, name: str) -> None:
        if self._canary_seen is not None and name == self._canary_name:
            self._canary_seen.set()
            return
        parsed = parse_sem(name)
        if parsed is None or parsed[2] == "ready":
            return
        exp_id, nonce, _ = parsed
        event = self._waiters.get((exp_id, nonce))
        if event is not None:
            event.set()
        elif ((exp_id, nonce) in self._taken or any(k[0] == exp_id for k in self._waiters)
              ) and len(self._checks) < MAX_CHECKS:
            # one warning per file, none for the events of the answer just taken
            task = asyncio.get_running_loop().create_task(self._warn_once(name, (exp_id, nonce)))
            self._checks.add(task)
            task.add_done_callback(self._checks.discard)

    async def _warn_once(self, name: str, key: tuple[str, str]) -> None:
        ident = await asyncio.to_thread(_identity, self.sem / name)
        if ident is None or (name, ident) in self._warned:
            return
        if key in self._taken:
            if self._taken[key] == ident:
                return
            log.warning("share=%s duplicate_semaphore=%s (already taken; ignored)",
                        self.share, name)
        else:
            log.warning("share=%s stale_semaphore=%s (another nonce; ignored)", self.share, name)
        if len(self._warned) >= MAX_REMEMBERED:
            self._warned.clear()
        self._warned.add((name, ident))

    async def _liveness_loop(self) -> None:
        """Prove inotify still delivers: write a canary and wait for its event."""
        k = 0
        while self.observer_kind == "inotify":
            await asyncio.sleep(self._canary_s)
            k += 1
            self._canary_name = f".canary.{os.getpid()}.{k}"
            self._canary_seen = asyncio.Event()
            path = self.sem / self._canary_name
            await asyncio.to_thread(path.write_bytes, b"")
            try:
                async with asyncio.timeout(self._canary_timeout_s):
                    await self._canary_seen.wait()
            except TimeoutError:
                log.warning("share=%s inotify delivered no event for the canary within %g s; "
                            "falling back to polling", self.share, self._canary_timeout_s)
                await self._start_observer("polling")
            finally:
                self._canary_seen = None
                path.unlink(missing_ok=True)

    def _check_robot(self, robot: Any) -> None:
        if self.rapid and robot.n > MAX_AXES:
            raise ConfigError(f"driver.rapid: RAPID joint targets hold at most {MAX_AXES} axes, "
                              f"robot {robot.name} has {robot.n} (set rapid: false)")

    # -- the cycle
    async def _put_program(self, program: MotionProgram) -> None:
        await self.transfer.put_program(program)

    async def _give_ready(self, exp_id: str, nonce: str) -> None:
        path = self.sem / sem_name(exp_id, nonce, "ready")
        if path.exists():  # given before a restart: giving again must not start it twice
            return
        body = json.dumps({"experiment": exp_id, "nonce": nonce, "time": time.time()}).encode()
        await asyncio.to_thread(self.transfer.folder, self.sem)
        await asyncio.to_thread(atomic_write, path, body + b"\n")

    def _forget_old(self) -> None:
        """Keep the newest MAX_REMEMBERED taken answers (dicts keep insertion order)."""
        while len(self._taken) > MAX_REMEMBERED:
            del self._taken[next(iter(self._taken))]

    async def _wait_done(self, exp_id: str, nonce: str) -> Done:
        key = (exp_id, nonce)
        self._forget_old()
        event = asyncio.Event()
        self._waiters[key] = event
        try:
            while True:
                # look right after subscribing, and after every event: an answer written
                # before the subscription raised no event we could see
                reason = await asyncio.to_thread(self.transfer.failed, exp_id, nonce)
                if reason is not None:
                    self._taken[key] = await asyncio.to_thread(self.transfer.identity, exp_id,
                                                               nonce, "failed")
                    raise DriverError(f"controller reports experiment {exp_id} failed: "
                                      f"{reason or 'no reason given'}")
                try:
                    done = await asyncio.to_thread(self.transfer.done, exp_id, nonce, exp_id,
                                                   nonce)
                except ProtocolError:  # answered, malformed: a failed attempt, no re-run
                    self._taken[key] = await asyncio.to_thread(self.transfer.identity, exp_id,
                                                               nonce, "done")
                    raise
                if done is not None:
                    self._taken[key] = await asyncio.to_thread(self.transfer.identity, exp_id,
                                                               nonce, "done")
                    return done
                await event.wait()
                event.clear()
        finally:
            self._waiters.pop(key, None)

    async def _fetch_logs(self, done: Done) -> bytes:
        return await self.transfer.fetch_log(done.exp_id, done.nonce, limit=done.size)

    async def _acknowledge(self, done: Done) -> None:
        await self.transfer.remove(done.exp_id, done.nonce, "ready", "done")

    async def _withdraw(self, exp_id: str, nonce: str) -> None:
        await self.transfer.clear(exp_id, nonce)

    async def _upload_parameters(self, doc: Any, body: bytes) -> None:
        """``params/params-<robot>.<nonce>.json``, then its ``ready`` semaphore; the
        controller loads the set and answers ``.done`` with the file's SHA-256 (or
        ``.failed`` with the reason). The nonce is the set's hash plus a fresh token, so the
        same set uploaded again (a rollback) is a new attempt."""
        sha = hashlib.sha256(body).hexdigest()
        exp_id, nonce = self._param_names(doc), f"{sha[:12]}{secrets.token_hex(2)}"
        self._param_attempts[sha] = (exp_id, nonce)
        folder = self.share / "params"
        await asyncio.to_thread(folder.mkdir, exist_ok=True)
        await asyncio.to_thread(atomic_write, folder / f"{exp_id}.{nonce}.json", body)
        await self._give_ready(exp_id, nonce)
        done = await self._wait_done(exp_id, nonce)
        if done.sha256 != sha:
            raise DriverError(f"controller acknowledged parameter set {sha[:12]} with "
                              "another checksum: it loaded something else")
        await self._acknowledge(done)

    async def _withdraw_parameters(self, doc: Any, body: bytes) -> None:
        attempt = self._param_attempts.pop(hashlib.sha256(body).hexdigest(), None)
        if attempt is None:
            return
        exp_id, nonce = attempt
        await self._withdraw(exp_id, nonce)
        await asyncio.to_thread((self.share / "params" / f"{exp_id}.{nonce}.json").unlink,
                                True)

    @staticmethod
    def _param_names(doc: Any) -> str:
        robot = str(doc.get("robot", "robot")) if isinstance(doc, dict) else "robot"
        return "params-" + re.sub(r"[^A-Za-z0-9_\-]", "_", robot)[:40]
