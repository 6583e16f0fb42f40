"""``robid demo --driver X`` over every link, from the plain install (issue 19, item 6): each
tells the same story — the hidden effect (ripple on axis 1) found by the diagnosis, the
validation error of axis 1 falling once it is added — and, where the link can upload, the
calibration runs too. ``--quick`` (a 20 s excitation). ``make test`` runs the one link whose
story needed its own read-out (CANopen's torque object); the others run under ``make
validate`` (each demo is a minute or more on two shared cores). ``tests/test_cli.py`` runs the
full-length file-share demo of ``make demo`` in ``make test``, ``tests/drivers/test_ur_rtde.py``
the UR one under ``make validate``."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from robid_link.demo import HIDDEN

VALIDATE = [pytest.mark.slow, pytest.mark.skipif(not os.environ.get("ROBID_VALIDATE"),
                                                 reason="make validate")]
LINKS = [pytest.param("abb_rws", marks=VALIDATE), pytest.param("canopen_drives", marks=VALIDATE),
         pytest.param("modbus_plc", marks=VALIDATE), pytest.param("serial_line", marks=VALIDATE)]


@pytest.mark.demo
@pytest.mark.timeout(900)
@pytest.mark.parametrize("driver", LINKS)
def test_every_link_tells_the_same_story(tmp_path: Path, driver: str) -> None:
    out = subprocess.run([sys.executable, "-m", "robid_link.cli", "demo", "--quick",
                          "--driver", driver, "--out", "rep", "--json", "demo.json"],
                         cwd=tmp_path, capture_output=True, text=True, timeout=840)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    hidden = f"{HIDDEN['name']}@{HIDDEN['joint']}"
    assert f"the diagnosis suggests {hidden}" in out.stdout
    doc = json.loads((tmp_path / "demo.json").read_text())
    assert doc["run"]["state"] == "completed" and doc["model"][-1] == hidden
    before = next(r["record"]["rmse"] for r in doc["results"] if r["kind"] == "identify")
    assert doc["final_rmse"][0] < 0.85 * before[0], (before, doc["final_rmse"])
    # the other axes have nothing hidden: at the noise floor before and after
    assert all(b < 1.0 and abs(a - b) < 0.05 for a, b in zip(doc["final_rmse"][1:],
                                                             before[1:], strict=True))
    can_upload = driver in ("file_share", "abb_rws", "canopen_drives")
    assert ("calibrate and verify: skipped" in out.stdout) is not can_upload
    assert (tmp_path / "rep" / "error_ladder.png").is_file()
