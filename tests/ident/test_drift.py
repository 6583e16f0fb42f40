"""Drift across nightly identifications: friction rising 30 % over 10 runs is flagged at the
first run past the thresholds; 20 nightly runs of a healthy robot raise no flag."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import pytest

from robid_link.exceptions import ModelError
from robid_link.ident.diagnosis.drift import DEFAULT_MIN_CHANGE, compare, parameter_kind, trend
from robid_link.ident.diagnosis.history import result_record
from robid_link.ident.fit.identify import identify, load_logs
from robid_link.ident.model.effects import DEFAULT_MODEL
from robid_link.ident.model.robot import Robot
from tests.conftest import simulate

# the arm's a-priori model has no friction: slow logs warn of a torque-scale mismatch
pytestmark = pytest.mark.filterwarnings(
    "ignore:.*a-priori model's torque:robid_link.exceptions.DataWarning")


def _nightly(robot: Robot, tmp: Path, factors: list[float], name: str,
             seed0: int) -> list[dict[str, Any]]:
    """Stored results of one robot's nightly runs, friction scaled by ``factors``."""
    rows = []
    for k, f in enumerate(factors):
        log = simulate(robot, tmp / f"{name}{k}.csv", duration=20.0, rate=250.0, noise=0.3,
                       effects=({"name": "viscous", "fv": 2.0 * f},
                                {"name": "coulomb", "fc": 1.5 * f}), seed=seed0 + k,
                       inertials=robot.nominal)
        res = identify(robot, load_logs(robot, [log.path]), DEFAULT_MODEL)
        rec = result_record("identify", res.to_dict())
        rec["time"] = f"2026-11-{k + 1:02d}T02:30:00"
        rows.append({"run_id": f"{name}-{k:02d}", "robot": name, "kind": "identify",
                     "record": rec})
    return rows


def test_rising_friction_is_flagged_at_the_first_run_past_the_threshold(
        arm3: Robot, tmp_path: Path) -> None:
    factors = [1.0 + 0.3 * k / 9 for k in range(10)]  # +30 % over 10 nightly runs
    tr = trend(_nightly(arm3, tmp_path, factors, "worn", 40), "worn")
    base = sum(factors[:3]) / 3
    expected = next(k for k, f in enumerate(factors) if (f - base) / base > DEFAULT_MIN_CHANGE)
    friction = [f for f in tr.flags if f.kind == "friction"]
    assert friction, tr.table()
    # the robot is flagged at that run; each friction parameter by the next one at the latest
    # (its own estimate and the baseline's scatter set its confidence interval)
    assert min(f.run_id for f in friction) == f"worn-{expected:02d}", tr.table()
    assert {f.parameter for f in friction} == {f"f{c}_{j}" for c in "vc" for j in (1, 2, 3)}
    assert max(f.run_id for f in friction) <= f"worn-{expected + 1:02d}", tr.table()
    assert all(f.change > 0 and "wear" in f.message for f in friction)
    assert not [f for f in tr.flags if f.kind != "friction"], tr.table()


@pytest.mark.slow
@pytest.mark.skipif(not os.environ.get("ROBID_VALIDATE"), reason="make validate")
def test_twenty_healthy_nights_raise_no_flag(arm3: Robot, tmp_path: Path) -> None:
    tr = trend(_nightly(arm3, tmp_path, [1.0] * 20, "healthy", 70), "healthy")
    assert tr.flags == [], tr.table()


def test_a_healthy_week_raises_no_flag(arm3: Robot, tmp_path: Path) -> None:
    tr = trend(_nightly(arm3, tmp_path, [1.0] * 6, "healthy", 90), "healthy")
    assert tr.flags == [], tr.table()
    assert "no drift beyond the thresholds" in tr.table()


