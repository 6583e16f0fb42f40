"""The daemon and the fake controller as separate processes over a temporary share: a campaign
completes through the CLI and its result is in the store; a daemon SIGKILLed at every point of
a campaign and restarted finishes it with every log intact exactly once."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import time
from pathlib import Path

from robid_link.link.store import Store

from .conftest import ARM3, QUICK, process, robid, wait_socket, write_config


def _controller(tmp: Path):  # type: ignore[no-untyped-def]
    return process("fake-controller", "--share", str(tmp / "share"), "--robot", str(ARM3),
                   log=tmp / "controller.log")


def test_campaign_through_the_cli(tmp_path: Path) -> None:
    cfg = write_config(tmp_path, {"quick": {**QUICK, "diagnose": True}})
    with _controller(tmp_path), process("daemon", "--config", str(cfg),
                                        log=tmp_path / "daemon.log") as daemon:
        wait_socket(tmp_path / "ctl.sock", daemon)
        out = robid("campaign", "start", "quick", "--config", str(cfg), "--wait", "--json",
                    str(tmp_path / "run.json"))
        assert out.returncode == 0, out.stderr + (tmp_path / "daemon.log").read_text()
        run_id = out.stdout.splitlines()[0]
        assert "2/2 logs" in out.stdout and "completed" in out.stdout
        status = robid("status", "--config", str(cfg))
        assert run_id in status.stdout and "completed" in status.stdout
        listed = robid("campaign", "list", "--config", str(cfg))
        assert "quick: rigid_body (rigid_body), friction (friction)" in listed.stdout
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(30) == 0
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
    log = tmp_path / "daemon.log"
    run_id = None
    with _controller(tmp_path):
        for k, point in enumerate(kill_points):
            env = {"ROBID_FAULT_KILL_AFTER": f"{point}:1"}
            with process("daemon", "--config", str(cfg), env=env, log=log) as daemon:
                if run_id is None:
                    wait_socket(tmp_path / "ctl.sock", daemon)
                    out = robid("campaign", "start", "quick", "--config", str(cfg))
                    run_id = out.stdout.strip()
                    assert run_id, out.stderr
                rc = daemon.wait(120)
                assert rc == -signal.SIGKILL, f"kill point {k} ({point}): exit {rc}"
        with process("daemon", "--config", str(cfg), log=log) as daemon:
            wait_socket(tmp_path / "ctl.sock", daemon)  # a stale socket file was left behind
            end = time.monotonic() + 120
            while time.monotonic() < end:
                st = robid("status", "--config", str(cfg), "--json", str(tmp_path / "s.json"))
                assert st.returncode == 0, st.stderr
                runs = json.loads((tmp_path / "s.json").read_text())["runs"]
                if runs[0]["state"] in ("completed", "failed"):
                    break
                time.sleep(0.5)
            daemon.send_signal(signal.SIGTERM)
            daemon.wait(30)
    run = runs[0]
    assert run["state"] == "completed", run["error"]
    with Store(tmp_path / "state", readonly=True) as store:
        exps = store.experiments(run_id)
        shas = [e["log_sha"] for e in exps]
        assert all(shas) and len(set(shas)) == 2
        for sha in shas:  # intact: each file still hashes to its name
            assert hashlib.sha256(store.log_path(sha).read_bytes()).hexdigest() == sha
        assert store.log_count() == 2  # exactly once: no second copy of any capture
        assert [e["attempt"] for e in exps] == [1, 1]  # no experiment ran twice
        results = store.results(run_id=run_id)
        assert [r["kind"] for r in results] == ["identify"]
        steps = [j["step"] for j in store.journal(run_id)]
    outbox = [n for n in os.listdir(tmp_path / "share" / "outbox") if n.endswith(".log.csv")]
    assert len(outbox) == 2  # the controller ran each program once
    assert steps.count("stored") == 2
