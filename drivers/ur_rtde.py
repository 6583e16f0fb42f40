"""Universal Robots over RTDE (protocol 2): the program goes to the script port as URScript, the
run is recorded from the RTDE stream, stops go through the dashboard server.

give: an RTDE session (version 2, URControl version, output recipe, start), the controller
checked stopped with the robot running and its safety normal, then the URScript program
(``drivers/ur_script.py``) on the script port; from then on a task reads every data package
(the controller drops slow readers) and records the rows on the path. take: the program's
``runtime_state`` back from playing (2) to stopped (1) with the path's end marker. A lost
connection, a stalled stream, a protective stop or a malformed package stop the program
(dashboard ``stop``, else ``stopj`` on the script port) before the failure is stored. UR has no
parameter upload: the capability is absent.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import logging
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from robid_link.drivers import ur_rtde_codec as rtde
from robid_link.drivers.ur_rtde_record import (
    DONE,
    ROBOT_MODES,
    RUNNING,
    RUNTIME_STATES,
    SAFETY_MODES,
    STOPPED,
    EndedEarly,
    Recording,
    mode_name,
)
from robid_link.drivers.ur_script import Knots, marker_tag, plan_knots, render_script
from robid_link.exceptions import ConfigError, DriverError, ProtocolError
from robid_link.link.driver import Done, Driver, MotionProgram, RobotInfo

__all__ = ["UrRtdeDriver"]

log = logging.getLogger("robid.driver.ur_rtde")

TORQUE_FIELDS = ("target_moment", "actual_current")
#: a controller generation's highest RTDE output frequency (URControl major version)
MAX_HZ = {3: 125.0}
E_SERIES_HZ = 500.0
_KEEP_RUNS = 8


def _positive(key: str, value: Any, lo: float = 0.0, hi: float = float("inf")) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not lo < value <= hi:
        raise ConfigError(f"driver.{key}: expected a number in ({lo:g}, {hi:g}], got {value!r}")
    return float(value)


def _port(key: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 < value < 65536:
        raise ConfigError(f"driver.{key}: expected a TCP port 1-65535, got {value!r}")
    return value


@dataclass
class _Attempt:
    """One given attempt: its recording, the task that reads the stream, its outcome."""

    key: tuple[str, str]
    rec: Recording
    finished: asyncio.Event = field(default_factory=asyncio.Event)
    done: Done | None = None
    log: bytes | None = None
    error: DriverError | None = None
    task: asyncio.Task[None] | None = None
    script_conn: asyncio.Task[None] | None = None


class _Session:
    """One RTDE connection: set up for the run's recipe, then read package after package."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer
        self.recipe: rtde.Recipe | None = None
        self.version: tuple[int, int, int, int] = (0, 0, 0, 0)

    async def ask(self, request: bytes, kind: int) -> bytes:
        """Send one request and read up to its answer (text messages on the way are logged)."""
        self.writer.write(request)
        await self.writer.drain()
        for _ in range(64):
            got, payload = await rtde.read_package(self.reader)
            if got == kind:
                return payload
            if got == rtde.TEXT_MESSAGE:
                _log_text(payload)
                continue
            raise ProtocolError(f"RTDE: expected a {rtde.PACKAGE_NAMES[kind]} answer, got "
                                f"package type {got}")
        raise ProtocolError(f"RTDE: no {rtde.PACKAGE_NAMES[kind]} answer among 64 text messages")

    async def close(self) -> None:
        self.writer.close()
        with contextlib.suppress(OSError, TimeoutError, asyncio.IncompleteReadError):
            async with asyncio.timeout(1.0):
                await self.writer.wait_closed()


def _log_text(payload: bytes) -> None:
    level, source, message = rtde.parse_text_message(payload)
    log.log(logging.WARNING if level in ("exception", "error", "warning") else logging.INFO,
            "driver=ur_rtde controller %s from %s: %s", level, source, message[:200])


