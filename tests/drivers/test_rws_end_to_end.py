"""The daemon and the fake RWS controller as separate processes (``robid fake-controller
--driver abb_rws``): a campaign through the CLI over RWS 1.0 and 2.0, and a daemon SIGKILLed
at points of the cycle and restarted that finishes with every log stored exactly once."""

from __future__ import annotations

import hashlib
import json
import signal
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

from robid_link.link.store import Store
from tests.link.conftest import ARM3, QUICK, process, robid, wait_socket, write_config


@contextmanager
def rws_controller(tmp: Path, version: int) -> Iterator[dict[str, Any]]:
    """The fake RWS controller as a process; yields the daemon's ``driver:`` mapping."""
    work, ready = tmp / "cell", tmp / "ready.json"
    work.mkdir(exist_ok=True)
    with process("fake-controller", "--driver", "abb_rws", "--workdir", str(work), "--robot",
                 str(ARM3), "--option", f"version={version}", "--option", "ping_interval_s=1",
                 "--ready-file", str(ready), log=tmp / "controller.log") as proc:
        end = time.monotonic() + 60
        while not ready.exists():
            assert proc.poll() is None, (tmp / "controller.log").read_text()
            assert time.monotonic() < end, "fake controller not ready"
            time.sleep(0.05)
        yield json.loads(ready.read_text())


@pytest.mark.parametrize("version", [1, 2])
def test_campaign_over_rws_through_the_cli(tmp_path: Path, version: int) -> None:
    with rws_controller(tmp_path, version) as driver:
        cfg = write_config(tmp_path, {"quick": QUICK}, driver=driver)
        with process("daemon", "--config", str(cfg), log=tmp_path / "daemon.log") as daemon:
            wait_socket(tmp_path / "ctl.sock", daemon)
            out = robid("campaign", "start", "quick", "--config", str(cfg), "--wait")
            assert out.returncode == 0, out.stderr + (tmp_path / "daemon.log").read_text()
            assert "2/2 logs" in out.stdout and "completed" in out.stdout
            daemon.send_signal(signal.SIGTERM)
            assert daemon.wait(30) == 0
    text = (tmp_path / "daemon.log").read_text() + (tmp_path / "controller.log").read_text()
    assert f"rws={version}.0" in text and "session logged out" in text
    password = (tmp_path / "cell" / "rws-credentials").read_text().split(":", 1)[1].strip()
    assert password not in text  # neither the daemon nor the controller logs the secret


def test_sigkill_mid_campaign_then_resume_exactly_once(tmp_path: Path) -> None:
    kill_points = ["giving", "given", "taken", "raw_stored", "stored", "given"]
    log = tmp_path / "daemon.log"
    run_id = None
    with rws_controller(tmp_path, 1) as driver:
        cfg = write_config(tmp_path, {"quick": QUICK}, driver=driver)
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
            wait_socket(tmp_path / "ctl.sock", daemon)
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
    assert runs[0]["state"] == "completed", runs[0]["error"]
    with Store(tmp_path / "state", readonly=True) as store:
        exps = store.experiments(run_id)
        shas = [e["log_sha"] for e in exps]
        assert all(shas) and len(set(shas)) == 2
        for sha in shas:
            assert hashlib.sha256(store.log_path(sha).read_bytes()).hexdigest() == sha
        assert store.log_count() == 2  # exactly once
        assert [e["attempt"] for e in exps] == [1, 1]  # no experiment ran twice
    ran = [ln for ln in (tmp_path / "controller.log").read_text().splitlines()
           if " running" in ln and "exp=" in ln]
    assert len(ran) == 2, ran  # the controller ran each program once
    logs = list((tmp_path / "cell" / "HOME" / "robid").glob("*.log.csv"))
    assert len(logs) == 2
