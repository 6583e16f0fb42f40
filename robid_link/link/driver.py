"""The driver contract: one controller link, seen by the daemon as put → give → take → fetch.

The base class owns the public methods (state, timeouts, checks, logging); a driver overrides
the small ``_hooks``. Drivers are async context managers and ``close()`` is safe twice.
"""

from __future__ import annotations

import abc
import asyncio
import concurrent.futures
import hashlib
import io
import json
import logging
import re
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, Self

import numpy as np
import yaml

from robid_link.exceptions import ConfigError, DriverError, DriverTimeoutError
from robid_link.link.options import Options, Values
from robid_link.safeyaml import load_yaml

if TYPE_CHECKING:
    from robid_link.ident.model.robot import Robot

__all__ = [
    "Driver",
    "ThreadBridge",
    "MotionProgram",
    "ProgramTrajectory",
    "RobotInfo",
    "Done",
    "check_name",
    "parameter_bytes",
    "CAP_UPLOAD",
    "CAP_RAPID",
]

log = logging.getLogger("robid.driver")

#: capability names a driver may advertise
CAP_UPLOAD = "upload_parameters"
CAP_RAPID = "rapid"

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_\-]{0,63}$")


def parameter_bytes(doc: Mapping[str, Any]) -> bytes:
    """A parameter set as uploaded: canonical JSON, so the same set is the same bytes (a
    rollback restores the previous set byte for byte)."""
    return (json.dumps(doc, sort_keys=True, allow_nan=False, separators=(",", ":"))
            + "\n").encode()


def check_name(value: str, what: str) -> str:
    """Experiment ids and nonces become file names: letters, digits, '_' and '-' only, so no
    name can escape a folder or collide with the protocol's dots."""
    if not isinstance(value, str) or not _NAME.match(value):
        raise DriverError(f"{what} {value!r}: expected 1-64 letters, digits, '_' or '-'")
    return value


@dataclass(frozen=True)
class RobotInfo:
    """What a driver needs to know of the robot it moves (picklable, no Pinocchio model):
    joints in model order, their types and limits in SI units (``inf`` where unknown)."""

    name: str
    joint_names: tuple[str, ...]
    joint_types: tuple[str, ...]
    q_min: tuple[float, ...]
    q_max: tuple[float, ...]
    qd_max: tuple[float, ...]
    qdd_max: tuple[float, ...]
    tau_max: tuple[float, ...]

    @property
    def n(self) -> int:
        return len(self.joint_names)

    @classmethod
    def of(cls, robot: Robot) -> RobotInfo:
        lim = robot.limits
        return cls(robot.name, tuple(robot.joint_names), tuple(robot.joint_types),
                   *(tuple(float(x) for x in a)
                     for a in (lim.q_min, lim.q_max, lim.qd_max, lim.qdd_max, lim.tau_max)))


@dataclass(frozen=True)
class ProgramTrajectory:
    """The neutral trajectory of a program, parsed back from its files: what a driver renders
    for its controller (RAPID, counts per SYNC, …)."""

    t: np.ndarray
    q: np.ndarray
    rate_hz: float
    kind: str
    robot: str
    joint_types: tuple[str, ...]
    header: Mapping[str, Any]


