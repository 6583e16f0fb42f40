"""Hostile controllers against the whole link (issue 19): every defect class of the audit, and
the ones found beside it, played by a misbehaving peer while the daemon runs a campaign. Each
cell runs in a process of its own (``tests/drivers/hostile.py``) so its memory is its own:
the run fails with one line, the stop/abort reaches the controller side before the failure is
stored, status requests are answered meanwhile, and the process stays under 300 MB."""

from __future__ import annotations

import asyncio
import json
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from robid_link.exceptions import ConfigError, DriverError

ROOT = Path(__file__).resolve().parents[2]
MAX_RSS_MB = 300.0
#: a quick serial line: a silent controller is noticed within two STATs of 0.4 s
QUICK_SERIAL = {"io_timeout_s": 0.2, "retries": 1}

#: (id, spec, what the run's one line says — None: the run completes —, whether a stop/abort
#: must reach the controller side, whether any motion may have been given)
CASES: list[tuple[str, dict[str, Any], str | None, bool, bool]] = [
    # 1: RWS status answers that are not JSON, or JSON of another shape
    ("rws-not-json", {"driver": "abb_rws", "fault": "garbage_state"},
     r"execution state: the answer is not JSON", True, True),
    ("rws-wrong-shape", {"driver": "abb_rws", "fault": "wrong_shape"},
     r"execution state: no ctrlexecstate", True, True),
    # 5: an endless log; a redirect of the websocket (the session would follow it)
    ("rws-endless-log", {"driver": "abb_rws", "fault": "endless_log"},
     r"answer over \d+ bytes refused \(the size 'done' announced\)", False, True),
    ("rws-redirect", {"driver": "abb_rws", "fault": "redirect"},
     r"HTTP 302 redirect refused", True, True),
    # 2: a PLC heartbeat that freezes while BUSY; one frozen from the start
    ("modbus-heartbeat-frozen-busy", {"driver": "modbus_plc", "fault": "heartbeat_frozen"},
     r"PLC heartbeat frozen at \d+", True, True),
    ("modbus-heartbeat-dead", {"driver": "modbus_plc", "fault": "heartbeat_dead"},
     r"PLC heartbeat frozen at 0", False, False),
    # 3: another node on a drive's COB-ID (two different TPDOs for one SYNC); a TPDO mapped
    # otherwise; a drive fault whose EMCY is lost (0x603F read and named, item 5)
    ("can-foreign-tpdo", {"driver": "canopen_drives", "fault": "foreign_tpdo",
                          "peer": {"fault_node": 1}},
     r"node 2 \(joint 2 j2\): two different TPDO1 for SYNC", True, True),
    ("can-bad-length", {"driver": "canopen_drives", "fault": "bad_length",
                        "peer": {"fault_node": 1}},
     r"node 1 \(joint 1 j1\): TPDO2 of \d bytes, \d mapped", True, True),
    ("can-drive-fault-quiet", {"driver": "canopen_drives", "fault": "drive_fault_quiet",
                               "peer": {"fault_node": 1}},
     r"drive fault \(no EMCY received\), error code 0x603F = 0x2310 continuous over-current",
     True, True),
    # 4: an endless log; an unsolicited DONE flood; a transfer that never progresses; a
    # controller silent while its program runs; a compressed block that is a zip bomb
    ("serial-endless-log", {"driver": "serial_line", "fault": "endless_log"},
     r"announces a log of 1099511627776 bytes, over driver\.max_log_bytes", True, True),
    ("serial-done-flood", {"driver": "serial_line", "fault": "done_flood"}, None, False, True),
    ("serial-stalled-put", {"driver": "serial_line", "fault": "stalled_put"},
     r"traj\.\w+ makes no progress", False, False),
    ("serial-silent-run", {"driver": "serial_line", "fault": "silent_run",
                           "driver_over": QUICK_SERIAL},
     r"controller silent while experiment friction runs", True, True),
    # Universal Robots: the stream stalls mid-motion (connection kept); a data package of the
    # largest size RTDE allows, zeros; the controller gone (no stop can reach it: the line
    # says so)
    ("ur-rtde-stall", {"driver": "ur_rtde", "fault": "rtde_stall", "robot": "industrial6"},
     r"the RTDE stream stopped: no data package for 1 s during experiment friction; program "
     r"stopped \(dashboard\)", True, True),
    ("ur-rtde-garbage", {"driver": "ur_rtde", "fault": "rtde_garbage", "robot": "industrial6"},
     r"corrupt RTDE data package: 65532 bytes, the recipe needs \d+; program stopped", True,
     True),
    ("ur-controller-gone", {"driver": "ur_rtde", "fault": "die", "robot": "industrial6"},
     r"RTDE connection to [\d.:]+ lost during experiment friction \(connection closed\); "
     r"could not stop the program \(dashboard Connection refused; script port Connection "
     r"refused\)", False, True),
    # a log block that inflates to a thousand times its size (the caps hold after inflating)
    ("serial-zip-bomb", {"driver": "serial_line", "fault": "zip_bomb"},
     r"block at offset 0 not decoded after 9 tries \(inflates beyond \d+ bytes\)", True, True),
    # 7: the share's inbox replaced by a link after the daemon opened it
    ("share-symlinked-inbox", {"driver": "file_share", "fault": None, "symlink_inbox": True},
     r"inbox: a symbolic link; refusing to write through it", False, False),
    # 8: 64 control-socket clients that send and never read
    ("socket-mute-clients", {"driver": "file_share", "fault": None, "mute_clients": 64},
     None, False, True),
]


