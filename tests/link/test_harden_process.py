"""Issue 14 item 8 (and the CLI side of 3, 4, 11) with real processes: a daemon SIGKILLed
while its identification worker runs leaves no worker behind, and the model's history gets
one record per run and kind after the resumed run; cancel, config check, list, start --json
through the CLI."""

from __future__ import annotations

import json
import os
import signal
import time
import uuid
from pathlib import Path

from .conftest import ARM3, QUICK, process, robid, wait_socket, write_config


def _marked(mark: str) -> list[int]:
    """Processes whose environment carries ``mark`` (the daemon's and its children's)."""
    pids = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            env = Path(f"/proc/{entry}/environ").read_bytes()
            state = Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if mark.encode() in env and state != "Z":
            pids.append(int(entry))
    return pids


def _wait_gone(mark: str, timeout_s: float = 15.0) -> list[int]:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and _marked(mark):
        time.sleep(0.1)
    return _marked(mark)


def _controller(tmp: Path):  # type: ignore[no-untyped-def]
    return process("fake-controller", "--share", str(tmp / "share"), "--robot", str(ARM3),
                   log=tmp / "controller.log")


def test_sigkill_during_identification_leaves_no_worker_and_one_history_record(
        tmp_path: Path) -> None:
    model = tmp_path / "model.yaml"
    model.write_text("effects: [rigid_body, viscous, coulomb]\n")
    cfg = write_config(tmp_path, {"quick": {**QUICK, "model": str(model)}})
    log = tmp_path / "daemon.log"
    mark = f"ROBID_TEST_MARK={uuid.uuid4().hex}"
    key, _, value = mark.partition("=")
    with _controller(tmp_path):
        env = {"ROBID_FAULT_KILL_AFTER": "identify_started:1", key: value}
        with process("daemon", "--config", str(cfg), env=env, log=log) as daemon:
            wait_socket(tmp_path / "ctl.sock", daemon)
            out = robid("campaign", "start", "quick", "--config", str(cfg))
            run_id = out.stdout.strip()
            assert run_id, out.stderr
            assert daemon.wait(180) == -signal.SIGKILL, log.read_text()
            daemon_pid = daemon.pid
        left = _wait_gone(mark, timeout_s=3.0)  # well before the identification could end
        history_file = tmp_path / "model.yaml.history.jsonl"
        time.sleep(0 if left else 10.0)
        orphan_wrote = history_file.exists()  # a surviving worker finishes and appends
        for pid in _marked(mark):  # do not leak them into other tests
            os.kill(pid, signal.SIGKILL)
        assert left == [], f"processes outlived the daemon {daemon_pid}: {left}"
        assert not orphan_wrote
        with process("daemon", "--config", str(cfg), log=log) as daemon:
            wait_socket(tmp_path / "ctl.sock", daemon)
            end = time.monotonic() + 180
            while time.monotonic() < end:
                robid("status", "--config", str(cfg), "--json", str(tmp_path / "s.json"))
                run = json.loads((tmp_path / "s.json").read_text())["runs"][0]
                if run["state"] in ("completed", "failed"):
                    break
                time.sleep(0.5)
            daemon.send_signal(signal.SIGTERM)
            daemon.wait(30)
    assert run["state"] == "completed", run["error"]
    history = [json.loads(ln) for ln in
               (tmp_path / "model.yaml.history.jsonl").read_text().splitlines()]
    assert [(r["run_id"], r["kind"]) for r in history] == [(run_id, "identify")]


def test_cli_config_check_list_cancel_and_start_json(tmp_path: Path) -> None:
    bad = {**QUICK, "model": str(tmp_path / "missing.yaml")}
    cfg = write_config(tmp_path, {"quick": QUICK, "broken": bad,
                                  "odd": {**QUICK, "add": ["no_such_effect@2"]}})
    out = robid("config", "check", "--config", str(cfg))
    assert out.returncode == 1, out.stderr
    lines = dict(ln.split(": ", 1) for ln in out.stdout.splitlines())
    assert lines["quick"] == "ok"
    assert lines["broken"].startswith("campaigns.broken.model: ") and "not found" in lines[
        "broken"]
    assert "no_such_effect" in lines["odd"]
    listed = robid("campaign", "list", "--config", str(cfg))  # no daemon: read the config
    assert listed.returncode == 0, listed.stderr
    assert "quick: rigid_body (rigid_body), friction (friction)" in listed.stdout
    # a run nobody answers: cancel withdraws its 'ready'; start --json without --wait
    with process("daemon", "--config", str(cfg), log=tmp_path / "daemon.log") as daemon:
        wait_socket(tmp_path / "ctl.sock", daemon)
        out = robid("campaign", "start", "quick", "--config", str(cfg), "--json",
                    str(tmp_path / "start.json"))
        assert out.returncode == 0, out.stderr
        run_id = out.stdout.strip()
        assert json.loads((tmp_path / "start.json").read_text())["run_id"] == run_id
        end = time.monotonic() + 120
        while not any(n.endswith(".ready") for n in os.listdir(tmp_path / "share" / "sem")):
            assert time.monotonic() < end, (tmp_path / "daemon.log").read_text()
            time.sleep(0.1)
        out = robid("campaign", "cancel", run_id, "--config", str(cfg))
        assert out.returncode == 0, out.stderr
        assert f"run {run_id} cancelled" in out.stdout
        assert not any(n.endswith(".ready") for n in os.listdir(tmp_path / "share" / "sem"))
        st = robid("status", "--config", str(cfg))
        assert "cancelled" in st.stdout
        refused = robid("campaign", "start", "broken", "--config", str(cfg))
        assert refused.returncode != 0 and "missing.yaml" in refused.stderr
        assert refused.stderr.strip().count("\n") == 0
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(30) == 0
