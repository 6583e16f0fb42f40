"""The protocol-neutral fake controller: a motion program run on the simulated robot gives the
log a real cell would record, and the faults a real cell produces are chosen here. Protocol
peers (``file_share_peer.py``, …) carry programs, answers and logs over their protocol and are
found by driver name (``robid_link.link.registry.peer_class``)."""

from __future__ import annotations

import abc
import io
import json
import logging
import os
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Self

import numpy as np
import yaml

from robid_link.exceptions import RobidError
from robid_link.fakes.plant import Plant, Truth
from robid_link.ident.excite.excitation import Trajectory, trajectory_states
from robid_link.ident.model.robot import Robot
from robid_link.jobs import MotionProgram

__all__ = ["FAULTS", "ControllerCore", "Peer", "RunResult", "default_truth", "log_csv",
           "logged_torques", "make_peer"]

log = logging.getLogger("robid.fake_controller")

#: faults every peer plays in its own protocol: no answer, the controller dies mid-program, a
#: log cut short or with a flipped byte (the announced checksum is the true log's), two answers
#: to one program, an answer to an attempt that no longer exists, NaN in the log, a controller
#: that reports failure, a controller that never acknowledges an uploaded parameter set
FAULTS = ("never_answer", "die", "truncated_log", "corrupt_log", "answer_twice",
          "stale_semaphore", "nan_log", "fail", "no_param_ack")


def log_csv(t: np.ndarray, q: np.ndarray, tau: np.ndarray,
            torques: list[int] | None = None) -> bytes:
    """A log in the project's CSV format (``t,q1..qn,tau1..taun``); ``torques`` (joints from
    1): only those torque channels, as a controller with a signal budget logs them."""
    n = q.shape[1]
    keep = list(range(1, n + 1)) if torques is None else torques
    buf = io.StringIO()
    header = ",".join(["t"] + [f"q{j}" for j in range(1, n + 1)] + [f"tau{j}" for j in keep])
    np.savetxt(buf, np.hstack([t[:, None], q, tau[:, [j - 1 for j in keep]]]), delimiter=",",
               header=header, comments="", fmt="%.10g")
    return buf.getvalue().encode()


def logged_torques(header: dict[str, Any], n: int) -> list[int] | None:
    """The program's ``log_torques`` (joints from 1 whose torque to log), checked."""
    js = header.get("log_torques")
    if js is None:
        return None
    if not isinstance(js, list) or not js or not all(
            isinstance(j, int) and not isinstance(j, bool) and 1 <= j <= n for j in js) \
            or sorted(set(js)) != js:
        raise RobidError(f"log_torques: expected ascending joint numbers 1..{n}, got {js!r}")
    return js


@dataclass(frozen=True)
class RunResult:
    """One program's outcome on the fake controller: the true log (and its checksum) and the
    bytes the controller side will deliver (damaged for the log faults), or a failure."""

    exp_id: str
    nonce: str
    fault: str | None
    log: bytes = b""
    delivered: bytes = b""
    error: str | None = None

    @property
    def sha256(self) -> str:
        import hashlib

        return hashlib.sha256(self.log).hexdigest()


