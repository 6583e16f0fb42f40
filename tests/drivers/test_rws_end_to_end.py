"""The daemon and the fake RWS controller as separate processes (``robid fake-controller
--driver abb_rws``): a campaign through the CLI over RWS 1.0 and 2.0, and a daemon SIGKILLed
at points of the cycle and restarted that finishes with every log stored exactly once."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from tests.link.conftest import (
    QUICK,
    assert_stored_once,
    campaign_via_cli,
    controller_runs,
    kill_then_resume,
    peer_process,
    robid,
    write_config,
)


def rws_controller(tmp: Path, version: int) -> Any:
    """The fake RWS controller as a process; yields the daemon's ``driver:`` mapping."""
    return peer_process(tmp, "abb_rws", f"version={version}", "ping_interval_s=1")


@pytest.mark.parametrize("version", [1, 2])
def test_campaign_over_rws_through_the_cli(tmp_path: Path, version: int) -> None:
    with rws_controller(tmp_path, version) as driver:
        campaign_via_cli(tmp_path, write_config(tmp_path, {"quick": QUICK}, driver=driver))
    text = (tmp_path / "daemon.log").read_text() + (tmp_path / "controller.log").read_text()
    assert f"rws={version}.0" in text and "session logged out" in text
    password = (tmp_path / "cell" / "rws-credentials").read_text().split(":", 1)[1].strip()
    assert password not in text  # neither the daemon nor the controller logs the secret


def test_sigkill_mid_campaign_then_resume_exactly_once(tmp_path: Path) -> None:
    with rws_controller(tmp_path, 1) as driver:
        cfg = write_config(tmp_path, {"quick": QUICK}, driver=driver)
        run_id, run = kill_then_resume(tmp_path, cfg, ["giving", "given", "taken", "raw_stored",
                                                       "stored", "given"])
    assert run["state"] == "completed", run["error"]
    assert_stored_once(tmp_path / "state", run_id)
    assert len(controller_runs(tmp_path)) == 2  # the controller ran each program once
    logs = list((tmp_path / "cell" / "HOME" / "robid").glob("*.log.csv"))
    assert len(logs) == 2
    out = robid("status", "--config", str(tmp_path / "nope.yaml"))
    assert out.returncode == 2 and "daemon config not found" in out.stderr
