"""report.html in headless Chromium: every figure draws, nothing is logged as an error, nothing
is fetched, zoom is shared by every joint, and decimation keeps every extreme."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from robid_link.ident.diagnosis.history import read_history
from robid_link.ident.elastic.elasticity import (
    ElasticityResult,
    coupled_frf,
    fit_coupled,
    fit_two_mass,
    two_mass_frf,
)
from robid_link.ident.elastic.frequency import Frf
from robid_link.ident.fit.identify import load_logs
from robid_link.ident.model.effects import DEFAULT_MODEL, EffectSpec, save_model
from robid_link.ident.model.robot import load_robot
from robid_link.ident.report.html import add_to_report, write_html_report
from robid_link.ident.runner import run_job

from ..conftest import ROBOTS, simulate

pytestmark = pytest.mark.browser

RIPPLE = {"name": "ripple", "joint": 1, "amplitude": 0.6, "period": 0.1}
#: what every identify + diagnose report holds (at least)
NAMES = {"measured-vs-model", "residual", "residual-vs-q", "residual-vs-qd",
         "residual-histogram", "residual-acf", "residual-ccf", "parameters", "diagnosis",
         "evidence", "ladder", "tracking", "tracking-trace", "robot", "errors", "files",
         "joints"}
_T = [0.01 * k for k in range(400)]
TRACKING = {"before": {"joint_rms": [2e-3, 1e-3, 1e-3], "joint_max": [6e-3, 3e-3, 3e-3],
                       "tool_rms_mm": 0.4, "tool_max_mm": 1.4, "residual_mm": 0.5,
                       "trace": {"t": _T, "mm": [1.4 * abs(math.sin(t)) for t in _T]}},
            "after": {"joint_rms": [3e-4, 2e-4, 2e-4], "joint_max": [9e-4, 6e-4, 6e-4],
                      "tool_rms_mm": 0.05, "tool_max_mm": 0.16, "residual_mm": 0.11,
                      "trace": {"t": _T[:-5], "mm": [0.16 * abs(math.sin(t)) for t in _T[:-5]]}}}

#: per [data-figure] element: what it drew (table rows, SVG shapes, inked canvas pixels and
#: finite points of its plots, or text)
DRAWN = """els => els.map(el => {
  const out = {name: el.dataset.figure, joint: el.dataset.joint || null};
  const tag = el.tagName.toLowerCase();
  if (tag === "table") { out.rows = el.querySelectorAll("tr").length - 1; return out; }
  if (tag === "svg") {
    out.shapes = el.querySelectorAll("line,rect,circle,path").length;
    return out;
  }
  out.ink = 0;
  for (const c of el.querySelectorAll("canvas")) {
    const d = c.getContext("2d").getImageData(0, 0, c.width, c.height).data;
    for (let i = 3; i < d.length; i += 4 * 5) if (d[i] > 0) out.ink++;
  }
  out.points = 0;
  for (const p of window.robidReport ? window.robidReport.plots : []) {
    if (!el.contains(p.el)) continue;
    for (const s of p.u.data.slice(1)) {
      const ys = Array.isArray(s) && Array.isArray(s[1]) ? s[1] : s;  // a scatter: [xs, ys]
      for (const v of ys || []) if (v != null && isFinite(v)) out.points++;
    }
  }
  out.plots = el.querySelectorAll(".uplot").length;
  out.text = el.textContent.trim().length;
  return out;
})"""


@pytest.fixture(scope="module")
def reports(tmp_path_factory) -> dict[str, Path]:
    """An identify + diagnose report of a robot with a hidden ripple, its error ladder after
    the ripple was added, tracking before and after; an elasticity report (joint 1, pair 2–3)."""
    tmp = tmp_path_factory.mktemp("reports")
    arm3 = load_robot(ROBOTS / "arm3.yaml")
    sim = simulate(arm3, tmp / "log.csv", seed=5, duration=20.0,
                   effects=({"name": "viscous", "fv": 2.0}, {"name": "coulomb", "fc": 1.5},
                            RIPPLE))
    model_file = tmp / "model.yaml"
    save_model(model_file, DEFAULT_MODEL)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the identification's notes
        logs = load_logs(arm3, [sim.path])
        job = run_job(arm3, logs, DEFAULT_MODEL, analyses=("identify", "diagnose"),
                      history=model_file)
        page = write_html_report(tmp / "run", result=job.result, diagnosis=job.diagnosis,
                                 history=read_history(model_file), model_file=model_file)
        ripple = EffectSpec("ripple", 1, (("period", RIPPLE["period"]),))
        run_job(arm3, logs, DEFAULT_MODEL.with_added(ripple), history=model_file)
    add_to_report(page, history=read_history(model_file), tracking=TRACKING)
    return {"run": page, "elastic": _elastic_report(tmp / "elastic")}


def _elastic_report(out: Path) -> Path:
    f = np.geomspace(2, 60, 24)
    coherence = np.linspace(0.7, 1.0, f.size)
    one = Frf((1,), f, two_mass_frf(f, 3.0, 7.0, 3e4, 30.0), coherence, np.full(f.size, 200.0))
    kg = np.array([[-250.0, -50.0], [-50.0, -50.0]])
    g = coupled_frf(f, (8.0, 2.0), (22.0, 3.3), 6.5, (1.5e5, 6e4), (90.0, 25.0), (3.0, 2.0), kg)
    pair = Frf((2, 3), f, g, coherence, np.full(f.size, 200.0))
    (a, b), coupled = fit_coupled(pair, kg=kg)
    res = ElasticityResult("industrial6", [fit_two_mass(one), a, b], [one, pair], coupled,
                           data_files=["steps.csv"])
    return write_html_report(out, elasticity=res, robot=load_robot(ROBOTS / "industrial6.yaml"))


def _open(page, path: Path) -> list[dict]:
    page.page.goto(path.as_uri())
    page.page.wait_for_selector("body[data-rendered]", timeout=30_000)
    assert page.page.evaluate("document.body.dataset.rendered") == "1"
    return page.page.eval_on_selector_all("[data-figure]", DRAWN)


def _empty(fig: dict) -> bool:
    if "rows" in fig:
        return fig["rows"] < 1
    if "shapes" in fig:
        return fig["shapes"] < 3
    if fig["plots"]:
        return fig["ink"] < 50 or fig["points"] < 3
    return fig["text"] == 0


def test_every_figure_of_a_run_draws_with_no_error_and_no_request(page, reports):
    figs = _open(page, reports["run"])
    assert {f["name"] for f in figs} >= NAMES
    assert [f for f in figs if _empty(f)] == []
    per_joint = {"measured-vs-model", "residual", "residual-vs-q", "residual-acf"}
    for name in per_joint:  # one per joint, numbered from 1
        assert sorted(f["joint"] for f in figs if f["name"] == name) == ["1", "2", "3"], name
    assert page.problems() == []
    assert page.requests == [reports["run"].as_uri()]  # the page itself, nothing else


def test_the_hidden_effect_is_the_first_suggestion_with_its_command(page, reports):
    _open(page, reports["run"])
    rows = page.page.eval_on_selector_all('[data-figure="diagnosis"] tr', "rs => rs.map(r => "
                                          "r.textContent)")
    assert "ripple@1" in rows[1] and "robid model add" in rows[1]
    assert str(reports["run"].parent.parent / "model.yaml") in rows[1]
    ladder = page.page.eval_on_selector_all('[data-figure="ladder-table"] tr',
                                            "rs => rs.map(r => r.textContent)")
    assert "v1: rigid_body, viscous, coulomb" in ladder[1] and "v2: +ripple@1" in ladder[2]


def _ranges(page) -> list[list[float]]:
    return page.page.evaluate("window.robidReport.timePlots.map(p => "
                              "[p.u.scales.x.min, p.u.scales.x.max])")


def test_zoom_on_one_joint_moves_every_joint(page, reports):
    _open(page, reports["run"])
    full = _ranges(page)
    over = page.page.locator('[data-figure="measured-vs-model"][data-joint="2"] .u-over')
    over.scroll_into_view_if_needed()
    box = over.bounding_box()
    y = box["y"] + box["height"] / 2
    page.page.mouse.move(box["x"] + 0.3 * box["width"], y)
    page.page.mouse.down()
    page.page.mouse.move(box["x"] + 0.45 * box["width"], y, steps=8)
    page.page.mouse.up()
    zoomed = _ranges(page)
    assert len(zoomed) == 6  # torque and residual of 3 joints
    for lo, hi in zoomed:
        assert (lo, hi) == pytest.approx(zoomed[0])
        assert hi - lo < 0.3 * (full[0][1] - full[0][0])
    page.page.dblclick('[data-figure="residual"][data-joint="3"] .u-over')
    assert np.allclose(_ranges(page), full)
    assert page.problems() == []


#: per time plot: does the full view hold each series' min and max, and does a zoom to 40
#: samples show exactly those samples?
SAMPLES = """async () => {
  const out = [];
  const R = window.robidReport;
  for (const p of R.timePlots) {
    const t = p.spec.t;
    for (let k = 0; k < p.spec.ys.length; k++) {
      const y = p.spec.ys[k], shown = p.u.data[k + 1].filter(v => v != null);
      let lo = Infinity, hi = -Infinity;
      for (const v of y) if (v === v) { lo = Math.min(lo, v); hi = Math.max(hi, v); }
      out.push({full: y.length, shown: shown.length,
                keeps: Math.min(...shown) === lo && Math.max(...shown) === hi});
    }
  }
  const t = R.timePlots[0].spec.t, a = Math.floor(t.length / 2);
  R.zoomAll([t[a], t[a + 39]]);
  await new Promise(done => setTimeout(done, 50));  // uPlot commits a new scale in a task
  const p = R.timePlots[0];
  const idx = p.u.data[0].map(x => t.indexOf(x));
  const same = idx.every((i, k) => i >= 0 && p.u.data[1][k] === p.spec.ys[0][i]);
  return {series: out, idx: idx, same: same};
}"""


def test_decimation_keeps_extremes_and_zoom_shows_every_sample(page, reports):
    _open(page, reports["run"])
    got = page.page.evaluate(SAMPLES)
    for s in got["series"]:
        assert s["keeps"], s
        assert s["shown"] < s["full"]  # decimated: fewer points than samples
    idx = got["idx"]
    assert got["same"] and idx == list(range(idx[0], idx[0] + len(idx)))  # consecutive rows
    assert len(idx) >= 40


def test_elasticity_report_draws_bode_and_coherence_of_each_response(page, reports):
    figs = _open(page, reports["elastic"])
    bode = [f for f in figs if f["name"] == "bode"]
    assert len(bode) == 5  # joint 1; H22, H23, H32, H33
    assert all(f["plots"] == 3 and not _empty(f) for f in bode)
    assert [f for f in figs if _empty(f)] == []
    assert page.problems() == [] and page.requests == [reports["elastic"].as_uri()]
