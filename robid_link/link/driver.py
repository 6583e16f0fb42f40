"""The driver contract: one controller link, seen by the daemon as put → give → take → fetch.

The base class owns the public methods (state, timeouts, checks, logging); a driver overrides
the small ``_hooks``. Drivers are async context managers and ``close()`` is safe twice.

One rule for every driver, kept here: whatever a hook raises that is not already a RobidError
(an unparseable or oddly shaped answer, a decode error, an OSError) leaves the base as a
DriverError of one line — a ProtocolError once the motion command may have gone out (give,
take, fetch: the controller answered, nobody retries that motion unasked); every call has a
timeout and a fetched log a size cap (``LINK_OPTIONS``, which every driver has); the link is
checked alive before a motion command (``_check_link``); and a give runs to its end even when
its caller is cancelled, so a ``withdraw`` that follows always finds what it takes back.
"""

from __future__ import annotations

import abc
import asyncio
import concurrent.futures
import contextlib
import hashlib
import json
import logging
import threading
from collections.abc import Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Self, TypeVar

from robid_link.exceptions import (
    ConfigError,
    DriverError,
    DriverTimeoutError,
    ProtocolError,
    RobidError,
)
from robid_link.jobs import FeedforwardTable, MotionProgram, ParameterSet, RobotInfo, check_name
from robid_link.link.options import Integer, Number, Options, Values

__all__ = [
    "Driver",
    "ThreadBridge",
    "Done",
    "FeedforwardSource",
    "parameter_bytes",
    "CAP_UPLOAD",
    "CAP_RAPID",
    "CAP_FEEDFORWARD",
    "LINK_OPTIONS",
    "one_line",
]

log = logging.getLogger("robid.driver")

T = TypeVar("T")

#: capability names a driver may advertise
CAP_UPLOAD = "upload_parameters"
CAP_RAPID = "rapid"
#: the driver is the motion master and streams a parameter set's model torque with each
#: setpoint: it asks for the table through ``feedforward_table`` (it computes no dynamics)
CAP_FEEDFORWARD = "feedforward"

#: the link's way to the worker for a feed-forward table: (set, period_s, setpoints q) → table
FeedforwardSource = Callable[[ParameterSet, float, Sequence[Sequence[float]]],
                             Awaitable[FeedforwardTable]]


#: the options every driver has (a driver may declare one of them again with its own default):
#: the longest a give, acknowledge, withdraw or parameter send may take, the longest a program
#: or log transfer may take (a slow serial line moves a 10 MB log in ~20 min at 115200 baud),
#: and the largest log accepted (a longer one is refused while it is read, never held whole)
LINK_OPTIONS = Options(
    command_timeout_s=Number(60.0, above=0, high=3600),
    transfer_timeout_s=Number(3600.0, above=0, high=86400),
    max_log_bytes=Integer(256 << 20, low=1024, high=1 << 34))

#: the longest message of a DriverError (a controller's text is cut there)
MAX_MESSAGE = 400


def one_line(text: str, limit: int = MAX_MESSAGE) -> str:
    """``text`` as one printable line of at most ``limit`` characters (what a controller sent
    may hold newlines, control characters, or megabytes)."""
    flat = "".join(ch if ch.isprintable() else " " for ch in text[: 4 * limit])
    flat = " ".join(flat.split())
    return flat if len(flat) <= limit else flat[: limit - 1] + "…"


def parameter_bytes(doc: Mapping[str, Any]) -> bytes:
    """A parameter set as uploaded: canonical JSON, so the same set is the same bytes (a
    rollback restores the previous set byte for byte)."""
    return (json.dumps(doc, sort_keys=True, allow_nan=False, separators=(",", ":"))
            + "\n").encode()


@dataclass(frozen=True)
class Done:
    """The controller's 'done' for one experiment and nonce: the log's SHA-256 and size."""

    exp_id: str
    nonce: str
    sha256: str
    size: int | None = None


