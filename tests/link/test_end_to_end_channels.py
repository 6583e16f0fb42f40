"""A campaign with ``channels: 3`` on a 6-axis robot over the fake file-share controller: each
excitation runs twice (main axes' torques, then wrist axes'), the controller's logs hold three
torque channels each, and the identification joins them."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

from robid_link.config import load_daemon_config
from robid_link.ident.model.robot import load_robot
from robid_link.link.daemon import Daemon

from .conftest import ROOT, ControllerThread, wait_run, write_config

SIX = ROOT / "examples" / "robots" / "industrial6.yaml"
BUDGET = {
    "experiments": [{"kind": "rigid_body", "duration_s": 5, "base_hz": 0.2, "harmonics": 3,
                     "evaluations": 10, "rate_hz": 50}],
    "channels": 3, "timeout_s": 30, "backoff_s": 0.05, "retries": 1,
}


def test_channels_campaign_joins_partial_logs(tmp_path: Path) -> None:
    cfg = write_config(tmp_path, {"budget": BUDGET}, robot=str(SIX))

    async def go() -> tuple[dict[str, Any], list[dict[str, Any]], dict[str, Any]]:
        async with asyncio.timeout(120), Daemon(load_daemon_config(cfg), env={}) as d:
            listed = await d.handle({"cmd": "list"})
            ans = await d.handle({"cmd": "start", "campaign": "budget", "trigger": "operator"})
            run = await wait_run(d, ans["run_id"])
            assert d.store is not None
            return run, await d.store.results(run_id=run["run_id"]), listed

    with ControllerThread(tmp_path / "share", load_robot(SIX)) as ctrl:
        run, results, listed = asyncio.run(go())
    assert run["state"] == "completed", run["error"]
    ids = [e["exp_id"] for e in run["experiments"]]
    assert ids == ["rigid_body-j1-3", "rigid_body-j4-6"]
    assert [e["id"] for e in listed["campaigns"][0]["experiments"]] == ids
    assert sorted(e for e, _ in ctrl.handled) == ids
    logs = sorted((tmp_path / "share" / "outbox").glob("*.log.csv"))
    heads = {p.name.split(".")[0]: p.read_text().splitlines()[0].split(",") for p in logs}
    torques = {k: [h for h in v if h.startswith("tau")] for k, v in heads.items()}
    assert sorted(map(tuple, torques.values())) == [("tau1", "tau2", "tau3"),
                                                    ("tau4", "tau5", "tau6")]
    assert all(sum(h.startswith("q") for h in v) == 6 for v in heads.values())
    rec = next(r["record"] for r in results if r["kind"] == "identify")
    assert len(rec["rmse"]) == 6 and all(x is not None and x > 0 for x in rec["rmse"])
    assert len(rec["data"]) == 2
    html = (tmp_path / "state" / "reports" / run["run_id"] / "report.html").read_text()
    assert "partial logs joined" in html
