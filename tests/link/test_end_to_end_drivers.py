"""Per driver (Modbus PLC, serial line), the daemon and the fake controller as separate
processes: a daemon SIGKILLed at several points of a campaign and restarted finishes it with
every log stored intact exactly once, and the controller ran each program once."""

from __future__ import annotations

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


@pytest.mark.parametrize("driver", ["modbus_plc", "serial_line"])
def test_sigkill_then_resume_exactly_once(tmp_path: Path, driver: str) -> None:
    with peer_process(tmp_path, driver) as options:
        cfg = write_config(tmp_path, {"quick": QUICK}, driver=options)
        run_id, run = kill_then_resume(tmp_path, cfg, ["given", "taken", "raw_stored", "given"])
    assert run["state"] == "completed", run["error"]
    assert_stored_once(tmp_path / "state", run_id)
    assert len(controller_runs(tmp_path)) == 2  # each program ran once on the controller
