"""Fixtures of the link tests: a temporary share and state dir, configs, the fake controller in
a thread or a process, the daemon in-process or as a process; everything stopped by the test."""

from __future__ import annotations

import asyncio
import contextlib
import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from robid_link.fakes.controller import default_truth, make_peer
from robid_link.fakes.file_share_peer import FileSharePeer
from robid_link.ident.robot import Robot, load_robot

ROOT = Path(__file__).resolve().parents[2]
ARM3 = ROOT / "examples" / "robots" / "arm3.yaml"

#: a short campaign: a 10 s Fourier run and a two-speed friction sweep at 100 Hz
QUICK = {
    "experiments": [
        {"kind": "rigid_body", "duration_s": 10, "harmonics": 4, "evaluations": 40,
         "rate_hz": 100},
        {"kind": "friction", "speeds": [0.3, 0.6], "joints": [1, 3], "rate_hz": 100},
    ],
    "timeout_s": 20, "backoff_s": 0.05, "retries": 2,
}


def write_config(tmp: Path, campaigns: dict[str, Any] | None = None, **over: Any) -> Path:
    (tmp / "share").mkdir(exist_ok=True)
    doc = {"robot": str(ARM3), "state_dir": str(tmp / "state"),
           "control_socket": str(tmp / "ctl.sock"),
           "driver": {"name": "file_share", "share": str(tmp / "share"),
                      "canary_interval_s": 0},
           "worker_start_method": "forkserver",
           "campaigns": campaigns or {"quick": QUICK}}
    doc.update(over)
    path = tmp / "daemon.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


@pytest.fixture(scope="session")
def arm3_robot() -> Robot:
    return load_robot(ARM3)


class ControllerThread:
    """The file-share peer serving in a thread (``with ... as peer``; ``peer.handled``)."""

    def __init__(self, share: Path, robot: Robot, **kw: Any) -> None:
        truth = default_truth(robot, rate_hz=200.0)
        self.ctrl: FileSharePeer = make_peer("file_share", robot, truth, share, poll_s=0.002,
                                             **kw)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.ctrl.serve, args=(self.stop,),
                                       name="fake-controller", daemon=True)

    def __enter__(self) -> FileSharePeer:
        self.thread.start()
        return self.ctrl

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join(10)


@pytest.fixture
def controller(tmp_path: Path, arm3_robot: Robot) -> Any:
    """``with controller(fault=...) as ctrl:`` a fake controller thread on tmp_path/share."""
    (tmp_path / "share").mkdir(exist_ok=True)

    def make(**kw: Any) -> ControllerThread:
        return ControllerThread(tmp_path / "share", arm3_robot, **kw)

    return make


def robid(*args: str, env: dict[str, str] | None = None, **kw: Any
          ) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "robid_link.cli", *args], capture_output=True,
                          text=True, env={**os.environ, **(env or {})}, timeout=240, **kw)


@contextlib.contextmanager
def process(*args: str, env: dict[str, str] | None = None, log: Path | None = None
            ) -> Iterator[subprocess.Popen[bytes]]:
    out = open(log, "ab") if log else subprocess.DEVNULL  # noqa: SIM115
    proc = subprocess.Popen([sys.executable, "-m", "robid_link.cli", *args], stdout=out,
                            stderr=subprocess.STDOUT, env={**os.environ, **(env or {})})
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        if log:
            out.close()  # type: ignore[union-attr]


def wait_socket(path: Path, proc: subprocess.Popen[bytes] | None = None,
                timeout_s: float = 60.0) -> None:
    from robid_link.exceptions import DaemonUnreachable
    from robid_link.link.control import request

    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if proc is not None and proc.poll() is not None:
            raise AssertionError(f"daemon exited with {proc.returncode}")
        with contextlib.suppress(DaemonUnreachable, OSError):
            request(path, {"cmd": "ping"}, timeout_s=2.0)
            return
        time.sleep(0.1)
    raise AssertionError(f"no daemon on {path} within {timeout_s} s")


async def wait_run(daemon: Any, run_id: str, timeout_s: float = 120.0) -> dict[str, Any]:
    async with asyncio.timeout(timeout_s):
        while True:
            run = daemon.store.run(run_id)
            if run["state"] in ("completed", "failed"):
                return run
            await asyncio.sleep(0.05)
