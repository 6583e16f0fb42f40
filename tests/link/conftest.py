"""Fixtures of the link tests: a temporary share and state dir, configs, the fake controller in
a thread or a process, the daemon in-process or as a process; everything stopped by the test."""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import yaml

from robid_link.fakes.controller import default_truth, make_peer
from robid_link.fakes.file_share_peer import FileSharePeer
from robid_link.ident.model.robot import Robot, load_robot

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


def _answers(path: Path) -> bool:
    from robid_link.exceptions import DaemonUnreachable
    from robid_link.link.control import request

    try:
        request(path, {"cmd": "ping"}, timeout_s=2.0)
    except (DaemonUnreachable, OSError):
        return False
    return True


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
            run = await daemon.store.run(run_id)
            if run["state"] in ("completed", "failed"):
                return run
            await asyncio.sleep(0.05)


# ------------------------------------------------------ daemon and controller as processes
@contextlib.contextmanager
def peer_process(tmp: Path, driver: str, *options: str) -> Iterator[dict[str, Any]]:
    """``robid fake-controller --driver D`` as a process on ``tmp/cell``; yields the daemon's
    ``driver:`` mapping it writes to its ready file. ``options``: ``key=value`` peer options."""
    work, ready, log = tmp / "cell", tmp / "ready.json", tmp / "controller.log"
    work.mkdir(exist_ok=True)
    opts = [a for o in options for a in ("--option", o)]
    with process("fake-controller", "--driver", driver, "--workdir", str(work), "--robot",
                 str(ARM3), "--ready-file", str(ready), *opts, log=log) as proc:
        end = time.monotonic() + 60
        while not ready.exists():
            assert proc.poll() is None, log.read_text()
            assert time.monotonic() < end, f"fake {driver} not ready"
            time.sleep(0.05)
        yield dict(json.loads(ready.read_text()))


def run_status(cfg: Path, tmp: Path, timeout_s: float = 180.0) -> dict[str, Any]:
    """Poll ``robid status`` until the newest run ends; its record."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        st = robid("status", "--config", str(cfg), "--json", str(tmp / "s.json"))
        assert st.returncode == 0, st.stderr
        runs = json.loads((tmp / "s.json").read_text())["runs"]
        if runs[0]["state"] in ("completed", "failed"):
            return dict(runs[0])
        time.sleep(0.5)
    raise AssertionError(f"run did not finish within {timeout_s} s")


def resume_when_interrupted(cfg: Path, tmp: Path, run_id: str,
                            daemon: subprocess.Popen[bytes], timeout_s: float = 180.0
                            ) -> dict[str, Any] | None:
    """After a restart: wait for the daemon's bookkeeping of ``run_id`` (no motion), check it
    waits as 'interrupted' with a time, then give the operator's ``robid campaign resume``.
    The run's record as the bookkeeping left it; None when the daemon died first (a kill
    point reached during the bookkeeping)."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        st = robid("status", "--config", str(cfg), "--json", str(tmp / "s.json"))
        if daemon.poll() is not None:
            return None
        assert st.returncode == 0, st.stderr
        run = next(r for r in json.loads((tmp / "s.json").read_text())["runs"]
                   if r["run_id"] == run_id)
        if run["state"] in ("completed", "failed"):
            return dict(run)  # nothing was left that needed motion
        if run["state"] == "interrupted":
            assert run["state_since"] > 0 and "since" in st.stdout, st.stdout
            out = robid("campaign", "resume", run_id, "--config", str(cfg))
            if daemon.poll() is not None:
                return None
            assert out.returncode == 0 and "resumed" in out.stdout, out.stderr
            return dict(run)
        time.sleep(0.3)
    raise AssertionError(f"run {run_id}: no bookkeeping end within {timeout_s} s")