class ThreadBridge:
    """How a driver's threads (a serial reader, a watchdog observer, a CAN motion master and
    its log writer) reach the event loop, the one way every driver uses.

    ``call(fn, *args)`` runs ``fn`` on the loop from any thread; at most ``maxsize`` calls wait
    there at once: a thread that outruns the loop waits for room (its own input buffers
    back up) instead of growing the loop's queue without bound. ``await wait(future)`` awaits
    a thread's ``concurrent.futures.Future`` (cancelling the wait leaves the future alone).
    The driver binds the bridge to its loop on ``open`` and closes it with itself: calls made
    after that are dropped and return False.
    """

    def __init__(self, name: str, maxsize: int = 1024) -> None:
        self.name = name
        self.maxsize = maxsize
        self._room = threading.BoundedSemaphore(maxsize)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._loop_thread: int | None = None
        self._closed = threading.Event()

    def bind(self, loop: asyncio.AbstractEventLoop) -> None:
        """Deliver to ``loop`` (called from the loop's thread)."""
        self._loop, self._loop_thread = loop, threading.get_ident()

    @property
    def closed(self) -> bool:
        return self._closed.is_set()

    def close(self) -> None:
        """Drop every later call (and the ones still waiting for room); safe twice."""
        self._closed.set()

    def call(self, fn: Callable[..., object], *args: object) -> bool:
        """Run ``fn(*args)`` on the loop, soon; False if the bridge is closed or unbound."""
        loop = self._loop
        if loop is None or self._closed.is_set():
            return False
        if threading.get_ident() == self._loop_thread:
            try:
                loop.call_soon(self._deliver, fn, args, False)
            except RuntimeError:  # the loop has closed
                return False
            return True
        while not self._room.acquire(timeout=0.1):
            if self._closed.is_set():
                return False
        try:
            loop.call_soon_threadsafe(self._deliver, fn, args, True)
        except RuntimeError:  # the loop has closed meanwhile
            self._room.release()
            return False
        return True

    def _deliver(self, fn: Callable[..., object], args: tuple[object, ...], counted: bool
                 ) -> None:
        if counted:
            self._room.release()
        if not self._closed.is_set():
            fn(*args)

    async def wait(self, future: concurrent.futures.Future[Any]) -> Any:
        """The result of a thread's future, awaited on the loop (one wake-up per future: it
        is delivered even after ``close``, so no waiter hangs on a closed bridge)."""
        loop = asyncio.get_running_loop()
        done = asyncio.Event()

        def wake(_: concurrent.futures.Future[Any]) -> None:
            try:
                loop.call_soon_threadsafe(done.set)
            except RuntimeError:  # that loop has closed meanwhile
                pass

        future.add_done_callback(wake)
        await done.wait()
        return future.result()


