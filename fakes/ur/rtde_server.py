"""The fake UR controller's RTDE server (protocol 2), from UR's RTDE guide: output recipes
of the fields this controller generation has, and one data package per period at the
client's frequency, time-stamped by the controller's clock; the RTDE faults (``rtde_drop`` is
struck by the peer). A mixin of ``UrRtdePeer`` (``peer.py``), which owns the arm and the
other two ports."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from robid_link.fakes.controller import ControllerCore
from robid_link.fakes.ur.program import Motion

__all__ = ["RtdeServer", "RtdeClient", "SERIES"]

log = logging.getLogger("robid.fake_controller")


@dataclass(frozen=True)
class _Series:
    """A controller generation: its control step, RTDE's top rate, URControl version, how
    many output registers RTDE offers."""

    steptime: float
    max_hz: float
    version: tuple[int, int, int, int]
    registers: int


SERIES = {"e": _Series(0.002, 500.0, (5, 11, 1, 108318), 48),
          "cb3": _Series(0.008, 125.0, (3, 15, 7, 106331), 24)}
_FMT = {"DOUBLE": "d", "VECTOR6D": "6d", "INT32": "i", "UINT32": "I", "VECTOR6INT32": "6i"}


@dataclass
class RtdeClient:
    """One RTDE connection's recipe, rate and counters."""

    writer: asyncio.StreamWriter
    names: tuple[str, ...] = ()
    recipe: int = 0
    frequency: float = 0.0
    task: asyncio.Task[None] | None = None
    sent: int = 0
    skipped: int = 0  # packages this controller did not send in time (its host was busy)
    dropped: int = 0  # packages not sent because the client did not read
    stalled: bool = False
    damaged: set[int] = field(default_factory=set)  # motions that got their bad package


