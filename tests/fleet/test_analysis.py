"""The fleet's analysis run in this process on a synthetic plant (the same task code Dask
runs): the wearing robots are flagged with their evidence, each type's planted outlier is
found, a healthy robot is neither; the task code imports only what the design allows."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from robid_link.fleet.analysis import analyse, fleet_view, summary
from robid_link.fleet.engine import InlineEngine
from robid_link.fleet.synthetic import PlantSpec, fill_store
from robid_link.fleet.tasks import type_outliers
from robid_link.link.store import Store

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def plant(tmp_path: Path) -> tuple[Path, dict]:
    with Store(tmp_path / "plant") as store:
        planted = fill_store(store, PlantSpec(robots=12, nights=10))
    return tmp_path / "plant", planted


def test_wear_and_outliers_are_found_with_their_evidence(plant: tuple[Path, dict]) -> None:
    folder, planted = plant
    with Store(folder, readonly=True) as store:
        engine = InlineEngine()
        report = analyse(store, engine)
    assert engine.tasks == 12 + 2  # a task per robot, one per (type, model version)
    flagged = {f["robot"] for f in report["flags"]}
    assert flagged == set(planted["wearing"]), summary(report)
    for f in report["flags"]:
        assert f["kind"] == "friction" and f["change"] > 0.1
        ev = f["evidence"]
        assert len(ev["baseline_runs"]) == 3 and ev["series"][-1]["value"] > f["baseline"]
    odd = {(o["type"], o["robot"]) for o in report["outliers"] if o["parameter"] == "zz1r"}
    assert odd == {(t, r) for t, r in planted["outliers"].items()}, summary(report)
    healthy = [r["robot"] for r in report["robots"]
               if r["robot"] not in planted["wearing"] and r["robot"]
               not in planted["outliers"].values()]
    assert healthy and not {o["robot"] for o in report["outliers"]} & set(healthy)
    text = summary(report)
    assert "industrial6-003 (industrial6), model campaign [viscous, coulomb]" in text
    with Store(folder, readonly=True) as again:  # the page's view: the same report
        assert fleet_view(again)["flags"] == report["flags"]


def test_a_spread_needs_three_robots_and_ignores_estimation_noise() -> None:
    def robot(name: str, value: float, std: float) -> dict:
        return {"robot": name, "type": "t", "versions": {"v": {"latest": {
            "p": {"value": value, "std": std}}}}}

    two = type_outliers("t", "v", [robot("a", 1.0, 0.01), robot("b", 9.0, 0.01)])
    assert two["spread"] == {} and two["outliers"] == []
    # identical robots but one off by less than their standard errors: no outlier (MAD = 0)
    noisy = [robot(n, 1.0, 0.05) for n in "abcd"] + [robot("e", 1.1, 0.05)]
    assert type_outliers("t", "v", noisy)["outliers"] == []
    off = [robot(n, 1.0 + 0.001 * k, 0.001) for k, n in enumerate("abcd")] + [
        robot("e", 1.5, 0.001)]
    out = type_outliers("t", "v", off)["outliers"]
    assert [o["robot"] for o in out] == ["e"] and out[0]["robust_z"] > 3.5


def test_no_robot_is_one_line(tmp_path: Path) -> None:
    from robid_link.exceptions import RobidError

    Store(tmp_path / "empty").close()
    with Store(tmp_path / "empty", readonly=True) as store:
        with pytest.raises(RobidError, match="no robot in the store yet"):
            analyse(store)


ALLOWED = ("robid_link.exceptions", "robid_link.atomic", "robid_link.safeyaml",
           "robid_link.yamlio", "robid_link.safeopen", "robid_link.jobs", "robid_link.kinds",
           "robid_link.config", "robid_link.ident", "robid_link.link.store", "robid_link.fleet")


def test_the_fleet_imports_only_its_edges() -> None:
    """docs/design.md: fleet may import neutral, door, config, worker, link.store."""
    bad = []
    for path in sorted((ROOT / "robid_link" / "fleet").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                     [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            bad += [(path.name, n) for n in names
                    if n.startswith("robid_link") and not n.startswith(ALLOWED)]
    assert bad == []
