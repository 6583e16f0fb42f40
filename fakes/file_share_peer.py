"""The controller side of the file-share protocol (DESIGN.md): every new
``sem/<id>.<nonce>.ready`` is run on the fake controller, the log written atomically to
``outbox/``, then ``sem/<id>.<nonce>.done`` (SHA-256 and size) or ``.failed`` (the reason)."""

from __future__ import annotations

import hashlib
import logging
import os
import threading
import time
from pathlib import Path
from typing import Any

from robid_link.atomic import atomic_write
from robid_link.drivers.file_share import done_text, log_name, parse_sem, sem_name
from robid_link.exceptions import RobidError
from robid_link.fakes.controller import ControllerCore, Peer

__all__ = ["FileSharePeer"]

log = logging.getLogger("robid.fake_controller")


class FileSharePeer(Peer):
    """Serve the share ``workdir`` from a thread (``start``/``stop``) or the caller's thread
    (``serve``). ``die`` leaves half a log in a temp file and stops serving."""

    driver = "file_share"

    def __init__(self, core: ControllerCore, workdir: Path, *, poll_s: float = 0.005) -> None:
        super().__init__(core, workdir)
        self.share, self.poll_s = Path(workdir), poll_s
        self._seen: set[tuple[str, str]] = set()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        for d in ("inbox", "outbox", "sem"):
            (self.share / d).mkdir(parents=True, exist_ok=True)

    @property
    def handled(self) -> list[tuple[str, str]]:
        return self.core.handled

    def driver_options(self) -> dict[str, Any]:
        return {"name": "file_share", "share": str(self.share)}

    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self.serve, args=(self._stop,),
                                            name="fake-controller", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(10)

    def serve(self, stop: threading.Event | None = None, max_programs: int | None = None
              ) -> None:
        stop = stop or threading.Event()
        while not stop.is_set():
            for exp_id, nonce in self._new_readies():
                if not self._handle(exp_id, nonce):
                    self.died.set()
                    return
                if max_programs is not None and len(self.handled) >= max_programs:
                    return
            stop.wait(self.poll_s)

    def _new_readies(self) -> list[tuple[str, str]]:
        names = set(os.listdir(self.share / "sem"))
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

    def _load_parameters(self, exp_id: str, nonce: str) -> None:
        """An uploaded parameter set: load it and acknowledge with its file's SHA-256."""
        sem = self.share / "sem"
        if self.core.fault == "no_param_ack" and self.core.take_fault():
            return
        try:
            body = (self.share / "params" / f"{exp_id}.{nonce}.json").read_bytes()
            self.core.receive_parameters(body)
        except (OSError, RobidError) as err:
            atomic_write(sem / sem_name(exp_id, nonce, "failed"), f"{err}\n".encode())
            return
        atomic_write(sem / sem_name(exp_id, nonce, "done"),
                     done_text(hashlib.sha256(body).hexdigest(), len(body)))

    def _handle(self, exp_id: str, nonce: str) -> bool:
        self._seen.add((exp_id, nonce))
        if exp_id.startswith("params-"):
            self._load_parameters(exp_id, nonce)
            return True
        sem, outbox, inbox = self.share / "sem", self.share / "outbox", self.share / "inbox"
        try:
            csv = (inbox / f"{exp_id}.traj.csv").read_bytes()
            header = (inbox / f"{exp_id}.traj.yaml").read_bytes()
        except OSError as err:
            atomic_write(sem / sem_name(exp_id, nonce, "failed"),
                         f"program {exp_id}: {err.strerror}\n".encode())
            return True
        res = self.core.run(exp_id, nonce, csv, header)
        if res.fault == "never_answer":
            return True
        if res.error is not None:
            atomic_write(sem / sem_name(exp_id, nonce, "failed"), f"{res.error}\n".encode())
            return True
        if res.fault == "die":  # half a log in a temp file, no rename, no 'done'
            (outbox / f".{log_name(exp_id, nonce)}.partial").write_bytes(res.log[: len(res.log)
                                                                                 // 2])
            self.core.die()
            return False
        atomic_write(outbox / log_name(exp_id, nonce), res.delivered)
        if res.fault == "stale_semaphore":  # an answer to an attempt that no longer exists
            atomic_write(sem / sem_name(exp_id, "0stale0", "done"), done_text("0" * 64, 1))
        done = done_text(res.sha256, len(res.log))
        atomic_write(sem / sem_name(exp_id, nonce, "done"), done)
        if res.fault == "answer_twice":
            time.sleep(0.05)
            atomic_write(sem / sem_name(exp_id, nonce, "done"), done)
        return True
