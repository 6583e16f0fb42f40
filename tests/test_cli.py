"""The robid command: JSON fields, report files, and one-line errors."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from robid_link.cli import main

from .conftest import ROBOTS, simulate


@pytest.fixture
def arm3_log(arm3, tmp_path):
    return simulate(arm3, tmp_path / "log.csv", seed=21, duration=20.0).path


def test_identify_json_and_report(arm3_log, tmp_path, capsys):
    out_json, out_dir = tmp_path / "r.json", tmp_path / "rep"
    rc = main(["identify", "--robot", str(ROBOTS / "arm3.yaml"), "--data", str(arm3_log),
               "--add", "offset", "--json", str(out_json), "--out", str(out_dir)])
    assert rc == 0
    doc = json.loads(out_json.read_text())
    for key in ("joints", "effects", "n_samples", "condition_number", "rmse", "rmse_fit",
                "rmse_nominal", "relative_error", "parameters"):
        assert key in doc, key
    assert doc["effects"] == ["rigid_body", "viscous", "coulomb", "offset"]
    assert [j["joint"] for j in doc["joints"]] == [1, 2, 3]
    assert len(doc["rmse"]) == 3 and 0 < doc["relative_error"] < 0.2
    p = doc["parameters"][0]
    assert set(p) >= {"name", "value", "std", "expression"}
    assert any(q["expression"] == "zz_2 + 0.16·m_3" for q in doc["parameters"])
    assert {f.name for f in out_dir.iterdir()} >= {
        "summary.txt", "parameters.csv", "parameters.yaml", "torque_joint1.png", "report.html"}
    text = capsys.readouterr().out
    assert "relative error" in text and "zz_2 + 0.16·m_3" in text
    assert f"report: {out_dir / 'report.html'}" in text


def test_identify_loads_its_modules_without_the_collector_and_turns_it_back_on(arm3_log,
                                                                              tmp_path):
    """A fresh process: the numerical modules load with the cyclic collector off, which is on
    again when the command returns (their objects frozen); the output is whole at exit."""
    code = ("import gc, sys\nfrom robid_link.cli import main\nrc = main(sys.argv[1:])\n"
            "print('collector', gc.isenabled(), gc.get_freeze_count() > 0)\nsys.exit(rc)\n")
    done = subprocess.run([sys.executable, "-c", code, "identify", "--robot",
                           str(ROBOTS / "arm3.yaml"), "--data", str(arm3_log), "--json",
                           str(tmp_path / "r.json")], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "relative error" in done.stdout
    assert done.stdout.rstrip().endswith("collector True True")
    assert json.loads((tmp_path / "r.json").read_text())["relative_error"] > 0


@pytest.mark.parametrize("method", ["wls", "irls"])
def test_identify_methods(arm3_log, method, tmp_path, capsys):
    """The method reaches the estimator: other weights, other estimates, as good a model."""
    docs = {}
    for m in ("ols", method):
        out = tmp_path / f"{m}.json"
        weight = ["--weight", "huber"] if m == "irls" else []
        rc = main(["identify", "--robot", str(ROBOTS / "arm3.yaml"), "--data", str(arm3_log),
                   "--method", m, *weight, "--json", str(out)])
        assert rc == 0
        docs[m] = json.loads(out.read_text())
    assert f"{method.upper()}\n" in capsys.readouterr().out
    ols, other = docs["ols"], docs[method]
    assert other["method"] == method
    assert [p["name"] for p in other["parameters"]] == [p["name"] for p in ols["parameters"]]
    values = np.array([[p["value"] for p in d["parameters"]] for d in (ols, other)])
    assert not np.allclose(values[0], values[1], rtol=1e-9, atol=0.0)
    assert other["relative_error"] < 1.5 * ols["relative_error"]


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--data", "missing.csv"], "robid: error: missing.csv: log file not found"),
        (["--add", "warp_drive"], "robid: error: --add warp_drive: unknown effect 'warp_drive'"),
        (["--add", "viscous@9"], "robid: error: --add viscous@9: effect viscous@9: the robot "
                                 "has 3 joints"),
        (["--interval", "0"], "robid: error: argument --interval: expected a whole number in "
                              "[1, 100000], got '0'"),
        (["--cutoff", "-3"], "robid: error: argument --cutoff: expected a number in (0, 1e+06]"),
        (["--method", "irls", "--weight", "nope"], "robid: error: argument --weight: invalid "
                                                   "choice: 'nope'"),
    ],
)
def test_identify_errors_are_one_line(arm3_log, argv, message, capsys):
    base = ["identify", "--robot", str(ROBOTS / "arm3.yaml")]
    if "--data" not in argv:
        base += ["--data", str(arm3_log)]
    rc = main(base + argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert err[-1].startswith(message)
    assert "Traceback" not in "\n".join(err)


def test_wrong_joint_count_is_one_line(arm3_log, capsys):
    rc = main(["identify", "--robot", str(ROBOTS / "industrial6.yaml"), "--data", str(arm3_log)])
    assert rc == 2
    assert capsys.readouterr().err.strip() == (
        f"robid: error: {arm3_log}: the log has 3 joints (q1..q3), the robot has 6")


def test_show_robot(tmp_path, capsys):
    png = tmp_path / "r.png"
    assert main(["show-robot", "--robot", str(ROBOTS / "industrial6.yaml"), "--q", "0", "-30",
                 "30", "0", "45", "0", "--out", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "1  a1  (revolute)" in capsys.readouterr().out
    assert main(["show-robot", "--robot", str(ROBOTS / "arm3.yaml"), "--q", "0",
                 "--out", str(png)]) == 2
    assert "--q: 1 values given, the robot has 3 joints" in capsys.readouterr().err


def test_model_add(tmp_path, capsys):
    m = tmp_path / "model.yaml"
    assert main(["model", "add", str(m), "offset@2"]) == 0
    assert main(["model", "add", str(m), "friction_power@3"]) == 0
    text = m.read_text()
    assert "offset@2" in text and "viscous" in text
    assert main(["model", "add", str(m), "flux"]) == 2
    assert "unknown effect 'flux'" in capsys.readouterr().err
    m.write_text("effects: [rigid_body, {name: viscous, joint: zero}]")
    assert main(["model", "add", str(m), "offset"]) == 2
    assert "effects[1].joint: expected a joint number from 1" in capsys.readouterr().err


def test_excite_simulate_identify_chain(tmp_path, capsys):
    traj = tmp_path / "exc.csv"
    assert main(["excite", "--robot", str(ROBOTS / "arm3.yaml"), "--out", str(traj),
                 "--duration", "20", "--harmonics", "5", "--evaluations", "150"]) == 0
    out = capsys.readouterr().out
    assert "median of 20 random trajectories" in out and traj.with_suffix(".yaml").is_file()
    truth = tmp_path / "truth.yaml"
    truth.write_text("perturb: {seed: 1, spread: 0.1}\neffects: [{name: viscous, fv: 2.0}, "
                     "{name: coulomb, fc: 1.0}]\nnoise: {tau: 0.2}\nrate_hz: 500\n")
    log = tmp_path / "log.csv"
    assert main(["simulate", "--robot", str(ROBOTS / "arm3.yaml"), "--truth", str(truth),
                 "--trajectory", str(traj), "--out", str(log)]) == 0
    out_json = tmp_path / "r.json"
    assert main(["identify", "--robot", str(ROBOTS / "arm3.yaml"), "--data", str(log),
                 "--json", str(out_json)]) == 0
    doc = json.loads(out_json.read_text())
    assert all(abs(r - 0.2) < 0.03 for r in doc["rmse"])


def test_simulate_errors(tmp_path, capsys):
    truth = tmp_path / "truth.yaml"
    truth.write_text("effects: [{name: viscous}]\n")
    rc = main(["simulate", "--robot", str(ROBOTS / "arm3.yaml"), "--truth", str(truth),
               "--trajectory", str(tmp_path / "none.csv"), "--out", str(tmp_path / "l.csv")])
    assert rc == 2
    assert "effects[0] (viscous): missing key 'fv'" in capsys.readouterr().err


def test_demo_runs_the_whole_job_through_the_daemon(tmp_path):
    """`make demo`'s command, from another folder with a relative --out."""
    import json
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-m", "robid_link.cli", "demo", "--out", "rep",
                          "--json", "demo.json"], cwd=tmp_path, capture_output=True, text=True,
                         timeout=600)
    assert out.returncode == 0, out.stderr + out.stdout
    assert "[####################] 1/1 logs  completed" in out.stdout
    doc = json.loads((tmp_path / "demo.json").read_text())
    assert doc["run"]["state"] == "completed"
    assert doc["model"][-1] == "ripple@1"  # the hidden effect, found and added
    before = next(r["record"]["rmse"] for r in doc["results"] if r["kind"] == "identify")
    assert doc["final_rmse"][0] < 0.7 * before[0]
    for name in ("summary.txt", "diagnose.json", "error_ladder.png", "daemon.log",
                 "model.yaml", "residual_joint1.png", "report.html"):
        assert (tmp_path / "rep" / name).is_file(), name
    assert out.stdout.rstrip().endswith(f"open the report: {tmp_path / 'rep' / 'report.html'}")
    from robid_link.ident.report.html import read_report_data

    page = read_report_data(tmp_path / "rep" / "report.html")  # the diagnosis, then the ladder
    # the demo's plant has nothing else: nothing else is suggested (issue 21, case 8)
    assert [s["label"] for s in page["diagnosis"]["suggestions"]] == ["ripple@1"]
    assert [r["label"] for r in page["ladder"]["rungs"]][-1] == "v2: +ripple@1"
    assert set(page["tracking"]["phases"]) == {"before", "after"}