class UrRtdeDriver(Driver):
    """Daemon side of a Universal Robots cell. Options: ``host``, ``rtde_port`` (30004),
    ``script_port`` (30002), ``dashboard_port`` (29999), ``frequency`` (RTDE Hz: ≤ 125 on CB3,
    ≤ 500 on e-Series), ``torque`` (auto | target_moment | actual_current), ``current_gain``
    (6 N·m/A, to log actual_current as torque), ``marker_register`` (24), ``lookahead_time_s``
    and ``servo_gain`` (servoj), ``approach_speed_rad_s``/``approach_acceleration_rad_s2``
    (movej to the path's start), ``path_tolerance_rad``, ``max_script_bytes``,
    ``io_timeout_s``, ``stream_timeout_s``, ``start_timeout_s``."""

    name = "ur_rtde"
    options = frozenset({"host", "rtde_port", "script_port", "dashboard_port", "frequency",
                         "torque", "current_gain", "marker_register", "lookahead_time_s",
                         "servo_gain", "approach_speed_rad_s", "approach_acceleration_rad_s2",
                         "path_tolerance_rad", "max_script_bytes", "io_timeout_s",
                         "stream_timeout_s", "start_timeout_s"})

    def __init__(self, *, host: str | None = None, rtde_port: int = 30004,
                 script_port: int = 30002, dashboard_port: int = 29999,
                 frequency: float = 500.0, torque: str = "auto",
                 current_gain: list[float] | None = None, marker_register: int = 24,
                 lookahead_time_s: float = 0.05, servo_gain: float = 1000.0,
                 approach_speed_rad_s: float = 0.35, approach_acceleration_rad_s2: float = 0.7,
                 path_tolerance_rad: float = 1e-4, max_script_bytes: int = 1_000_000,
                 io_timeout_s: float = 5.0, stream_timeout_s: float = 1.0,
                 start_timeout_s: float = 10.0) -> None:
        super().__init__()
        if not isinstance(host, str) or not host.strip():
            raise ConfigError("driver.host: missing (the controller's address)")
        self.host = host
        self.ports = {"rtde_port": _port("rtde_port", rtde_port),
                      "script_port": _port("script_port", script_port),
                      "dashboard_port": _port("dashboard_port", dashboard_port)}
        self.frequency = _positive("frequency", frequency, 0.0, E_SERIES_HZ)
        if torque not in ("auto", *TORQUE_FIELDS):
            raise ConfigError(f"driver.torque: expected auto, target_moment or actual_current, "
                              f"got {torque!r}")
        self.torque = torque
        self.current_gain = self._gain(current_gain)
        if torque == "actual_current" and self.current_gain is None:
            raise ConfigError("driver.current_gain: needed with torque: actual_current "
                              "(6 numbers, N·m per A of each joint)")
        if (isinstance(marker_register, bool) or not isinstance(marker_register, int)
                or not 0 <= marker_register <= 47):
            raise ConfigError(f"driver.marker_register: expected an output integer register "
                              f"0-47, got {marker_register!r}")
        self.marker_register = marker_register
        self.lookahead_s = _positive("lookahead_time_s", lookahead_time_s, 0.029, 0.2)
        self.servo_gain = _positive("servo_gain", servo_gain, 99.0, 2000.0)
        self.approach_speed = _positive("approach_speed_rad_s", approach_speed_rad_s, 0.0, 3.14)
        self.approach_acc = _positive("approach_acceleration_rad_s2",
                                      approach_acceleration_rad_s2, 0.0, 15.0)
        self.path_tolerance = _positive("path_tolerance_rad", path_tolerance_rad, 0.0, 0.01)
        if (isinstance(max_script_bytes, bool) or not isinstance(max_script_bytes, int)
                or not 10_000 <= max_script_bytes <= 50_000_000):
            raise ConfigError(f"driver.max_script_bytes: expected 10000-50000000, got "
                              f"{max_script_bytes!r}")
        self.max_script_bytes = max_script_bytes
        self.io_timeout_s = _positive("io_timeout_s", io_timeout_s, 0.0, 600.0)
        self.stream_timeout_s = _positive("stream_timeout_s", stream_timeout_s, 0.0, 60.0)
        self.start_timeout_s = _positive("start_timeout_s", start_timeout_s, 0.0, 600.0)
        self._programs: dict[str, tuple[MotionProgram, Knots]] = {}
        self._attempts: dict[tuple[str, str], _Attempt] = {}
        self._active: _Attempt | None = None
        self.controller_version: tuple[int, int, int, int] | None = None
        #: the last attempt's stream figures (benchmarks, logs)
        self.last_stats: dict[str, float] = {}

    @staticmethod
    def _gain(value: Any) -> np.ndarray | None:
        if value is None:
            return None
        if (not isinstance(value, list | tuple) or len(value) != 6
                or not all(isinstance(x, int | float) and not isinstance(x, bool) and x > 0
                           for x in value)):
            raise ConfigError(f"driver.current_gain: expected 6 positive numbers (N·m/A per "
                              f"joint), got {value!r}")
        return np.asarray(value, dtype=float)

    def _check_robot(self, robot: RobotInfo) -> None:
        if robot.n != 6 or any(t != "revolute" for t in robot.joint_types):
            raise ConfigError(f"driver.name: ur_rtde moves the 6 revolute joints of a Universal "
                              f"Robots arm; robot {robot.name} has {robot.n} joints "
                              f"({', '.join(robot.joint_types)})")

    def where(self, port: str) -> str:
        return f"{self.host}:{self.ports[port]}"

    # -- life cycle
    async def _open(self) -> None:
        answer = await self._dashboard("robotmode")
        if not answer.startswith("Robotmode:"):
            raise DriverError(f"{self.name}: {self.where('dashboard_port')} answered "
                              f"{answer[:80]!r} to robotmode: not a UR dashboard server")
        log.info("driver=ur_rtde host=%s %s", self.host, answer)

    async def _close(self) -> None:
        active = self._active
        if active is not None and not active.finished.is_set():
            log.warning("driver=ur_rtde closing during experiment %s: stopping the program",
                        active.key[0])
            await self._cancel_tasks(active)
            reason = await self._stop_program()
            self._finish(active, error=DriverError(f"{self.name}: the link closed during "
                                                   f"experiment {active.key[0]}; {reason}"))
        for att in list(self._attempts.values()):
            await self._cancel_tasks(att)

    # -- small connections: dashboard and script port
    async def _dashboard(self, command: str) -> str:
        """One dashboard command on its own connection: greeting, command, one answer line."""
        where = self.where("dashboard_port")
        try:
            async with asyncio.timeout(self.io_timeout_s):
                reader, writer = await asyncio.open_connection(self.host,
                                                               self.ports["dashboard_port"])
                try:
                    greeting = (await reader.readline())[:200].decode("utf-8", "replace")
                    if "Dashboard Server" not in greeting:
                        raise DriverError(f"{self.name}: {where} greeted "
                                          f"{greeting.strip()[:80]!r}: not a UR dashboard")
                    writer.write(command.encode() + b"\n")
                    await writer.drain()
                    answer = await reader.readline()
                finally:
                    writer.close()
        except (OSError, TimeoutError) as err:
            raise DriverError(f"{self.name}: dashboard {where}: {_reason(err)}") from err
        if not answer.endswith(b"\n"):
            raise DriverError(f"{self.name}: dashboard {where} closed without answering "
                              f"{command!r}")
        return answer[:200].decode("utf-8", "replace").strip()

    async def _send_script(self, script: bytes) -> asyncio.Task[None]:
        """The program on the script port; the connection stays open (its state messages read
        and dropped) until the program plays, so closing cannot reset unread script bytes."""
        try:
            async with asyncio.timeout(self.io_timeout_s):
                reader, writer = await asyncio.open_connection(self.host,
                                                               self.ports["script_port"])
                writer.write(script)
                await writer.drain()
        except (OSError, TimeoutError) as err:
            raise DriverError(f"{self.name}: script port {self.where('script_port')}: "
                              f"{_reason(err)}") from err

        async def drain_loop() -> None:
            try:
                while await reader.read(65536):
                    pass
            except OSError:
                pass
            finally:
                writer.close()

        return asyncio.create_task(drain_loop(), name="ur_rtde-script-port")

    async def _stop_program(self) -> str:
        """Dashboard ``stop``; when the dashboard cannot, ``stopj`` on the script port. Returns
        how it went (for the failure's line); never raises."""
        try:
            answer = await self._dashboard("stop")
        except DriverError as err:
            answer = f"dashboard {_reason(err.__cause__ or err)}"
        if answer.startswith("Stopped"):
            log.warning("driver=ur_rtde program stopped through the dashboard")
            return "program stopped (dashboard)"
        try:
            task = await self._send_script(b"stopj(4.0)\n")
            await asyncio.sleep(0.2)
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
        except DriverError as err:
            line = f"could not stop the program ({answer}; script port " \
                   f"{_reason(err.__cause__ or err)})"
            log.error("driver=ur_rtde %s", line)
            return line
        log.warning("driver=ur_rtde dashboard stop: %s; stopj sent on the script port", answer)
        return "program stopped (stopj on the script port)"

    # -- RTDE
    def _fields(self, torque: str) -> tuple[str, ...]:
        return ("timestamp", "actual_q", "actual_qd", torque, "runtime_state", "robot_mode",
                "safety_mode", f"output_int_register_{self.marker_register}")

    async def _session(self) -> tuple[_Session, str]:
        """Connect, negotiate, set up the recipe and start: (session, torque field)."""
        where = self.where("rtde_port")
        try:
            async with asyncio.timeout(self.io_timeout_s):
                session = _Session(*await asyncio.open_connection(self.host,
                                                                  self.ports["rtde_port"]))
        except (OSError, TimeoutError) as err:
            raise DriverError(f"{self.name}: RTDE {where}: {_reason(err)}") from err
        try:
            async with asyncio.timeout(self.io_timeout_s):
                torque = await self._setup(session)
        except TimeoutError as err:
            await session.close()
            raise DriverError(f"{self.name}: RTDE {where}: no answer within "
                              f"{self.io_timeout_s:g} s during set-up") from err
        except (OSError, asyncio.IncompleteReadError) as err:
            await session.close()
            raise DriverError(f"{self.name}: RTDE {where}: connection lost during set-up "
                              f"({_reason(err)})") from err
        except BaseException:
            await session.close()
            raise
        return session, torque

    async def _setup(self, s: _Session) -> str:
        where = self.where("rtde_port")
        answer = await s.ask(rtde.request_protocol_version(2), rtde.REQUEST_PROTOCOL_VERSION)
        if not rtde.parse_accepted(rtde.REQUEST_PROTOCOL_VERSION, answer):
            raise DriverError(f"{self.name}: the controller at {where} refused RTDE protocol "
                              "version 2 (URControl 3.2 or older: update the robot's software)")
        s.version = rtde.parse_urcontrol_version(
            await s.ask(rtde.get_urcontrol_version(), rtde.GET_URCONTROL_VERSION))
        self.controller_version = s.version
        top = MAX_HZ.get(s.version[0], E_SERIES_HZ)
        if self.frequency > top:
            raise DriverError(f"driver.frequency: {self.frequency:g} Hz is above the "
                              f"{top:g} Hz of this controller (URControl "
                              f"{'.'.join(map(str, s.version[:3]))})")
        torque = "target_moment" if self.torque == "auto" else self.torque
        try:
            s.recipe = await self._recipe(s, torque)
        except rtde.MissingFields as err:
            if not (self.torque == "auto" and err.names == ("target_moment",)
                    and self.current_gain is not None):
                hint = ("; give driver.current_gain to log actual_current instead"
                        if err.names == ("target_moment",) else
                        "; set driver.marker_register to a register this controller has "
                        "(0-23 before URControl 3.9/5.3)" if f"output_int_register_"
                        f"{self.marker_register}" in err.names else "")
                raise DriverError(f"{self.name}: {err} by the controller at {where} "
                                  f"(URControl {'.'.join(map(str, s.version[:3]))}){hint}"
                                  ) from err
            log.info("driver=ur_rtde target_moment not available: logging actual_current "
                     "times driver.current_gain")
            torque = "actual_current"
            s.recipe = await self._recipe(s, torque)
        if not rtde.parse_accepted(rtde.START, await s.ask(rtde.start(), rtde.START)):
            raise DriverError(f"{self.name}: the controller at {where} refused to start the "
                              "RTDE stream")
        return torque

    async def _recipe(self, s: _Session, torque: str) -> rtde.Recipe:
        names = self._fields(torque)
        recipe = rtde.parse_setup_outputs(
            await s.ask(rtde.setup_outputs(self.frequency, names), rtde.SETUP_OUTPUTS), names)
        want = ("DOUBLE", "VECTOR6D", "VECTOR6D", "VECTOR6D", "UINT32", "INT32", "INT32",
                "INT32")
        for name, got, exp in zip(names, recipe.types, want, strict=True):
            if got != exp:
                raise ProtocolError(f"{self.name}: RTDE output field {name} has type {got}, "
                                    f"expected {exp}")
        return recipe

    async def _next_values(self, s: _Session) -> tuple[Any, ...]:
        """The next data package's values (text messages logged on the way)."""
        assert s.recipe is not None
        layout = s.recipe.layout
        while True:
            kind, payload = await rtde.read_package(s.reader)
            if kind == rtde.TEXT_MESSAGE:
                _log_text(payload)
                continue
            if kind != rtde.DATA_PACKAGE:
                raise ProtocolError(f"{self.name}: corrupt RTDE stream: package type {kind} "
                                    "where data packages flow")
            if len(payload) != layout.size:
                what = "truncated" if len(payload) < layout.size else "corrupt"
                raise ProtocolError(f"{self.name}: {what} RTDE data package: {len(payload)} "
                                    f"bytes, the recipe needs {layout.size}")
            if payload[0] != s.recipe.id:
                raise ProtocolError(f"{self.name}: corrupt RTDE data package for recipe "
                                    f"{payload[0]}, the stream was set up as recipe "
                                    f"{s.recipe.id}")
            return layout.unpack(payload)

    # -- the cycle
    async def _put_program(self, program: MotionProgram) -> None:
        traj = program.trajectory()
        if traj.q.shape[1] != 6 or any(t != "revolute" for t in traj.joint_types):
            raise DriverError(f"{self.name}: program {program.exp_id} has {traj.q.shape[1]} "
                              "joints: a UR arm takes 6 revolute ones")
        qd_max = np.asarray(self.robot.qd_max) if self.robot is not None else None
        knots = plan_knots(traj, self.path_tolerance, qd_max)
        size = len(self._render(program, knots, "x", "0"))
        if size > self.max_script_bytes - 256:
            raise DriverError(f"{self.name}: program {program.exp_id} renders to {size} bytes "
                              f"of URScript ({knots.intervals + 1} knots every {knots.h:.3f} s), "
                              f"above driver.max_script_bytes ({self.max_script_bytes}): "
                              "shorten the experiment or raise the limit")
        self._programs[program.exp_id] = (program, knots)

    def _render(self, program: MotionProgram, knots: Knots, exp_id: str, nonce: str) -> bytes:
        traj = program.trajectory()
        return render_script(knots, exp_id=exp_id, nonce=nonce, robot=traj.robot, kind=traj.kind,
                             register=self.marker_register, speed_rad_s=self.approach_speed,
                             acceleration_rad_s2=self.approach_acc,
                             lookahead_s=self.lookahead_s, gain=self.servo_gain)

    async def _give_ready(self, exp_id: str, nonce: str) -> None:
        key = (exp_id, nonce)
        if key in self._attempts:
            return  # given already: giving again must not start it twice
        if self._active is not None and not self._active.finished.is_set():
            raise DriverError(f"{self.name}: experiment {self._active.key[0]} is still running; "
                              f"refusing to start {exp_id}")
        if exp_id not in self._programs:
            raise DriverError(f"{self.name}: no program was put for experiment {exp_id}")
        program, knots = self._programs[exp_id]
        script = self._render(program, knots, exp_id, nonce)
        session, torque = await self._session()
        try:
            await self._check_idle(session, exp_id)
        except BaseException:
            await session.close()
            raise
        loop = asyncio.get_running_loop()
        rows = int((knots.duration_s * 1.5 + 30.0) * self.frequency)
        rec = Recording(exp_id, marker_tag(exp_id, nonce), self.frequency, loop.time(),
                        self.start_timeout_s, rows,
                        self.current_gain if torque == "actual_current" else None)
        att = _Attempt(key, rec)
        try:
            att.script_conn = await self._send_script(script)
        except BaseException:
            await session.close()
            raise
        rec.sent_at = loop.time()
        self._attempts[key] = self._active = att
        att.task = asyncio.create_task(self._record_loop(att, session),
                                       name=f"ur_rtde-record-{exp_id}")
        self._forget_old()
        log.info("driver=ur_rtde exp=%s nonce=%s program sent (%d bytes, %d knots every %.3f s,"
                 " %s, %g Hz)", exp_id, nonce, len(script), knots.intervals + 1, knots.h,
                 torque, self.frequency)

    async def _check_idle(self, s: _Session, exp_id: str) -> None:
        """Before motion: the first data package says robot running, safety normal, nothing
        playing."""
        assert s.recipe is not None
        slots = s.recipe.slices()
        try:
            async with asyncio.timeout(self.stream_timeout_s + self.io_timeout_s):
                values = await self._next_values(s)
        except TimeoutError as err:
            raise DriverError(f"{self.name}: RTDE {self.where('rtde_port')} started but sent no "
                              "data package") from err
        except (OSError, asyncio.IncompleteReadError) as err:
            raise DriverError(f"{self.name}: RTDE {self.where('rtde_port')}: connection lost "
                              f"({_reason(err)})") from err
        runtime, robot_mode, safety = (values[slots[f]][0] for f in
                                       ("runtime_state", "robot_mode", "safety_mode"))
        if robot_mode != RUNNING:
            raise DriverError(f"{self.name}: robot mode {mode_name(ROBOT_MODES, robot_mode)}: "
                              f"power it on and release the brakes before experiment {exp_id}")
        if safety not in (1, 2):
            raise DriverError(f"{self.name}: safety mode {mode_name(SAFETY_MODES, safety)}: "
                              f"clear it before experiment {exp_id}")
        if runtime != STOPPED:
            raise DriverError(f"{self.name}: a program is "
                              f"{mode_name(RUNTIME_STATES, runtime)} on the controller; refusing "
                              f"to start experiment {exp_id}")

    async def _record_loop(self, att: _Attempt, s: _Session) -> None:
        """Read every package until the attempt ends; on any failure the stop goes out first,
        then the failure is stored."""
        rec, loop = att.rec, asyncio.get_running_loop()
        assert s.recipe is not None
        sl = s.recipe.slices()
        ts, q, qd, tau, rt, rm, sm, mk = (sl[f] for f in s.recipe.names)
        where = self.where("rtde_port")
        try:
            while True:
                try:
                    async with asyncio.timeout(self.stream_timeout_s):
                        v = await self._next_values(s)
                except TimeoutError:
                    raise DriverError(f"{self.name}: the RTDE stream stopped: no data package "
                                      f"for {self.stream_timeout_s:g} s during experiment "
                                      f"{rec.exp_id}") from None
                except (OSError, asyncio.IncompleteReadError) as err:
                    raise DriverError(f"{self.name}: RTDE connection to {where} lost during "
                                      f"experiment {rec.exp_id} ({_reason(err)})") from err
                was = rec.stage
                state = rec.feed(v[ts][0], v[q], v[qd], v[tau], v[rt][0], v[rm][0], v[sm][0],
                                 v[mk][0], loop.time())
                if was == "sent" and rec.stage != "sent":
                    await self._close_script_conn(att)
                if state == DONE:
                    break
        except EndedEarly as err:  # already stopped: nothing to stop
            self._finish(att, error=err)
            return
        except DriverError as err:
            reason = await self._stop_program()
            self._finish(att, error=type(err)(f"{err}; {reason}"))
            return
        finally:
            await s.close()
            await self._close_script_conn(att)
        try:
            data = await asyncio.to_thread(rec.log_bytes)
        except DriverError as err:
            self._finish(att, error=err)
            return
        self._finish(att, data=data)

    def _finish(self, att: _Attempt, *, data: bytes | None = None,
                error: DriverError | None = None) -> None:
        if att.finished.is_set():
            return
        rec = att.rec
        gaps = rec.inter_arrival_s()
        self.last_stats = {"packages": rec.packages, "rows": rec.rows, "missed": rec.missed,
                           "path_missed": rec.path_missed,
                           "p99_inter_arrival_ms": float(np.percentile(gaps, 99) * 1e3)
                           if gaps.size else float("nan"),
                           "max_inter_arrival_ms": float(gaps.max() * 1e3) if gaps.size
                           else float("nan")}
        if rec.path_missed:
            log.warning("driver=ur_rtde exp=%s %d of %d RTDE packages on the path missed (the "
                        "controller skipped them or the link is slow): the log has holes, its "
                        "time stamps are the controller's", rec.exp_id, rec.path_missed,
                        rec.rows + rec.path_missed)
        elif rec.missed:
            log.info("driver=ur_rtde exp=%s %d RTDE packages missed before or after the path",
                     rec.exp_id, rec.missed)
        if error is not None:
            att.error = error
            log.error("driver=ur_rtde exp=%s failed: %s", rec.exp_id, error)
        else:
            assert data is not None
            att.log = data
            att.done = Done(att.key[0], att.key[1], hashlib.sha256(data).hexdigest(), len(data))
            log.info("driver=ur_rtde exp=%s path recorded: %d rows, %d bytes", rec.exp_id,
                     rec.rows, len(data))
        att.finished.set()

    async def _close_script_conn(self, att: _Attempt) -> None:
        task, att.script_conn = att.script_conn, None
        if task is not None:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    async def _cancel_tasks(self, att: _Attempt) -> None:
        if att.task is not None and att.task is not asyncio.current_task():
            att.task.cancel()
            await asyncio.gather(att.task, return_exceptions=True)
        await self._close_script_conn(att)

    def _forget_old(self) -> None:
        """Bounded memory: finished attempts beyond the newest few are dropped."""
        done = [k for k, a in self._attempts.items() if a.finished.is_set()]
        for key in done[: max(0, len(self._attempts) - _KEEP_RUNS)]:
            del self._attempts[key]

    async def _wait_done(self, exp_id: str, nonce: str) -> Done:
        att = self._attempts.get((exp_id, nonce))
        if att is None:
            raise DriverError(f"{self.name}: experiment {exp_id} (nonce {nonce}) was not given "
                              "by this link session: its stream was not recorded")
        await att.finished.wait()
        if att.error is not None:
            raise att.error
        assert att.done is not None
        return att.done

    async def _fetch_logs(self, done: Done) -> bytes:
        att = self._attempts.get((done.exp_id, done.nonce))
        if att is None or att.log is None:
            raise DriverError(f"{self.name}: no recorded log for experiment {done.exp_id} "
                              f"(nonce {done.nonce}) in this link session")
        return att.log

    async def _acknowledge(self, done: Done) -> None:
        self._attempts.pop((done.exp_id, done.nonce), None)

    async def _withdraw(self, exp_id: str, nonce: str) -> None:
        att = self._attempts.pop((exp_id, nonce), None)
        if att is not None:
            if not att.finished.is_set():
                log.warning("driver=ur_rtde exp=%s nonce=%s given up: stopping the program",
                            exp_id, nonce)
                await self._cancel_tasks(att)
                reason = await self._stop_program()
                self._finish(att, error=DriverError(f"{self.name}: experiment {exp_id} "
                                                    f"withdrawn; {reason}"))
            return
        state = await self._dashboard("programState")
        if state.startswith(("PLAYING", "PAUSED")):  # given before a restart, maybe ours
            log.warning("driver=ur_rtde exp=%s nonce=%s given up while a program is %s: "
                        "stopping it", exp_id, nonce, state.split()[0].lower())
            await self._stop_program()


def _reason(err: BaseException) -> str:
    """A short cause: 'connection closed', 'Connection refused', 'timed out', …"""
    if isinstance(err, asyncio.IncompleteReadError):
        return "connection closed"
    if isinstance(err, OSError) and err.errno:
        return os.strerror(err.errno)
    if isinstance(err, TimeoutError):
        return "timed out"
    text = str(err).splitlines()[0][:160] if str(err) else ""
    return f"{type(err).__name__}: {text}" if text else type(err).__name__
