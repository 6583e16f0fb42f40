"""CiA 402 servo drives on a CAN bus, the daemon as motion master (python-can + canopen).

Open brings the drives up by NMT and SDO (boot-up, identity, PDO mapping, cyclic synchronous
position, the power state machine); a ``SyncMaster`` thread then streams each program one
setpoint per SYNC and records the drives' answers as the experiment's log (CSV + BLF).
"""

from __future__ import annotations

import asyncio
import hashlib
import logging
import math
import os
import struct
import tempfile
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import can
import canopen
import numpy as np
from scipy.interpolate import CubicSpline

from robid_link.atomic import atomic_write
from robid_link.drivers.canopen.cia402 import (
    CW_ENABLE,
    CW_FAULT_RESET,
    CW_SHUTDOWN,
    CW_SWITCH_ON,
    MODE_CSP,
    NMT_RESET_COMM,
    NMT_START,
    PROFILE_402,
    RPDO1_MAP,
    SYNC_ECHO,
    SYNC_OVERFLOW,
    TORQUE_ACTUAL,
    drive_state,
    error_words,
    tpdo2_struct,
    tpdo_maps,
)
from robid_link.drivers.canopen.feedforward import KeptParameterSet, torque_offsets
from robid_link.drivers.canopen.master import Axis, Job, SyncMaster, quintic, ramp_to_rest
from robid_link.drivers.canopen.realtime import ProcessHold, RealtimeListener, realtime
from robid_link.drivers.canopen.record import BlfTap, log_bytes
from robid_link.exceptions import ConfigError, DriverError
from robid_link.jobs import MotionProgram, RobotInfo
from robid_link.link.driver import CAP_FEEDFORWARD, CAP_UPLOAD, Done, Driver
from robid_link.link.options import (
    File,
    Folder,
    Integer,
    Number,
    Option,
    Options,
    Retired,
    Table,
    Text,
    Vector,
)

__all__ = ["CanopenDrivesDriver", "log_bytes"]

log = logging.getLogger("robid.driver.canopen")
# python-can's socketcand client warns at every frame split across two TCP reads, which a
# stream does all the time; it recovers the frame, so this is not worth a line per SYNC
logging.getLogger("can.interfaces.socketcand.socketcand").setLevel(logging.ERROR)

_INT32 = 2**31 - 1


class _ObjectEntry(Option):
    """An object dictionary entry given as ``"0x2100:0"``, ``"0x2100"`` or an int index,
    manufacturer-specific (0x2000..0x5FFF) or one of ``also``: ``(index, subindex)``."""

    def __init__(self, default: Any, *, also: tuple[tuple[int, int], ...] = ()) -> None:
        super().__init__(default)
        self.also = also
        named = "".join(f"'0x{i:04X}:{s}' or " for i, s in also)
        self.expect = f"{named}a manufacturer-specific object as '0xIIII:SS' (index " \
                      "0x2000..0x5FFF)"

    def convert(self, key: str, value: Any) -> tuple[int, int]:
        if isinstance(value, int) and not isinstance(value, bool):
            index, sub = value, 0
        else:
            try:
                head, _, tail = str(value).partition(":") if isinstance(value, str) else (
                    "", "", "")
                index, sub = int(head, 0), int(tail or "0", 0)
            except ValueError:
                index = sub = -1
        if (index, sub) not in self.also and not (0x2000 <= index <= 0x5FFF
                                                  and 0 <= sub <= 0xFF):
            raise self.refuse(key, value)
        return index, sub


