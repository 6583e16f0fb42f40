"""One RTDE connection of the ``ur_rtde`` driver: connect, negotiate protocol version 2, read the
URControl version, set up the output recipe (with the torque field's fallback) and start; then
data packages one by one, each checked against the recipe; pause before closing."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from robid_link.drivers.ur import codec as rtde
from robid_link.exceptions import DriverError, ProtocolError

__all__ = ["RtdeOptions", "RtdeSession", "open_session", "reason", "MAX_HZ", "E_SERIES_HZ",
           "recipe_fields"]

log = logging.getLogger("robid.driver.ur_rtde")

#: a controller generation's highest RTDE output frequency (URControl major version)
MAX_HZ = {3: 125.0}
E_SERIES_HZ = 500.0
#: the recipe's types, field by field (the torque field is the fourth)
TYPES = ("DOUBLE", "VECTOR6D", "VECTOR6D", "VECTOR6D", "UINT32", "INT32", "INT32", "INT32")


def recipe_fields(torque: str, marker_register: int) -> tuple[str, ...]:
    return ("timestamp", "actual_q", "actual_qd", torque, "runtime_state", "robot_mode",
            "safety_mode", f"output_int_register_{marker_register}")


@dataclass(frozen=True)
class RtdeOptions:
    """What the set-up needs of the driver's options."""

    host: str
    port: int
    frequency: float
    torque: str  # auto | target_moment | actual_current
    current_gain: np.ndarray | None
    marker_register: int
    io_timeout_s: float

    @property
    def where(self) -> str:
        return f"{self.host}:{self.port}"


