"""The operator's page in headless Chromium: every page's figures draw with no console error,
a run's page is its report, and a form POST without the token is refused and changes nothing."""

from __future__ import annotations

from dataclasses import replace

import pytest

from robid_link.config import load_daemon_config
from robid_link.link.store import Store
from robid_link.web.server import WebServer

from ..web.cell import TOKEN, Recorder, build_cell, serving
from .test_report_page import DRAWN, _empty

pytestmark = pytest.mark.browser

@pytest.fixture(scope="module")
def site(tmp_path_factory):
    cell = build_cell(tmp_path_factory.mktemp("cell"))
    cfg = load_daemon_config(cell.config)
    cfg = replace(cfg, web=replace(cfg.web, token=TOKEN))
    rec = Recorder()
    with serving(WebServer(cfg, "127.0.0.1:0", cell.robot, actions=rec)) as url:
        yield url, cell, rec


def _figures(page, url: str) -> list[dict]:
    page.page.goto(url)
    page.page.wait_for_load_state("load")
    return page.page.eval_on_selector_all("[data-figure]", DRAWN)


def test_runs_page_lists_every_run_and_refreshes(page, site):
    url, cell, _ = site
    figs = _figures(page, url)
    runs = next(f for f in figs if f["name"] == "runs")
    assert runs["rows"] == len(cell.runs)
    page.page.wait_for_timeout(3500)  # one refresh of the list
    assert page.page.locator('#runs-table tr[data-state="running"]').count() == 1
    assert page.problems() == []
    assert {r.split("?")[0] for r in page.requests} == {url}  # the page and its refresh


def test_a_runs_page_is_its_report(page, site):
    url, cell, _ = site
    page.page.goto(f"{url}runs/{cell.runs['reported']}")
    page.page.wait_for_selector("body[data-rendered]", timeout=30_000)
    figs = page.page.eval_on_selector_all("[data-figure]", DRAWN)
    assert {"measured-vs-model", "residual", "parameters", "tracking"} <= {
        f["name"] for f in figs}
    assert [f for f in figs if _empty(f)] == []
    assert page.problems() == []


@pytest.mark.parametrize("path, names", [
    ("trend", {"trend-rmse", "trend"}),
    ("compare?a=robot:arm3&b=robot:arm3", {"compare-sides", "compare-errors",
                                           "compare-parameters"}),
    ("params", {"params"}),
    ("fleet", {"fleet-robots", "fleet-flags", "fleet-types"}),
])
def test_trend_compare_and_parameter_sets_draw(page, site, path, names):
    url, _, _ = site
    figs = _figures(page, url + path)
    assert names <= {f["name"] for f in figs}
    if path == "trend":
        page.page.wait_for_selector("body[data-rendered]")
        for f in page.page.eval_on_selector_all("[data-figure]", DRAWN):  # uPlot, not a report
            assert f["plots"] == 1 and f["ink"] > 50, f
    else:
        assert [f for f in figs if _empty(f)] == []
    assert page.problems() == []


def test_a_form_post_without_the_token_is_refused_and_changes_nothing(page, site):
    url, cell, rec = site
    with Store(cell.state, readonly=True) as store:
        before = store.runs(1000)
    page.page.goto(url)
    with page.page.expect_navigation():
        page.page.click("form[action='/actions/start'] button")
    assert "forbidden: token missing or wrong" in page.page.content()
    assert rec.calls == []
    with Store(cell.state, readonly=True) as store:
        assert store.runs(1000) == before
    page.page.goto(url)  # with the operator's token typed in, the same form starts the run
    page.page.fill("#op-token", TOKEN)
    with page.page.expect_navigation():
        page.page.click("form[action='/actions/start'] button")
    assert "run r-new queued" in page.page.content()
    assert rec.calls == [{"cmd": "start", "campaign": "nightly", "by": "web",
                          "trigger": "web"}]
    rec.calls.clear()