class Driver(abc.ABC):
    """Base of every controller driver (the daemon's side of the link).

    Subclasses set ``name``, ``capabilities`` and ``options`` and implement ``_open``,
    ``_close``, ``_put_program``, ``_give_ready``, ``_wait_done``, ``_fetch_logs``; optionally
    ``_upload_parameters`` and ``_acknowledge``. The base checks the options into
    ``self.config`` and owns ``self.bridge``, the way the driver's threads reach the loop. A
    ``CAP_FEEDFORWARD`` driver keeps the set it was given and asks ``feedforward_table`` for
    its setpoints' torques when it gives.
    """

    name: ClassVar[str] = "driver"
    #: the driver's capabilities, read from the class before an instance exists (``robid
    #: demo``: upload); an instance may state its own from its options (``rapid``)
    capabilities: frozenset[str] = frozenset()
    #: the options the driver accepts (besides ``name``), declared once: ``__init__`` checks
    #: the given ones into ``self.config``; per-joint vectors are checked by ``bind_robot``.
    #: (A plain set of names is still accepted from older plug-ins: only unknown keys are
    #: refused then.)
    options: ClassVar[Options | frozenset[str]] = LINK_OPTIONS

    def __init_subclass__(cls, **kw: Any) -> None:
        super().__init_subclass__(**kw)
        spec = cls.__dict__.get("options")
        if isinstance(spec, Options):  # every driver has the link's options too
            cls.options = LINK_OPTIONS.merged(spec)
        elif spec is not None:
            cls.options = frozenset(spec) | frozenset(LINK_OPTIONS)

    def __init__(self, **options: Any) -> None:
        spec = type(self).options
        if isinstance(spec, Options):
            self.config = spec.parse(options, owner=self.name)
        else:  # a plain set of names: only the link's options are checked
            link = LINK_OPTIONS.parse({k: v for k, v in options.items() if k in LINK_OPTIONS},
                                      owner=self.name)
            self.config = Values({**options, **link.as_dict()})
        self.bridge = ThreadBridge(self.name)
        self._opened = False
        self._closed = False
        self.robot: RobotInfo | None = None
        self._feedforward_source: FeedforwardSource | None = None
        #: gives under way: a cancelled caller leaves them running to their end, and a
        #: withdraw of the same attempt waits for them first
        self._gives: dict[tuple[str, str], asyncio.Task[None]] = {}

    def bind_robot(self, robot: RobotInfo) -> None:
        """The robot this link moves, given before ``open``: a driver checks its options
        against it (unit vectors per joint, axis counts) so a mismatch is refused before any
        motion, with the option's name."""
        spec = type(self).options
        if isinstance(spec, Options):
            spec.check_joints(self.config, robot.n, robot.name)
        self._check_robot(robot)
        self.robot = robot

    def bind_feedforward(self, source: FeedforwardSource) -> None:
        """How a ``CAP_FEEDFORWARD`` driver gets torques: the link binds ``source(set,
        period_s, q)``, which runs a FeedforwardJob in the worker (before ``open``)."""
        self._feedforward_source = source

    async def feedforward_table(self, pset: ParameterSet, period_s: float,
                                q: Sequence[Sequence[float]]) -> FeedforwardTable:
        """The model torque of ``pset`` along setpoints ``q`` (rad, one row per ``period_s``),
        computed by the worker (the driver's ``_give_ready`` calls this before it streams);
        a DriverError, before any motion, when none can be had or it does not fit."""
        where = f"{self.name}: feed-forward of parameter set {pset.sha256[:12]}"
        if self._feedforward_source is None:
            raise DriverError(f"{where}: no worker bound to compute it (bind_feedforward)")
        try:
            table = await self._feedforward_source(pset, period_s, q)
        except DriverError:
            raise
        except RobidError as err:
            raise DriverError(f"{where}: {err}") from err
        n = len(q[0]) if len(q) else 0
        if (table.set_sha256 != pset.sha256 or len(table.tau) != len(q)
                or any(len(row) != n for row in table.tau)):
            raise DriverError(f"{where}: the table answered does not fit ({len(table.tau)} "
                              f"rows for {len(q)} setpoints, set {table.set_sha256[:12]})")
        return table

    # -- lifecycle
    async def open(self) -> None:
        if self._closed:
            raise DriverError(f"{self.name}: driver was closed")
        if not self._opened:
            self.bridge.bind(asyncio.get_running_loop())
            await self._open()
            self._opened = True
            log.info("driver=%s opened", self.name)

    async def close(self) -> None:
        if self._opened and not self._closed:
            self._closed = True
            try:
                await self._close()
            finally:
                self.bridge.close()
            log.info("driver=%s closed", self.name)
        self._closed = True
        self.bridge.close()

    async def __aenter__(self) -> Self:
        await self.open()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    def _require_open(self) -> None:
        if not self._opened or self._closed:
            raise DriverError(f"{self.name}: driver is not open")

    # -- the cycle
    async def _guarded(self, what: str, call: Awaitable[T], timeout_s: float, *,
                       answered: bool = False) -> T:
        """``call`` under ``timeout_s``; whatever escapes it is one line: a RobidError as it is
        (its text flattened), the timeout as DriverTimeoutError, anything else as DriverError —
        ProtocolError when ``answered`` (the motion command may have gone out)."""
        try:
            async with asyncio.timeout(timeout_s) as cm:
                return await call
        except RobidError as err:
            text = one_line(str(err))
            if text != str(err):
                err.args = (text,)
            raise
        except TimeoutError as err:
            if not cm.expired():
                raise self._unexpected(what, err, answered) from err
            raise DriverTimeoutError(f"{self.name}: {what}: no answer within {timeout_s:g} s "
                                     "(driver.command_timeout_s / transfer_timeout_s)") from err
        except Exception as err:  # noqa: BLE001 - the one rule: one line, never a traceback
            raise self._unexpected(what, err, answered) from err

    def _unexpected(self, what: str, err: Exception, answered: bool) -> DriverError:
        cls = ProtocolError if answered else DriverError
        return cls(one_line(f"{self.name}: {what}: unexpected from the controller "
                            f"({type(err).__name__}: {err})"))

    async def put_program(self, program: MotionProgram) -> None:
        """Hand the motion program to the controller (idempotent for the same program)."""
        self._require_open()
        check_name(program.exp_id, "experiment id")
        await self._guarded(f"put program of {program.exp_id}", self._put_program(program),
                            self.config.transfer_timeout_s)

    async def give_ready(self, exp_id: str, nonce: str) -> None:
        """semGive: tell the controller the program of ``exp_id`` is ready (idempotent). The
        link is checked alive first; the give itself runs to its end even if the caller is
        cancelled meanwhile (``withdraw`` then waits for it)."""
        self._require_open()
        key = (check_name(exp_id, "experiment id"), check_name(nonce, "nonce"))
        await self._guarded("link check before motion", self._check_link(),
                            self.config.command_timeout_s)
        task = self._gives.get(key)
        if task is None:
            task = asyncio.create_task(self._guarded(
                f"give experiment {exp_id}", self._give_ready(*key),
                self.config.command_timeout_s, answered=True), name=f"{self.name}-give")
            self._gives[key] = task
            task.add_done_callback(lambda t: self._give_ended(key, t))
        await asyncio.shield(task)

    def _give_ended(self, key: tuple[str, str], task: asyncio.Task[None]) -> None:
        if self._gives.get(key) is task:
            del self._gives[key]
        if not task.cancelled():
            task.exception()  # the caller has it, or was cancelled: never 'not retrieved'

    async def take_done(self, exp_id: str, nonce: str, timeout_s: float) -> Done:
        """semTake with a timeout: wait for this experiment's 'done' of this nonce."""
        self._require_open()
        check_name(exp_id, "experiment id")
        check_name(nonce, "nonce")
        if not timeout_s > 0:
            raise ConfigError(f"timeout_s: expected a positive number, got {timeout_s!r}")
        try:
            done = await self._guarded(f"take experiment {exp_id}",
                                       self._wait_done(exp_id, nonce), timeout_s, answered=True)
        except DriverTimeoutError as err:
            raise DriverTimeoutError(f"{self.name}: no 'done' for experiment {exp_id} "
                                     f"(nonce {nonce}) within {timeout_s:g} s") from err
        cap = self.config.max_log_bytes
        if done.size is not None and not 0 <= done.size <= cap:
            raise ProtocolError(f"{self.name}: 'done' of experiment {exp_id} announces a log "
                                f"of {done.size} bytes, over driver.max_log_bytes ({cap})")
        return done

    async def fetch_logs(self, done: Done) -> bytes:
        """The raw log of a finished experiment, checked against the 'done' checksum."""
        self._require_open()
        data = await self._guarded(f"fetch log of experiment {done.exp_id}",
                                   self._fetch_logs(done), self.config.transfer_timeout_s,
                                   answered=True)
        if len(data) > self.config.max_log_bytes:
            raise ProtocolError(f"{self.name}: log of experiment {done.exp_id} is over "
                                f"driver.max_log_bytes ({self.config.max_log_bytes})")
        if done.size is not None and len(data) != done.size:
            raise DriverError(f"{self.name}: log of experiment {done.exp_id} has {len(data)} "
                              f"bytes, 'done' announced {done.size} (truncated log)")
        got = hashlib.sha256(data).hexdigest()
        if got != done.sha256:
            raise DriverError(f"{self.name}: log of experiment {done.exp_id} fails its checksum "
                              f"(sha256 {got[:12]}…, 'done' says {done.sha256[:12]}…): "
                              "truncated or corrupt")
        return data

    async def acknowledge(self, done: Done) -> None:
        """The log is stored: the controller side may clean up this experiment's semaphores."""
        self._require_open()
        await self._guarded(f"acknowledge experiment {done.exp_id}", self._acknowledge(done),
                            self.config.command_timeout_s)

    async def withdraw(self, exp_id: str, nonce: str) -> None:
        """An attempt was given up (timeout, bad answer, cancel): its stop/abort goes out, so a
        controller that wakes up later does not run an obsolete program. A give of the same
        attempt still under way ends first (what it gives is then taken back)."""
        self._require_open()
        giving = self._gives.get((exp_id, nonce))
        if giving is not None:
            with contextlib.suppress(Exception):
                async with asyncio.timeout(self.config.command_timeout_s):
                    await asyncio.shield(giving)
        await self._guarded(f"withdraw experiment {exp_id}", self._withdraw(exp_id, nonce),
                            self.config.command_timeout_s)

    async def upload_parameters(self, doc: Mapping[str, Any], timeout_s: float = 60.0
                                ) -> None:
        """Send a parameter set to the controller and wait until it acknowledges loading it.
        A set the controller never acknowledges is withdrawn after ``timeout_s`` (the
        controller keeps its previous set) and raises DriverTimeoutError."""
        self._require_open()
        if CAP_UPLOAD not in self.capabilities:
            raise DriverError(f"{self.name}: this driver cannot upload parameters")
        body = parameter_bytes(doc)
        sha = hashlib.sha256(body).hexdigest()
        if not timeout_s > 0:
            raise ConfigError(f"timeout_s: expected a positive number, got {timeout_s!r}")
        try:
            await self._guarded("upload parameters", self._upload_parameters(doc, body),
                                timeout_s)
        except DriverTimeoutError as err:
            await self._guarded("withdraw parameters", self._withdraw_parameters(doc, body),
                                self.config.command_timeout_s)
            raise DriverTimeoutError(
                f"{self.name}: the controller did not acknowledge parameter set "
                f"{str(doc.get('sha256', sha))[:12]} within {timeout_s:g} s; withdrawn, it "
                "keeps its previous set") from err

    # -- hooks
    @abc.abstractmethod
    async def _open(self) -> None: ...

    @abc.abstractmethod
    async def _close(self) -> None: ...

    @abc.abstractmethod
    async def _put_program(self, program: MotionProgram) -> None: ...

    @abc.abstractmethod
    async def _give_ready(self, exp_id: str, nonce: str) -> None: ...

    @abc.abstractmethod
    async def _wait_done(self, exp_id: str, nonce: str) -> Done: ...

    @abc.abstractmethod
    async def _fetch_logs(self, done: Done) -> bytes: ...

    def _check_robot(self, robot: RobotInfo) -> None:
        return None

    async def _check_link(self) -> None:
        """Before every motion command: raise DriverError unless the controller shows it is
        alive (a heartbeat that moves, a session that answers). Default: nothing to check."""
        return None

    async def _acknowledge(self, done: Done) -> None:
        return None

    async def _withdraw(self, exp_id: str, nonce: str) -> None:
        return None

    async def _upload_parameters(self, doc: Mapping[str, Any], body: bytes) -> None:
        """Deliver ``body`` (the set's exact bytes) and return once the controller has
        acknowledged it; raise DriverError when it refuses."""
        raise NotImplementedError

    async def _withdraw_parameters(self, doc: Mapping[str, Any], body: bytes) -> None:
        return None
