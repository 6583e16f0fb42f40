"""Per driver (Modbus PLC, serial line), the daemon and the fake controller as separate
processes: a daemon SIGKILLed at several points of a campaign and restarted finishes it with
every log stored intact exactly once, and the controller ran each program once."""

from __future__ import annotations

import hashlib
import json
import signal
import time
from pathlib import Path

import pytest

from robid_link.link.store import Store

from .conftest import ARM3, QUICK, process, robid, wait_socket, write_config

KILL_POINTS = ["given", "taken", "raw_stored", "given"]


def _wait_file(path: Path, proc: object, timeout_s: float = 60.0) -> dict[str, object]:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if path.is_file():
            return dict(json.loads(path.read_text()))
        assert proc.poll() is None, "fake controller exited"  # type: ignore[attr-defined]
        time.sleep(0.05)
    raise AssertionError(f"no {path} within {timeout_s} s")


def _wait_run(cfg: Path, tmp: Path) -> dict[str, object]:
    end = time.monotonic() + 180
    while time.monotonic() < end:
        st = robid("status", "--config", str(cfg), "--json", str(tmp / "s.json"))
        assert st.returncode == 0, st.stderr
        runs = json.loads((tmp / "s.json").read_text())["runs"]
        if runs[0]["state"] in ("completed", "failed"):
            return dict(runs[0])
        time.sleep(0.5)
    raise AssertionError("campaign did not finish")


@pytest.mark.parametrize("driver", ["modbus_plc", "serial_line"])
def test_sigkill_then_resume_exactly_once(tmp_path: Path, driver: str) -> None:
    cell = tmp_path / "cell"
    cell.mkdir()
    ready = tmp_path / "driver.json"
    ctl_log = tmp_path / "controller.log"
    with process("fake-controller", "--driver", driver, "--workdir", str(cell), "--robot",
                 str(ARM3), "--ready-file", str(ready), log=ctl_log) as ctl:
        cfg = write_config(tmp_path, {"quick": QUICK}, driver=_wait_file(ready, ctl))
        log = tmp_path / "daemon.log"
        run_id = None
        for k, point in enumerate(KILL_POINTS):
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
            run = _wait_run(cfg, tmp_path)
            daemon.send_signal(signal.SIGTERM)
            daemon.wait(30)
        assert ctl.poll() is None, ctl_log.read_text()
    assert run["state"] == "completed", run["error"]
    with Store(tmp_path / "state", readonly=True) as store:
        exps = store.experiments(run_id)
        shas = [e["log_sha"] for e in exps]
        assert all(shas) and len(set(shas)) == 2
        for sha in shas:
            assert hashlib.sha256(store.log_path(sha).read_bytes()).hexdigest() == sha
        assert store.log_count() == 2 and [e["attempt"] for e in exps] == [1, 1]
    runs = [ln for ln in ctl_log.read_text().splitlines() if " running" in ln]
    assert len(runs) == 2, runs  # each program ran once on the controller
