"""The controller side of the file-share protocol (``docs/file_share_protocol.md``): every new
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

from robid_link.exceptions import RobidError
from robid_link.fakes.controller import ControllerCore, Peer
from robid_link.fakes.share_protocol import PARAMS_PREFIX, Share, parse_semaphore

__all__ = ["FileSharePeer"]

log = logging.getLogger("robid.fake_controller")


class FileSharePeer(Peer):
    """Serve the share ``workdir`` from a thread (``start``/``stop``) or the caller's thread
    (``serve``). ``die`` leaves half a log in a temp file and stops serving."""

    driver = "file_share"

    def __init__(self, core: ControllerCore, workdir: Path, *, poll_s: float = 0.005) -> None:
        super().__init__(core, workdir)
        self.share, self.poll_s = Path(workdir), poll_s
        self.files = Share(self.share)
        self._seen: set[tuple[str, str]] = set()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.files.make()

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
        """Readies not answered yet, in name order (page: "The controller", 1)."""
        names = set(os.listdir(self.files.sem))
        out = []
        for name in sorted(names):
            p = parse_semaphore(name)
            if p is None or p[2] != "ready" or (p[0], p[1]) in self._seen:
                continue
            if f"{p[0]}.{p[1]}.done" in names or f"{p[0]}.{p[1]}.failed" in names:
                self._seen.add((p[0], p[1]))  # answered before a restart
                continue
            out.append((p[0], p[1]))
        return out

    def _load_parameters(self, key: str, nonce: str) -> None:
        """An uploaded parameter set: load it and acknowledge with its file's SHA-256."""
        if self.core.fault == "no_param_ack" and self.core.take_fault():
            return
        try:
            body = self.files.parameter_set(key, nonce)
            self.core.receive_parameters(body)
        except (OSError, RobidError) as err:
            self.files.answer_failed(key, nonce, str(err))
            return
        self.files.answer_done(key, nonce, hashlib.sha256(body).hexdigest(), len(body))

    def _handle(self, exp_id: str, nonce: str) -> bool:
        self._seen.add((exp_id, nonce))
        if exp_id.startswith(PARAMS_PREFIX):
            self._load_parameters(exp_id, nonce)
            return True
        if not self.files.semaphore(exp_id, nonce, "ready").exists():
            return True  # withdrawn before it started: never run (page: "The controller", 4)
        try:
            csv, header = self.files.program(exp_id)
        except OSError as err:
            self.files.answer_failed(exp_id, nonce, f"program {exp_id}: {err.strerror}")
            return True
        res = self.core.run(exp_id, nonce, csv, header)
        if res.fault == "never_answer":
            return True
        if res.error is not None:
            self.files.answer_failed(exp_id, nonce, res.error)
            return True
        if res.fault == "die":  # half a log in a temp file, no rename, no 'done'
            self.files.write_partial(exp_id, nonce, res.log[: len(res.log) // 2])
            self.core.die()
            return False
        self.files.write_log(exp_id, nonce, res.delivered)
        if res.fault == "stale_semaphore":  # an answer to an attempt that no longer exists
            self.files.answer_done(exp_id, "0stale0", "0" * 64, 1)
        self.files.answer_done(exp_id, nonce, res.sha256, len(res.log))
        if res.fault == "answer_twice":
            time.sleep(0.05)
            self.files.answer_done(exp_id, nonce, res.sha256, len(res.log))
        return True
