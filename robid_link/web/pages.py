"""HTML of the operator's page, rendered from the views (``views.py``) with Jinja2; a run's
report is the worker's report.html page of the same document."""

from __future__ import annotations

import time
from functools import cache
from typing import Any

from robid_link.ident.report.html import embed_json, render_html, static_text

__all__ = ["runs_page", "run_page", "compare_page", "trend_page", "params_page",
           "message_page"]


def _when(t: float | None) -> str:
    return "—" if t is None else time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(t))


def _ago(t: float | None) -> str:
    if t is None:
        return "—"
    s = max(0.0, time.time() - t)
    if s < 90:
        return f"{s:.0f} s"
    if s < 5400:
        return f"{s / 60:.0f} min"
    return f"{s / 3600:.1f} h" if s < 172800 else f"{s / 86400:.1f} d"


def _num(x: Any, digits: int = 4) -> str:
    if x is None:
        return "—"
    return f"{x:.{digits}g}" if isinstance(x, float) else str(x)


@cache
def _environment() -> Any:
    import jinja2
    import markupsafe

    env = jinja2.Environment(loader=jinja2.PackageLoader("robid_link.web", "templates"),
                             autoescape=True, trim_blocks=True, lstrip_blocks=True,
                             undefined=jinja2.StrictUndefined)
    env.filters.update(when=_when, ago=_ago, num=_num,
                       json=lambda d: markupsafe.Markup(embed_json(d)))
    env.globals["static"] = {name: markupsafe.Markup(static_text(name)) for name in
                             ("report.css", "uPlot.min.css", "uPlot.iife.min.js")}
    return env


def _render(template: str, ctx: dict[str, Any], **kw: Any) -> str:
    return str(_environment().get_template(template).render(ctx=ctx, **kw))


def runs_page(view: dict[str, Any], ctx: dict[str, Any], *, fragment: bool = False) -> str:
    return _render("runs_table.html.j2" if fragment else "runs.html.j2", ctx, view=view)


def run_page(view: dict[str, Any], ctx: dict[str, Any]) -> str:
    """The run's report page (the worker's report.html of its document) when it has one."""
    if view["report"] is not None:
        run = view["run"]
        return render_html(view["report"], nav=[("all runs", "/"), (
            f"run {run['run_id']}: {run['state']}", f"/api/runs/{run['run_id']}"), (
            "compare", f"/compare?a={run['run_id']}"), ("trend", "/trend"),
            ("parameter sets", "/params")])
    return _render("run.html.j2", ctx, view=view)


def compare_page(view: dict[str, Any] | None, recent: dict[str, Any], ctx: dict[str, Any],
                 selected: dict[str, str | None]) -> str:
    return _render("compare.html.j2", ctx, view=view, recent=recent, selected=selected)


def trend_page(view: dict[str, Any], ctx: dict[str, Any]) -> str:
    return _render("trend.html.j2", ctx, view=view)


def params_page(view: dict[str, Any], ctx: dict[str, Any]) -> str:
    return _render("params.html.j2", ctx, view=view)


def fleet_page(view: dict[str, Any], ctx: dict[str, Any]) -> str:
    return _render("fleet.html.j2", ctx, view=view)


def message_page(doc: dict[str, Any]) -> str:
    return _render("message.html.j2", {}, doc=doc)
