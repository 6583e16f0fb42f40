"""Per driver (Modbus PLC, serial line), the daemon and the fake controller as separate
processes: a daemon SIGKILLed at several points of a campaign and restarted finishes it with
every log stored intact exactly once, and the controller ran each program once."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from .conftest import (
    QUICK,
    assert_stored_once,
    controller_runs,
    kill_then_resume,
    peer_process,
    write_config,
)

_VALIDATE = [pytest.mark.slow, pytest.mark.skipif(not os.environ.get("ROBID_VALIDATE"),
                                                  reason="make validate")]


# make test kills the file share, RWS and CANopen daemons mid-run (their own end-to-end files);
# these two links' kills run under make validate
@pytest.mark.parametrize("driver", [pytest.param("modbus_plc", marks=_VALIDATE),
                                    pytest.param("serial_line", marks=_VALIDATE)])
def test_sigkill_then_resume_exactly_once(tmp_path: Path, driver: str) -> None:
    with peer_process(tmp_path, driver) as options:
        cfg = write_config(tmp_path, {"quick": QUICK}, driver=options)
        run_id, run = kill_then_resume(tmp_path, cfg, ["given", "taken", "raw_stored", "given"])
    assert run["state"] == "completed", run["error"]
    assert_stored_once(tmp_path / "state", run_id)
    assert len(controller_runs(tmp_path)) == 2  # each program ran once on the controller
