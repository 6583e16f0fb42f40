"""report.html without a browser: packed arrays, the report document (ladder, parameter checks,
residual statistics), one self-contained file written by the job runner, and bad inputs."""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest

from robid_link.exceptions import RobidError
from robid_link.ident.data.preprocess import ZeroPhaseFilter
from robid_link.ident.diagnosis.history import read_history
from robid_link.ident.fit.identify import load_logs
from robid_link.ident.model.effects import DEFAULT_MODEL, save_model
from robid_link.ident.report.content import ladder_section, parameter_rows, report_document
from robid_link.ident.report.html import (
    add_to_report,
    read_report_data,
    render_html,
    write_html_report,
)
from robid_link.ident.report.pack import BITS, pack, unpack
from robid_link.ident.report.series import white_step
from robid_link.ident.runner import run_job

from ..conftest import simulate


def test_pack_keeps_time_exactly_and_signals_to_a_millionth_of_their_range():
    rng = np.random.default_rng(0)
    t = np.arange(20_000) / 1000.0 + 1234.5
    np.testing.assert_array_equal(unpack(pack(t, "f8")), t)
    x = np.cumsum(rng.normal(size=20_000)) + 100.0
    x[50:70] = np.nan
    x[-1] = np.nan
    back = unpack(pack(x))
    assert np.array_equal(np.isnan(back), np.isnan(x))
    ok = ~np.isnan(x)
    span = np.ptp(x[ok])
    assert np.max(np.abs(back[ok] - x[ok])) <= 0.5 * span / 2**BITS * 1.0001
    assert back[ok].max() == pytest.approx(x[ok].max(), abs=span / 2**BITS)
    for edge in (np.full(5, 3.25), np.full(4, np.nan), np.array([])):
        np.testing.assert_array_equal(unpack(pack(edge)), edge)
    with pytest.raises(ValueError, match="dtype 'f4'"):
        pack(x, "f4")


def test_pack_is_compact_for_a_smooth_signal():
    t = np.arange(40_000) / 1000.0
    smooth = 50.0 * np.sin(2 * np.pi * 0.3 * t)
    noisy = smooth + np.random.default_rng(1).normal(scale=0.3, size=t.size)
    assert len(pack(smooth)["z"]) < 0.35 * len(pack(noisy)["z"]) < 0.35 * 4 * t.size


def test_white_step_samples_filtered_white_noise_where_it_is_white():
    filt = ZeroPhaseFilter(10.0, 1000.0)
    step = white_step(filt)
    assert 45 <= step <= 65  # ≈ 0.55 / fc
    y = filt.apply(np.random.default_rng(2).normal(size=400_000))[::step]
    y = y - y.mean()
    lag1 = float(y[1:] @ y[:-1] / (y @ y))
    assert abs(lag1) < 2.58 / np.sqrt(y.size)  # inside the 99 % band of white noise
    assert white_step(ZeroPhaseFilter(200.0, 250.0)) == 1  # an inactive filter


def _record(kind, effects, rmse, sha="a" * 64, run_id=None, verdict=None):
    rec = {"time": "2026-01-01T00:00:00", "kind": kind, "effects": effects, "rmse": rmse,
           "relative_error": 0.01, "data": [{"path": "/logs/run.csv", "sha256": sha}]}
    if run_id:
        rec["run_id"] = run_id
    if verdict:
        rec["verdict"] = verdict
    return rec


def test_ladder_merges_a_runs_records_and_labels_each_version_by_its_effects():
    base = ["rigid_body", "viscous", "coulomb"]
    records = [_record("identify", base, [0.5, 0.3], run_id="r1"),
               _record("diagnose", base, [0.5, 0.3], run_id="r1", verdict="missing_effect"),
               _record("identify", [*base, "ripple@1"], [0.34, 0.3], sha="b" * 64),
               _record("identify", [*base, "ripple@1"], [0.33, 0.3]),
               _record("identify", ["rigid_body", "viscous", "ripple@1"], [0.4, 0.3])]
    lad = ladder_section(records, ["a" * 64])
    rungs = lad["rungs"]
    assert [r["label"] for r in rungs] == ["v1: rigid_body, viscous, coulomb", "v2: +ripple@1",
                                           "v2: +ripple@1", "v3: −coulomb"]
    assert rungs[0]["kinds"] == ["identify", "diagnose"]
    assert rungs[0]["verdict"] == "missing_effect"
    assert [r["same_data"] for r in rungs] == [True, False, True, True]
    assert lad["versions"] == 3 and rungs[1]["data"] == ["run.csv"]


