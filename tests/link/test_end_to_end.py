"""The daemon and the fake controller as separate processes over a temporary share: a campaign
completes through the CLI and its result is in the store; a daemon SIGKILLed at every point of
a campaign and restarted finishes it with every log intact exactly once."""

from __future__ import annotations

import json
import os
from pathlib import Path

from robid_link.link.store import Store

from .conftest import (
    ARM3,
    QUICK,
    assert_stored_once,
    campaign_via_cli,
    kill_then_resume,
    process,
    robid,
    write_config,
)


def _controller(tmp: Path):  # type: ignore[no-untyped-def]
    return process("fake-controller", "--share", str(tmp / "share"), "--robot", str(ARM3),
                   log=tmp / "controller.log")


def test_campaign_through_the_cli(tmp_path: Path) -> None:
    cfg = write_config(tmp_path, {"quick": {**QUICK, "diagnose": True}})
    seen: list[str] = []

    def while_up() -> None:  # the daemon answers both
        seen.append(robid("status", "--config", str(cfg)).stdout)
        seen.append(robid("campaign", "list", "--config", str(cfg)).stdout)

    with _controller(tmp_path):
        out = campaign_via_cli(tmp_path, cfg, "--json", str(tmp_path / "run.json"),
                               while_up=while_up)
    run_id = out.stdout.splitlines()[0]
    assert run_id in seen[0] and "completed" in seen[0]
    assert "quick: rigid_body (rigid_body), friction (friction)" in seen[1]
    doc = json.loads((tmp_path / "run.json").read_text())
    assert doc["run"]["state"] == "completed"
    assert {r["kind"] for r in doc["results"]} == {"identify", "diagnose"}
    log_lines = (tmp_path / "daemon.log").read_text().splitlines()
    assert any("step=stored" in ln for ln in log_lines)
    assert any("daemon stopped" in ln for ln in log_lines)
    # with no daemon, status and results read the store
    res = robid("results", "--config", str(cfg), "--robot", "arm3")
    assert res.returncode == 0 and run_id in res.stdout and "identify" in res.stdout
    with Store(tmp_path / "state", readonly=True) as st:
        assert st.run(run_id)["state"] == "completed"


def test_bad_config_is_one_line(tmp_path: Path) -> None:
    cfg = write_config(tmp_path)
    cfg.write_text(cfg.read_text().replace("control_socket", "control_sock"))
    out = robid("daemon", "--config", str(cfg))
    assert out.returncode == 2
    assert out.stderr.strip().count("\n") == 0
    assert "unknown key 'control_sock'" in out.stderr
    out = robid("status", "--config", str(tmp_path / "nope.yaml"))
    assert out.returncode == 2 and "daemon config not found" in out.stderr


def test_sigkill_at_every_step_then_resume_exactly_once(tmp_path: Path) -> None:
    cfg = write_config(tmp_path, {"quick": QUICK})
    kill_points = ["giving", "given", "taken", "raw_stored", "stored",  # experiment 1
                   "given", "raw_stored", "identifying"]  # experiment 2, then the worker
    with _controller(tmp_path):
        run_id, run = kill_then_resume(tmp_path, cfg, kill_points)
    assert run["state"] == "completed", run["error"]
    assert_stored_once(tmp_path / "state", run_id)
    with Store(tmp_path / "state", readonly=True) as store:
        results = store.results(run_id=run_id)
        assert [r["kind"] for r in results] == ["identify"]
        steps = [j["step"] for j in store.journal(run_id)]
    outbox = [n for n in os.listdir(tmp_path / "share" / "outbox") if n.endswith(".log.csv")]
    assert len(outbox) == 2  # the controller ran each program once
    assert steps.count("stored") == 2