class CanopenDrivesDriver(Driver):
    """One CiA 402 drive per joint; the daemon streams the trajectory (see module docstring).

    Options: ``interface``, ``channel``, ``bitrate`` (python-can bus; ``host`` and ``port``
    of the server with ``interface: socketcand``), ``nodes`` (node id per
    joint), ``sync_period_s`` (≥ 1 ms), ``counts_per_rad`` and ``rated_torque_nm`` (per joint:
    encoder counts per joint radian — per metre for prismatic joints — and the joint torque of
    1000 per mille; default from 0x6076), ``eds``, ``record_dir`` (logs and BLF files),
    ``following_error_rad``, ``heartbeat_ms``, ``heartbeat_timeout_s``, ``boot_timeout_s``,
    ``state_timeout_s``, ``settle_timeout_s``, ``standstill_rad_s``, ``max_missed``,
    ``overrun_streak``, ``max_approach_rad``, ``sync_priority`` (0: normal scheduling; 1-99:
    SCHED_FIFO for the SYNC thread and the CAN receive thread, as a real-time master runs, and
    one below for the BLF recorder and the log writer),
    ``bus_options`` (extra python-can arguments),
    ``robot_file`` (refused: no longer used, the feedforward's inverse dynamics runs in the
    worker on the daemon's robot),
    ``sync_echo`` (the drive's UNSIGNED8 object, mappable, that holds the counter of the SYNC
    at which its TPDO values were latched: ``"0x2100:0"`` by default; each TPDO carries it, so
    a late answer is still put at its own SYNC; the driver sets 0x1019 so SYNCs carry a
    counter), ``torque_object`` (what TPDO2 carries as the log's torque: ``"0x6077:0"``,
    INTEGER16 per mille of the rated torque, by default; a manufacturer object is an INTEGER32
    — a finer torque, or a current — with ``torque_unit_nm``, the joint N·m of one unit, per
    joint: a 500 N·m joint reads 0x6077 in 0.5 N·m steps, coarser than the noise an effect
    hides in).

    An uploaded parameter set is the driver's own feedforward: every setpoint carries the set's
    model torque (a table the worker computes, ``feedforward_table``) as torque offset 0x60B2
    (``feedforward.torque_offsets``, mapped in RPDO1 by ``cia402``).
    """

    name = "canopen_drives"
    capabilities = frozenset({CAP_UPLOAD, CAP_FEEDFORWARD})
    options = Options(
        interface=Text("socketcan", expect="a name"), channel=Text("can0", expect="a name"),
        bitrate=Integer(1_000_000, low=10_000, high=1_000_000),
        host=Text(None, expect="the socketcand server's host name or address"),
        port=Integer(None, low=1, high=65535,
                     expect="the socketcand server's TCP port (1..65535)"),
        robot_file=Retired("the feedforward's inverse dynamics runs in the worker on the "
                           "daemon's robot, the config's robot:"),
        nodes=Vector(Integer(low=1, high=127, expect="a node id in 1..127"), per_joint=True,
                     unique=True, hint="a list of node ids, one per joint"),
        sync_period_s=Number(0.004, low=0.001, high=0.1),
        counts_per_rad=Vector(Number(above=0), per_joint=True,
                              hint="encoder counts per joint radian, one per joint"),
        rated_torque_nm=Vector(Number(above=0), None, per_joint=True),
        eds=File(exists=True, hint="the drives' EDS file"), record_dir=Folder(None, created=True),
        following_error_rad=Number(0.15, low=1e-6),
        heartbeat_ms=Integer(100, low=1, high=65535),
        heartbeat_timeout_s=Number(0.35, low=0.001), boot_timeout_s=Number(2.0, low=0.01),
        state_timeout_s=Number(0.5, low=0.001), settle_timeout_s=Number(2.0, low=0.01),
        standstill_rad_s=Number(0.01, low=0.0),
        # answers are put at their SYNC by its counter, unambiguous within SYNC_OVERFLOW
        max_missed=Integer(3, low=1, high=SYNC_OVERFLOW - 40),
        overrun_streak=Integer(5, low=1, high=1_000_000), max_approach_rad=Number(1.0, low=0),
        sync_priority=Integer(0, low=0, high=99),
        bus_options=Table(None), sync_echo=_ObjectEntry(SYNC_ECHO),
        torque_object=_ObjectEntry(TORQUE_ACTUAL, also=(TORQUE_ACTUAL,)),
        torque_unit_nm=Vector(Number(above=0), None, per_joint=True))

    def __init__(self, **options: Any) -> None:
        super().__init__(**options)
        o = self.config
        self.interface, self.channel = o.interface, o.channel
        self.server = _server(o.interface, o.host, o.port)
        self.bitrate = o.bitrate
        self.nodes: tuple[int, ...] = o.nodes
        self.period = o.sync_period_s
        self.counts_per_rad: tuple[float, ...] | None = o.counts_per_rad
        self.rated_torque_nm: tuple[float, ...] | None = o.rated_torque_nm
        self.eds = o.eds
        self.record_dir = o.record_dir or Path(tempfile.gettempdir()) / "robid-canopen"
        self.window = o.following_error_rad
        self.heartbeat_ms = o.heartbeat_ms
        self.hb_timeout = o.heartbeat_timeout_s
        if self.hb_timeout < 2e-3 * self.heartbeat_ms:
            raise ConfigError(f"driver.heartbeat_timeout_s: expected at least two heartbeats "
                              f"({2e-3 * self.heartbeat_ms:g} s), got {self.hb_timeout:g}")
        self.boot_timeout, self.state_timeout = o.boot_timeout_s, o.state_timeout_s
        self.settle_timeout, self.standstill = o.settle_timeout_s, o.standstill_rad_s
        self.max_missed = o.max_missed
        self.torque_object, self.torque_unit_nm = o.torque_object, o.torque_unit_nm
        fine = self.torque_object != TORQUE_ACTUAL  # a manufacturer object: INTEGER32
        if fine and self.torque_unit_nm is None:
            raise ConfigError(f"driver.torque_unit_nm: missing (the joint N·m of one unit of "
                              f"0x{self.torque_object[0]:04X}:{self.torque_object[1]:02X}, one "
                              "per joint)")
        if not fine and self.torque_unit_nm is not None:
            raise ConfigError("driver.torque_unit_nm: only with a manufacturer torque_object "
                              "(0x6077 is in per mille of rated_torque_nm)")
        self.tpdo_maps = tpdo_maps(o.sync_echo, self.torque_object, 32 if fine else 16)
        self.tpdo2 = tpdo2_struct(32 if fine else 16)
        self.overrun_streak, self.max_approach = o.overrun_streak, o.max_approach_rad
        self.sync_priority = o.sync_priority
        self.bus_options = dict(o.bus_options or {})
        self.parameters: KeptParameterSet | None = None
        self.network: canopen.Network | None = None
        self.axes: list[Axis] = []
        self.master: SyncMaster | None = None
        self._tap: BlfTap | None = None
        # the heap frozen, the GIL switch interval a quarter period while the master runs
        self._hold = ProcessHold(self.period / 4)
        self._writer: ThreadPoolExecutor | None = None
        self._programs: dict[str, tuple[np.ndarray, float]] = {}
        self._jobs: dict[tuple[str, str], Job] = {}

    # -- configuration against the robot
    def _check_robot(self, robot: RobotInfo) -> None:
        assert self.counts_per_rad is not None  # lengths: the base's check_joints
        for j in range(robot.n):
            reach = max(abs(robot.q_min[j]), abs(robot.q_max[j]))
            if math.isfinite(reach) and reach * self.counts_per_rad[j] > _INT32:
                raise ConfigError(f"driver.counts_per_rad[{j}]: joint {j + 1} reaches "
                                  f"{reach:.4g} rad = {reach * self.counts_per_rad[j]:.3g} "
                                  "counts, beyond the drive's 32-bit position")
            if self.torque_unit_nm is not None and math.isfinite(robot.tau_max[j]) and (
                    robot.tau_max[j] / self.torque_unit_nm[j] > _INT32):
                raise ConfigError(f"driver.torque_unit_nm[{j}]: joint {j + 1} torque limit "
                                  f"{robot.tau_max[j]:g} N·m overflows the 32-bit torque object")
            if (self.torque_unit_nm is None and self.rated_torque_nm is not None
                    and math.isfinite(robot.tau_max[j])
                    and robot.tau_max[j] / self.rated_torque_nm[j] * 1000 > 32767):
                raise ConfigError(f"driver.rated_torque_nm[{j}]: joint {j + 1} torque limit "
                                  f"{robot.tau_max[j]:g} N·m overflows 0x6077 (16-bit per mille)")

    # -- lifecycle
    async def _open(self) -> None:
        if self.robot is None:
            raise DriverError(f"{self.name}: no robot bound (bind_robot before open)")
        self.record_dir.mkdir(parents=True, exist_ok=True)
        self.parameters = KeptParameterSet(self.robot, self.record_dir / "parameters.json")
        await asyncio.to_thread(self.parameters.restore)
        try:
            await asyncio.to_thread(self._bring_up)
        except BaseException:
            await asyncio.to_thread(self._shutdown, False)
            raise

    def _bring_up(self) -> None:
        """Bus, boot-up, identity, PDOs, CSP mode, power state machine, SYNC master."""
        assert self.robot is not None and self.counts_per_rad is not None
        try:
            bus = can.Bus(interface=self.interface, channel=self.channel, bitrate=self.bitrate,
                          **self.server, **self.bus_options)
        except (can.CanError, OSError, ValueError, ImportError) as err:
            raise DriverError(f"driver.channel: cannot open CAN channel {self.channel} on "
                              f"{self.interface} ({err})") from err
        self.network = net = canopen.Network(bus)
        net.connect()
        # the recorder (every frame of a job) and the log writer (a job's CSV) take the GIL:
        # under SCHED_FIFO below the motion path, no other process keeps them off the CPU
        # while they hold it (the SYNC thread would wait that long)
        below = max(1, self.sync_priority - 1) if self.sync_priority else 0
        self._tap = BlfTap(below)
        assert net.notifier is not None
        net.notifier.add_listener(self._tap)
        if below:
            self._writer = ThreadPoolExecutor(1, thread_name_prefix="ThreadPoolExecutor-canopen",
                                              initializer=realtime, initargs=(below,))
        else:
            self._writer = ThreadPoolExecutor(1, thread_name_prefix="ThreadPoolExecutor-canopen")
        for j, node_id in enumerate(self.nodes):
            self.axes.append(Axis(node_id, j + 1, self.robot.joint_names[j],
                                  self.counts_per_rad[j], 0.0,
                                  self.window * self.counts_per_rad[j]))
        boot = {a.node: threading.Event() for a in self.axes}
        for i, a in enumerate(self.axes):
            net.subscribe(0x700 + a.node, self._heartbeat_cb(i, boot[a.node]))
        net.nmt.send_command(NMT_RESET_COMM)  # every node answers with its boot-up message
        end = time.monotonic() + self.boot_timeout
        for a in self.axes:
            if not boot[a.node].wait(max(0.0, end - time.monotonic())):
                raise DriverError(f"{a.label()}: no boot-up or heartbeat within "
                                  f"{self.boot_timeout:g} s (missing node, no power, or "
                                  "wrong bitrate)")
        for a in self.axes:
            self._configure(a)
        hold = np.array([self._enable(a) for a in self.axes], dtype=np.int64)
        self._start_master(bus, hold)

    def _heartbeat_cb(self, i: int, event: threading.Event) -> Any:
        def cb(can_id: int, data: bytearray, timestamp: float) -> None:
            event.set()
            if self.master is not None:
                self.master.on_heartbeat(i, bytes(data))
        return cb

    def _sdo(self, a: Axis, index: int, sub: int, value: int | None = None, fmt: str = "<I"
             ) -> int:
        """One SDO transfer; aborts and timeouts become a DriverError naming node and object."""
        assert self.network is not None
        node = self.network[a.node]
        try:
            if value is None:
                return int(struct.unpack(fmt, node.sdo.upload(index, sub)[:struct.calcsize(
                    fmt)])[0])
            node.sdo.download(index, sub, struct.pack(fmt, value))
            return value
        except (canopen.SdoAbortedError, canopen.SdoCommunicationError, struct.error) as err:
            raise DriverError(f"{a.label()}: SDO {'write' if value is not None else 'read'} "
                              f"0x{index:04X}:{sub:02X} failed ({err})") from err

    def _configure(self, a: Axis) -> None:
        assert self.network is not None and self.robot is not None
        node = self.network.add_node(a.node, str(self.eds))
        node.sdo.RESPONSE_TIMEOUT = 0.5
        kind = self._sdo(a, 0x1000, 0)
        if kind & 0xFFFF != PROFILE_402:
            raise DriverError(f"{a.label()}: device type 0x{kind:08X} is not a CiA 402 drive")
        ident = [self._sdo(a, 0x1018, s) for s in (1, 2, 3, 4)]
        log.info("%s vendor=0x%08X product=0x%08X revision=0x%08X serial=%d", a.label(), *ident)
        self._sdo(a, 0x1017, 0, self.heartbeat_ms, "<H")
        # SYNCs carry a counter 1..240 (CiA 301: 0x1019 is written while 0x1006 is 0)
        self._sdo(a, 0x1006, 0, 0)
        self._sdo(a, 0x1019, 0, SYNC_OVERFLOW, "<B")
        tpdo1, tpdo2 = self.tpdo_maps
        for comm, mapping, cob, entries in ((0x1400, 0x1600, 0x200, RPDO1_MAP),
                                            (0x1800, 0x1A00, 0x180, tpdo1),
                                            (0x1801, 0x1A01, 0x280, tpdo2)):
            self._sdo(a, comm, 1, 0x80000000 | (cob + a.node))  # invalid while mapping
            self._sdo(a, mapping, 0, 0, "<B")
            for k, entry in enumerate(entries, 1):
                self._sdo(a, mapping, k, entry)
            self._sdo(a, mapping, 0, len(entries), "<B")
            self._sdo(a, comm, 2, 1, "<B")  # synchronous, every SYNC
            self._sdo(a, comm, 1, cob + a.node)
        self._sdo(a, 0x1401, 1, 0x80000000 | (0x300 + a.node))  # RPDO2 unused
        self._sdo(a, 0x1006, 0, round(self.period * 1e6))
        self._sdo(a, 0x60C2, 1, round(self.period * 1e4), "<B")
        self._sdo(a, 0x60C2, 2, -4, "<b")
        self._sdo(a, 0x6065, 0, min(0xFFFFFFFE, round(a.window_counts)))
        qdd = self.robot.qdd_max[a.joint - 1]
        self._sdo(a, 0x6085, 0, min(0xFFFFFFFE, round((qdd if math.isfinite(qdd) else 2.0)
                                                      * a.counts_per_rad)))
        self._sdo(a, 0x605A, 0, 2, "<h")  # quick stop: ramp down, then Switch on disabled
        self._sdo(a, 0x6060, 0, MODE_CSP, "<b")
        mode = self._sdo(a, 0x6061, 0, fmt="<b")
        if mode != MODE_CSP:
            raise DriverError(f"{a.label()}: mode of operation display is {mode}, not "
                              f"{MODE_CSP} (cyclic synchronous position)")
        if self.rated_torque_nm is None:
            a.rated_torque_nm = self._sdo(a, 0x6076, 0) / 1000.0
        else:
            a.rated_torque_nm = self.rated_torque_nm[a.joint - 1]
        if self.torque_unit_nm is not None:
            a.torque_unit_nm = self.torque_unit_nm[a.joint - 1]

    def _enable(self, a: Axis) -> int:
        """Walk the power state machine to Operation enabled (by SDO, a timeout per step),
        the target set to where the axis is so that enabling moves nothing."""
        status = self._sdo(a, 0x6041, 0, fmt="<H")
        if drive_state(status) in ("Fault", "Fault reaction active"):
            code = self._sdo(a, 0x603F, 0, fmt="<H")
            log.warning("%s was in Fault (%s) at start-up: resetting it", a.label(),
                        error_words(code))
            self._sdo(a, 0x6040, 0, 0, "<H")
            self._step(a, CW_FAULT_RESET, "Switch on disabled")
        pos = self._sdo(a, 0x6064, 0, fmt="<i")
        self._sdo(a, 0x607A, 0, pos, "<i")
        self._step(a, CW_SHUTDOWN, "Ready to switch on")
        self._step(a, CW_SWITCH_ON, "Switched on")
        self._step(a, CW_ENABLE, "Operation enabled")
        return pos

    def _step(self, a: Axis, cw: int, want: str) -> None:
        self._sdo(a, 0x6040, 0, cw, "<H")
        end = time.monotonic() + self.state_timeout
        while True:
            state = drive_state(self._sdo(a, 0x6041, 0, fmt="<H"))
            if state == want:
                return
            if time.monotonic() > end:
                raise DriverError(f"{a.label()}: state machine stuck in {state}, expected "
                                  f"{want} within {self.state_timeout:g} s")
            time.sleep(0.002)

    def _start_master(self, bus: can.BusABC, hold: np.ndarray) -> None:
        assert self.network is not None and self.robot is not None and self._tap is not None
        qdd = np.array([x if math.isfinite(x) else 2.0 for x in self.robot.qdd_max])
        self.master = master = SyncMaster(
            bus, self.axes, self.period, heartbeat_timeout_s=self.hb_timeout,
            max_missed=self.max_missed, overrun_streak=self.overrun_streak,
            standstill_rad_s=self.standstill, decel_rad_s2=0.5 * qdd, on_end=self._job_ended,
            tap=self._tap.on_message_received, send_lock=self.network.send_lock,
            tpdo2=self.tpdo2, priority=self.sync_priority)
        net = self.network
        if self.sync_priority:  # the answers' way in is the motion path too
            assert net.notifier is not None
            net.notifier.add_listener(RealtimeListener(self.sync_priority))
        for i, a in enumerate(self.axes):
            net.subscribe(0x180 + a.node, _frames_of(i, master.on_tpdo1))
            net.subscribe(0x280 + a.node, _frames_of(i, master.on_tpdo2))
            net.subscribe(0x80 + a.node, _frames_of(i, master.on_emcy))
        net.nmt.send_command(NMT_START)
        self._hold.hold()
        master.start(hold)
        log.info("drives %s in Operation enabled (CSP), SYNC every %g ms",
                 list(self.nodes), 1000 * self.period)

    async def _close(self) -> None:
        await asyncio.to_thread(self._shutdown, True)

    def _shutdown(self, ramp: bool) -> None:
        """Moving axes ramp to rest, then every drive is disabled; threads end; bus closes."""
        master, self.master = self.master, None
        if master is not None:
            if ramp:
                master.request_rest(then="disable", reason="daemon stopping")
                master.idle.wait(5.0)
                time.sleep(5 * self.period)  # the shutdown controlword reaches every drive
            master.stop()
        self._hold.release()
        if self._tap is not None:
            self._tap.stop()
            self._tap = None
        if self._writer is not None:
            self._writer.shutdown(wait=True)
            self._writer = None
        net, self.network = self.network, None
        if net is not None:
            try:
                net.disconnect()
            except (can.CanError, OSError) as err:
                log.warning("CAN bus did not close cleanly: %s", err)

    # -- the cycle
    async def _put_program(self, program: MotionProgram) -> None:
        counts, t0 = await asyncio.to_thread(self._render, program)
        self._programs[program.exp_id] = (counts, t0)

    def _render(self, program: MotionProgram) -> tuple[np.ndarray, float]:
        """The trajectory at the SYNC period in counts (the spline the plant also uses),
        checked once more against the limits; it must begin at rest (a step to its first
        velocity within one period's acceleration) and is brought to rest after its end."""
        assert self.robot is not None and self.counts_per_rad is not None
        robot, where = self.robot, f"experiment {program.exp_id}"
        tr = program.trajectory()
        if tr.q.shape[1] != robot.n:
            raise DriverError(f"{where}: program has {tr.q.shape[1]} joints, robot "
                              f"{robot.name} has {robot.n}")
        if tr.t.size < 2 or np.any(np.diff(tr.t) <= 0):
            raise DriverError(f"{where}: program time stamps are not increasing")
        spline = CubicSpline(tr.t, tr.q, axis=0)
        t = np.arange(tr.t[0], tr.t[-1] + 1e-9, self.period)
        q, qd, qdd = spline(t), spline(t, 1), spline(t, 2)
        qdd_cap = np.array([x if math.isfinite(x) else 2.0 for x in robot.qdd_max])
        tail = ramp_to_rest(q[-1], qd[-1], 0.5 * qdd_cap, self.period)
        if len(tail):
            t = np.concatenate([t, t[-1] + self.period * np.arange(1, len(tail) + 1)])
            qd = np.vstack([qd, np.diff(np.vstack([q[-1:], tail]), axis=0) / self.period])
            q, qdd = np.vstack([q, tail]), np.vstack([qdd, np.zeros_like(tail)])
        jump = np.abs(qd[0]) / self.period
        for j in range(robot.n):
            if jump[j] > qdd_cap[j]:
                raise DriverError(f"unsafe program refused: {where}: joint {j + 1} starts "
                                  f"moving at {qd[0, j]:.4g} rad/s; a program must begin at "
                                  "rest")
            self._check_limits(where, j, t, q[:, j], qd[:, j], qdd[:, j])
        counts = np.rint(q * np.array(self.counts_per_rad)).astype(np.int64)
        return counts, float(tr.t[0])

    def _check_limits(self, where: str, j: int, t: np.ndarray, q: np.ndarray,
                      qd: np.ndarray, qdd: np.ndarray) -> None:
        robot = self.robot
        assert robot is not None
        for what, arr, low, high, unit in (
                ("position", q, robot.q_min[j], robot.q_max[j], "rad"),
                ("velocity", qd, -robot.qd_max[j], robot.qd_max[j], "rad/s"),
                ("acceleration", qdd, -robot.qdd_max[j], robot.qdd_max[j], "rad/s²")):
            bad = np.flatnonzero((arr < low - 1e-9) | (arr > high + 1e-9))
            if bad.size:
                k = int(bad[0])
                raise DriverError(f"unsafe program refused: {where}: joint {j + 1} {what} "
                                  f"{arr[k]:.4g} {unit} at t={t[k]:.3f} s outside "
                                  f"[{low:.4g}, {high:.4g}] (at the SYNC period "
                                  f"{1000 * self.period:g} ms)")

    async def _give_ready(self, exp_id: str, nonce: str) -> None:
        if (exp_id, nonce) in self._jobs:
            return  # given already: giving again must not move twice
        master = self.master
        if master is None:
            raise DriverError(f"{self.name}: motion master not running")
        if master.halt_reason is not None:
            raise DriverError(f"experiment {exp_id}: drives are stopped after "
                              f"'{master.halt_reason}'; not moving again until the daemon "
                              "restarts with the cause cleared")
        if exp_id not in self._programs:
            raise DriverError(f"experiment {exp_id}: no program put before give")
        job = await self._job(exp_id, nonce, master)
        if (exp_id, nonce) in self._jobs:
            return
        assert self._tap is not None
        self._tap.begin(self.record_dir / f"{exp_id}.{nonce}.blf")
        try:
            master.submit(job)
        except RuntimeError as err:
            self._tap.end()
            raise DriverError(f"experiment {exp_id}: drives busy or stopped ({err})") from err
        self._jobs[(exp_id, nonce)] = job
        log.info("exp=%s nonce=%s streaming %d setpoints (%d to approach the start)", exp_id,
                 nonce, len(job.targets), job.record_from)

    async def _job(self, exp_id: str, nonce: str, master: SyncMaster) -> Job:
        """The program with a rest-to-rest approach from where the drives are, and the torque
        offsets of the set in use along every setpoint (a table the worker computes)."""
        assert self.robot is not None and self.counts_per_rad is not None
        targets, approach = await asyncio.to_thread(self._targets, exp_id, master)
        pset = self.parameters.in_use if self.parameters is not None else None
        offsets = None
        if pset is not None:
            q = targets / np.array(self.counts_per_rad)
            table = await self.feedforward_table(pset, self.period, q.tolist())
            offsets = torque_offsets(table, [a.rated_torque_nm for a in self.axes])
        return Job(exp_id, nonce, targets, approach, self._programs[exp_id][1], self.period,
                   self.settle_timeout + 0.0, offsets)

    def _targets(self, exp_id: str, master: SyncMaster) -> tuple[np.ndarray, int]:
        """Setpoints in counts (the approach, then the program) and the approach's length."""
        assert self.robot is not None and self.counts_per_rad is not None
        counts = self._programs[exp_id][0]
        cpr = np.array(self.counts_per_rad)
        here = master.hold / cpr
        start = counts[0] / cpr
        far = np.abs(start - here)
        if np.any(far > self.max_approach):
            j = int(np.argmax(far))
            raise DriverError(f"experiment {exp_id}: joint {j + 1} is {far[j]:.3g} rad from "
                              f"the program's start (max_approach_rad {self.max_approach:g}); "
                              "move the robot near the start first")
        cap_v = 0.5 * np.array([x if math.isfinite(x) else 1.0 for x in self.robot.qd_max])
        cap_a = 0.5 * np.array([x if math.isfinite(x) else 2.0 for x in self.robot.qdd_max])
        approach = np.rint(quintic(here, start, cap_v, cap_a, self.period) * cpr)
        return np.vstack([approach.astype(np.int64), counts]), len(approach)

    def _job_ended(self, job: Job) -> None:
        """From the master thread: write the log (or what was captured) off that thread."""
        tap_done = self._tap.end() if self._tap is not None else None
        if self._writer is None:
            job.result.set_exception(DriverError(f"experiment {job.exp_id}: driver closed"))
            return
        self._writer.submit(self._write_log, job, tap_done)

    def _write_log(self, job: Job, tap_done: Future[None] | None) -> None:
        try:
            if tap_done is not None:
                tap_done.result(5.0)
            data = log_bytes(job, self.axes)
            stem = f"{job.exp_id}.{job.nonce}"
            partial = job.error is not None
            path = self.record_dir / (f"{stem}.partial.csv" if partial else f"{stem}.log.csv")
            atomic_write(path, data)
            blf = self.record_dir / f"{stem}.blf"
            if partial and blf.exists():
                os.replace(blf, self.record_dir / f"{stem}.partial.blf")
            job.result.set_result((path, hashlib.sha256(data).hexdigest(), len(data)))
        except Exception as err:  # noqa: BLE001 - the waiter gets it as one line
            job.result.set_exception(DriverError(f"experiment {job.exp_id}: log not written "
                                                 f"({err})"))

    async def _wait_done(self, exp_id: str, nonce: str) -> Done:
        job = self._jobs.get((exp_id, nonce))
        if job is None:
            raise DriverError(f"experiment {exp_id}: nonce {nonce} was not streamed by this "
                              "daemon (restarted mid-experiment: its motion ended with the "
                              "old process and is not repeated)")
        path, sha, size = await self.bridge.wait(job.result)
        if job.error is not None:
            what = "quick stop on every drive" if job.quick_stop else "no quick stop needed"
            code = "" if job.drive_fault is None else await self._error_code(job.drive_fault)
            raise DriverError(f"experiment {exp_id}: {job.error}{code}; {what}; log captured "
                              f"so far kept as {path} ({len(job.rows)} samples, incomplete)")
        if job.missing_rows:
            log.warning("exp=%s %d SYNC periods without every drive's answer (gaps in the log)",
                        exp_id, job.missing_rows)
        return Done(exp_id, nonce, sha, size)

    async def _error_code(self, axis: Axis) -> str:
        """The drive's own error code after its fault: 0x603F read by SDO (an EMCY may be lost
        or never sent), named in words."""
        try:
            code = await asyncio.to_thread(self._sdo, axis, 0x603F, 0, None, "<H")
        except DriverError as err:
            return f", error code 0x603F unreadable ({err})"
        return f", error code 0x603F = {error_words(code)}"

    async def _fetch_logs(self, done: Done) -> bytes:
        path = self.record_dir / f"{done.exp_id}.{done.nonce}.log.csv"
        try:
            return await asyncio.to_thread(path.read_bytes)
        except FileNotFoundError as err:
            raise DriverError(f"{path}: recorded log missing") from err

    async def _upload_parameters(self, doc: Any, body: bytes) -> None:
        """The set becomes this driver's feedforward (the daemon is the motion master, so its
        acknowledgement is the driver's own): checked, saved to ``record_dir``, used from the
        next experiment given on. A refused set leaves the previous one in use."""
        if self.parameters is None:
            raise DriverError(f"{self.name}: not open")
        await asyncio.to_thread(self.parameters.load, body)

    async def _withdraw(self, exp_id: str, nonce: str) -> None:
        job = self._jobs.get((exp_id, nonce))
        master = self.master
        if job is None or master is None or job.ended.is_set():
            return
        master.request_rest(then="hold", reason="withdrawn")
        await asyncio.to_thread(master.idle.wait, 10.0)


def _server(interface: str, host: str | None, port: int | None) -> dict[str, Any]:
    """python-can's socketcand arguments (``host``, ``port``), only with that interface."""
    if interface != "socketcand":
        for key, val in (("host", host), ("port", port)):
            if val is not None:
                raise ConfigError(f"driver.{key}: only for interface socketcand (a socketcand "
                                  f"server), not {interface}")
        return {}
    for key, val in (("host", host), ("port", port)):
        if val is None:
            raise ConfigError(f"driver.{key}: missing (the socketcand server's "
                              f"{'host name or address' if key == 'host' else 'TCP port'})")
    return {"host": host, "port": port, "tcp_tune": True}  # TCP_NODELAY: no Nagle delay


def _frames_of(i: int, handler: Callable[[int, bytes | bytearray], None]
               ) -> Callable[[int, bytearray, float], None]:
    """A canopen subscriber handing drive ``i``'s frames to one of the master's inputs."""
    def cb(can_id: int, data: bytearray, timestamp: float) -> None:
        handler(i, data)
    return cb