def test_parameter_checks_name_what_is_not_physical():
    doc = {"parameters": [
        {"name": "fv_1", "value": -2.0, "std": 0.1, "expression": "fv_1", "unit": "N·m·s/rad"},
        {"name": "fc_2", "value": 1.5, "std": 0.1, "expression": "fc_2"},
        {"name": "zz_1", "value": 3.0, "std": 0.1, "expression": "zz_1 + 0.2·m_2",
         "nominal": 2.5},
        {"name": "yz_3", "value": 0.01, "std": 0.05, "expression": "yz_3"}]}
    fv, fc, zz, yz = parameter_rows(doc)
    assert fv["check_ok"] is False and "negative viscous friction" in fv["check"]
    assert fc["check_ok"] is True and fc["meaning"] == "Coulomb friction, joint 2"
    assert zz["check"].startswith("combination") and zz["change"] == pytest.approx(0.5)
    assert zz["change_sigmas"] == pytest.approx(5.0) and zz["meaning"].startswith("inertia Izz")
    assert not yz["identified"] and "not identified" in yz["check"]


def test_a_report_of_nothing_is_refused():
    with pytest.raises(ValueError, match="nothing to show"):
        report_document()


@pytest.fixture(scope="module")
def job_report(tmp_path_factory):
    """A job with --out and a model file: identify writes report.html with its ladder."""
    from robid_link.ident.model.robot import load_robot

    from ..conftest import ROBOTS

    tmp = tmp_path_factory.mktemp("job")
    arm3 = load_robot(ROBOTS / "arm3.yaml")
    sim = simulate(arm3, tmp / "log.csv", seed=21, duration=20.0)
    model_file = tmp / "model.yaml"
    save_model(model_file, DEFAULT_MODEL)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        logs = load_logs(arm3, [sim.path])
        job = run_job(arm3, logs, DEFAULT_MODEL, report_dir=tmp / "rep", history=model_file,
                      run_id="run-1", campaign="nightly")
    return job, sim, model_file


def test_job_writes_one_self_contained_report(job_report):
    job, sim, _ = job_report
    page = job.report_html
    assert page is not None and page.name == "report.html" and page.is_file()
    text = page.read_text("utf-8")
    assert not re.search(r"<(script|link|img|iframe)[^>]+(src|href)=", text)
    assert "Content-Security-Policy" in text and "connect-src 'none'" in text
    for name in ("measured-vs-model", "residual", "parameters", "ladder", "robot"):
        assert f'data-figure="{name}"' in text, name
    assert text.count('data-figure="measured-vs-model"') == 3
    assert 'data-figure="diagnosis"' not in text  # identify only: nothing diagnosed
    doc = read_report_data(page)
    assert doc["run"] == {"run_id": "run-1", "campaign": "nightly"}
    assert doc["verdict"]["code"] == "not_diagnosed"
    assert [f["role"] for f in doc["files"]] == ["data"] and doc["files"][0]["valid"]
    meas = unpack(doc["series"][0]["joints"][1]["meas"])
    step = doc["series"][0]["joints"][1]["meas"]["step"]
    np.testing.assert_allclose(meas, sim.data["tau"][:, 1], atol=step)
    assert [r["label"] for r in doc["ladder"]["rungs"]] == ["v1: rigid_body, viscous, coulomb"]
    stats = doc["residual_stats"]
    assert stats["rows"] == "held-out" and len(stats["joints"][0]["acf"]) == 51
    assert stats["joints"][0]["acf"][25] == pytest.approx(1.0)


def test_a_report_can_be_given_its_ladder_and_tracking_later(job_report, tmp_path):
    job, _, model_file = job_report
    page = tmp_path / "report.html"
    page.write_bytes(job.report_html.read_bytes())
    tracking = {"before": {"joint_rms": [0.01] * 3, "joint_max": [0.02] * 3,
                           "tool_rms_mm": 1.0, "tool_max_mm": 2.0, "residual_mm": 0.5}}
    add_to_report(page, history=read_history(model_file) * 2, tracking=tracking)
    doc = read_report_data(page)
    assert len(doc["ladder"]["rungs"]) == 2
    assert doc["tracking"]["phases"]["before"]["joint_max"][0] == pytest.approx(
        np.degrees(0.02))
    assert 'data-figure="tracking"' in page.read_text("utf-8")