def test_compare_two_robots_of_one_type(arm3: Robot, tmp_path: Path) -> None:
    rows = (_nightly(arm3, tmp_path, [1.0], "a", 1) + _nightly(arm3, tmp_path, [1.3], "b", 2))
    text = compare(rows, "a", "b")
    fv1 = next(line for line in text.splitlines() if line.strip().startswith("fv_1"))
    assert float(fv1.split()[-2].rstrip("%")) == pytest.approx(30.0, abs=5.0)
    with pytest.raises(ModelError, match="robot c: no stored identification"):
        compare(rows, "a", "c")


def test_parameter_kinds() -> None:
    assert parameter_kind("fv_2")[0] == "friction"  # type: ignore[index]
    assert parameter_kind("fcn_6")[0] == "friction"  # type: ignore[index]
    assert parameter_kind("mx_3", "mx_3 + 0.4·m_3")[0] == "gravity"  # type: ignore[index]
    assert parameter_kind("zz_1", "zz_1 + 0.16·m_2") is None
    assert parameter_kind("off_1") is None


def test_results_trend_and_compare_from_the_cli(arm3: Robot, tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    import json

    from robid_link.cli import main
    from robid_link.link.store import Store

    rows = _nightly(arm3, tmp_path, [1.0, 1.0, 1.0, 1.4], "r1", 5)
    rows += _nightly(arm3, tmp_path, [1.0], "r2", 9)
    with Store(tmp_path / "state") as store:
        for r in rows:
            store.add_result(r["run_id"], r["robot"], "identify", r["record"])
    cfg = _daemon_config(tmp_path)
    assert main(["results", "--config", str(cfg), "--robot", "r1", "--trend", "--json",
                 str(tmp_path / "t.json"), "--out", str(tmp_path / "t.png")]) == 0
    out = capsys.readouterr().out
    assert "trend of r1 over 4 runs" in out and "friction rose" in out
    doc = json.loads((tmp_path / "t.json").read_text())
    assert {f["run_id"] for f in doc["flags"]} == {"r1-03"}
    assert (tmp_path / "t.png").stat().st_size > 1000
    assert main(["results", "--config", str(cfg), "--compare", "r1", "r2"]) == 0
    assert "r1 (run r1-03) vs r2 (run r2-00)" in capsys.readouterr().out
    assert main(["results", "--config", str(cfg), "--trend"]) == 2
    assert "--trend: name the robot with --robot NAME" in capsys.readouterr().err


def test_status_names_the_drift(arm3: Robot, tmp_path: Path,
                                capsys: pytest.CaptureFixture[str]) -> None:

    from robid_link.cli import main
    from robid_link.link.campaign import drift_flags
    from robid_link.link.store import Store

    rows = _nightly(arm3, tmp_path, [1.0, 1.0, 1.0, 1.4], "arm3", 21)
    with Store(tmp_path / "state") as store:
        for r in rows:
            store.add_result(r["run_id"], r["robot"], "identify", r["record"])
        assert {f.run_id for f in drift_flags(store, "arm3", "arm3-03")} == {"arm3-03"}
        assert drift_flags(store, "arm3", "arm3-02") == []
    cfg = _daemon_config(tmp_path)
    assert main(["status", "--config", str(cfg)]) == 0
    out = capsys.readouterr().out
    assert "drift: " in out and "friction rose (wear or lubrication)" in out


def _daemon_config(tmp_path: Path) -> Path:
    """A daemon config over tmp_path/state (no daemon runs: the CLI reads the store)."""
    import yaml

    cfg = tmp_path / "link.yaml"
    cfg.write_text(yaml.safe_dump({
        "robot": str(Path(__file__).resolve().parents[2] / "examples/robots/arm3.yaml"),
        "state_dir": str(tmp_path / "state"), "control_socket": str(tmp_path / "no.sock"),
        "driver": {"name": "file_share", "share": str(tmp_path)},
        "campaigns": {"nightly": {"experiments": ["rigid_body"]}}}))
    return cfg