@pytest.fixture(scope="module", autouse=True)
def _numba_cached() -> None:
    """The fakes' numba kernels compiled and cached once, in a process of their own, before
    any cell measures its peak memory (a fresh clone's first cell compiled them itself)."""
    out = subprocess.run([sys.executable, "-m", "tests.drivers.hostile", "warm"], cwd=ROOT,
                         capture_output=True, text=True, timeout=280)
    assert out.returncode == 0, out.stderr[-3000:]


def _cell(spec: dict[str, Any]) -> dict[str, Any]:
    out = subprocess.run([sys.executable, "-m", "tests.drivers.hostile", json.dumps(spec)],
                         cwd=ROOT, capture_output=True, text=True, timeout=280)
    assert out.returncode == 0, out.stderr[-3000:]
    return dict(json.loads(out.stdout.strip().splitlines()[-1]))


@pytest.mark.parametrize("spec, line, stop, moves",
                         [pytest.param(s, ln, st, mv, id=i) for i, s, ln, st, mv in CASES])
def test_a_hostile_controller_never_takes_the_link(spec: dict[str, Any], line: str | None,
                                                   stop: bool, moves: bool) -> None:
    got = _cell(spec)
    assert got["error_at_start"] is None, got
    if line is None:
        assert got["state"] == "completed", got
    else:
        assert got["state"] == "failed", got
        assert re.search(line, got["error"]) and "\n" not in got["error"], got["error"]
    if stop:  # the stop/abort reached the controller side before the failure was stored
        assert got["stops"] and min(got["stops"]) <= got["failure_stored"], got
    if not moves:  # refused before any motion command
        assert got["given"] == 0 and got["plc_runs"] == 0, got
    assert all(got["status_during"]) and got["status_after"], got  # the daemon serves
    # what the cell allocated (the shared libraries' file pages depend on the page cache)
    assert got["peak_anon_mb"] < MAX_RSS_MB, got
    assert got["outside"] == [] and got.get("elsewhere_hits", 0) == 0, got


# ------------------------------------------------------------- refused before anything runs
def test_credentials_in_the_url_are_refused_without_being_shown(tmp_path: Path) -> None:
    from robid_link.link import registry

    creds = tmp_path / "creds"
    creds.write_text("robid:s3cret\n")
    creds.chmod(0o600)
    with pytest.raises(ConfigError) as err:
        registry.make_driver({"name": "abb_rws", "version": 1, "credentials_file": str(creds),
                              "url": "https://admin:hunter2@10.0.0.1"})
    assert "hunter2" not in str(err.value) and "admin" not in str(err.value)
    assert str(err.value).startswith("driver.url: credentials in the URL are refused")


def test_rws_credentials_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    from robid_link.link import registry

    opts = {"name": "abb_rws", "version": 1, "url": "http://127.0.0.1:8080"}
    with pytest.raises(ConfigError, match=r"driver\.credentials_file: missing .*ROBID_RWS_USER "
                                          r"and ROBID_RWS_PASSWORD"):
        registry.make_driver(opts)
    monkeypatch.setenv("ROBID_RWS_USER", "robid")
    monkeypatch.setenv("ROBID_RWS_PASSWORD", "s3cret")
    driver = registry.make_driver(opts)
    assert "s3cret" not in repr(driver.config) and driver.credentials_file.startswith(
        "ROBID_RWS_USER")


@pytest.mark.parametrize("kind", ["fifo", "dev_zero", "huge"])
def test_modbus_reads_its_index_through_the_safe_open(tmp_path: Path, kind: str) -> None:
    """Issue 19, 7: a FIFO as inbox/experiments.json hung the driver, a link to /dev/zero
    raised MemoryError; now each is refused in one line, unread."""
    from robid_link.drivers.modbus_plc import ModbusPlcDriver

    share = tmp_path / "share"
    (share / "inbox").mkdir(parents=True)
    index = share / "inbox" / "experiments.json"
    if kind == "fifo":
        os.mkfifo(index)
    elif kind == "dev_zero":
        index.symlink_to("/dev/zero")
    else:
        index.write_bytes(b" " * (5 << 20))
    driver = ModbusPlcDriver(host="127.0.0.1", port=1, share=str(share), connect_retries=0)

    async def go() -> None:
        async with asyncio.timeout(20), driver:
            pass

    with pytest.raises(DriverError) as err:
        asyncio.run(go())
    assert "experiment index refused" in str(err.value) and "\n" not in str(err.value)


def test_a_symlinked_share_folder_is_refused_at_open(tmp_path: Path) -> None:
    from robid_link.drivers.file_share import FileShareDriver

    share, elsewhere = tmp_path / "share", tmp_path / "elsewhere"
    share.mkdir()
    elsewhere.mkdir()
    (share / "sem").symlink_to(elsewhere, target_is_directory=True)
    driver = FileShareDriver(share=str(share), canary_interval_s=0)

    async def go() -> None:
        async with driver:
            pass

    with pytest.raises(DriverError, match=r"sem: a symbolic link; refusing to write through it"):
        asyncio.run(go())
    assert os.listdir(elsewhere) == []