def kill_then_resume(tmp: Path, cfg: Path, kill_points: list[str], during: Any = None,
                     after_kill: Any = None) -> tuple[str, dict[str, Any]]:
    """Start the campaign 'quick' on a daemon process and SIGKILL the daemon after each journal
    step of ``kill_points`` (``ROBID_FAULT_KILL_AFTER``; a point named ``@...`` is the test's
    own: ``during(point, daemon)`` kills it); ``after_kill(point)`` runs after each kill. Every
    restarted daemon only finishes the run's bookkeeping: the run moves on after the operator's
    ``robid campaign resume``; a last daemon finishes the run. Returns the run id and the final
    run record."""
    log, run_id = tmp / "daemon.log", None
    for k, point in enumerate(kill_points):
        own = point.startswith("@")
        env = {} if own else {"ROBID_FAULT_KILL_AFTER": f"{point}:1"}
        with process("daemon", "--config", str(cfg), env=env, log=log) as daemon:
            if run_id is None:
                wait_socket(tmp / "ctl.sock", daemon)
                out = robid("campaign", "start", "quick", "--config", str(cfg))
                run_id = out.stdout.strip()
                assert run_id, out.stderr
            else:  # the kill point may come in the bookkeeping, before the socket answers
                end = time.monotonic() + 60
                while daemon.poll() is None and not _answers(tmp / "ctl.sock"):
                    assert time.monotonic() < end, "restarted daemon never answered"
                    time.sleep(0.1)
                resume_when_interrupted(cfg, tmp, run_id, daemon)
            if own:
                during(point, daemon)
            rc = daemon.wait(120)
            assert rc == -signal.SIGKILL, f"kill point {k} ({point}): exit {rc}"
        if after_kill is not None:
            after_kill(point)
    assert run_id is not None
    with process("daemon", "--config", str(cfg), log=log) as daemon:
        wait_socket(tmp / "ctl.sock", daemon)  # a stale socket file was left behind
        resume_when_interrupted(cfg, tmp, run_id, daemon)
        run = run_status(cfg, tmp)
        daemon.send_signal(signal.SIGTERM)
        daemon.wait(30)
    return run_id, run


def assert_stored_once(state: Path, run_id: str, attempts: list[int] | None = None) -> None:
    """Every log of the run intact (its file hashes to its name), stored exactly once, and no
    experiment given more often than ``attempts`` says (default: each once)."""
    from robid_link.link.store import Store

    with Store(state, readonly=True) as store:
        exps = store.experiments(run_id)
        shas = [e["log_sha"] for e in exps]
        assert all(shas) and len(set(shas)) == len(exps)
        for sha in shas:
            assert hashlib.sha256(store.log_path(sha).read_bytes()).hexdigest() == sha
        assert store.log_count() == len(exps)  # no second copy of any capture
        assert [e["attempt"] for e in exps] == (attempts or [1] * len(exps))


def controller_runs(tmp: Path) -> list[str]:
    """The fake controller's 'running' lines (one per program it executed)."""
    return [ln for ln in (tmp / "controller.log").read_text().splitlines()
            if " running" in ln and "exp=" in ln]


def campaign_via_cli(tmp: Path, cfg: Path, *args: str,
                     while_up: Any = None) -> subprocess.CompletedProcess[str]:
    """A daemon process runs the campaign 'quick' to completion through ``robid campaign start
    --wait`` (``args`` added), ``while_up()`` runs before the daemon gets SIGTERM and must exit
    0; the CLI's output."""
    log = tmp / "daemon.log"
    with process("daemon", "--config", str(cfg), log=log) as daemon:
        wait_socket(tmp / "ctl.sock", daemon)
        out = robid("campaign", "start", "quick", "--config", str(cfg), "--wait", *args)
        assert out.returncode == 0, out.stderr + log.read_text()
        n = len(yaml.safe_load(cfg.read_text())["campaigns"]["quick"]["experiments"])
        assert f"{n}/{n} logs" in out.stdout and "completed" in out.stdout
        if while_up is not None:
            while_up()
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(30) == 0
    return out


# ------------------------------------------------------------------ the store's backends
@dataclass
class Backend:
    """A store backend under test: a cell's SQLite file (``url`` None) or a fresh database of
    the session's real PostgreSQL. ``store``/``async_store`` open it as robot ``robot``'s
    daemon would; ``reader`` as an operator command does."""

    name: str
    url: str | None
    robot: str = "arm3"

    def store(self, state_dir: Path, **kw: Any) -> Any:
        from robid_link.link.store import Store

        kw.setdefault("robot", self.robot)
        return Store(state_dir, url=self.url, **kw)

    def async_store(self, state_dir: Path, **kw: Any) -> Any:
        from robid_link.link.store import open_store

        kw.setdefault("robot", self.robot)
        reserve = kw.pop("reserve_bytes", None)
        store = open_store(state_dir, url=self.url, **kw)
        if reserve is not None:
            store.reserve_bytes = reserve
        return store

    def reader(self, state_dir: Path) -> Any:
        from robid_link.link.store import Store

        return Store(None if self.url else state_dir, url=self.url, readonly=True)


@pytest.fixture(params=["sqlite", "postgresql"])
def backend(request: pytest.FixtureRequest) -> Backend:
    """Each store test runs on both backends (PostgreSQL: tests/servers.py)."""
    if request.param == "sqlite":
        return Backend("sqlite", None)
    return Backend("postgresql", request.getfixturevalue("pg_url"))