class ControllerCore:
    """Program → plant → log, and the fault schedule: ``fault`` hits the first
    ``fault_count`` programs. Thread-safe; one instance serves one peer."""

    def __init__(self, robot: Robot, truth: Truth, *, fault: str | None = None,
                 fault_count: int = 1, seed: int = 0, exit_on_die: bool = False,
                 extra_faults: tuple[str, ...] = ()) -> None:
        known = FAULTS + tuple(extra_faults)
        if fault is not None and fault not in known:
            raise RobidError(f"--fault: expected one of {', '.join(known)}, got {fault!r}")
        self.robot, self.plant = robot, Plant(robot, truth)
        self.rate_hz = truth.rate_hz
        self.fault, self.faults_left = fault, fault_count if fault else 0
        self.seed, self.exit_on_die = seed, exit_on_die
        self.handled: list[tuple[str, str]] = []
        self.parameters: list[dict[str, Any]] = []  # every set loaded, in order
        self.feedforward: Any = None  # the loaded set's feedforward (None: a-priori model)
        self._lock = threading.Lock()

    def take_fault(self) -> str | None:
        """The fault for the next program (consumes one of ``fault_count``)."""
        with self._lock:
            if self.faults_left > 0:
                self.faults_left -= 1
                return self.fault
            return None

    def trajectory(self, csv: bytes, header: bytes | None = None) -> Trajectory:
        """A program's neutral trajectory files as the plant's Trajectory."""
        prog = MotionProgram("p", {"traj.csv": csv, "traj.yaml": header or b"rate_hz: 0\n"},
                             0.0)
        if header is None:  # rate from the time stamps
            arr = np.loadtxt(io.BytesIO(csv), delimiter=",", skiprows=1, ndmin=2)
            rate = 1.0 / float(np.median(np.diff(arr[:, 0])))
            prog = MotionProgram("p", {"traj.csv": csv, "traj.yaml": yaml.safe_dump(
                {"rate_hz": rate, "kind": "custom"}).encode()}, 0.0)
        tr = prog.trajectory()
        return Trajectory(tr.t, tr.q, tr.rate_hz, tr.kind, tr.robot, dict(tr.header))

    def simulate(self, traj: Trajectory, seed: int) -> bytes:
        if traj.q.shape[1] != self.robot.n:
            raise RobidError(f"program has {traj.q.shape[1]} joints, robot has {self.robot.n}")
        torques = logged_torques(traj.header, self.robot.n)
        t, q, qd, qdd = trajectory_states(traj, self.rate_hz)
        out = self.plant.run(t, q, qd, qdd, seed=seed, feedforward=self.feedforward)
        return log_csv(out["t"], out["q"], out["tau"], torques)

    def run(self, exp_id: str, nonce: str, csv: bytes, header: bytes | None = None
            ) -> RunResult:
        """Run one program: the plant's log, damaged as the fault schedule says. ``die`` and
        ``never_answer`` are the peer's to play (it stops talking); ``fail`` and an unreadable
        program come back as ``error``."""
        fault = None if self.fault == "no_param_ack" else self.take_fault()
        with self._lock:
            seed = self.seed + len(self.handled)
            self.handled.append((exp_id, nonce))
        log.info("exp=%s nonce=%s running%s", exp_id, nonce, f" (fault {fault})" if fault else "")
        if fault == "fail":
            return RunResult(exp_id, nonce, fault, error="motion supervision triggered")
        if fault == "never_answer":
            return RunResult(exp_id, nonce, fault)
        try:
            data = self.simulate(self.trajectory(csv, header), seed)
        except RobidError as err:
            return RunResult(exp_id, nonce, fault, error=f"program {exp_id}: {err}")
        if fault == "nan_log":  # the controller logged NaN: its checksum is consistent
            lines = data.split(b"\n")
            cells = lines[len(lines) // 2].split(b",")
            cells[1] = b"nan"
            lines[len(lines) // 2] = b",".join(cells)
            data = b"\n".join(lines)
        delivered = data
        if fault == "truncated_log":
            delivered = data[: len(data) // 2]
        elif fault == "corrupt_log":
            bad = bytearray(data)
            bad[len(bad) // 2] ^= 0x01
            delivered = bytes(bad)
        return RunResult(exp_id, nonce, fault, data, delivered)

    def die(self) -> None:
        """The controller process dies (``die`` fault) where the peer runs as a process."""
        log.info("controller dies mid-program")
        if self.exit_on_die:
            os._exit(70)

    def receive_parameters(self, body: bytes) -> None:
        """Load an uploaded parameter set: from now on the closed loop's feedforward uses it
        (like a controller that loads new dynamic parameters). A set that does not fit this
        robot raises RobidError and the previous set stays in use."""
        from robid_link.ident.fit.paramset import feedforward

        try:
            doc = json.loads(body)
        except ValueError as err:
            raise RobidError(f"parameter set: not JSON ({err})") from err
        ff = feedforward(doc, self.robot.n)
        with self._lock:
            self.parameters.append(doc)
            self.feedforward = ff
        log.info("parameter set %s loaded", ff.sha256[:12])


class Peer(abc.ABC):
    """The controller side of one protocol over a ``ControllerCore``. ``start`` serves in the
    background, ``stop`` is safe twice, ``driver_options`` is the ``driver:`` mapping of a
    daemon config that reaches this peer. Peers are context managers."""

    driver: ClassVar[str] = ""
    #: protocol-specific faults on top of the core's FAULTS
    faults: ClassVar[tuple[str, ...]] = ()
    #: core faults this protocol cannot express → why (the contract suite skips them, saying so)
    unsupported: ClassVar[dict[str, str]] = {}

    def __init__(self, core: ControllerCore, workdir: Path, **options: Any) -> None:
        self.core, self.workdir = core, Path(workdir)
        self.died = threading.Event()

    @abc.abstractmethod
    def start(self) -> None: ...

    @abc.abstractmethod
    def stop(self) -> None: ...

    @abc.abstractmethod
    def driver_options(self) -> dict[str, Any]: ...

    def wait(self, stop: threading.Event) -> None:
        """Block until ``stop`` is set or the peer died (the CLI's foreground loop)."""
        while not stop.is_set() and not self.died.is_set():
            stop.wait(0.2)

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def make_peer(driver: str, robot: Robot, truth: Truth, workdir: str | Path, *,
              fault: str | None = None, fault_count: int = 1, seed: int = 0,
              exit_on_die: bool = False, **options: Any) -> Peer:
    """The fake controller for ``driver``'s protocol (not started)."""
    from robid_link.link.registry import peer_class

    cls = peer_class(driver)
    core = ControllerCore(robot, truth, fault=fault, fault_count=fault_count, seed=seed,
                          exit_on_die=exit_on_die, extra_faults=cls.faults)
    return cls(core, Path(workdir), **options)


def default_truth(robot: Robot, rate_hz: float = 1000.0) -> Truth:
    """The robot's nominal inertials with viscous and Coulomb friction and torque noise."""
    if robot.nominal is None:
        raise RobidError(f"{robot.name}: no nominal inertials; give the fake controller a "
                         "--truth file")
    return Truth(inertials=robot.nominal.copy(),
                 effects=({"name": "viscous", "fv": 2.0}, {"name": "coulomb", "fc": 1.5}),
                 noise_tau=0.2, q_resolution=2 * np.pi / 2**20, rate_hz=rate_hz)
