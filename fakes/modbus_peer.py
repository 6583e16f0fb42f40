"""The PLC side of the Modbus handshake (``docs/modbus_plc_protocol.md``, written from that page):
a pymodbus TCP server on 127.0.0.1 whose registers a scan cycle reads and writes like a PLC
program, running programs from the share on the fake controller and writing logs and ``done``
files back to the share.

Own faults: ``plc_gone`` (the server stops for good once a RUN arrives), ``heartbeat_frozen``
(the PLC heartbeat stops for ``freeze_s`` while BUSY), ``heartbeat_dead`` (it never counts:
the PLC program does not run, the Modbus server answers all the same), ``error_code`` (ERROR
with code 4, emergency stop), ``register_garbage`` (status and echo registers hold nonsense;
nothing runs). The PLC keeps ``runs`` (each request it started) and ``aborts`` (the wall-clock
time each ABORT written to ``command`` arrived).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
import zlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from robid_link.exceptions import RobidError
from robid_link.fakes.controller import ControllerCore, Peer
from robid_link.fakes.share_protocol import Share

__all__ = ["ModbusPeer", "REGISTER_OFFSETS", "register_addresses"]

log = logging.getLogger("robid.fake_controller")

#: the register map (page: "Register map"): name → offset from base_address
REGISTER_OFFSETS = {"command": 0, "exp": 1, "nonce_hi": 2, "nonce_lo": 3,
                    "daemon_heartbeat": 4, "status": 5, "exp_echo": 6, "nonce_echo_hi": 7,
                    "nonce_echo_lo": 8, "error_code": 9, "plc_heartbeat": 10}
# command and status values (page: "Register map")
CMD_IDLE, CMD_RUN, CMD_ABORT = 0, 1, 2
IDLE, BUSY, DONE, ERROR = 0, 1, 2, 3
# error codes (page: "Register map")
E_PROGRAM, E_SUPERVISION, E_ESTOP = 1, 2, 4


def register_addresses(base_address: int = 0, registers: Mapping[str, int] | None = None
                       ) -> dict[str, int]:
    """Each register's protocol address: ``base_address`` + its offset, moved by ``registers``
    (name → address) as a cell configures it."""
    addr = {name: base_address + k for name, k in REGISTER_OFFSETS.items()}
    for name, a in (registers or {}).items():
        if name not in addr or not 0 <= int(a) <= 65535:
            raise RobidError(f"--option registers: {name}={a!r} is not a register of the map")
        addr[name] = int(a)
    if len(set(addr.values())) != len(addr):
        raise RobidError("--option registers: two registers share an address")
    return addr


class ModbusPeer(Peer):
    """A fake PLC: ``start`` serves in a thread with its own event loop, ``stop`` joins it."""

    driver = "modbus_plc"
    faults = ("plc_gone", "heartbeat_frozen", "heartbeat_dead", "error_code",
              "register_garbage")

    def __init__(self, core: ControllerCore, workdir: Path, *, port: int = 0,
                 device_id: int = 1, base_address: int = 0,
                 registers: dict[str, int] | None = None, scan_s: float = 0.002,
                 heartbeat_s: float = 0.05, freeze_s: float = 4.0) -> None:
        super().__init__(core, workdir)
        self.share = Share(Path(workdir))
        self.share.make()
        self.addr = register_addresses(base_address, registers)
        self._lo = min(self.addr.values())
        self.image = [0] * (max(self.addr.values()) - self._lo + 1)
        self.port, self.device_id = port, device_id
        self.scan_s, self.heartbeat_s, self.freeze_s = scan_s, heartbeat_s, freeze_s
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._stop: asyncio.Event | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._error: BaseException | None = None
        self._server: Any = None
        self._job: asyncio.Task[None] | None = None
        self._last: tuple[int, int, int] | None = None
        self._frozen_until = 0.0
        #: nonce tag (8 hex digits) → time.perf_counter() when DONE was set (benchmarks)
        self.answer_times: dict[str, float] = {}
        self.runs: list[tuple[int, int, int]] = []
        self.aborts: list[float] = []

    # -- register image (touched only on the server's loop)
    def get(self, name: str) -> int:
        return self.image[self.addr[name] - self._lo]

    def set(self, **values: int) -> None:
        for name, v in values.items():
            self.image[self.addr[name] - self._lo] = v & 0xFFFF

    async def _action(self, fc: int, start: int, address: int, count: int, regs: list[int],
                      values: list[int] | list[bool] | None) -> Any:
        """pymodbus hook on every access: writes land in the image, reads see the image."""
        if values is not None:
            for k, v in enumerate(values):
                if 0 <= address - self._lo + k < len(self.image):
                    self.image[address - self._lo + k] = int(v)
                if address + k == self.addr["command"] and int(v) == CMD_ABORT:
                    self.aborts.append(time.time())  # the ABORT has reached the PLC
        else:
            regs[self._lo - start: self._lo - start + len(self.image)] = self.image
        return None

    # -- life cycle
    def driver_options(self) -> dict[str, Any]:
        return {"name": "modbus_plc", "host": "127.0.0.1", "port": self.port,
                "device_id": self.device_id, "share": str(self.workdir)}

    def start(self) -> None:
        if self._thread is not None:
            return
        self._thread = threading.Thread(target=self._run, name="fake-plc", daemon=True)
        self._thread.start()
        self._ready.wait(30)
        if self._error is not None:
            raise RobidError(f"fake PLC could not start: {self._error}")

    def stop(self) -> None:
        if self._loop is not None and self._stop is not None:
            with contextlib.suppress(RuntimeError):  # loop already closed
                self._loop.call_soon_threadsafe(self._stop.set)
        if self._thread is not None:
            self._thread.join(30)

    def _run(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as err:  # noqa: B036  # reported by start()
            self._error = err
            self._ready.set()

    async def _main(self) -> None:
        self._loop, self._stop = asyncio.get_running_loop(), asyncio.Event()
        device = SimDevice(id=self.device_id, action=self._action, simdata=[SimData(
            self._lo, count=len(self.image), values=0, datatype=DataType.REGISTERS)])
        self._server = ModbusTcpServer(device, address=("127.0.0.1", self.port))
        await self._server.serve_forever(background=True)
        self.port = self._server.transport.sockets[0].getsockname()[1]
        self._ready.set()
        scan = asyncio.create_task(self._scan_loop(), name="fake-plc-scan")
        try:
            await self._stop.wait()
        finally:
            scan.cancel()
            if self._job is not None:
                self._job.cancel()
            await asyncio.gather(scan, *([self._job] if self._job else []),
                                 return_exceptions=True)
            await self._go_offline()

    async def _go_offline(self) -> None:
        if self._server is not None:
            server, self._server = self._server, None
            await server.shutdown()

    # -- the PLC program
    async def _scan_loop(self) -> None:
        loop = asyncio.get_running_loop()
        next_beat = 0.0
        while True:
            now = loop.time()
            if (now >= next_beat and now >= self._frozen_until
                    and self.core.fault != "heartbeat_dead"):
                self.set(plc_heartbeat=self.get("plc_heartbeat") + 1)
                next_beat = now + self.heartbeat_s
            self._scan()
            await asyncio.sleep(self.scan_s)

    def _scan(self) -> None:
        """One PLC cycle (page: "What the PLC must do", 2, 5 and 6)."""
        cmd, busy = self.get("command"), self._job is not None and not self._job.done()
        request = (self.get("exp"), self.get("nonce_hi"), self.get("nonce_lo"))
        running = (self.get("exp_echo"), self.get("nonce_echo_hi"), self.get("nonce_echo_lo"))
        if cmd == CMD_ABORT and running == request and self.get("status") == BUSY:
            if self._job is not None:
                self._job.cancel()
            self.set(status=IDLE, error_code=0)
        elif cmd == CMD_RUN and not busy and self.get("status") != BUSY and (
                request != self._last and request[0] > 0):
            self._last = request
            self.runs.append(request)
            self.set(exp_echo=request[0], nonce_echo_hi=request[1], nonce_echo_lo=request[2],
                     error_code=0, status=BUSY)
            self._job = asyncio.create_task(self._run_program(*request), name="fake-plc-job")
        elif cmd == CMD_IDLE and self.get("status") in (DONE, ERROR):
            self.set(status=IDLE)  # the daemon acknowledged

    async def _run_program(self, n: int, hi: int, lo: int) -> None:
        key, nkey = str(n), f"{(hi << 16) | lo:08x}"
        fault = self.core.take_fault() if self.core.fault in self.faults else None
        if fault is not None:
            log.info("plc exp=%s tag=%s playing fault %s", key, nkey, fault)
            await self._play(fault)
            return
        try:
            csv, header = await asyncio.to_thread(self.share.program, key)
        except OSError as err:
            await self._fail(key, nkey, E_PROGRAM, f"program {key}: {err.strerror}")
            return
        res = await asyncio.to_thread(self.core.run, key, nkey, csv, header)
        if res.fault == "never_answer":
            return
        if res.error is not None:
            await self._fail(key, nkey, E_SUPERVISION if res.fault == "fail" else E_PROGRAM,
                             res.error)
            return
        if res.fault == "die":
            await asyncio.to_thread(self.share.write_partial, key, nkey,
                                    res.log[: len(res.log) // 2])
            self.core.die()
            self.died.set()
            await self._go_offline()
            return
        await asyncio.to_thread(self.share.write_log, key, nkey, res.delivered)
        if res.fault == "stale_semaphore":  # an older attempt's answer shows first
            stale = zlib.crc32(b"0stale0")
            await self._answer(key, f"{stale:08x}", n, stale, "0" * 64, 1)
            await asyncio.sleep(0.3)
        await self._answer(key, nkey, n, (hi << 16) | lo, res.sha256, len(res.log))
        if res.fault == "answer_twice":
            await asyncio.sleep(0.05)
            self.set(status=BUSY)
            await asyncio.sleep(0.05)
            await self._answer(key, nkey, n, (hi << 16) | lo, res.sha256, len(res.log))

    async def _answer(self, key: str, nkey: str, n: int, tag: int, sha: str, size: int) -> None:
        """The 'done' file on the share first, then the registers that point at it."""
        await asyncio.to_thread(self.share.answer_done, key, nkey, sha, size)
        self.set(exp_echo=n, nonce_echo_hi=tag >> 16, nonce_echo_lo=tag & 0xFFFF, status=DONE)
        self.answer_times[nkey] = time.perf_counter()

    async def _fail(self, key: str, nkey: str, code: int, reason: str) -> None:
        await asyncio.to_thread(self.share.answer_failed, key, nkey, reason)
        self.set(error_code=code, status=ERROR)

    async def _play(self, fault: str) -> None:
        if fault == "plc_gone":
            await asyncio.sleep(0.1)
            self.died.set()
            await self._go_offline()
        elif fault == "heartbeat_frozen":
            self._frozen_until = asyncio.get_running_loop().time() + self.freeze_s
            await asyncio.sleep(self.freeze_s)
            self.set(status=IDLE)
        elif fault == "error_code":
            self.set(error_code=E_ESTOP, status=ERROR)
        elif fault == "register_garbage":
            self.set(status=0xBEEF, exp_echo=0xFFFF, nonce_echo_hi=0x1234, error_code=0xDEAD)
