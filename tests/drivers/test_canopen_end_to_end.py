"""The daemon and the fake CiA 402 drives as separate processes (``robid fake-controller --driver
canopen_drives`` serves them over socketcand on 127.0.0.1): a campaign through the CLI whose
identified model is as accurate as over the file share, and a daemon SIGKILLed while the drives
stream — the drives quick-stop on the lost SYNC — restarted to finish with every log once."""

from __future__ import annotations

import hashlib
import json
import re
import signal
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from robid_link.link.store import Store
from tests.link.conftest import ARM3, QUICK, process, robid, wait_socket, write_config

#: QUICK with a shorter friction sweep: the drives move in real time (≈ 20 s of motion in all),
#: so the take timeout covers the longest program
CAN_QUICK = {**QUICK, "timeout_s": 60,
             "experiments": [QUICK["experiments"][0],
                             {"kind": "friction", "speeds": [0.6, 0.9], "joints": [1],
                              "rate_hz": 100}]}


@contextmanager
def fake_drives(tmp: Path) -> Iterator[dict[str, Any]]:
    """The fake drives as a process; yields the daemon's ``driver:`` mapping."""
    work, ready = tmp / "cell", tmp / "ready.json"
    work.mkdir(exist_ok=True)
    with process("fake-controller", "--driver", "canopen_drives", "--workdir", str(work),
                 "--robot", str(ARM3), "--ready-file", str(ready),
                 log=tmp / "controller.log") as proc:
        end = time.monotonic() + 60
        while not ready.exists():
            assert proc.poll() is None, (tmp / "controller.log").read_text()
            assert time.monotonic() < end, "fake drives not ready"
            time.sleep(0.05)
        yield json.loads(ready.read_text())


def _campaign(tmp: Path, driver: dict[str, Any] | None) -> dict[str, Any]:
    """One QUICK campaign (identification + diagnosis) through the CLI; the run's JSON."""
    over = {} if driver is None else {"driver": driver}
    cfg = write_config(tmp, {"quick": {**CAN_QUICK, "diagnose": True}}, **over)
    with process("daemon", "--config", str(cfg), log=tmp / "daemon.log") as daemon:
        wait_socket(tmp / "ctl.sock", daemon)
        out = robid("campaign", "start", "quick", "--config", str(cfg), "--wait", "--json",
                    str(tmp / "run.json"))
        assert out.returncode == 0, out.stderr + (tmp / "daemon.log").read_text()
        assert "2/2 logs" in out.stdout and "completed" in out.stdout
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(30) == 0
    return json.loads((tmp / "run.json").read_text())


def _identified(doc: dict[str, Any]) -> dict[str, Any]:
    [rec] = [r for r in doc["results"] if r["kind"] == "identify"]
    return rec.get("record", rec)


def test_campaign_over_socketcand_as_accurate_as_file_share(tmp_path: Path) -> None:
    (tmp_path / "can").mkdir()
    (tmp_path / "fs").mkdir()
    with fake_drives(tmp_path / "can") as driver:
        assert driver["interface"] == "socketcand" and driver["host"] == "127.0.0.1"
        can_doc = _campaign(tmp_path / "can", driver)
    (tmp_path / "fs" / "share").mkdir()
    with process("fake-controller", "--share", str(tmp_path / "fs" / "share"), "--robot",
                 str(ARM3), log=tmp_path / "fs" / "controller.log"):
        fs_doc = _campaign(tmp_path / "fs", None)
    for doc in (can_doc, fs_doc):
        assert doc["run"]["state"] == "completed"
        assert {r["kind"] for r in doc["results"]} == {"identify", "diagnose"}
    can_id, fs_id = _identified(can_doc), _identified(fs_doc)
    print(f"relative error: canopen/socketcand {can_id['relative_error']:.4f}, file share "
          f"{fs_id['relative_error']:.4f}; rmse N·m {can_id['rmse']} vs {fs_id['rmse']}")
    # same robot, same truth (nominal inertials, viscous + Coulomb, 0.2 N·m noise): the drives
    # log at the SYNC rate (250 Hz) from a drive's velocity observer, the file share at 1 kHz
    assert can_id["relative_error"] < 1.5 * fs_id["relative_error"] + 0.01
    for a, b in zip(can_id["rmse"], fs_id["rmse"], strict=True):
        assert a < 1.5 * b + 0.05
    text = (tmp_path / "can" / "daemon.log").read_text()
    assert "Operation enabled (CSP)" in text and "step=stored" in text
    assert "no SYNC from the master" not in (tmp_path / "can" / "controller.log").read_text()


