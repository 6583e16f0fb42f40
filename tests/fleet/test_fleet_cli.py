"""``robid fleet`` over a plant's real PostgreSQL store, its tasks on a real Dask scheduler and
worker (started by the session) and on a LocalCluster: the same report either way, the tasks
seen by the named scheduler; ``robid status/results --store``; bad inputs in one line."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from robid_link.fleet.synthetic import PlantSpec, fill_store
from robid_link.link.store import Store
from tests.link.conftest import robid


def _comparable(report: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in report.items() if k not in ("time", "engine")}


def scheduler_task_counts(address: str) -> dict[str, int]:
    """Tasks per function that the scheduler at ``address`` computed (from its transition
    log; asked from a process of its own: a client leaves threads behind in this one)."""
    code = ("import collections, json, sys\n"
            "from distributed import Client\n"
            "def done(dask_scheduler):\n"
            "    keys = {str(t[0]) for t in dask_scheduler.transition_log if t[2] == 'memory'}\n"
            "    return collections.Counter(k.rsplit('-', 1)[0] for k in keys)\n"
            "with Client(sys.argv[1], timeout=30) as c:\n"
            "    print(json.dumps(c.run_on_scheduler(done)))\n")
    out = subprocess.run([sys.executable, "-c", code, address], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    return dict(json.loads(out.stdout.strip().splitlines()[-1]))


@pytest.fixture
def plant_url(pg_url: str, tmp_path: Path) -> tuple[str, dict]:
    with Store(None, url=pg_url, exclusive=False, create=True) as store:
        planted = fill_store(store, PlantSpec(robots=8, nights=8, wear_every=4))
    return pg_url, planted


def test_the_named_scheduler_and_a_local_cluster_give_the_same_report(
        plant_url: tuple[str, dict], dask_scheduler: Any, tmp_path: Path) -> None:
    url, planted = plant_url
    before = scheduler_task_counts(dask_scheduler.address).get("robot_trends", 0)
    remote = robid("fleet", "--store", url, "--scheduler", dask_scheduler.address,
                   "--json", str(tmp_path / "remote.json"), "--out", str(tmp_path / "out"))
    assert remote.returncode == 0, remote.stderr
    local = robid("fleet", "--store", url, "--workers", "1", "--json",
                  str(tmp_path / "local.json"))
    assert local.returncode == 0, local.stderr
    a = json.loads((tmp_path / "remote.json").read_text())
    b = json.loads((tmp_path / "local.json").read_text())
    assert _comparable(a) == _comparable(b)
    assert a["engine"]["scheduler"] == dask_scheduler.address
    assert b["engine"]["local_cluster"] and b["engine"]["scheduler"] != dask_scheduler.address
    # the robots' tasks ran on the named scheduler (one per robot)
    after = scheduler_task_counts(dask_scheduler.address)
    assert after["robot_trends"] - before == 8 and after.get("type_outliers", 0) >= 2
    assert {f["robot"] for f in a["flags"]} == set(planted["wearing"])
    assert {o["robot"] for o in a["outliers"] if o["parameter"] == "zz1r"} == set(
        planted["outliers"].values())
    assert f"tasks on {dask_scheduler.address}" in remote.stdout
    assert "password" not in remote.stdout + remote.stderr
    figures = sorted(p.name for p in (tmp_path / "out").glob("*.png"))
    assert len(figures) == len(planted["wearing"]) and (tmp_path / "out" / "fleet.txt").is_file()


def test_status_and_results_read_the_plant_store(plant_url: tuple[str, dict]) -> None:
    url, _ = plant_url
    res = robid("results", "--store", url, "--robot", "arm3-000")
    assert res.returncode == 0, res.stderr
    assert len(res.stdout.strip().splitlines()) == 8 and "arm3-002" not in res.stdout
    trend = robid("results", "--store", url, "--robot", "arm3-002", "--trend")
    assert trend.returncode == 0 and "trend of arm3-002 over 8 runs" in trend.stdout
    st = robid("status", "--store", url)
    assert st.returncode == 0, st.stderr
    assert "store: plant store postgresql://" in st.stdout and "8 robot(s)" in st.stdout


@pytest.mark.parametrize("args, message", [
    (["fleet", "--store", "postgresql://robid:hunter2@127.0.0.1:1/robid"],
     "the URL holds a password; give it in PGPASSWORD or a PGPASSFILE"),
    (["fleet", "--store", "postgresql://robid@127.0.0.1:1/robid"], "cannot connect"),
    (["fleet", "--store", "x", "--scheduler", "tcp://h:1", "--workers", "2"],
     "--workers: the named scheduler has its own workers"),
    (["fleet", "--store", "x", "--scheduler", "h:1"], "expected an address like tcp://"),
    (["fleet"], "--store: name the plant's store"),
    (["status", "--store", "postgresql://robid:hunter2@h/robid"], "the URL holds a password"),
    (["status", "--store", ""], "--store '': expected postgresql://USER@HOST:PORT/DB or a "),
    (["results", "--store", "/dev/null"], "--store /dev/null: not a folder"),
    (["results", "--store", "/nonexistent/robid"], "--store /nonexistent/robid: no such folder"),
    (["fleet", "reidentify", "--store", "/nonexistent/robid", "--model", "m.yaml"],
     "m.yaml: model file not found"),  # checked before any store or task
])
def test_bad_inputs_are_one_line(args: list[str], message: str) -> None:
    out = robid(*args)
    assert out.returncode == 2, out.stdout + out.stderr
    assert message in out.stderr and len(out.stderr.strip().splitlines()) == 1, out.stderr
    assert "hunter2" not in out.stderr + out.stdout