def test_reading_what_is_not_a_report_names_the_file(tmp_path):
    with pytest.raises(RobidError, match=r"missing\.html: not a readable report"):
        read_report_data(tmp_path / "missing.html")
    other = tmp_path / "other.html"
    other.write_text("<html><body>hello</body></html>")
    with pytest.raises(RobidError, match=r"other\.html: no report data in it"):
        read_report_data(other)
    bad = tmp_path / "bad.html"
    bad.write_text('<script type="application/json" id="robid-data">{"format": "x/9"}</script>')
    with pytest.raises(RobidError, match=r"bad\.html: report format x/9, expected robid-report/1"):
        read_report_data(bad)


def test_write_html_report_into_a_file_or_a_folder(job_report, tmp_path):
    job, _, _ = job_report
    assert write_html_report(tmp_path / "a", result=job.result) == tmp_path / "a" / "report.html"
    assert write_html_report(tmp_path / "b.html", result=job.result) == tmp_path / "b.html"


def test_elasticity_section_shows_what_the_fit_found_in_the_log(tmp_path):
    """The elasticity table carries the arm's Coulomb friction, the torque delay and χ²/dof; a
    held torque and a third mass are stated under it; a record stored without those fields
    (an older run's) still renders."""
    from robid_link.ident.elastic.elasticity import (
        ElasticityResult,
        JointElasticity,
        two_mass_frf,
    )
    from robid_link.ident.elastic.frequency import Frf
    from robid_link.ident.model.robot import load_robot

    from ..conftest import ROBOTS

    robot = load_robot(ROBOTS / "arm3.yaml")
    f = np.geomspace(2, 60, 12)
    frf = Frf((1,), f, two_mass_frf(f, 0.8, 2.5, 9000.0, 6.0, 1.5), np.ones(f.size),
              np.full(f.size, 200.0))
    std = dict.fromkeys(("jm", "ja", "k", "d", "ba", "delay_s"), 1e-3)
    joint = JointElasticity(1, 0.8, 2.5, 9000.0, 6.0, std, 0.01, ba=1.5, fc=0.97,
                            delay_s=-2.5e-4, hold_s=5e-4, third=(0.6, 37900.0, 9.0), chi2=1.07)
    res = ElasticityResult("twomass", [joint], [frf], notes=["[F = 15, p = 1e-06] a note"])
    doc = read_report_data(write_html_report(tmp_path / "a", elasticity=res,
                                            robot=robot))
    [row] = doc["bode"]["joints"]
    assert row["fc_arm"] == 0.97 and row["delay_s"] == -2.5e-4 and row["chi2"] == 1.07
    text = re.sub(r"<[^>]+>", " ", (tmp_path / "a" / "report.html").read_text("utf-8"))
    for shown in ("Fc arm", "0.97", "delay [ms]", "-0.25", "χ²/dof", "1.07",
                  "held over each sample (0.0005 s)", "third mass behind the arm, j3 0.6",
                  "37900", "F = 15, p = 1e-06"):
        assert shown in text, shown
    old = {k: v for k, v in joint.as_dict().items()
           if k not in ("fc_arm", "delay_s", "hold_s", "third_mass", "chi2", "tests")}
    page = render_html({**report_document(elasticity=res, robot=robot),
                        "bode": {"frfs": [], "joints": [old], "notes": [], "coupled": None}})
    assert "Fc arm" in page


def test_every_function_of_the_report_script_is_used():
    """A helper nobody calls (``caption`` was one) is dead weight in every report file."""
    import re
    from pathlib import Path

    import robid_link.ident.report as report_pkg

    js = (Path(report_pkg.__file__).parent / "static" / "report.js").read_text()
    declared = re.findall(r"\bfunction\s+([A-Za-z_$][\w$]*)\s*\(", js)
    declared += re.findall(r"\bconst\s+([A-Za-z_$][\w$]*)\s*=\s*(?:\([^)]*\)|\w+)\s*=>", js)
    assert declared
    unused = [n for n in declared if len(re.findall(rf"(?<![\w$.]){re.escape(n)}\b", js)) < 2]
    assert not unused, unused
