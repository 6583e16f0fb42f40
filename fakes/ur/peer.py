"""A fake Universal Robots controller on 127.0.0.1: the RTDE server (protocol 2,
``rtde_server.py``), the script port (URScript programs run by ``urscript_vm`` on the simulated
arm) and the dashboard server, written from UR's RTDE guide, URScript manual and dashboard
server description (nothing from drivers/).

A program received on the script port replaces the running one: it plays (runtime_state 2) while
it is compiled and simulated, then the arm follows it in real time and every RTDE client gets
its recipe at its frequency, time-stamped by the controller's clock; at its end runtime_state
goes back to stopped (1). Own faults (``fault_at``: the share of the path where they strike):
``rtde_drop`` (RTDE connections reset), ``rtde_stall`` (the stream stops, connection kept),
``rtde_slow`` (one package in ``slow_every``), ``rtde_garbage`` (one data package of the
largest size, zeros), ``rtde_not_found`` (``missing_field`` answered
NOT_FOUND at the next set-up), ``rtde_refuse_v2`` (the next version request refused). Core faults:
``fail`` is a protective stop, ``die`` the controller gone, ``never_answer`` a program that never
moves nor ends, ``truncated_log``/``corrupt_log`` one short / foreign-recipe data package,
``answer_twice`` a second playing→stopped blip, ``nan_log`` NaN in actual_q. ``compile_s``
delays every program (a controller slow to compile a long script).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import re
import struct
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from robid_link.exceptions import RobidError
from robid_link.fakes.controller import ControllerCore, Peer
from robid_link.fakes.ur.program import Motion, simulate
from robid_link.fakes.ur.rtde_server import SERIES, RtdeClient, RtdeServer
from robid_link.fakes.ur.vm import ScriptError, compile_program

__all__ = ["UrRtdePeer"]

log = logging.getLogger("robid.fake_controller")

GREETING = b"Connected: Universal Robots Dashboard Server\n"
_STATES = {1: "STOPPED", 2: "PLAYING", 4: "PAUSED"}
_MAX_PROGRAM = 16_000_000
_STOP_ONLY = re.compile(r"^\s*(stopj|stopl)\s*\([^()]*\)\s*$|^\s*halt\s*$")


class UrRtdePeer(RtdeServer, Peer):
    """``start`` serves the three ports from a thread with its own event loop; ``stop`` joins."""

    driver = "ur_rtde"
    #: the contract suite's robot: a UR controller moves six revolute joints
    contract_robot = "industrial6.yaml"
    faults = ("rtde_drop", "rtde_stall", "rtde_slow", "rtde_garbage", "rtde_not_found",
              "rtde_refuse_v2")
    unsupported = {
        "stale_semaphore": "RTDE answers carry no nonce and the driver sends a program only "
                           "while the controller is stopped: no earlier run can end into it",
        "answer_twice": "RTDE answers carry no nonce: a second stop right after a run is a stop "
                        "the next attempt sees as it starts, and the driver fails that attempt "
                        "rather than guess (test_ur_rtde.py covers the duplicate of one run)",
    }

    def __init__(self, core: ControllerCore, workdir: Path, *, rtde_port: int = 0,
                 script_port: int = 0, dashboard_port: int = 0, frequency: float = 500.0,
                 series: str = "e", missing_field: str = "actual_qd",
                 absent: list[str] | tuple[str, ...] = (),
                 current_gain: list[float] | None = None, slow_every: int = 5,
                 fault_at: float = 0.5, compile_s: float = 0.0) -> None:
        super().__init__(core, workdir)
        if core.robot.n != 6:
            raise RobidError(f"the fake UR controller moves 6 joints; robot {core.robot.name} "
                             f"has {core.robot.n}")
        if series not in SERIES:
            raise RobidError(f"--option series: expected e or cb3, got {series!r}")
        self.series = SERIES[series]
        self.ports = {"rtde_port": rtde_port, "script_port": script_port,
                      "dashboard_port": dashboard_port}
        self.frequency, self.missing_field = float(frequency), missing_field
        self.absent = set(absent)
        self.gain = np.asarray(current_gain or [0.1, 0.1, 0.1, 0.05, 0.05, 0.05], dtype=float)
        self.slow_every, self.fault_at = max(1, int(slow_every)), float(fault_at)
        self.compile_s = float(compile_s)  # a controller slow to compile (long scripts)
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._servers: list[asyncio.Server] = []
        self._conns: set[asyncio.StreamWriter] = set()
        self._handlers: set[asyncio.Task[Any]] = set()
        self._workers: list[threading.Thread] = []
        self.clients: list[RtdeClient] = []
        self.motion: Motion | None = None
        self.runtime, self.safety, self.robot_mode = 1, 1, 7
        self.registers: dict[int, int] = {}
        self.q, self.qd, self.tau = np.zeros(6), np.zeros(6), np.zeros(6)
        self._blip: tuple[float, float] | None = None
        self._boot = 0.0
        self._programs = 0
        self._received = 0  # programs and stop requests received on the script port
        self.stops: list[str] = []  # stop requests received: dashboard, script (stopj)
        self.stop_times: list[float] = []  # time.time() of each of them
        self.programs: list[str] = []  # names of the programs received, in order

    def driver_options(self) -> dict[str, Any]:
        opts: dict[str, Any] = {"name": "ur_rtde", "host": "127.0.0.1", **self.ports,
                                "frequency": self.frequency}
        if "target_moment" in self.absent:
            opts["current_gain"] = self.gain.tolist()
        return opts

    # -- life cycle
    def start(self) -> None:
        if self._thread is not None:
            return
        self._thread = threading.Thread(target=self._run, name="fake-ur", daemon=True)
        self._thread.start()
        self._ready.wait(30)
        if self._error is not None:
            raise RobidError(f"fake UR controller could not start: {self._error}")

    def stop(self) -> None:
        if self._loop is not None and self._stop is not None:
            with contextlib.suppress(RuntimeError):
                self._loop.call_soon_threadsafe(self._stop.set)
        if self._thread is not None:
            self._thread.join(30)
        for worker in self._workers:
            worker.join(60)

    def _run(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as err:  # noqa: B036  # reported by start()
            self._error = err
            self._ready.set()

    async def _main(self) -> None:
        self._loop, self._stop = asyncio.get_running_loop(), asyncio.Event()
        self._boot = self._loop.time() - 1000.0  # the controller has been up a while
        self.q = np.zeros(6)
        self.tau = self.core.plant.rigid_torque(self.q[None], np.zeros((1, 6)),
                                                np.zeros((1, 6)))[0]
        for key, handler in (("rtde_port", self._rtde), ("script_port", self._script),
                             ("dashboard_port", self._dashboard)):
            server = await asyncio.start_server(handler, "127.0.0.1", self.ports[key],
                                                limit=_MAX_PROGRAM)
            self._servers.append(server)
            self.ports[key] = server.sockets[0].getsockname()[1]
        self._ready.set()
        try:
            await self._stop.wait()
        finally:
            await self._shutdown()

    async def _shutdown(self) -> None:
        for server in self._servers:
            server.close()
        for w in list(self._conns):
            w.transport.abort()
        tasks = [c.task for c in self.clients if c.task is not None] + list(self._handlers)
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        for server in self._servers:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(server.wait_closed(), 5)
        self._servers.clear()

    def _die(self) -> None:
        log.info("controller dies mid-program")
        self.core.die()
        self.died.set()
        assert self._stop is not None
        self._stop.set()

    @contextlib.asynccontextmanager
    async def _connection(self, writer: asyncio.StreamWriter) -> Any:
        """One client connection: tracked (shutdown cancels and awaits it), closed at the end."""
        task = asyncio.current_task()
        assert task is not None
        self._conns.add(writer)
        self._handlers.add(task)
        try:
            yield
        except (ConnectionError, asyncio.IncompleteReadError, OSError):
            pass
        finally:
            self._handlers.discard(task)
            self._conns.discard(writer)
            writer.close()

    # -- the arm and its program
    def _now(self) -> float:
        assert self._loop is not None
        return self._loop.time()

    def _state(self, now: float) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
        """The arm at controller time ``now``: (runtime state, q, q̇, τ). Moves the program on
        (register writes, its fault, its end); a time before the motion began (a client's
        clock running late) sees the arm still holding."""
        m = self.motion
        hold = (self.runtime, self.q, self.qd, self.tau)
        if m is None or m.start is None or now < m.start or self.runtime == 4:
            if m is None and self._blip and self._blip[0] <= now < self._blip[1]:
                return (2, *hold[1:])
            return hold
        tau_ = now - m.start
        while m.next_event < len(m.events) and m.events[m.next_event][0] <= tau_:
            _, reg, value = m.events[m.next_event]
            self.registers[reg] = value
            m.next_event += 1
        if tau_ >= m.duration:
            self._hold(m.rows[-1])
            self._end(m, "ended")
            if m.fault == "answer_twice":
                self._blip = (now + 0.02, now + 0.04)
            return (self.runtime, self.q, self.qd, self.tau)
        i, w = divmod(tau_ * m.rate, 1.0)
        a = m.rows[int(i)]
        row = a + (m.rows[min(int(i) + 1, m.rows.shape[0] - 1)] - a) * w
        if not m.struck and tau_ >= m.fault_at:
            m.struck = True
            self._strike(m, row)
            if self.motion is not m or self.runtime == 4:
                return (self.runtime, self.q, self.qd, self.tau)
        return 2, row[:6], row[6:12], row[12:]

    def _hold(self, row: np.ndarray) -> None:
        self.q, self.qd, self.tau = row[:6].copy(), np.zeros(6), row[12:].copy()

    def _strike(self, m: Motion, row: np.ndarray) -> None:
        if m.fault == "fail":
            log.info("protective stop in %s", m.name)
            self._hold(row)
            self.safety, self.runtime = 3, 4
        elif m.fault == "die":
            self._die()
        elif m.fault == "rtde_drop":
            log.info("RTDE connections dropped in %s", m.name)
            for c in self.clients:
                c.writer.transport.abort()

    def _end(self, m: Motion, how: str) -> None:
        if self.motion is m:
            self.motion = None
            self.runtime = 1
            log.info("program %s %s", m.name, how)

    def _stop_program(self, who: str) -> bool:
        """Stop the running program (``who`` asked); False when none runs. The arm holds
        where it is."""
        m = self.motion
        if m is None and self.runtime != 4:
            return False
        if m is not None:
            _, q, _, tau = self._state(self._now())
            self._hold(np.concatenate([q, np.zeros(6), tau]))
            self._end(m, f"stopped by the {who}")
        self.runtime = 1
        return True

    def _play(self, text: str) -> None:
        """A program from the script port: compiled (a program with a syntax error is refused
        and nothing changes), then it replaces the running one and plays; a program that only
        stops (``stopj(a)``, ``halt``) is a stop request. Compiling and simulating run in a
        thread: the controller's streams go on meanwhile."""
        self._received += 1
        if _STOP_ONLY.match(text):
            self.stops.append("script")
            self.stop_times.append(time.time())
            self._stop_program("script")
            return
        self._programs += 1
        run, seq = self._programs, self._received
        assert self._loop is not None
        loop = self._loop
        verdict: list[bool] = []  # the controller's answer to the compiled program
        decided = threading.Event()

        def post(*call: Any) -> bool:
            try:
                loop.call_soon_threadsafe(*call)
            except RuntimeError:  # the controller was shut down
                return False
            return True

        def accepted() -> bool:
            """Whether the program replaced the running one: the controller always decides,
            unless it was shut down before it could."""
            while not decided.wait(0.1):
                if loop.is_closed():
                    return False
            return verdict[0]

        def work() -> None:
            time.sleep(self.compile_s)
            try:
                program = compile_program(text)
            except ScriptError as err:
                log.warning("script port: program refused: %s", err)
                return
            m = Motion(program.name, start=None)
            if not post(self._accept, m, seq, verdict, decided) or not accepted():
                return
            try:
                simulate(self.core, program, m, q_start=m.rows[0, :6], steptime=self.series
                         .steptime, run=run, fault_at=self.fault_at)
            except (ScriptError, RobidError, ValueError) as err:
                post(self._failed, m, str(err))
                return
            if m.fault != "never_answer":
                post(self._moving, m)

        self._workers = [w for w in self._workers if w.is_alive()]
        worker = threading.Thread(target=work, name="fake-ur-program", daemon=True)
        self._workers.append(worker)
        worker.start()

    def _accept(self, m: Motion, seq: int, verdict: list[bool],
                decided: threading.Event) -> None:
        """The compiled program replaces the running one and plays from where the arm is,
        unless a stop or another program came in after it (it was replaced before it ran):
        either way the compiling thread hears it (``verdict``, then ``decided``)."""
        verdict.append(seq == self._received)
        if not verdict[0]:
            decided.set()
            log.info("program %s replaced before it started", m.name)
            return
        self._stop_program("script")
        self.programs.append(m.name)
        m.rows = np.concatenate([self.q, np.zeros(6), self.tau])[None]
        self.motion, self.runtime = m, 2
        decided.set()

    def _failed(self, m: Motion, reason: str) -> None:
        log.warning("program %s: runtime error: %s", m.name, reason)
        self._end(m, "failed")

    def _moving(self, m: Motion) -> None:
        """The arm starts at the next controller step (clients' clocks are on that grid)."""
        if self.motion is m:
            step = self.series.steptime
            m.start = self._boot + (int((self._now() - self._boot) / step) + 1) * step

    # -- script port (secondary client interface: URScript in, state messages out)
    async def _script(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        async with self._connection(writer):
            chatter = asyncio.get_running_loop().create_task(self._state_messages(writer))
            try:
                await self._read_programs(reader)
            finally:
                chatter.cancel()
                await asyncio.gather(chatter, return_exceptions=True)

    async def _state_messages(self, writer: asyncio.StreamWriter) -> None:
        with contextlib.suppress(ConnectionError, OSError):
            while True:  # an (empty) robot state package every 100 ms, as the port streams
                writer.write(struct.pack(">iB", 5, 16))
                await asyncio.sleep(0.1)

    async def _read_programs(self, reader: asyncio.StreamReader) -> None:
        lines: list[str] = []
        size = 0
        while raw := await reader.readline():
            line = raw.decode("utf-8", "replace").rstrip("\r\n")
            size += len(raw)
            if size > _MAX_PROGRAM:
                log.warning("script port: program over %d bytes refused", _MAX_PROGRAM)
                return
            if not lines and not line.strip():
                continue
            if not lines and not line.startswith(("def ", "sec ")):
                self._play(line)  # one statement is a program of its own
                continue
            lines.append(line)
            if line.rstrip() == "end":
                text, lines, size = "\n".join(lines), [], 0
                if text.startswith("sec "):
                    log.info("script port: secondary program ignored (no motion)")
                else:
                    self._play(text)

    # -- dashboard server
    async def _dashboard(self, reader: asyncio.StreamReader,
                         writer: asyncio.StreamWriter) -> None:
        async with self._connection(writer):
            writer.write(GREETING)
            while raw := await reader.readline():
                command = raw.decode("utf-8", "replace").strip()
                writer.write(self._dashboard_answer(command).encode() + b"\n")
                await writer.drain()
                if command == "quit":
                    return

    def _dashboard_answer(self, command: str) -> str:
        runtime = self._state(self._now())[0]
        name = self.programs[-1] if self.programs else "<unnamed>"
        if command == "stop":
            self.stops.append("dashboard")
            self.stop_times.append(time.time())
            return "Stopped" if self._stop_program("dashboard") else "Failed to execute: stop"
        if command == "pause":
            if runtime != 2:
                return "Failed to execute: pause"
            self.runtime = 4
            return "Pausing program"
        answers = {
            "play": "Failed to execute: play",
            "programState": f"{_STATES.get(runtime, 'STOPPED')} {name}",
            "running": f"Program running: {'true' if runtime == 2 else 'false'}",
            "robotmode": "Robotmode: RUNNING",
            "safetymode": f"Safetymode: {'NORMAL' if self.safety == 1 else 'PROTECTIVE_STOP'}",
            "safetystatus": f"Safetystatus: "
                            f"{'NORMAL' if self.safety == 1 else 'PROTECTIVE_STOP'}",
            "is in remote control": "true",
            "PolyscopeVersion": "URSoftware {}.{}.{}.{} (fake)".format(*self.series.version),
            "quit": "Disconnected",
        }
        if command == "unlock protective stop":
            self.safety = 1
            return "Protective stop releasing"
        return answers.get(command, f"could not understand: '{command}'")
