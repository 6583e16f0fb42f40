"""Fake CiA 402 drives on a CAN bus (python-can's virtual bus, served over socketcand on
loopback when the daemon is another process): one ``canopen.LocalNode`` per joint with the
shipped EDS, the power state machine, and TPDOs answering each SYNC from the simulated robot
following the streamed setpoints. Drives that lose the master's SYNC quick-stop by themselves.

The axis follows its targets with a three-SYNC lag (its position loop); velocity and
acceleration come from a seven-point local fit, as a drive's observer would estimate them; the
torque is the plant's (rigid body, friction, …, noise) in per mille of the rated torque.
"""

from __future__ import annotations

import collections
import logging
import math
import os
import struct
import threading
import time
import uuid
from importlib import resources
from pathlib import Path
from typing import Any

import can
import canopen
import numpy as np
from can.interfaces.virtual import VirtualBus

from robid_link.exceptions import RobidError
from robid_link.fakes.canopen.socketcand_server import SocketcandServer
from robid_link.fakes.canopen.tables import (
    COB_EMCY,
    COB_NMT,
    COB_RPDO1,
    COB_SYNC,
    EMCY_HEARTBEAT,
    EMCY_OVER_CURRENT,
    ERROR_REGISTER_COMMUNICATION,
    ERROR_REGISTER_GENERIC,
    MODE_CSP,
    NMT_PRE_OPERATIONAL,
    NMT_RESET_COMMUNICATION,
    NMT_RESET_NODE,
    NMT_START,
    STATUSWORD,
    SYNC_ECHO,
    error_text,
    next_state,
)
from robid_link.fakes.controller import ControllerCore, Peer

__all__ = ["Cia402Peer", "EDS"]

log = logging.getLogger("robid.fake_controller")

EDS = Path(str(resources.files("robid_link.fakes.canopen") / "cia402_drive.eds"))

#: seven-point quadratic fit at the centre: value, first and second derivative weights
_SG_D1 = np.array([-3, -2, -1, 0, 1, 2, 3]) / 28.0
_SG_D2 = np.array([5, 0, -3, -4, -3, 0, 5]) / 42.0
_FAULT_CODE = EMCY_OVER_CURRENT
#: the fake drives' manufacturer object with the torque actual value in mN·m (INTEGER32)
TORQUE_FINE = (0x2101, 0)
#: SYNCs at rest that separate two runs: the master streams the next program (its approach
#: first) about 7 SYNCs after the last one ended
RUN_REST = 5
_MASTER_LOST = EMCY_HEARTBEAT  # here: no SYNC from the master


def _fifo(priority: int, tid: int = 0) -> str | None:
    """SCHED_FIFO at ``priority`` for the calling thread (or the thread ``tid``): None when it
    took, else why not."""
    try:
        os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
    except (OSError, AttributeError) as err:
        return str(err)
    return None


class _DrivesBus(VirtualBus):
    """The drives' end of the virtual bus. Its cyclic senders (the heartbeat producers canopen
    starts per node, a thread each) run under SCHED_FIFO at ``priority`` (0: as started), as
    the drives' SYNC handling does: in the master's process a sender under normal scheduling
    that other processes keep off the CPU while it holds or asks for the GIL stalls the
    master's SYNC thread (8–16 ms measured at load 4 on 2 cores)."""

    def __init__(self, channel: str, priority: int) -> None:
        super().__init__(channel=channel)
        self.priority = priority

    def _send_periodic_internal(self, *args: Any, **kwargs: Any) -> Any:
        task = super()._send_periodic_internal(*args, **kwargs)
        thread = getattr(task, "thread", None)
        if self.priority and thread is not None and thread.native_id is not None:
            why = _fifo(self.priority, thread.native_id)
            if why is not None:
                log.warning("fake drives: SCHED_FIFO %d refused for %s (%s)", self.priority,
                            thread.name, why)
        return task