@dataclass(frozen=True)
class MotionProgram:
    """One experiment's program as it leaves the daemon: the neutral trajectory
    (``traj.csv`` + ``traj.yaml``), already checked against the robot's limits. This is what
    an operator approves by hash; a driver renders it for its controller in ``_put_program``."""

    exp_id: str
    files: Mapping[str, bytes]
    duration_s: float
    meta: Mapping[str, Any] = field(default_factory=dict)

    @property
    def sha256(self) -> str:
        """Hash of the program's content (what an operator approves)."""
        h = hashlib.sha256()
        for suffix in sorted(self.files):
            h.update(suffix.encode() + b"\0" + self.files[suffix] + b"\0")
        return h.hexdigest()

    def trajectory(self) -> ProgramTrajectory:
        """``traj.csv`` + ``traj.yaml`` parsed; a DriverError names what is wrong."""
        where = f"program {self.exp_id}"
        try:
            head = load_yaml(self.files["traj.yaml"], f"{where}: traj.yaml", error=DriverError)
            arr = np.loadtxt(io.BytesIO(self.files["traj.csv"]), delimiter=",", skiprows=1,
                             ndmin=2)
        except KeyError as err:
            raise DriverError(f"{where}: file {err.args[0]} missing") from err
        except (ValueError, UnicodeDecodeError, yaml.YAMLError) as err:
            raise DriverError(f"{where}: unreadable trajectory ({err})") from err
        if not isinstance(head, dict) or arr.shape[1] < 2 or arr.shape[0] < 1:
            raise DriverError(f"{where}: trajectory header or samples malformed")
        n = arr.shape[1] - 1
        types = tuple(head.get("joint_types") or ("revolute",) * n)
        if len(types) != n or not np.all(np.isfinite(arr)):
            raise DriverError(f"{where}: {n} joints in traj.csv, {len(types)} joint types in "
                              "traj.yaml, or non-finite samples")
        try:
            rate = float(head["rate_hz"])
        except (KeyError, TypeError, ValueError) as err:
            raise DriverError(f"{where}: traj.yaml has no valid rate_hz") from err
        return ProgramTrajectory(arr[:, 0], arr[:, 1:], rate, str(head.get("kind", "custom")),
                                 str(head.get("robot", "")), types, head)


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
    ``self.config`` and owns ``self.bridge``, the way the driver's threads reach the loop.
    """

    name: ClassVar[str] = "driver"
    capabilities: ClassVar[frozenset[str]] = frozenset()
    #: the options the driver accepts (besides ``name``), declared once: ``__init__`` checks
    #: the given ones into ``self.config``; per-joint vectors are checked by ``bind_robot``.
    #: (A plain set of names is still accepted from older plug-ins: only unknown keys are
    #: refused then.)
    options: ClassVar[Options | frozenset[str]] = Options()

    def __init__(self, **options: Any) -> None:
        spec = type(self).options
        self.config = (spec.parse(options, owner=self.name) if isinstance(spec, Options)
                       else Values(options))
        self.bridge = ThreadBridge(self.name)
        self._opened = False
        self._closed = False
        self.robot: RobotInfo | None = None

    def bind_robot(self, robot: RobotInfo) -> None:
        """The robot this link moves, given before ``open``: a driver checks its options
        against it (unit vectors per joint, axis counts) so a mismatch is refused before any
        motion, with the option's name."""
        spec = type(self).options
        if isinstance(spec, Options):
            spec.check_joints(self.config, robot.n, robot.name)
        self._check_robot(robot)
        self.robot = robot

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
    async def put_program(self, program: MotionProgram) -> None:
        """Hand the motion program to the controller (idempotent for the same program)."""
        self._require_open()
        check_name(program.exp_id, "experiment id")
        await self._put_program(program)

    async def give_ready(self, exp_id: str, nonce: str) -> None:
        """semGive: tell the controller the program of ``exp_id`` is ready (idempotent)."""
        self._require_open()
        await self._give_ready(check_name(exp_id, "experiment id"), check_name(nonce, "nonce"))

    async def take_done(self, exp_id: str, nonce: str, timeout_s: float) -> Done:
        """semTake with a timeout: wait for this experiment's 'done' of this nonce."""
        self._require_open()
        check_name(exp_id, "experiment id")
        check_name(nonce, "nonce")
        if not timeout_s > 0:
            raise ConfigError(f"timeout_s: expected a positive number, got {timeout_s!r}")
        try:
            async with asyncio.timeout(timeout_s):
                return await self._wait_done(exp_id, nonce)
        except TimeoutError as err:
            raise DriverTimeoutError(f"{self.name}: no 'done' for experiment {exp_id} "
                                     f"(nonce {nonce}) within {timeout_s:g} s") from err

    async def fetch_logs(self, done: Done) -> bytes:
        """The raw log of a finished experiment, checked against the 'done' checksum."""
        self._require_open()
        data = await self._fetch_logs(done)
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
        await self._acknowledge(done)

    async def withdraw(self, exp_id: str, nonce: str) -> None:
        """An attempt was given up (timeout, bad log): take back its 'ready' so a controller
        that wakes up later does not run an obsolete program."""
        self._require_open()
        await self._withdraw(exp_id, nonce)

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
            async with asyncio.timeout(timeout_s):
                await self._upload_parameters(doc, body)
        except TimeoutError as err:
            await self._withdraw_parameters(doc, body)
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
