"""A cell's state dir for the web page's tests: a daemon config, stored runs in every state,
identify results on two model versions, one run with its report.html, tracking, parameter
sets (one approved, one in use)."""

from __future__ import annotations

import asyncio
import hashlib
import json
import threading
import time
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from robid_link.config import load_daemon_config
from robid_link.ident.fit.identify import load_logs
from robid_link.ident.model.effects import DEFAULT_MODEL, EffectSpec
from robid_link.ident.model.robot import load_robot
from robid_link.ident.runner import run_job
from robid_link.link.store import Store

from ..conftest import ROBOTS, simulate

TOKEN = "operator-token-0123456789"
TRACKING = {"joint_rms": [2e-3, 1e-3, 1e-3], "joint_max": [6e-3, 3e-3, 3e-3],
            "tool_rms_mm": 0.4, "tool_max_mm": 1.4, "residual_mm": 0.5}
QUICK = {"experiments": [{"kind": "rigid_body", "duration_s": 10, "harmonics": 4,
                          "evaluations": 40, "rate_hz": 100}], "timeout_s": 20}


class Recorder:
    """The daemon's request handler as the page sees it: records, answers like the daemon."""

    def __init__(self) -> None:
        self.calls: list[dict[str, Any]] = []

    async def __call__(self, req: dict[str, Any]) -> dict[str, Any]:
        self.calls.append(req)
        return {"ok": True, "run_id": "r-new"}


@dataclass
class Cell:
    config: Path
    state: Path
    runs: dict[str, str]  # role → run_id: reported, queued, running, failed, other
    robot: str


def write_config(tmp: Path, **web: Any) -> Path:
    (tmp / "share").mkdir(exist_ok=True)
    doc: dict[str, Any] = {
        "robot": str(ROBOTS / "arm3.yaml"), "state_dir": str(tmp / "state"),
        "control_socket": str(tmp / "ctl.sock"),
        "driver": {"name": "file_share", "share": str(tmp / "share"), "canary_interval_s": 0},
        "campaigns": {"nightly": QUICK}}
    if web:
        doc["web"] = web
    path = tmp / "daemon.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def _param_set(store: Store, robot: str, run_id: str, n: int) -> str:
    body = json.dumps({"robot": robot, "n": n}).encode()
    sha = hashlib.sha256(body).hexdigest()
    store.add_param_set({"sha256": sha, "robot": robot, "run_id": run_id}, body)
    return sha


def build_cell(tmp: Path) -> Cell:
    cfg = load_daemon_config(write_config(tmp))
    arm3 = load_robot(cfg.robot)
    sim = simulate(arm3, tmp / "log.csv", seed=5, duration=12.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        logs = load_logs(arm3, [sim.path])
        with Store(cfg.state_dir) as store:
            runs = {}
            for role, effects in (("older", DEFAULT_MODEL), ("reported", DEFAULT_MODEL.with_added(
                    EffectSpec("offset", 2, ())))):
                run_id = store.create_run("nightly", "timer", {}, [("rigid_body", "rigid_body")])
                store.set_run(run_id, "running", step="identifying")
                job = run_job(arm3, logs, effects, run_id=run_id, campaign="nightly",
                              report_dir=cfg.state_dir / "reports" / run_id
                              if role == "reported" else None)
                store.add_result(run_id, arm3.name, "identify",
                                 {**job.records["identify"], "run_id": run_id})
                store.set_run(run_id, "completed")
                runs[role] = run_id
                time.sleep(0.01)  # distinct creation times: the newest first
            store.add_result(runs["reported"], arm3.name, "verify_before",
                             {"tracking": TRACKING})
            store.add_result(runs["reported"], arm3.name, "verify_after", {"tracking": {
                **TRACKING, "tool_rms_mm": 0.05, "tool_max_mm": 0.16, "residual_mm": 0.1}})
            first = _param_set(store, arm3.name, runs["older"], 1)
            second = _param_set(store, arm3.name, runs["reported"], 2)
            store.approve_param_set(first, "operator")
            store.record_upload(arm3.name, first, runs["older"], "acknowledged")
            del second
            runs["failed"] = store.create_run("nightly", "operator", {}, [("a", "rigid_body")])
            store.set_run(runs["failed"], "failed", error="controller did not answer")
            runs["running"] = store.create_run("nightly", "timer", {},
                                               [("a", "rigid_body"), ("b", "friction")])
            store.set_run(runs["running"], "running", step="experiment 1/2 a")
            runs["queued"] = store.create_run("nightly", "operator", {}, [("a", "rigid_body")])
    return Cell(cfg.path, cfg.state_dir, runs, arm3.name)


@contextmanager
def serving(server: Any) -> Iterator[str]:
    """Run a WebServer (or anything entered with ``async with``) in a thread of its own;
    yields its URL, stops it on exit."""
    loop = asyncio.new_event_loop()
    started = threading.Event()
    errors: list[BaseException] = []
    stop: asyncio.Event | None = None

    async def main() -> None:
        nonlocal stop
        stop = asyncio.Event()
        try:
            async with server:
                started.set()
                await stop.wait()
        except BaseException as err:  # reported to the caller
            errors.append(err)
            started.set()

    thread = threading.Thread(target=loop.run_until_complete, args=(main(),),
                              name="asyncio_web_test", daemon=True)
    thread.start()
    started.wait(30)
    if errors:
        raise errors[0]
    try:
        yield server.url
    finally:
        assert stop is not None
        loop.call_soon_threadsafe(stop.set)
        thread.join(30)
        loop.close()
