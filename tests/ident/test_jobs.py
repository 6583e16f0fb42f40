"""One job runner: the result keeps its fit, diagnose reuses it, files and history are written."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from robid_link.atomic import append_durable
from robid_link.ident.diagnosis import diagnose as diagnose_module
from robid_link.ident.diagnosis.history import read_history
from robid_link.ident.fit.identify import identify, load_logs
from robid_link.ident.model.effects import DEFAULT_MODEL, save_model
from robid_link.ident.runner import run_job

from ..conftest import simulate


@pytest.fixture
def arm3_logs(arm3, tmp_path):
    return load_logs(arm3, [simulate(arm3, tmp_path / "log.csv", seed=21, duration=20.0).path])


def test_result_computes_its_figures_from_what_it_was_fitted_on(arm3, arm3_logs):
    res = identify(arm3, arm3_logs, DEFAULT_MODEL)
    assert "held_out" not in vars(res)  # nothing computed before it is asked for
    pb = res.problem
    # the held-out RMSE is the residual of the kept fit on the held-out rows
    pc = pb.valid[0]
    r = res.residuals(pc.prep)[pc.lo: pc.hi]
    np.testing.assert_allclose(res.rmse, np.sqrt(np.mean(r**2, axis=0)), rtol=1e-9)
    assert "held_out" in vars(res)
    np.testing.assert_allclose(res.predict() + res.residuals(), pb.preps[0].tau)


def test_job_diagnoses_on_the_identification_it_wrote(arm3, arm3_logs, tmp_path,
                                                      monkeypatch):
    model_file = tmp_path / "model.yaml"
    save_model(model_file, DEFAULT_MODEL)
    seen = []
    real = diagnose_module.identify
    monkeypatch.setattr(diagnose_module, "identify", lambda *a, **k: seen.append(1) or real(
        *a, **k))
    out = tmp_path / "rep"
    job = run_job(arm3, arm3_logs, DEFAULT_MODEL, analyses=("identify", "diagnose"),
                  json_files={"identify": out / "i.json", "diagnose": out / "d.json"},
                  report_dir=out, history=model_file)
    assert seen == []  # the diagnosis reused the job's fit
    assert job.diagnosis is not None and job.diagnosis.result is job.result
    ident, diag = (json.loads((out / n).read_text()) for n in ("i.json", "d.json"))
    assert diag["rmse"] == ident["rmse"] and diag["data_files"] == ident["data_files"]
    assert {p.name for p in job.report_files["identify"]} >= {"summary.txt", "parameters.csv"}
    assert all(p.is_file() for files in job.report_files.values() for p in files)
    assert [r["kind"] for r in read_history(model_file)] == ["identify", "diagnose"]
    assert not [f for f in os.listdir(out) if f.endswith(".tmp")]


def test_job_refuses_unknown_analyses(arm3, arm3_logs):
    with pytest.raises(ValueError, match="elasticity"):
        run_job(arm3, arm3_logs, DEFAULT_MODEL, analyses=("identify", "elasticity"))


def test_append_durable_appends_whole_lines(tmp_path):
    path = tmp_path / "h.jsonl"
    append_durable(path, b"one\n")
    append_durable(path, b"two\n")
    assert path.read_bytes() == b"one\ntwo\n"
