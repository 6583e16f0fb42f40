"""Issue 22, done when: two daemons for two robots (one robot type) share one real PostgreSQL
store; one is SIGKILLed mid-campaign and resumes with no log stored twice; a third daemon for a
robot already held is refused; ``robid fleet --store URL --scheduler tcp://…`` reports both
robots' trends from tasks run on that scheduler and the same without ``--scheduler``; ``robid
fleet reidentify`` stores the robots' runs again as a new model version, beside the first."""

from __future__ import annotations

import hashlib
import json
import signal
from pathlib import Path
from typing import Any

import yaml

from robid_link.link.store import Store
from tests.fleet.test_fleet_cli import _comparable, scheduler_task_counts
from tests.link.conftest import (
    ARM3,
    kill_then_resume,
    process,
    robid,
    run_status,
    wait_socket,
    write_config,
)


def _cell(tmp: Path, name: str, url: str) -> Path:
    cell = tmp / name
    cell.mkdir()
    return write_config(cell, store=url, robot_name=name)


def _stored_once(url: str, robot: str, run_id: str) -> None:
    """Every log of the run intact and stored exactly once, each experiment given once."""
    with Store(None, url=url, robot=robot, readonly=True) as store:
        exps = store.experiments(run_id)
        shas = [e["log_sha"] for e in exps]
        assert all(shas) and len(set(shas)) == len(exps)
        assert store.log_count() == len(exps)  # this robot's rows: no second copy
        for row in store.identify_inputs(robot):
            for log in row["logs"]:
                assert hashlib.sha256(Path(log["url"]).read_bytes()).hexdigest() == \
                    log["sha256"]
        assert [e["attempt"] for e in exps] == [1] * len(exps)


def test_two_robots_share_a_plant_store_and_the_fleet_sees_both(
        tmp_path: Path, pg_url: str, dask_scheduler: Any) -> None:
    cfg_a, cfg_b = _cell(tmp_path, "cell-a", pg_url), _cell(tmp_path, "cell-b", pg_url)
    a, b = cfg_a.parent, cfg_b.parent
    with process("fake-controller", "--share", str(a / "share"), "--robot", str(ARM3),
                 log=a / "controller.log"), \
         process("fake-controller", "--share", str(b / "share"), "--robot", str(ARM3),
                 log=b / "controller.log"), \
         process("daemon", "--config", str(cfg_a), log=a / "daemon.log") as daemon_a:
        wait_socket(a / "ctl.sock", daemon_a)
        started = robid("campaign", "start", "quick", "--config", str(cfg_a))
        run_a = started.stdout.strip()
        assert run_a, started.stderr
        # a second daemon for robot cell-a, from another cell folder: refused in one line
        twin = tmp_path / "twin"
        twin.mkdir()
        twin_cfg = write_config(twin, store=pg_url, robot_name="cell-a")
        refused = robid("daemon", "--config", str(twin_cfg))
        assert refused.returncode != 0
        assert "robot cell-a is in use by another daemon (pid" in refused.stderr, refused.stderr
        # cell-b is killed right after its first raw log was stored, then resumes
        run_b, rec_b = kill_then_resume(b, cfg_b, ["raw_stored"])
        rec_a = run_status(cfg_a, a)
        daemon_a.send_signal(signal.SIGTERM)
        assert daemon_a.wait(30) == 0
    assert rec_a["state"] == rec_b["state"] == "completed", (rec_a, rec_b)
    _stored_once(pg_url, "cell-a", run_a)
    _stored_once(pg_url, "cell-b", run_b)
    with Store(None, url=pg_url, readonly=True) as plant:
        assert [r["robot"] for r in plant.runs()] == sorted(["cell-a", "cell-b"], key=lambda
                                                            r: {"cell-a": run_a,
                                                                "cell-b": run_b}[r])[::-1]
        robots = {r["robot"]: r for r in plant.robots()}
        assert set(robots) == {"cell-a", "cell-b"} and robots["cell-b"]["type"] == "arm3"
    # the fleet on the named scheduler, and on a local cluster: the same report
    before = scheduler_task_counts(dask_scheduler.address).get("robot_trends", 0)
    remote = robid("fleet", "--store", pg_url, "--scheduler", dask_scheduler.address,
                   "--json", str(tmp_path / "remote.json"))
    assert remote.returncode == 0, remote.stderr
    assert scheduler_task_counts(dask_scheduler.address)["robot_trends"] - before == 2
    local = robid("fleet", "--store", pg_url, "--json", str(tmp_path / "local.json"))
    assert local.returncode == 0, local.stderr
    report = json.loads((tmp_path / "remote.json").read_text())
    assert _comparable(report) == _comparable(json.loads((tmp_path / "local.json").read_text()))
    trends = {r["robot"]: r["versions"] for r in report["robots"]}
    assert set(trends) == {"cell-a", "cell-b"}
    for robot, run_id in (("cell-a", run_a), ("cell-b", run_b)):
        (label, doc), = trends[robot].items()
        assert label.startswith("campaign [") and [r["run_id"] for r in doc["runs"]] == [run_id]
        assert doc["parameters"] and all(len(v) == 1 for v in doc["parameters"].values())
    assert "cell-a (arm3), model campaign [" in remote.stdout
    # another model for both robots, on the scheduler, stored as a new model version
    model = tmp_path / "stribeck.yaml"
    model.write_text(yaml.safe_dump({"effects": ["rigid_body", "viscous", "coulomb",
                                                 "offset"]}))
    again = robid("fleet", "reidentify", "--store", pg_url, "--model", str(model),
                  "--robot", "cell-*", "--version", "with-offset", "--scheduler",
                  dask_scheduler.address)
    assert again.returncode == 0, again.stderr
    assert "cell-a: 1 run(s) stored as with-offset" in again.stdout, again.stdout
    with Store(None, url=pg_url, readonly=True) as plant:
        new = plant.results(model_version="with-offset")
        assert sorted((r["robot"], r["run_id"]) for r in new) == sorted(
            [("cell-a", run_a), ("cell-b", run_b)])
        assert all("offset" in r["record"]["effects"] for r in new)
        assert len(plant.results()) == len(plant.results(model_version=None)) - 2
    after = robid("fleet", "--store", pg_url, "--json", str(tmp_path / "after.json"))
    assert after.returncode == 0, after.stderr
    versions = {r["robot"]: sorted(r["versions"]) for r in
                json.loads((tmp_path / "after.json").read_text())["robots"]}
    assert all(len(v) == 2 and any(x.startswith("with-offset [") for x in v)
               for v in versions.values()), versions