class RtdeServer:
    """The RTDE port of ``UrRtdePeer``: what it reads of the peer is declared here."""

    core: ControllerCore
    series: _Series
    absent: set[str]
    missing_field: str
    gain: np.ndarray
    slow_every: int
    registers: dict[int, int]
    robot_mode: int
    safety: int
    clients: list[RtdeClient]
    motion: Motion | None
    _boot: float
    if TYPE_CHECKING:
        _state: Callable[[float], tuple[int, np.ndarray, np.ndarray, np.ndarray]]
        _connection: Callable[[asyncio.StreamWriter], contextlib.AbstractAsyncContextManager[Any]]

    def _field(self, name: str) -> str | None:
        """The RTDE type of an output field this controller has (None: NOT_FOUND)."""
        if name in self.absent:
            return None
        if name == "timestamp" or name in ("speed_scaling", "target_speed_fraction"):
            return "DOUBLE"
        if name in ("actual_q", "actual_qd", "target_q", "target_qd", "target_moment",
                    "actual_current", "target_current"):
            return "VECTOR6D"
        if name in ("robot_mode", "safety_mode", "safety_status"):
            return "INT32"
        if name == "runtime_state":
            return "UINT32"
        if name == "joint_mode":
            return "VECTOR6INT32"
        for prefix, typ in (("output_int_register_", "INT32"),
                            ("output_double_register_", "DOUBLE")):
            if name.startswith(prefix) and name[len(prefix):].isdigit():
                return typ if int(name[len(prefix):]) < self.series.registers else None
        return None

    def _value(self, name: str, ts: float, sample: tuple[int, np.ndarray, np.ndarray,
                                                          np.ndarray]) -> Any:
        runtime, q, qd, tau = sample
        if name == "timestamp":
            return ts
        if name in ("actual_q", "target_q"):
            return q
        if name in ("actual_qd", "target_qd"):
            return qd
        if name == "target_moment":
            return tau
        if name in ("actual_current", "target_current"):
            return tau / self.gain
        if name in ("speed_scaling", "target_speed_fraction"):
            return 1.0
        if name == "robot_mode":
            return self.robot_mode
        if name in ("safety_mode", "safety_status"):
            return self.safety
        if name == "runtime_state":
            return runtime
        if name == "joint_mode":
            return [253] * 6
        number = int(name.rsplit("_", 1)[1])
        return self.registers.get(number, 0) if "int" in name else 0.0

    @staticmethod
    def _package(kind: int, payload: bytes = b"") -> bytes:
        return struct.pack(">HB", 3 + len(payload), kind) + payload

    @staticmethod
    def _text(message: str, level: int = 1) -> bytes:
        msg, src = message.encode()[:255], b"fake-ur"
        return RtdeServer._package(77, bytes([len(msg)]) + msg + bytes([len(src)]) + src
                                    + bytes([level]))

    async def _rtde(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        client = RtdeClient(writer)
        self.clients.append(client)
        try:
            async with self._connection(writer):
                while True:
                    size, kind = struct.unpack(">HB", await reader.readexactly(3))
                    if size < 3:
                        return  # a client that cannot count: the controller hangs up
                    payload = await reader.readexactly(size - 3)
                    answer = self._rtde_answer(client, kind, payload)
                    if answer:
                        writer.write(answer)
                        await writer.drain()
        finally:
            if client.task is not None:
                client.task.cancel()
                await asyncio.gather(client.task, return_exceptions=True)
            if client.names:
                log.info("RTDE client closed: %d packages sent, %d skipped (this host late), "
                         "%d dropped (the client did not read)", client.sent, client.skipped,
                         client.dropped)

    def _rtde_answer(self, c: RtdeClient, kind: int, payload: bytes) -> bytes:
        fault = self.core.fault
        if kind == 86:  # REQUEST_PROTOCOL_VERSION: uint16 → uint8 accepted
            version = struct.unpack(">H", payload[:2])[0] if len(payload) >= 2 else 0
            refuse = fault == "rtde_refuse_v2" and version == 2 and self.core.take_fault()
            return self._package(86, bytes([int(version == 2 and not refuse)]))
        if kind == 118:  # GET_URCONTROL_VERSION → 4 × uint32
            return self._package(118, struct.pack(">IIII", *self.series.version))
        if kind == 79:  # SETUP_OUTPUTS: double frequency + names → uint8 id + types
            return self._setup_outputs(c, payload, fault)
        if kind == 73:  # SETUP_INPUTS: names → uint8 id + types
            names = payload.decode("ascii", "replace").split(",")
            types = ["INT32" if n.startswith("input_int_register_") else
                     "DOUBLE" if n.startswith("input_double_register_") else "NOT_FOUND"
                     for n in names]
            ok = "NOT_FOUND" not in types
            return self._package(73, bytes([1 if ok else 0]) + ",".join(types).encode())
        if kind == 83:  # START → uint8 accepted
            if not c.names:
                return self._text("start without an output recipe") + self._package(83, b"\0")
            if c.task is None or c.task.done():
                c.task = asyncio.get_running_loop().create_task(self._stream(c))
            return self._package(83, b"\x01")
        if kind == 80:  # PAUSE → uint8 accepted
            if c.task is not None:
                c.task.cancel()
            return self._package(80, b"\x01")
        if kind == 85:  # input data: nothing of ours listens to inputs
            return b""
        return self._text(f"unknown package type {kind}")

    def _setup_outputs(self, c: RtdeClient, payload: bytes, fault: str | None) -> bytes:
        if len(payload) < 9:
            return self._text("setup outputs: no frequency and names")
        frequency = struct.unpack(">d", payload[:8])[0]
        names = tuple(payload[8:].decode("ascii", "replace").split(","))
        types = [self._field(n) or "NOT_FOUND" for n in names]
        if (fault == "rtde_not_found" and self.missing_field in names
                and self.core.take_fault()):
            types[names.index(self.missing_field)] = "NOT_FOUND"
        if "NOT_FOUND" in types or not 0 < frequency <= self.series.max_hz:
            extra = b"" if 0 < frequency <= self.series.max_hz else self._text(
                f"output frequency {frequency:g} Hz out of range")
            return extra + self._package(79, b"\0" + ",".join(types).encode())
        c.names, c.frequency = names, frequency
        c.recipe = (c.recipe % 255) + 1
        return self._package(79, bytes([c.recipe]) + ",".join(types).encode())

    async def _stream(self, c: RtdeClient) -> None:
        """One package per period at the client's frequency, time-stamped by schedule."""
        loop = asyncio.get_running_loop()
        period = 1.0 / c.frequency
        fmt = struct.Struct(">B" + "".join(_FMT[self._field(n) or "INT32"] for n in c.names))
        # on the controller's cycle grid: time stamps are whole periods of its clock
        nxt = self._boot + int((loop.time() - self._boot) / period) * period
        k, backlog = 0, None
        while not c.writer.transport.is_closing():
            nxt += period
            delay = nxt - loop.time()
            if delay > 0:
                await asyncio.sleep(delay)
            elif delay < -5.0:  # this host stalled for long: skip, as a controller short of
                # time does; shorter lags go out late in a burst, time-stamped by schedule
                skip = int(-delay / period)
                nxt += skip * period
                c.skipped += skip
            sample = self._state(nxt)
            k += 1
            m = self.motion
            fault = m.fault if m is not None and m.start is not None else None
            struck = m is not None and m.struck
            if fault == "rtde_stall" and struck:
                c.stalled = True
            if c.stalled or (fault == "rtde_slow" and k % self.slow_every):
                continue
            if fault == "rtde_garbage" and struck and id(m) not in c.damaged:
                # a data package's header announcing the largest size RTDE allows, zeros for
                # its payload (a controller's corrupted send buffer)
                c.damaged.add(id(m))
                c.writer.write(struct.pack(">HB", 0xFFFF, 85) + bytes(0xFFFF - 3))
                continue
            values: list[Any] = [c.recipe]
            for name in c.names:
                v = self._value(name, nxt - self._boot, sample)
                values.extend(v if isinstance(v, list | np.ndarray) else [v])
            payload = fmt.pack(*values)
            if fault in ("truncated_log", "corrupt_log") and struck and id(m) not in c.damaged:
                c.damaged.add(id(m))
                payload = payload[:-10] if fault == "truncated_log" else \
                    bytes([c.recipe % 255 + 1]) + payload[1:]
            if c.writer.transport.get_write_buffer_size() > 256 * len(payload):
                c.dropped += 1  # the client does not read: the controller drops it soon
                backlog = backlog or loop.time()
                if loop.time() - backlog > 2.0:
                    log.info("RTDE client too slow: dropped")
                    c.writer.transport.abort()
                    return
                continue
            backlog = None
            c.writer.write(self._package(85, payload))
            c.sent += 1