class RtdeSession:
    """A started RTDE stream: ``next_values`` reads the next data package."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer
        self.recipe: rtde.Recipe | None = None
        self.version: tuple[int, int, int, int] = (0, 0, 0, 0)
        self.torque = "target_moment"
        self.packages = 0  # data packages read
        self._pending: asyncio.Future[tuple[Any, ...]] | None = None

    async def ask(self, request: bytes, kind: int) -> bytes:
        """Send one request and read up to its answer (text messages on the way are logged)."""
        self.writer.write(request)
        await self.writer.drain()
        for _ in range(64):
            got, payload = await rtde.read_package(self.reader)
            if got == kind:
                return payload
            if got == rtde.TEXT_MESSAGE:
                log_text(payload)
                continue
            raise ProtocolError(f"RTDE: expected a {rtde.PACKAGE_NAMES[kind]} answer, got "
                                f"package type {got}")
        raise ProtocolError(f"RTDE: no {rtde.PACKAGE_NAMES[kind]} answer among 64 text messages")

    async def next_values(self) -> tuple[Any, ...]:
        """The next data package's values (text messages logged on the way); a package of the
        wrong size or recipe is a ProtocolError. A caller's timeout never cuts a package in
        two: the read goes on and the next call gets its result."""
        if self._pending is None:
            self._pending = asyncio.ensure_future(self._read_values())
        try:
            return await asyncio.shield(self._pending)
        finally:
            if self._pending is not None and self._pending.done():
                self._pending = None

    async def _read_values(self) -> tuple[Any, ...]:
        assert self.recipe is not None
        layout = self.recipe.layout
        while True:
            kind, payload = await rtde.read_package(self.reader)
            if kind == rtde.TEXT_MESSAGE:
                log_text(payload)
                continue
            if kind != rtde.DATA_PACKAGE:
                raise ProtocolError(f"ur_rtde: corrupt RTDE stream: package type {kind} where "
                                    "data packages flow")
            if len(payload) != layout.size:
                what = "truncated" if len(payload) < layout.size else "corrupt"
                raise ProtocolError(f"ur_rtde: {what} RTDE data package: {len(payload)} bytes, "
                                    f"the recipe needs {layout.size}")
            if payload[0] != self.recipe.id:
                raise ProtocolError(f"ur_rtde: corrupt RTDE data package for recipe "
                                    f"{payload[0]}, the stream was set up as recipe "
                                    f"{self.recipe.id}")
            self.packages += 1
            return layout.unpack(payload)

    async def pause(self, timeout_s: float) -> None:
        """Pause the stream and read up to the pause's answer, so nothing the controller sent
        is left unread. A controller that does not answer in time is simply left."""
        with contextlib.suppress(OSError, TimeoutError, asyncio.IncompleteReadError, DriverError):
            async with asyncio.timeout(timeout_s):
                if self._pending is not None:  # a package being read: finish it first
                    await self._pending
                    self._pending = None
                self.writer.write(rtde.pause())
                await self.writer.drain()
                while (kind := (await rtde.read_package(self.reader))[0]) != rtde.PAUSE:
                    self.packages += kind == rtde.DATA_PACKAGE

    async def close(self) -> None:
        if self._pending is not None:
            self._pending.cancel()
            await asyncio.gather(self._pending, return_exceptions=True)
            self._pending = None
        self.writer.close()
        with contextlib.suppress(OSError, TimeoutError, asyncio.IncompleteReadError):
            async with asyncio.timeout(1.0):
                await self.writer.wait_closed()


async def open_session(opts: RtdeOptions) -> RtdeSession:
    """Connect, negotiate, set up the recipe and start; every failure one DriverError line."""
    try:
        async with asyncio.timeout(opts.io_timeout_s):
            session = RtdeSession(*await asyncio.open_connection(opts.host, opts.port))
    except (OSError, TimeoutError) as err:
        raise DriverError(f"ur_rtde: RTDE {opts.where}: {reason(err)}") from err
    try:
        async with asyncio.timeout(opts.io_timeout_s):
            await _setup(session, opts)
    except TimeoutError as err:
        await session.close()
        raise DriverError(f"ur_rtde: RTDE {opts.where}: no answer within "
                          f"{opts.io_timeout_s:g} s during set-up") from err
    except (OSError, asyncio.IncompleteReadError) as err:
        await session.close()
        raise DriverError(f"ur_rtde: RTDE {opts.where}: connection lost during set-up "
                          f"({reason(err)})") from err
    except BaseException:
        await session.close()
        raise
    return session


async def _setup(s: RtdeSession, opts: RtdeOptions) -> None:
    answer = await s.ask(rtde.request_protocol_version(2), rtde.REQUEST_PROTOCOL_VERSION)
    if not rtde.parse_accepted(rtde.REQUEST_PROTOCOL_VERSION, answer):
        raise DriverError(f"ur_rtde: the controller at {opts.where} refused RTDE protocol "
                          "version 2 (URControl 3.2 or older: update the robot's software)")
    s.version = rtde.parse_urcontrol_version(
        await s.ask(rtde.get_urcontrol_version(), rtde.GET_URCONTROL_VERSION))
    version = ".".join(map(str, s.version[:3]))
    top = MAX_HZ.get(s.version[0], E_SERIES_HZ)
    if opts.frequency > top:
        raise DriverError(f"driver.frequency: {opts.frequency:g} Hz is above the {top:g} Hz of "
                          f"this controller (URControl {version})")
    s.torque = "target_moment" if opts.torque == "auto" else opts.torque
    try:
        s.recipe = await _recipe(s, opts)
    except rtde.MissingFields as err:
        marker = f"output_int_register_{opts.marker_register}"
        if not (opts.torque == "auto" and err.names == ("target_moment",)
                and opts.current_gain is not None):
            hint = ("; give driver.current_gain to log actual_current instead"
                    if err.names == ("target_moment",) else
                    "; set driver.marker_register to a register this controller has (0-23 "
                    "before URControl 3.9/5.3)" if marker in err.names else "")
            raise DriverError(f"ur_rtde: {err} by the controller at {opts.where} (URControl "
                              f"{version}){hint}") from err
        log.info("driver=ur_rtde target_moment not available: logging actual_current times "
                 "driver.current_gain")
        s.torque = "actual_current"
        s.recipe = await _recipe(s, opts)
    if not rtde.parse_accepted(rtde.START, await s.ask(rtde.start(), rtde.START)):
        raise DriverError(f"ur_rtde: the controller at {opts.where} refused to start the RTDE "
                          "stream")


async def _recipe(s: RtdeSession, opts: RtdeOptions) -> rtde.Recipe:
    names = recipe_fields(s.torque, opts.marker_register)
    recipe = rtde.parse_setup_outputs(
        await s.ask(rtde.setup_outputs(opts.frequency, names), rtde.SETUP_OUTPUTS), names)
    for name, got, exp in zip(names, recipe.types, TYPES, strict=True):
        if got != exp:
            raise ProtocolError(f"ur_rtde: RTDE output field {name} has type {got}, expected "
                                f"{exp}")
    return recipe


def log_text(payload: bytes) -> None:
    level, source, message = rtde.parse_text_message(payload)
    log.log(logging.WARNING if level in ("exception", "error", "warning") else logging.INFO,
            "driver=ur_rtde controller %s from %s: %s", level, source, message[:200])


def reason(err: BaseException) -> str:
    """A short cause: 'connection closed', 'Connection refused', 'timed out', …"""
    if isinstance(err, asyncio.IncompleteReadError):
        return "connection closed"
    if isinstance(err, OSError) and err.errno:
        return os.strerror(err.errno)
    if isinstance(err, TimeoutError):
        return "timed out"
    text = str(err).splitlines()[0][:160] if str(err) else ""
    return f"{type(err).__name__}: {text}" if text else type(err).__name__
