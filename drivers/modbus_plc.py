"""A PLC between the cell PC and the robot: the give/take handshake in Modbus TCP holding
registers, programs and logs over a file share (the file-share driver's ``ShareTransfer``).

Register map (offsets from ``base_address``; each name can be moved with ``registers:``)::

    daemon → PLC   0 command (0 IDLE, 1 RUN, 2 ABORT)   1 exp (experiment number 1-65535)
                   2 nonce_hi  3 nonce_lo (32-bit tag)  4 daemon_heartbeat (+1 every period)
    PLC → daemon   5 status (0 IDLE, 1 BUSY, 2 DONE, 3 ERROR)   6 exp_echo
                   7 nonce_echo_hi  8 nonce_echo_lo  9 error_code  10 plc_heartbeat

give: program files on the share as ``inbox/<n>.traj.csv|yaml`` (``<n>`` the experiment
number, kept in ``inbox/experiments.json``), then command=IDLE, exp, nonce, and command=RUN
last. The PLC runs a RUN whose (exp, nonce) it has not run yet, echoes both with status BUSY,
writes ``outbox/<n>.<tag>.log.csv`` and ``sem/<n>.<tag>.done`` (``sha256 size=N``: a SHA-256
needs 16 registers, the share carries it for free) and sets status DONE — or ERROR with an error
code (and optionally ``sem/<n>.<tag>.failed`` with a reason). ``<tag>`` is the nonce's 32-bit
tag in 8 hex digits. An answer whose echo is not ours is stale and ignored; a status outside
0-3 or an echo of our nonce with another experiment is register garbage and refused. Both
heartbeats count up; a PLC heartbeat that does not change within ``heartbeat_timeout_s`` is an
error — also before the first RUN (a heartbeat seen moving since the link opened is required)
— and a withdraw writes ABORT whatever the heartbeat says. Modbus has no events: the status is
polled every ``poll_interval_s`` while waiting.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import re
import time
import zlib
from collections.abc import Mapping
from typing import Any

from pymodbus.client import AsyncModbusTcpClient
from pymodbus.exceptions import ModbusException

from robid_link.atomic import atomic_write
from robid_link.drivers.file_share import ShareTransfer
from robid_link.drivers.rapid import MAX_AXES
from robid_link.exceptions import ConfigError, DriverError
from robid_link.jobs import MotionProgram
from robid_link.link.driver import CAP_RAPID, Done, Driver
from robid_link.link.options import Flag, Folder, Integer, Number, Options, Table, Text
from robid_link.link.retry import Backoff
from robid_link.safeopen import read_regular

__all__ = ["ModbusPlcDriver", "REGISTERS", "Command", "Status", "ERROR_CODES", "nonce_tag",
           "register_map"]

log = logging.getLogger("robid.driver.modbus_plc")

#: register names in their default order (offset from ``base_address``)
REGISTERS = ("command", "exp", "nonce_hi", "nonce_lo", "daemon_heartbeat",
             "status", "exp_echo", "nonce_echo_hi", "nonce_echo_lo", "error_code",
             "plc_heartbeat")
#: the longest span one Modbus read (function 3) may cover
MAX_SPAN = 125


class Command:
    IDLE, RUN, ABORT = 0, 1, 2


class Status:
    IDLE, BUSY, DONE, ERROR = 0, 1, 2, 3
    NAMES = {0: "IDLE", 1: "BUSY", 2: "DONE", 3: "ERROR"}


#: what a PLC's error code means (README, "Modbus PLC")
ERROR_CODES = {1: "program missing or unreadable on the share",
               2: "motion supervision triggered",
               3: "joint limit reached",
               4: "emergency stop",
               5: "robot not in automatic mode",
               6: "share not writable (log not saved)",
               7: "aborted by the daemon"}
_HEX_NONCE = re.compile(r"^[0-9a-f]{1,8}$")
#: waits between connection attempts
CONNECT_BACKOFF = Backoff(0.05, 1.0)
#: the experiment index on the share: a JSON object of at most 65535 names
MAX_INDEX_BYTES = 4 << 20
#: stale answers remembered (one warning each), at most
MAX_WARNED = 1024


def nonce_tag(nonce: str) -> int:
    """The 32-bit tag a PLC sees for a nonce: its value when it is 1-8 hex digits (the daemon's
    nonces are), else the CRC-32 of its text."""
    return int(nonce, 16) if _HEX_NONCE.match(nonce) else zlib.crc32(nonce.encode())


_BASE_ADDRESS = Integer(0, low=0, high=65536 - len(REGISTERS))
_ADDRESS = Integer(low=0, high=65535, expect="an address 0-65535")
_REGISTERS = Table(None)


def register_map(base_address: Any = 0, registers: Any = None) -> dict[str, int]:
    """Address of each register: ``base_address`` + its default offset, moved by ``registers``
    (name → address). ConfigError names the key when an address is bad, shared or the map
    spans more than one Modbus read."""
    base = _BASE_ADDRESS.convert("driver.base_address", base_address)
    addr = {name: base + k for k, name in enumerate(REGISTERS)}
    moved: Mapping[str, Any] = ({} if registers is None
                                else _REGISTERS.convert("driver.registers", registers))
    for name, value in moved.items():
        if name not in addr:
            raise ConfigError(f"driver.registers.{name}: unknown register (known: "
                              f"{', '.join(REGISTERS)})")
        addr[name] = _ADDRESS.convert(f"driver.registers.{name}", value)
    seen: dict[int, str] = {}
    for name, a in addr.items():
        if a in seen:
            raise ConfigError(f"driver.registers.{name}: address {a} is also {seen[a]}")
        seen[a] = name
    span = max(addr.values()) - min(addr.values()) + 1
    if span > MAX_SPAN:
        raise ConfigError(f"driver.registers: the map spans {span} registers; one Modbus read "
                          f"covers at most {MAX_SPAN}")
    return addr


class ModbusPlcDriver(Driver):
    """Daemon side of the Modbus PLC handshake (module docstring; README "Modbus PLC").

    Options: ``host``, ``port`` (502), ``device_id`` (1), ``share`` (the folder the PLC side
    reads programs from and writes logs to), ``base_address`` / ``registers`` (the map),
    ``poll_interval_s`` (0.005), ``heartbeat_period_s`` (0.2), ``heartbeat_timeout_s`` (2),
    ``io_timeout_s`` (1), ``connect_retries`` (5), ``rapid`` (false: also write RAPID).
    """

    name = "modbus_plc"
    # no parameter upload: the handshake has no register for "load this set" and nothing that
    # acknowledges it (a driver without upload says so, and campaigns needing it are refused)
    capabilities: frozenset[str] = frozenset()
    options = Options(
        host=Text(hint="the PLC's address"), port=Integer(502, low=1, high=65535),
        device_id=Integer(1, low=0, high=255),
        share=Folder(hint="the folder programs and logs travel on"),
        base_address=_BASE_ADDRESS, registers=_REGISTERS,
        poll_interval_s=Number(0.005, low=0.001, high=10),
        heartbeat_period_s=Number(0.2, low=0.01, high=60),
        heartbeat_timeout_s=Number(2.0, above=0), io_timeout_s=Number(1.0, low=0.01, high=60),
        connect_retries=Integer(5, low=0, high=100), rapid=Flag(False))

    def __init__(self, **options: Any) -> None:
        super().__init__(**options)
        o = self.config
        self.host, self.port, self.device_id = o.host, o.port, o.device_id
        self.addr = register_map(o.base_address, o.registers)
        self._lo = min(self.addr.values())
        self._span = max(self.addr.values()) - self._lo + 1
        self.poll_s, self.hb_period_s = o.poll_interval_s, o.heartbeat_period_s
        self.hb_timeout_s = Number(low=2 * self.hb_period_s).convert(
            "driver.heartbeat_timeout_s", o.heartbeat_timeout_s)  # two periods at least
        self.io_timeout_s = o.io_timeout_s
        self.connect_retries = o.connect_retries
        if o.rapid:
            self.capabilities = frozenset({CAP_RAPID})
        self.transfer = ShareTransfer(o.share, rapid=o.rapid, max_log_bytes=o.max_log_bytes)
        self._index_path = self.transfer.inbox / "experiments.json"
        self._numbers: dict[str, int] = {}
        self._client: Any = None
        self._snap: dict[str, int] = {}
        self._fault: DriverError | None = None
        self._tick = asyncio.Event()
        self._wake = asyncio.Event()
        self._closing = False
        self._waiting = 0
        self._beat = 0
        self._hb_seen: tuple[int, float] | None = None
        self._hb_moved = False  # the PLC heartbeat was seen changing since the link opened
        self._warned: set[tuple[int, int, int]] = set()
        self._tasks: list[asyncio.Task[None]] = []

    def _check_robot(self, robot: Any) -> None:
        if CAP_RAPID in self.capabilities and robot.n > MAX_AXES:
            raise ConfigError(f"driver.rapid: RAPID joint targets hold at most {MAX_AXES} axes, "
                              f"robot {robot.name} has {robot.n} (set rapid: false)")

    @property
    def where(self) -> str:
        return f"PLC {self.host}:{self.port}"

    # -- lifecycle
    async def _open(self) -> None:
        await asyncio.to_thread(self.transfer.prepare)
        self._numbers = await asyncio.to_thread(self._load_index)
        self._client = AsyncModbusTcpClient(self.host, port=self.port,
                                            timeout=self.io_timeout_s, retries=0,
                                            reconnect_delay=0)
        await self._connect()
        self._check_status(await self._read_block())
        self._tasks.append(asyncio.create_task(self._poll_loop(), name="modbus_plc-poll"))

    async def _close(self) -> None:
        # the flag as well as the cancel: Python 3.11's wait_for (inside pymodbus) drops a
        # cancellation that meets a reply in the same instant
        self._closing = True
        self._wake.set()
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        self._tasks.clear()
        if self._client is not None:
            self._client.close()
            self._client = None

    async def _connect(self) -> None:
        """Connect with a bounded number of growing, jittered retries; one line if it fails."""
        for attempt in range(self.connect_retries + 1):
            try:
                async with asyncio.timeout(self.io_timeout_s + 1):
                    if await self._client.connect():
                        return
            except (TimeoutError, OSError, ModbusException):
                pass
            if attempt < self.connect_retries:
                await CONNECT_BACKOFF.sleep(attempt + 1)
        raise DriverError(f"{self.where} unreachable after {self.connect_retries + 1} "
                          "connection attempts (PLC gone or address wrong)")

    # -- registers
    async def _call(self, what: str, request: Any, *args: Any) -> Any:
        """One Modbus request (the client method and its arguments) under a timeout; every
        failure is a DriverError (pymodbus raises some at once, before anything is awaited)."""
        try:
            async with asyncio.timeout(self.io_timeout_s + 0.5):
                res = await request(*args, device_id=self.device_id)
        except (TimeoutError, ModbusException, OSError) as err:
            raise DriverError(f"{self.where}: {what} failed ({str(err) or 'timeout'})") from err
        if res.isError():
            raise DriverError(f"{self.where}: {what} refused by the PLC ({res}); check "
                              "driver.registers and driver.device_id")
        return res

    def _read(self, address: int, device_id: int) -> Any:
        return self._client.read_holding_registers(address, count=self._span,
                                                   device_id=device_id)

    async def _read_block(self) -> dict[str, int]:
        if self._client is None or not self._client.connected:
            raise DriverError(f"{self.where}: not connected")
        res = await self._call(f"reading registers {self._lo}-{self._lo + self._span - 1}",
                               self._read, self._lo)
        regs = list(res.registers)
        if len(regs) != self._span:
            raise DriverError(f"{self.where}: asked for {self._span} registers, got {len(regs)}")
        return {name: regs[a - self._lo] for name, a in self.addr.items()}

    async def _write(self, *, force: bool = False, **values: int) -> None:
        """Write named registers: one request per contiguous run, in the order given; refused
        while the link is faulty unless ``force`` (an ABORT goes out whatever the PLC's
        heartbeat says)."""
        if self._fault is not None and not force:
            raise self._fault
        if self._client is None or not self._client.connected:
            raise DriverError(f"{self.where}: not connected")
        items = [(self.addr[k], v & 0xFFFF) for k, v in values.items()]
        k = 0
        while k < len(items):
            start, run = items[k][0], [items[k][1]]
            while k + len(run) < len(items) and items[k + len(run)][0] == start + len(run):
                run.append(items[k + len(run)][1])
            await self._call(f"writing register {start}", self._client.write_registers, start,
                             run)
            k += len(run)

    def _check_status(self, snap: dict[str, int]) -> None:
        if snap["status"] not in Status.NAMES:
            raise DriverError(f"{self.where}: status register holds {snap['status']}, not a "
                              "known status (0-3): register garbage, refusing to run")

    async def _poll_loop(self) -> None:
        """Read the map (every ``poll_interval_s`` while someone waits, else every heartbeat
        period), count our heartbeat up, watch the PLC's; reconnect when the link drops."""
        next_beat = 0.0
        while not self._closing:
            try:
                now = time.monotonic()
                if now >= next_beat:
                    self._beat = (self._beat + 1) & 0xFFFF
                    await self._call("writing the heartbeat", self._client.write_register,
                                     self.addr["daemon_heartbeat"], self._beat)
                    next_beat = now + self.hb_period_s
                snap = await self._read_block()
                self._fault = self._heartbeat_fault(snap)
                self._snap = snap
            except DriverError as err:
                log.warning("%s: %s; reconnecting", self.where, err)
                self._client.close()
                self._hb_seen = None
                try:
                    await self._connect()
                    self._fault = None
                except DriverError as gone:
                    self._fault = gone
            except Exception as err:  # a bug here must not leave waiters hanging to a timeout
                self._fault = DriverError(f"{self.where}: register polling failed ({err!r})")
                self._tick.set()
                raise
            self._tick.set()
            self._tick = asyncio.Event()
            # a waiter that arrives during a long idle sleep wakes the loop up
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(self.poll_s if self._waiting else self.hb_period_s):
                    await self._wake.wait()
            self._wake.clear()

    def _heartbeat_fault(self, snap: dict[str, int]) -> DriverError | None:
        value, now = snap["plc_heartbeat"], time.monotonic()
        if self._hb_seen is None or self._hb_seen[0] != value:
            self._hb_moved = self._hb_moved or self._hb_seen is not None
            self._hb_seen = (value, now)
            return None
        frozen = now - self._hb_seen[1]
        if frozen > self.hb_timeout_s:
            return DriverError(f"{self.where}: PLC heartbeat frozen at {value} for {frozen:.1f} s "
                               f"(limit {self.hb_timeout_s:g} s): the PLC program is not running")
        return None

    async def _check_link(self) -> None:
        """Before a RUN: the PLC's heartbeat must have moved since the link opened and must
        not be frozen now (waits up to ``heartbeat_timeout_s`` for a first change)."""
        end = time.monotonic() + self.hb_timeout_s + 2 * self.hb_period_s
        while not self._hb_moved and self._fault is None and time.monotonic() < end:
            self._wake.set()
            await asyncio.sleep(self.poll_s)
        if self._fault is not None:
            raise self._fault
        if not self._hb_moved:
            value = self._hb_seen[0] if self._hb_seen else "?"
            raise DriverError(f"{self.where}: PLC heartbeat frozen at {value} since the link "
                              f"opened (limit {self.hb_timeout_s:g} s): the PLC program is not "
                              "running; no RUN given")

    # -- experiment numbers on the share
    def _load_index(self) -> dict[str, int]:
        """The index through the safe open: a regular file of bounded size (a FIFO or a link
        to /dev/zero put there is refused, never read)."""
        try:
            raw = read_regular(self._index_path, MAX_INDEX_BYTES)
        except FileNotFoundError:
            return {}
        except OSError as err:
            raise DriverError(f"{self._index_path}: experiment index refused "
                              f"({err.strerror or err})") from err
        try:
            doc = json.loads(raw)
        except ValueError as err:
            raise DriverError(f"{self._index_path}: unreadable experiment index ({err})") from err
        if not isinstance(doc, dict) or not all(isinstance(v, int) and not isinstance(v, bool)
                                                and 1 <= v <= 65535 for v in doc.values()):
            raise DriverError(f"{self._index_path}: expected a JSON object id → number "
                              "(1-65535)")
        return dict(doc)

    async def _number_of(self, exp_id: str) -> int:
        """The experiment's number, assigned once and kept on the share (survives restarts)."""
        if exp_id not in self._numbers:
            n = max(self._numbers.values(), default=0) + 1
            if n > 65535:
                raise DriverError(f"{self._index_path}: 65535 experiment numbers used; "
                                  "archive the share's inbox")
            self._numbers[exp_id] = n
            body = json.dumps(self._numbers, indent=1).encode()
            await asyncio.to_thread(self.transfer.folder, self.transfer.inbox)
            await asyncio.to_thread(atomic_write, self._index_path, body)
        return self._numbers[exp_id]

    def _keys(self, exp_id: str, nonce: str) -> tuple[str, str]:
        if exp_id not in self._numbers:
            raise DriverError(f"experiment {exp_id} has no number on {self._index_path} "
                              "(its program was never put)")
        return str(self._numbers[exp_id]), f"{nonce_tag(nonce):08x}"

    def _ours(self, snap: dict[str, int], n: int, tag: int, echo: bool = True) -> bool:
        pre = ("exp_echo", "nonce_echo_hi", "nonce_echo_lo") if echo else ("exp", "nonce_hi",
                                                                             "nonce_lo")
        return (snap[pre[0]], snap[pre[1]], snap[pre[2]]) == (n, tag >> 16, tag & 0xFFFF)

    async def _fresh(self) -> dict[str, int]:
        """The registers as they are now (a read), checked."""
        if self._fault is not None:
            raise self._fault
        snap = await self._read_block()
        self._check_status(snap)
        return snap

    def _latest(self) -> dict[str, int]:
        """The poll loop's last reading, checked."""
        if self._fault is not None:
            raise self._fault
        self._check_status(self._snap)
        return self._snap

    # -- the cycle
    async def _put_program(self, program: MotionProgram) -> None:
        n = await self._number_of(program.exp_id)
        await self.transfer.put_program(program, key=str(n))

    async def _give_ready(self, exp_id: str, nonce: str) -> None:
        n, tag = await self._number_of(exp_id), nonce_tag(nonce)
        snap = await self._fresh()
        if self._ours(snap, n, tag) and snap["status"] != Status.IDLE:
            return  # the PLC already took this one (given before a restart)
        if self._ours(snap, n, tag, echo=False) and snap["command"] == Command.RUN:
            return
        # IDLE first: the PLC never sees RUN next to half-written parameters
        if snap["command"] != Command.IDLE:
            await self._write(command=Command.IDLE)
        await self._write(exp=n, nonce_hi=tag >> 16, nonce_lo=tag & 0xFFFF)
        await self._write(command=Command.RUN)
        log.info("%s exp=%s number=%d nonce=%s tag=%08x command=RUN", self.where, exp_id, n,
                 nonce, tag)

    async def _wait_done(self, exp_id: str, nonce: str) -> Done:
        key, nkey = self._keys(exp_id, nonce)
        n, tag = int(key), nonce_tag(nonce)
        missing_since: float | None = None
        self._waiting += 1
        self._wake.set()
        try:
            snap = await self._fresh()
            while True:
                status = snap["status"]
                if status in (Status.DONE, Status.ERROR) and not self._ours(snap, n, tag):
                    self._stale(exp_id, snap)
                elif self._ours(snap, n, tag) and status == Status.ERROR:
                    raise self._error(exp_id, snap["error_code"], key, nkey)
                elif self._ours(snap, n, tag) and status == Status.DONE:
                    done = await asyncio.to_thread(self.transfer.done, key, nkey, exp_id, nonce)
                    if done is not None:
                        return done
                    missing_since = missing_since or time.monotonic()
                    if time.monotonic() - missing_since > 5.0:  # a share may lag a little
                        raise DriverError(f"{self.where}: status DONE for experiment {exp_id} "
                                          f"but no {self.transfer.sem_path(key, nkey, 'done')}")
                elif not self._ours(snap, n, tag) and snap["nonce_echo_hi"] == tag >> 16 and (
                        snap["nonce_echo_lo"] == tag & 0xFFFF) and status != Status.IDLE:
                    raise DriverError(f"{self.where}: PLC echoes our nonce with experiment "
                                      f"{snap['exp_echo']}, not {n}: register garbage, refused")
                await self._tick.wait()
                snap = self._latest()
        finally:
            self._waiting -= 1

    def _stale(self, exp_id: str, snap: dict[str, int]) -> None:
        key = (snap["exp_echo"], snap["nonce_echo_hi"], snap["nonce_echo_lo"])
        if key not in self._warned:
            if len(self._warned) >= MAX_WARNED:  # bounded: a PLC spraying echoes
                self._warned.clear()
            self._warned.add(key)
            log.warning("%s exp=%s stale answer (status %s for experiment %d, nonce tag "
                        "%04x%04x; ignored)", self.where, exp_id, Status.NAMES[snap["status"]],
                        *key)

    def _error(self, exp_id: str, code: int, key: str, nkey: str) -> DriverError:
        text = ERROR_CODES.get(code, "unknown error code")
        reason = self.transfer.failed(key, nkey)
        return DriverError(f"{self.where} reports experiment {exp_id} failed: error {code} "
                           f"({text})" + (f": {reason}" if reason else ""))

    async def _fetch_logs(self, done: Done) -> bytes:
        return await self.transfer.fetch_log(*self._keys(done.exp_id, done.nonce),
                                             limit=done.size)

    async def _release(self, exp_id: str, nonce: str, command: int) -> None:
        """Set ``command`` if the registers still hold this experiment's request."""
        n, tag = self._numbers.get(exp_id), nonce_tag(nonce)
        if n is None:
            return
        snap = await self._fresh()
        if self._ours(snap, n, tag, echo=False) and snap["command"] != command:
            await self._write(command=command)

    async def _acknowledge(self, done: Done) -> None:
        n, tag = self._numbers.get(done.exp_id, 0), nonce_tag(done.nonce)
        self._warned.add((n, tag >> 16, tag & 0xFFFF))  # its DONE lingers a scan: not stale
        await self._release(done.exp_id, done.nonce, Command.IDLE)
        await self.transfer.remove(*self._keys(done.exp_id, done.nonce), "done")

    async def _withdraw(self, exp_id: str, nonce: str) -> None:
        """ABORT if the registers still hold this request — read past a heartbeat fault, and
        written blindly when they cannot be read (the stop must go out)."""
        n, tag = self._numbers.get(exp_id), nonce_tag(nonce)
        if n is None:
            return
        try:
            snap = await self._read_block()
        except DriverError as err:
            log.warning("%s exp=%s registers unreadable (%s): writing ABORT anyway",
                        self.where, exp_id, err)
            await self._write(force=True, command=Command.ABORT)
            return
        if self._ours(snap, n, tag, echo=False) and snap["command"] != Command.ABORT:
            await self._write(force=True, command=Command.ABORT)
            log.warning("%s exp=%s nonce=%s given up: ABORT written", self.where, exp_id,
                        nonce)