class _Drive:
    """One drive: OD (LocalNode), controlword → statusword, PDOs as the master mapped them."""

    def __init__(self, node_id: int, joint: int, cpr: float, rated_nm: float) -> None:
        self.id, self.joint, self.cpr, self.rated_nm = node_id, joint, cpr, rated_nm
        self.node = canopen.LocalNode(node_id, str(EDS))
        self.node.add_write_callback(self._on_write)
        self.state, self.cw, self.error = "Switch on disabled", 0, 0
        self.rpdo: tuple[int, list[tuple[int, int, int]]] | None = None
        self.tpdos: list[tuple[int, list[tuple[int, int, int]]]] = []
        self.pending: bytes | None = None
        self.silent = self.frozen = False
        self.drop_until = -1
        self.decel = 1.0  # rad/s², from 0x6085
        self.received: list[tuple[int, int, int]] = []  # per SYNC: k, target, torque offset
        self.quick_stopped: list[float] = []  # wall-clock times of the master's quick stops
        self._put(0x1018, 4, joint, "<I")
        self._put(0x6076, 0, round(rated_nm * 1000 / 1), "<I")  # mN·m of 1000 per mille
        self._status()

    def _put(self, index: int, sub: int, value: int, fmt: str) -> None:
        self.node.data_store.setdefault(index, {})[sub] = struct.pack(fmt, value)

    def _get(self, index: int, sub: int, fmt: str) -> int:
        return int(struct.unpack(fmt, self.node.get_data(index, sub))[0])

    def _status(self) -> None:
        self._put(0x6041, 0, STATUSWORD[self.state], "<H")
        self._put(0x603F, 0, self.error, "<H")

    def _on_write(self, index: int, subindex: int, od: Any, data: bytes) -> None:
        if index == 0x6040:
            self._controlword(struct.unpack("<H", data)[0])
        elif index == 0x6060:
            self._put(0x6061, 0, struct.unpack("<b", data)[0], "<b")

    def _controlword(self, cw: int) -> None:
        prev, self.cw = self.cw, cw
        state = next_state(self.state, cw, prev)
        if state == "Quick stop active" and self.state != state:
            self.quick_stopped.append(time.time())
        if state == "Operation enabled" and self._get(0x6060, 0, "<b") != MODE_CSP:
            state = self.state  # this drive runs only in cyclic synchronous position mode
        if self.state == "Fault" and state != "Fault":
            self.error = 0
        self.state = state
        self._status()

    def fault(self, code: int, emcy: bool = True) -> None:
        self.state, self.error = "Fault", code
        self._status()
        if not self.silent and emcy:
            self.node.network.send_message(COB_EMCY + self.id, struct.pack(
                "<HB5x", code, ERROR_REGISTER_GENERIC))

    def read_maps(self) -> None:
        """The PDO mapping the master wrote by SDO (taken over at NMT start)."""
        def one(comm: int, mapping: int) -> tuple[int, list[tuple[int, int, int]]] | None:
            cob = self._get(comm, 1, "<I")
            if cob & 0x80000000:
                return None
            entries = [self._get(mapping, k, "<I") for k in
                       range(1, self._get(mapping, 0, "<B") + 1)]
            return cob & 0x7FF, [(e >> 16, (e >> 8) & 0xFF, e & 0xFF) for e in entries]
        self.rpdo = one(0x1400, 0x1600)
        self.tpdos = [m for m in (one(0x1800, 0x1A00), one(0x1801, 0x1A01)) if m]
        self.decel = max(self._get(0x6085, 0, "<I") / self.cpr, 1e-3)

    def apply_rpdo(self) -> None:
        """A synchronous RPDO takes effect at the SYNC after it arrived."""
        data, self.pending = self.pending, None
        if data is None or self.rpdo is None:
            return
        at = 0
        for index, sub, bits in self.rpdo[1]:
            self.node.set_data(index, sub, data[at: at + bits // 8])
            at += bits // 8

    def record(self, k: int) -> None:
        """What this SYNC's setpoint was (the torque offset is kept for tests: the fake's
        position loop is ideal, the plant's inverse dynamics, so it needs no feedforward)."""
        if self.state == "Operation enabled":
            self.received.append((k, self._get(0x607A, 0, "<i"), self._get(0x60B2, 0, "<h")))

    def target(self) -> float:
        return self._get(0x607A, 0, "<i") / self.cpr

    def tpdo_frames(self, k: int, twice: bool) -> list[tuple[int, bytes]]:
        """This SYNC's TPDOs as the master mapped them (none when silent or not started)."""
        if self.silent or k < self.drop_until or self.node.nmt.state != "OPERATIONAL":
            return []
        out, store = [], self.node.data_store
        for cob, entries in self.tpdos:  # what _put stored, else the node's (EDS default)
            data = b"".join(store[i][s] if s in store.get(i, ()) else self.node.get_data(i, s)
                            for i, s, _ in entries)
            out += [(cob, data)] * (2 if twice else 1)
        return out


def _clamp(x: float, limit: int) -> int:
    """``x`` rounded into [-limit, limit] (a scalar: np.clip costs microseconds each)."""
    return max(-limit, min(limit, int(round(x))))


class Cia402Peer(Peer):
    """The drives of one robot (node ids 1..n) on a CAN bus, over a ``ControllerCore``.

    Options: ``interface``: ``virtual`` (the daemon in this process) or ``socketcand`` (a
    virtual bus served over socketcand on 127.0.0.1:``port``, 0 = a free one; the default when
    the peer is its own process, ``robid fake-controller``), ``channel`` (default a fresh
    virtual channel), ``sync_period_s`` (default 1/truth.rate_hz, at least 4 ms over
    socketcand), ``sync_timeout_s`` (no SYNC that long while enabled: quick stop),
    ``answer_lag_periods`` (each SYNC's TPDOs go out up to that many periods late, at random
    and in order: a loaded socketcand host or network),
    ``fault_node`` (joint number the faults hit), ``fault_after_s`` (into the motion). A run
    starts with the first moving setpoint after a rest of ``RUN_REST`` SYNCs; the core's fault
    schedule is consumed per run. Faults beyond the core's: ``drive_fault`` (EMCY and 0x603F),
    ``drive_fault_quiet`` (its EMCY is lost: only 0x603F tells), ``no_boot``,
    ``heartbeat_loss``, ``following_error``, ``dropped_frames``, and two a hostile bus plays:
    ``foreign_tpdo`` (the fault node's TPDO1 goes out under the next node's COB-ID too) and
    ``bad_length`` (its TPDO2 one byte short). ``counts_per_rad``: the encoders (2^27 per joint
    turn); ``fine_torque``: the daemon maps the drives' 2101h, the torque in mN·m, instead of
    6077h (per mille of the rated torque); ``rt_priority``: SCHED_FIFO for the drives' threads
    (SYNC handling, heartbeat producers, SYNC supervision; 0: normal scheduling), for a bench of
    a real-time master in the same process (they share its GIL).
    """

    driver = "canopen_drives"
    #: the contract suite runs over the in-process virtual bus and over socketcand on loopback
    contract_variants: tuple[dict[str, Any], ...] = ({}, {"interface": "socketcand"})
    faults = ("drive_fault", "no_boot", "heartbeat_loss", "following_error", "dropped_frames",
              "drive_fault_quiet", "foreign_tpdo", "bad_length")
    unsupported = {
        "never_answer": "the daemon streams every setpoint itself: a drive that does not "
                        "answer is a lost node, stopped within a few SYNCs (a DriverError, not "
                        "a take timeout; see tests/drivers/test_canopen_drives.py)",
        "truncated_log": "the log never travels: the driver records the TPDOs and hashes the "
                         "file it writes; a damaged CAN frame fails the bus CRC and is lost "
                         "(the dropped_frames fault)",
        "corrupt_log": "as truncated_log: a corrupt frame never reaches the driver",
        "stale_semaphore": "PDOs answer the SYNC just sent and carry no experiment or nonce: "
                           "an answer for an older attempt cannot exist on the bus",
        "nan_log": "PDO values are integers (counts, per mille): no NaN on the bus",
    }

    def __init__(self, core: ControllerCore, workdir: Path, *, interface: str | None = None,
                 channel: str | None = None, port: int = 0, sync_period_s: float | None = None,
                 sync_timeout_s: float | None = None, fault_node: int | None = None,
                 fault_after_s: float = 0.2, answer_lag_periods: int = 0,
                 counts_per_rad: float = 2**27 / (2 * math.pi),
                 fine_torque: bool = True, rt_priority: int = 0) -> None:
        super().__init__(core, workdir)
        robot = core.robot
        self.n = robot.n
        # a peer in its own process (exit_on_die: the CLI) must be reachable from another one
        self.interface = interface or ("socketcand" if core.exit_on_die else "virtual")
        if self.interface not in ("virtual", "socketcand"):
            raise RobidError(f"--option interface: expected virtual or socketcand, got "
                             f"{self.interface!r}")
        self.channel = channel or f"robid-cia402-{uuid.uuid4().hex[:8]}"
        self.port = port
        self.server: SocketcandServer | None = None
        floor = 0.004 if self.interface == "socketcand" else 0.001
        self.period = float(sync_period_s or max(floor, 1.0 / core.rate_hz))
        # lenient by default: a loaded test host, and in-process one GIL with the master
        self.sync_timeout = float(sync_timeout_s or (1.0 if self.interface == "socketcand"
                                                     else 2.0))
        self.last_sync = math.inf  # no SYNC yet: nothing to supervise
        self.lock = threading.Lock()  # SYNC handling (notifier) and the supervisor
        self._quit = threading.Event()
        self._watch: threading.Thread | None = None
        self.master_lost = 0  # how many times the drives quick-stopped for a lost master
        # a 20-bit motor encoder behind a 128:1 gear (2^20 per joint turn, the former value,
        # made the plant's accelerations from rounded setpoints noisy by N·m on heavy axes)
        self.cpr = [float(counts_per_rad)] * self.n
        self.fine_torque = fine_torque  # 2101h (INTEGER32, mN·m) mapped, not 6077h
        # drives are hardware on their own clocks; in the daemon's process they share its GIL,
        # so a bench of a real-time master runs their SYNC handling under SCHED_FIFO too
        self.rt_priority, self._rt_threads = int(rt_priority), set[int]()
        #: time.perf_counter() of every SYNC as the drives' handler took it, while keep_times
        self.sync_seen: list[float] = []
        self.keep_times = False
        tau = [float(x) if math.isfinite(x) else 100.0 for x in robot.limits.tau_max]
        self.rated = [t / 3.0 for t in tau]  # peak ≈ 3 × rated, as servo drives are sized
        self.fault_joint = int(fault_node or min(2, self.n))
        self.fault_after = max(1, round(fault_after_s / self.period))
        self.drives = [_Drive(j + 1, j + 1, self.cpr[j], self.rated[j]) for j in range(self.n)]
        self.network: canopen.Network | None = None
        self.hist = np.zeros((7, self.n))
        self.k = 0
        self.idle = 10**9
        self.run_fault: str | None = None
        self.run_start = -1
        self.delay_buf: collections.deque[np.ndarray] = collections.deque(maxlen=1)
        self.rng = np.random.default_rng(core.seed)
        self.hostile: str | None = None  # foreign_tpdo, bad_length: from the fault on
        self.answer_lag = int(answer_lag_periods)
        self.lag_rng = np.random.default_rng(core.seed + 1)  # apart: the noise stays the same
        self.outbox: collections.deque[tuple[int, int, bytes]] = collections.deque()
        delay = sum(float(e["seconds"]) for e in core.plant.truth.effects
                    if e["name"] == "delay")
        self.delay_buf = collections.deque(maxlen=max(1, round(delay / self.period) + 1))

    def driver_options(self) -> dict[str, Any]:
        bus: dict[str, Any] = {"interface": self.interface, "channel": self.channel}
        if self.server is not None:
            bus.update(channel="can0", host="127.0.0.1", port=self.server.port)
        return {"name": "canopen_drives", **bus, "bitrate": 1_000_000,
                "nodes": [d.id for d in self.drives],
                "sync_period_s": self.period, "counts_per_rad": self.cpr,
                "rated_torque_nm": self.rated, "eds": str(EDS),
                **({"torque_object": f"0x{TORQUE_FINE[0]:04X}:{TORQUE_FINE[1]}",
                    "torque_unit_nm": [0.001] * self.n} if self.fine_torque else {}),
                "record_dir": str(self.workdir / "records"),
                # lenient supervision: the fake drives and the master share one Python
                # process (GIL) on what may be a loaded test machine
                "heartbeat_timeout_s": 2.0, "max_missed": 200, "overrun_streak": 100000,
                "following_error_rad": 0.3,
                # the fake axes start at zero, wherever a program begins
                "max_approach_rad": 2 * math.pi}

    def start(self) -> None:
        if self.network is not None:
            return
        self.network = net = canopen.Network(_DrivesBus(self.channel, self.rt_priority))
        for d in self.drives:
            if self.core.fault == "no_boot" and d.joint == self.fault_joint:
                continue  # never boots: absent from the bus
            net[d.id] = d.node
            net.subscribe(COB_RPDO1 + d.id, self._rpdo_cb(d))
        net.subscribe(COB_NMT, self._on_nmt)
        net.subscribe(COB_SYNC, self._on_sync)
        net.connect()
        for d in self.drives:
            if d.node.has_network():
                self._boot(d)
        if self.interface == "socketcand":
            self.server = SocketcandServer(can.Bus(interface="virtual", channel=self.channel),
                                           "can0", self.port)
            self.server.start()
        self._quit.clear()
        self._watch = threading.Thread(target=self._watch_loop, name="cia402-sync-watch",
                                       daemon=True)
        self._watch.start()

    def _boot(self, d: _Drive) -> None:
        d.node.nmt.send_command(NMT_RESET_COMMUNICATION)  # boot-up message
        d.node.nmt.send_command(NMT_PRE_OPERATIONAL)  # heartbeat producer starts (0x1017)

    def stop(self) -> None:
        self._quit.set()
        if self._watch is not None:
            self._watch.join(5.0)
            self._watch = None
        server, self.server = self.server, None
        if server is not None:
            server.stop()
            server.bus.shutdown()
        net, self.network = self.network, None
        if net is not None:
            for d in self.drives:
                d.node.nmt.stop_heartbeat()
            net.disconnect()

    def _rpdo_cb(self, d: _Drive) -> Any:
        def cb(can_id: int, data: bytearray, timestamp: float) -> None:
            if d.state != "Fault" and not d.silent:
                d.pending = bytes(data)
        return cb

    def _on_nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        cmd, target = data[0], data[1]
        for d in self.drives:
            if target not in (0, d.id) or not d.node.has_network() or d.silent:
                continue
            if cmd in (NMT_RESET_COMMUNICATION, NMT_RESET_NODE):
                self._boot(d)
            elif cmd == NMT_START:
                d.read_maps()

    # -- one SYNC: setpoints take effect, the robot moves, the drives report
    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if self.keep_times:
            self.sync_seen.append(time.perf_counter())
        if self.rt_priority and threading.get_ident() not in self._rt_threads:
            self._rt_threads.add(threading.get_ident())
            why = _fifo(self.rt_priority)
            if why is not None:
                log.warning("fake drives: SCHED_FIFO %d refused (%s)", self.rt_priority, why)
        try:
            with self.lock:
                self.last_sync = time.monotonic()
                self._sync(counter=data[0] if data else 0)
        except Exception:  # a bug in the fake must show, not kill the notifier quietly
            log.exception("fake drives: SYNC handling failed")
            raise

    def _sync(self, send: bool = True, counter: int = 0) -> None:
        self.k += 1
        for d in self.drives:
            d.apply_rpdo()
            d.record(self.k)
        cmd = self._commands()
        self._runs(cmd)
        self.hist = np.vstack([self.hist[1:], cmd])
        q = self.hist[3]
        qd = _SG_D1 @ self.hist / self.period
        qdd = _SG_D2 @ self.hist / self.period**2
        tau = self._torque(q, qd, qdd)
        twice = self.run_fault == "answer_twice" and self.run_start >= 0
        due = self.k + (int(self.lag_rng.integers(0, self.answer_lag + 1)) if self.answer_lag
                        else 0)
        due = max(due, self.outbox[-1][0] if self.outbox else 0)  # frames keep their order
        for j, d in enumerate(self.drives):
            d._put(0x6064, 0, int(round(q[j] * d.cpr)), "<i")
            d._put(0x606C, 0, int(round(qd[j] * d.cpr)), "<i")
            d._put(0x6077, 0, _clamp(tau[j] / d.rated_nm * 1000, 32767), "<h")
            d._put(*TORQUE_FINE, _clamp(tau[j] * 1000, 2**31 - 1), "<i")
            d._put(*SYNC_ECHO, counter, "<B")  # the SYNC these values were latched at
            if send:
                self.outbox.extend((due, cob, data) for cob, data in self._frames(d, twice))
        while self.outbox and self.outbox[0][0] <= self.k and self.network is not None:
            _, cob, data = self.outbox.popleft()
            self.network.send_message(cob, data)

    def _frames(self, d: _Drive, twice: bool) -> list[tuple[int, bytes]]:
        """The drive's TPDOs of this SYNC, as a hostile bus delivers them after the fault."""
        frames = d.tpdo_frames(self.k, twice)
        if self.hostile is None or d.joint != self.fault_joint or not frames:
            return frames
        if self.hostile == "bad_length":
            return [frames[0]] + [(cob, data[:-1]) for cob, data in frames[1:]]
        other = self.drives[self.fault_joint % self.n]  # the next node's COB-ID
        cob, data = frames[0]
        return [*frames, (cob - d.id + other.id, data)]

    # -- the master lost: what a drive's SYNC supervision does
    def _watch_loop(self) -> None:
        if self.rt_priority:  # it takes the GIL every 50 ms: as the SYNC handling (_DrivesBus)
            _fifo(self.rt_priority)
        while not self._quit.wait(min(0.05, self.sync_timeout / 4)):
            with self.lock:
                silent = time.monotonic() - self.last_sync
                enabled = [d for d in self.drives if d.state == "Operation enabled"]
                if silent <= self.sync_timeout or not enabled:
                    continue
                self.last_sync = math.inf
                self.master_lost += 1
                log.warning("fake drives: no SYNC from the master for %.3g s: quick stop on "
                            "nodes %s (%s)", silent, [d.id for d in enabled],
                            error_text(_MASTER_LOST))
                for d in enabled:
                    d.state = "Quick stop active"
                    d._status()
                    if not d.silent:
                        register = ERROR_REGISTER_GENERIC | ERROR_REGISTER_COMMUNICATION
                        d.node.network.send_message(COB_EMCY + d.id, struct.pack(
                            "<HB5x", _MASTER_LOST, register))
            self._brake()

    def _brake(self) -> None:
        """The quick-stop ramp on the drives' own clock (no SYNC comes to pace it)."""
        v0 = np.abs(self.hist[-1] - self.hist[-2]) / self.period
        for _ in range(100_000):
            with self.lock:
                if not any(d.state == "Quick stop active" for d in self.drives):
                    break
                self._sync(send=False)
            if self._quit.wait(self.period):
                return
        log.warning("fake drives: at rest after the quick stop (from %s rad/s), now %s",
                    np.array2string(v0, precision=3), sorted(set(self.states().values())))

    def _commands(self) -> np.ndarray:
        last, prev = self.hist[-1], self.hist[-2]
        cmd = last.copy()
        for j, d in enumerate(self.drives):
            if d.frozen:
                continue
            if d.state == "Operation enabled":
                cmd[j] = d.target()
            elif d.state == "Quick stop active":  # brake on the quick stop ramp
                v = (last[j] - prev[j]) / self.period
                v = math.copysign(max(abs(v) - d.decel * self.period, 0.0), v)
                cmd[j] = last[j] + v * self.period
                if v == 0.0:
                    d.state = "Switch on disabled"
                    d._status()
        return cmd

    def _torque(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
        plant = self.core.plant
        t = np.array([self.k * self.period])
        rigid = plant.rigid_torque(q[None], qd[None], qdd[None])
        true = (rigid + plant.effect_torque(t, q[None], qd[None], qdd[None], rigid))[0]
        self.delay_buf.append(true)
        noise = np.broadcast_to(np.asarray(plant.truth.noise_tau, dtype=float), (self.n,))
        return self.delay_buf[0] + self.rng.normal(size=self.n) * noise

    # -- runs and faults
    def _runs(self, cmd: np.ndarray) -> None:
        moving = bool(np.any(cmd != self.hist[-1]))
        if moving and self.idle >= RUN_REST:
            self.run_fault = self.core.take_fault()
            self.run_start = self.k
            self.core.handled.append(("motion", str(self.k)))
            log.info("fake drives: motion %d starts%s", len(self.core.handled),
                     f" (fault {self.run_fault})" if self.run_fault else "")
        self.idle = 0 if moving else self.idle + 1
        if self.run_fault and self.k - self.run_start == self.fault_after:
            self._inject(self.run_fault)

    def _inject(self, fault: str) -> None:
        d = self.drives[self.fault_joint - 1]
        log.info("fake drives: injecting %s on node %d", fault, d.id)
        if fault in ("fail", "drive_fault", "drive_fault_quiet"):
            d.fault(_FAULT_CODE, emcy=fault != "drive_fault_quiet")
            log.info("node %d: %s", d.id, error_text(_FAULT_CODE))
        elif fault in ("foreign_tpdo", "bad_length"):
            self.hostile = fault
        elif fault == "heartbeat_loss":
            d.node.nmt.stop_heartbeat()
        elif fault == "following_error":
            d.frozen = True
        elif fault == "dropped_frames":
            d.drop_until = self.k + 100
        elif fault == "die":
            for other in self.drives:
                other.silent = True
                other.node.nmt.stop_heartbeat()
            self.died.set()
            self.core.die()

    def quick_stops(self) -> list[float]:
        """When the master's quick stop reached each drive that obeyed one (tests)."""
        return sorted(t for d in self.drives for t in d.quick_stopped)

    def states(self) -> dict[int, str]:
        """Each node's power state (tests)."""
        return {d.id: d.state for d in self.drives}

    def velocity(self) -> np.ndarray:
        """The axes' last velocity in rad/s (tests)."""
        with self.lock:
            return (self.hist[-1] - self.hist[-2]) / self.period

