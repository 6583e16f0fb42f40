"""The controller side of the file-share protocol over the simulated robot, with the faults a
real cell produces: never answering, dying mid-program, truncated or corrupt logs (the 'done'
checksum must catch them), answering twice, stale semaphores, logs with NaN."""

from __future__ import annotations

import hashlib
import io
import logging
import os
import threading
import time
from pathlib import Path

import numpy as np
from robid_link.drivers.file_share import done_text, log_name, parse_sem, sem_name
from robid_link.fakes.plant import Plant, Truth

from robid_link.exceptions import RobidError
from robid_link.ident.excitation import read_trajectory, trajectory_states
from robid_link.ident.robot import Robot
from robid_link.link.atomic import atomic_write

__all__ = ["FAULTS", "FileShareController", "default_truth"]

log = logging.getLogger("robid.fake_controller")

FAULTS = ("never_answer", "die", "truncated_log", "corrupt_log", "answer_twice",
          "stale_semaphore", "nan_log", "fail")


class FileShareController:
    """Serve ``share``: run every new ``sem/<id>.<nonce>.ready`` on the plant, write
    ``outbox/<id>.<nonce>.log.csv`` atomically, then ``sem/<id>.<nonce>.done`` (SHA-256 and
    size). ``fault`` hits the first ``fault_count`` programs; ``die`` ends ``serve`` (and the
    process, with ``exit_on_die``) half-way through writing the log."""

    def __init__(self, share: str | Path, robot: Robot, truth: Truth, *,
                 fault: str | None = None, fault_count: int = 1, poll_s: float = 0.005,
                 seed: int = 0, exit_on_die: bool = False) -> None:
        if fault is not None and fault not in FAULTS:
            raise RobidError(f"--fault: expected one of {', '.join(FAULTS)}, got {fault!r}")
        self.share = Path(share)
        self.robot, self.plant = robot, Plant(robot, truth)
        self.rate_hz = truth.rate_hz
        self.fault, self.faults_left = fault, fault_count if fault else 0
        self.poll_s, self.seed, self.exit_on_die = poll_s, seed, exit_on_die
        self.handled: list[tuple[str, str]] = []
        self._seen: set[tuple[str, str]] = set()
        for d in ("inbox", "outbox", "sem"):
            (self.share / d).mkdir(parents=True, exist_ok=True)

    def serve(self, stop: threading.Event | None = None, max_programs: int | None = None) -> None:
        stop = stop or threading.Event()
        while not stop.is_set():
            for exp_id, nonce in self._new_readies():
                if not self._handle(exp_id, nonce):
                    return  # died
                if max_programs is not None and len(self.handled) >= max_programs:
                    return
            stop.wait(self.poll_s)

    def _new_readies(self) -> list[tuple[str, str]]:
        sem = self.share / "sem"
        names = set(os.listdir(sem))
        out = []
        for name in sorted(names):
            p = parse_sem(name)
            if p is None or p[2] != "ready" or (p[0], p[1]) in self._seen:
                continue
            if sem_name(p[0], p[1], "done") in names or sem_name(p[0], p[1], "failed") in names:
                self._seen.add((p[0], p[1]))  # answered before a restart
                continue
            out.append((p[0], p[1]))
        return out

    def _log_bytes(self, exp_id: str, seed: int) -> bytes:
        traj = read_trajectory(self.share / "inbox" / f"{exp_id}.traj.csv")
        if traj.q.shape[1] != self.robot.n:
            raise RobidError(f"program {exp_id}: {traj.q.shape[1]} joints, robot has "
                             f"{self.robot.n}")
        t, q, qd, qdd = trajectory_states(traj, self.rate_hz)
        out = self.plant.run(t, q, qd, qdd, seed=seed)
        q_log, tau = out["q"], out["tau"]
        buf = io.StringIO()
        n = self.robot.n
        header = ",".join(["t"] + [f"q{j}" for j in range(1, n + 1)]
                          + [f"tau{j}" for j in range(1, n + 1)])
        np.savetxt(buf, np.hstack([out["t"][:, None], q_log, tau]), delimiter=",",
                   header=header, comments="", fmt="%.10g")
        return buf.getvalue().encode()

    def _handle(self, exp_id: str, nonce: str) -> bool:
        self._seen.add((exp_id, nonce))
        sem, outbox = self.share / "sem", self.share / "outbox"
        fault = None
        if self.faults_left > 0:
            fault, self.faults_left = self.fault, self.faults_left - 1
        log.info("exp=%s nonce=%s running%s", exp_id, nonce, f" (fault {fault})" if fault else "")
        if fault == "never_answer":
            self.handled.append((exp_id, nonce))
            return True
        if fault == "fail":
            atomic_write(sem / sem_name(exp_id, nonce, "failed"), b"motion supervision triggered\n")
            self.handled.append((exp_id, nonce))
            return True
        try:
            data = self._log_bytes(exp_id, self.seed + len(self.handled))
        except RobidError as err:
            atomic_write(sem / sem_name(exp_id, nonce, "failed"), f"{err}\n".encode())
            self.handled.append((exp_id, nonce))
            return True
        if fault == "nan_log":
            lines = data.split(b"\n")
            cells = lines[len(lines) // 2].split(b",")
            cells[1] = b"nan"
            lines[len(lines) // 2] = b",".join(cells)
            data = b"\n".join(lines)
        sha = hashlib.sha256(data).hexdigest()
        log_path = outbox / log_name(exp_id, nonce)
        if fault == "die":  # half a log in a temp file, no rename, no 'done'
            (outbox / f".{log_name(exp_id, nonce)}.partial").write_bytes(data[: len(data) // 2])
            log.info("exp=%s nonce=%s controller dies mid-program", exp_id, nonce)
            if self.exit_on_die:
                os._exit(70)
            return False
        if fault == "truncated_log":
            atomic_write(log_path, data[: len(data) // 2])
        elif fault == "corrupt_log":
            bad = bytearray(data)
            bad[len(bad) // 2] ^= 0x01
            atomic_write(log_path, bytes(bad))
        else:
            atomic_write(log_path, data)
        if fault == "stale_semaphore":  # an answer to an attempt that no longer exists
            atomic_write(sem / sem_name(exp_id, "0stale0", "done"), done_text("0" * 64, 1))
        done = done_text(sha, len(data))
        atomic_write(sem / sem_name(exp_id, nonce, "done"), done)
        if fault == "answer_twice":
            time.sleep(0.05)
            atomic_write(sem / sem_name(exp_id, nonce, "done"), done)
        self.handled.append((exp_id, nonce))
        return True


def default_truth(robot: Robot, rate_hz: float = 1000.0) -> Truth:
    """The robot's nominal inertials with viscous and Coulomb friction and torque noise."""
    if robot.nominal is None:
        raise RobidError(f"{robot.name}: no nominal inertials; give the fake controller a "
                         "--truth file")
    return Truth(inertials=robot.nominal.copy(),
                 effects=({"name": "viscous", "fv": 2.0}, {"name": "coulomb", "fc": 1.5}),
                 noise_tau=0.2, q_resolution=2 * np.pi / 2**20, rate_hz=rate_hz)