def _wait_run(cfg: Path, tmp: Path) -> dict[str, Any]:
    end = time.monotonic() + 180
    while time.monotonic() < end:
        st = robid("status", "--config", str(cfg), "--json", str(tmp / "s.json"))
        assert st.returncode == 0, st.stderr
        runs = json.loads((tmp / "s.json").read_text())["runs"]
        if runs[0]["state"] in ("completed", "failed"):
            return dict(runs[0])
        time.sleep(0.5)
    raise AssertionError("run did not finish")


def test_sigkill_while_streaming_quick_stops_then_resume_exactly_once(tmp_path: Path) -> None:
    log, ctl_log = tmp_path / "daemon.log", tmp_path / "controller.log"
    run_id = None
    with fake_drives(tmp_path) as driver:
        cfg = write_config(tmp_path, {"quick": CAN_QUICK}, driver=driver)
        # first while the drives stream experiment 1 (1 s into its motion), then at 'taken'
        for k, point in enumerate(["streaming", "taken"]):
            stops = ctl_log.read_text().count("no SYNC from the master")
            env = {} if point == "streaming" else {"ROBID_FAULT_KILL_AFTER": f"{point}:1"}
            with process("daemon", "--config", str(cfg), env=env, log=log) as daemon:
                if run_id is None:
                    wait_socket(tmp_path / "ctl.sock", daemon)
                    out = robid("campaign", "start", "quick", "--config", str(cfg))
                    run_id = out.stdout.strip()
                    assert run_id, out.stderr
                if point == "streaming":
                    end = time.monotonic() + 60
                    while "fake drives: motion" not in ctl_log.read_text():
                        assert time.monotonic() < end, ctl_log.read_text()[-3000:]
                        time.sleep(0.05)
                    time.sleep(1.0)
                    daemon.send_signal(signal.SIGKILL)
                rc = daemon.wait(120)
                assert rc == -signal.SIGKILL, f"kill point {k} ({point}): exit {rc}"
            # the drives lost their master mid-stream: each quick-stops on its own and rests
            end = time.monotonic() + 30
            while ctl_log.read_text().count("at rest after the quick stop") <= stops:
                assert time.monotonic() < end, ctl_log.read_text()[-3000:]
                time.sleep(0.1)
        with process("daemon", "--config", str(cfg), log=log) as daemon:
            wait_socket(tmp_path / "ctl.sock", daemon)
            run = _wait_run(cfg, tmp_path)
            daemon.send_signal(signal.SIGTERM)
            daemon.wait(30)
    assert run["state"] == "completed", run["error"]
    text = ctl_log.read_text()
    assert text.count("no SYNC from the master") == 2
    stopped = re.findall(r"at rest after the quick stop \(from \[([^\]]*)\] rad/s\)", text)
    assert len(stopped) == 2
    # the first kill hit the drives while they moved; at 'taken' they were at rest
    assert max(abs(float(v)) for v in stopped[0].split()) > 0.01, stopped
    with Store(tmp_path / "state", readonly=True) as store:
        exps = store.experiments(run_id)
        shas = [e["log_sha"] for e in exps]
        assert all(shas) and len(set(shas)) == 2
        for sha in shas:
            assert hashlib.sha256(store.log_path(sha).read_bytes()).hexdigest() == sha
        assert store.log_count() == 2  # exactly once
        # the motion cut by the first kill is not resumed: that experiment ran again
        assert [e["attempt"] for e in exps] == [2, 1]
    daemon_text = log.read_text()
    assert "was not streamed by this daemon" in daemon_text
