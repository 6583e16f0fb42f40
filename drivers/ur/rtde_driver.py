"""Universal Robots over RTDE (protocol 2): the program goes to the script port as URScript, the
run is recorded from the RTDE stream, stops go through the dashboard server.

give: an RTDE session (version 2, URControl version, output recipe, start), the controller
checked stopped with the robot running and its safety normal, then the URScript program
(``drivers/ur/script.py``) on the script port; from then on a task reads every data package
(the controller drops slow readers) and records the rows on the path. take: the program's
``runtime_state`` back from playing (2) to stopped (1) with the path's end marker. A lost
connection, a stalled stream, a protective stop or a malformed package stop the program
(dashboard ``stop``; ``stopj`` on the script port when the dashboard cannot or the program may
not have started yet) before the failure is stored. UR has no parameter upload: the capability
is absent.
"""

from __future__ import annotations

import asyncio
import hashlib
import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from robid_link.drivers.ur.record import (
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
from robid_link.drivers.ur.script import Knots, marker_tag, plan_knots, render_script
from robid_link.drivers.ur.session import (
    E_SERIES_HZ,
    RtdeOptions,
    RtdeSession,
    open_session,
    reason,
)
from robid_link.exceptions import ConfigError, DriverError
from robid_link.jobs import MotionProgram, RobotInfo
from robid_link.link.driver import Done, Driver
from robid_link.link.options import Choice, Integer, Number, Options, Text, Vector

__all__ = ["UrRtdeDriver"]

log = logging.getLogger("robid.driver.ur_rtde")

TORQUE_FIELDS = ("target_moment", "actual_current")
_KEEP_RUNS = 8
_GRACE_S = 0.2  # a second look before a silent stream counts as stopped


class _PartlySent(DriverError):
    """The script port failed while the program was being written: part of it may be there."""


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


class UrRtdeDriver(Driver):
    """Daemon side of a Universal Robots cell. Options: ``host``, ``rtde_port`` (30004),
    ``script_port`` (30002), ``dashboard_port`` (29999), ``frequency`` (RTDE Hz: ≤ 125 on CB3,
    ≤ 500 on e-Series), ``torque`` (auto | target_moment | actual_current), ``current_gain``
    (6 N·m/A, to log actual_current as torque), ``marker_register`` (24), ``lookahead_time_s``
    and ``servo_gain`` (servoj), ``approach_speed_rad_s``/``approach_acceleration_rad_s2``
    (movej to the path's start), ``path_tolerance_rad``, ``max_script_bytes``,
    ``io_timeout_s``, ``stream_timeout_s``, ``start_timeout_s``."""

    name = "ur_rtde"
    options = Options(
        host=Text(pattern=r"[^\s]+", expect="a host name or address",
                  hint="the controller's address"),
        rtde_port=Integer(30004, low=1, high=65535),
        script_port=Integer(30002, low=1, high=65535),
        dashboard_port=Integer(29999, low=1, high=65535),
        frequency=Number(500.0, above=0.0, high=E_SERIES_HZ),
        torque=Choice("auto", *TORQUE_FIELDS, default="auto"),
        current_gain=Vector(Number(above=0.0), None, hint="6 numbers, N·m per A of each joint"),
        marker_register=Integer(24, low=0, high=47),
        lookahead_time_s=Number(0.05, above=0.029, high=0.2),
        servo_gain=Number(1000.0, above=99.0, high=2000.0),
        approach_speed_rad_s=Number(0.35, above=0.0, high=3.14),
        approach_acceleration_rad_s2=Number(0.7, above=0.0, high=15.0),
        path_tolerance_rad=Number(1e-4, above=0.0, high=0.01),
        max_script_bytes=Integer(1_000_000, low=10_000, high=50_000_000),
        io_timeout_s=Number(5.0, above=0.0, high=600.0),
        stream_timeout_s=Number(1.0, above=0.0, high=60.0),
        start_timeout_s=Number(10.0, above=0.0, high=600.0))

    def __init__(self, **options: Any) -> None:
        super().__init__(**options)
        o = self.config
        self.host = o.host
        self.ports = {"rtde_port": o.rtde_port, "script_port": o.script_port,
                      "dashboard_port": o.dashboard_port}
        self.frequency, self.torque = o.frequency, o.torque
        self.current_gain = self._gain(o.current_gain)
        if self.torque == "actual_current" and self.current_gain is None:
            raise ConfigError("driver.current_gain: needed with torque: actual_current "
                              "(6 numbers, N·m per A of each joint)")
        self.marker_register = o.marker_register
        self.lookahead_s, self.servo_gain = o.lookahead_time_s, o.servo_gain
        self.approach_speed = o.approach_speed_rad_s
        self.approach_acc = o.approach_acceleration_rad_s2
        self.path_tolerance = o.path_tolerance_rad
        self.max_script_bytes = o.max_script_bytes
        self.io_timeout_s, self.stream_timeout_s = o.io_timeout_s, o.stream_timeout_s
        self.start_timeout_s = o.start_timeout_s
        self._programs: dict[str, tuple[MotionProgram, Knots]] = {}
        self._attempts: dict[tuple[str, str], _Attempt] = {}
        self._active: _Attempt | None = None
        self._tasks: set[asyncio.Task[None]] = set()
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
            how = await self._stop_program(not_started=active.rec.stage == "sent")
            self._finish(active, error=DriverError(f"{self.name}: the link closed during "
                                                   f"experiment {active.key[0]}; {how}"))
        for att in list(self._attempts.values()):
            await self._cancel_tasks(att)
        for task in list(self._tasks):  # attempts already acknowledged or withdrawn
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)

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
            raise DriverError(f"{self.name}: dashboard {where}: {reason(err)}") from err
        except ValueError as err:  # a line past the reader's limit: not a dashboard answer
            raise DriverError(f"{self.name}: dashboard {where}: answer of over 64 KiB to "
                              f"{command!r}") from err
        if not answer.endswith(b"\n"):
            raise DriverError(f"{self.name}: dashboard {where} closed without answering "
                              f"{command!r}")
        return answer[:200].decode("utf-8", "replace").strip()

    async def _send_script(self, script: bytes) -> asyncio.Task[None]:
        """The program on the script port; the connection stays open (its state messages read
        and dropped) until the program plays, so closing cannot reset unread script bytes."""
        where = self.where("script_port")
        try:
            async with asyncio.timeout(self.io_timeout_s):
                reader, writer = await asyncio.open_connection(self.host,
                                                               self.ports["script_port"])
        except (OSError, TimeoutError) as err:
            raise DriverError(f"{self.name}: script port {where}: {reason(err)}") from err
        try:
            async with asyncio.timeout(self.io_timeout_s):
                writer.write(script)
                await writer.drain()
        except (OSError, TimeoutError) as err:
            writer.close()
            raise _PartlySent(f"{self.name}: script port {where}: {reason(err)} while "
                              "sending the program") from err

        async def drain_loop() -> None:
            try:
                while await reader.read(65536):
                    pass
            except OSError:
                pass
            finally:
                writer.close()

        return asyncio.create_task(drain_loop(), name="ur_rtde-script-port")

    async def _stop_program(self, not_started: bool = False) -> str:
        """Dashboard ``stop``; ``stopj`` on the script port when the dashboard cannot, or when
        the program may not have started yet (a controller still compiling it has nothing to
        stop: a newer program on the script port replaces it). Returns how it went (for the
        failure's line); never raises."""
        try:
            answer = await self._dashboard("stop")
        except DriverError as err:
            answer = f"dashboard {reason(err.__cause__ or err)}"
        stopped = answer.startswith("Stopped")
        if stopped and not not_started:
            log.warning("driver=ur_rtde program stopped through the dashboard")
            return "program stopped (dashboard)"
        try:
            task = await self._send_script(b"stopj(4.0)\n")
            await asyncio.sleep(0.2)
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
        except DriverError as err:
            line = f"could not stop the program ({answer}; script port " \
                   f"{reason(err.__cause__ or err)})"
            log.error("driver=ur_rtde %s", line)
            return line
        log.warning("driver=ur_rtde dashboard stop: %s; stopj sent on the script port", answer)
        return "program stopped (dashboard and stopj)" if stopped else \
            "program stopped (stopj on the script port)"

    # -- RTDE
    def _rtde_options(self) -> RtdeOptions:
        return RtdeOptions(self.host, self.ports["rtde_port"], self.frequency, self.torque,
                           self.current_gain, self.marker_register, self.io_timeout_s)

    # -- the cycle
    async def _put_program(self, program: MotionProgram) -> None:
        known = self._programs.get(program.exp_id)
        if known is None or known[0].sha256 != program.sha256:
            # seconds of numerical work for a long program: not on the daemon's event loop
            knots = await asyncio.to_thread(self._prepare, program)
            self._programs[program.exp_id] = (program, knots)

    def _prepare(self, program: MotionProgram) -> Knots:
        """The program's knots, checked: six revolute joints, the path, the script's size."""
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
        return knots

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
        script = await asyncio.to_thread(self._render, program, knots, exp_id, nonce)
        session = await open_session(self._rtde_options())
        self.controller_version, torque = session.version, session.torque
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
        except _PartlySent as err:  # part of it may have reached the controller
            await session.close()
            how = await self._stop_program(not_started=True)
            raise DriverError(f"{err}; {how}") from err
        except BaseException:
            await session.close()
            raise
        rec.sent_at = loop.time()
        self._attempts[key] = self._active = att
        att.task = asyncio.create_task(self._record_loop(att, session),
                                       name=f"ur_rtde-record-{exp_id}")
        self._tasks.add(att.task)
        att.task.add_done_callback(self._tasks.discard)
        self._forget_old()
        log.info("driver=ur_rtde exp=%s nonce=%s program sent (%d bytes, %d knots every %.3f s,"
                 " path within %.1e rad, acceleration within %.1f %%; %s, %g Hz)", exp_id,
                 nonce, len(script), knots.intervals + 1, knots.h, knots.error_rad,
                 100 * knots.accel_error, torque, self.frequency)

    async def _check_idle(self, s: RtdeSession, exp_id: str) -> None:
        """Before motion: the first data package says robot running, safety normal, nothing
        playing."""
        assert s.recipe is not None
        slots = s.recipe.slices()
        try:
            async with asyncio.timeout(self.stream_timeout_s + self.io_timeout_s):
                values = await s.next_values()
        except TimeoutError as err:
            raise DriverError(f"{self.name}: RTDE {self.where('rtde_port')} started but sent no "
                              "data package") from err
        except (OSError, asyncio.IncompleteReadError) as err:
            raise DriverError(f"{self.name}: RTDE {self.where('rtde_port')}: connection lost "
                              f"({reason(err)})") from err
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

    async def _record_loop(self, att: _Attempt, s: RtdeSession) -> None:
        """Read every package until the attempt ends; on any failure the stop goes out first,
        then the failure is stored."""
        rec, loop = att.rec, asyncio.get_running_loop()
        assert s.recipe is not None
        sl = s.recipe.slices()
        ts, q, qd, tau, rt, rm, sm, mk = (sl[f] for f in s.recipe.names)
        where = self.where("rtde_port")
        error: DriverError | None = None
        try:
            while True:
                try:
                    v = await self._next_in_time(s, rec.exp_id)
                except (OSError, asyncio.IncompleteReadError) as err:
                    raise DriverError(f"{self.name}: RTDE connection to {where} lost during "
                                      f"experiment {rec.exp_id} ({reason(err)})") from err
                was = rec.stage
                state = rec.feed(v[ts][0], v[q], v[qd], v[tau], v[rt][0], v[rm][0], v[sm][0],
                                 v[mk][0], loop.time())
                if was == "sent" and rec.stage != "sent":
                    await self._close_script_conn(att)
                if state == DONE:
                    await s.pause(self.io_timeout_s)
                    break
        except EndedEarly as err:  # already stopped: nothing to stop
            error = err
        except DriverError as err:
            how = await self._stop_program(not_started=rec.stage == "sent")
            error = type(err)(f"{err}; {how}")
        finally:
            rec.received = s.packages
            await s.close()
            await self._close_script_conn(att)
        if error is None:
            try:
                data = await asyncio.to_thread(rec.log_bytes)
            except DriverError as err:
                error = err
        if error is not None:
            self._finish(att, error=error)
        else:
            self._finish(att, data=data)

    async def _next_in_time(self, s: RtdeSession, exp_id: str) -> tuple[Any, ...]:
        """The next data package within ``stream_timeout_s``. When the wait runs out, a short
        second look: a daemon process descheduled for a while (the worker busy on every core)
        finds what the controller sent meanwhile waiting in the socket, a stalled stream
        does not."""
        try:
            async with asyncio.timeout(self.stream_timeout_s):
                return await s.next_values()
        except TimeoutError:
            pass
        try:
            async with asyncio.timeout(_GRACE_S):
                return await s.next_values()
        except TimeoutError:
            raise DriverError(f"{self.name}: the RTDE stream stopped: no data package for "
                              f"{self.stream_timeout_s:g} s during experiment {exp_id}") from None

    def _finish(self, att: _Attempt, *, data: bytes | None = None,
                error: DriverError | None = None) -> None:
        if att.finished.is_set():
            return
        rec = att.rec
        gaps = rec.inter_arrival_s()
        self.last_stats = {"packages": rec.received, "rows": rec.rows, "missed": rec.missed,
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
            if att.finished.is_set():
                await self._cancel_tasks(att)  # its task may still be closing the session
            else:
                log.warning("driver=ur_rtde exp=%s nonce=%s given up: stopping the program",
                            exp_id, nonce)
                await self._cancel_tasks(att)
                how = await self._stop_program(not_started=att.rec.stage == "sent")
                self._finish(att, error=DriverError(f"{self.name}: experiment {exp_id} "
                                                    f"withdrawn; {how}"))
            return
        state = await self._dashboard("programState")
        if state.startswith(("PLAYING", "PAUSED")):  # given before a restart, maybe ours
            log.warning("driver=ur_rtde exp=%s nonce=%s given up while a program is %s: "
                        "stopping it", exp_id, nonce, state.split()[0].lower())
            await self._stop_program()
