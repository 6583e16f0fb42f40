"""report.html: the report document rendered into one self-contained page (Jinja2 template,
styles, uPlot and the page's script inline, the document itself as embedded JSON)."""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping, Sequence
from functools import cache
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any

from robid_link.atomic import atomic_write
from robid_link.exceptions import RobidError
from robid_link.ident.fit.results import IdentResult
from robid_link.ident.model.robot import Robot
from robid_link.ident.report.content import (
    FORMAT,
    bode_section,
    ladder_section,
    report_document,
    tracking_section,
)

if TYPE_CHECKING:
    from robid_link.ident.diagnosis.diagnose import Diagnosis
    from robid_link.ident.elastic.elasticity import ElasticityResult

__all__ = ["render_html", "write_html_report", "write_document", "read_report_data",
           "static_text", "embed_json", "add_to_report", "REPORT_NAME"]

REPORT_NAME = "report.html"
_STATIC = ("uPlot.min.css", "report.css", "uPlot.iife.min.js", "report.js")
_DATA_TAG = re.compile(r'<script type="application/json" id="robid-data">(.*?)</script>', re.S)


@cache
def static_text(name: str) -> str:
    """A file of the report's static folder (styles, scripts) as text."""
    return (resources.files("robid_link.ident.report") / "static" / name).read_text("utf-8")


@cache
def _environment() -> Any:
    import jinja2

    env = jinja2.Environment(
        loader=jinja2.PackageLoader("robid_link.ident.report", "templates"),
        autoescape=True, trim_blocks=True, lstrip_blocks=True,
        undefined=jinja2.StrictUndefined)
    env.filters["num"] = _num
    env.filters["pct"] = lambda x, digits=3: "—" if x is None else f"{100 * x:.{digits}g} %"
    return env


def _num(x: Any, digits: int = 4) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "—"
    if isinstance(x, int) and not isinstance(x, bool):
        return str(x)
    return f"{x:.{digits}g}"


def _clean(x: Any) -> Any:
    """JSON without NaN or ∞ (the page and ``/api`` read it as strict JSON)."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_clean(v) for v in x]
    return x


def embed_json(doc: Any) -> str:
    """``doc`` as strict JSON (NaN, ∞ → null) that cannot end a script element early."""
    text = json.dumps(_clean(doc), ensure_ascii=False, separators=(",", ":"), allow_nan=False)
    return text.replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026")


def render_html(doc: Mapping[str, Any], nav: Sequence[tuple[str, str]] = ()) -> str:
    """One self-contained page of a report document (``report_document``); ``nav``: (label,
    link) pairs above it (the operator's page)."""
    import markupsafe

    static = {name.replace(".", "_").replace("-", "_"): markupsafe.Markup(static_text(name))
              for name in _STATIC}
    return str(_environment().get_template("report.html.j2").render(
        doc=doc, static=static, data=markupsafe.Markup(embed_json(doc)), nav=list(nav)))


def read_report_data(path: str | Path) -> dict[str, Any]:
    """The document embedded in a report.html this module wrote."""
    p = Path(path)
    try:
        text = p.read_text("utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise RobidError(f"{p}: not a readable report ({err})") from err
    m = _DATA_TAG.search(text)
    if m is None:
        raise RobidError(f"{p}: no report data in it (not written by robid)")
    try:
        doc = json.loads(m.group(1))
    except ValueError as err:
        raise RobidError(f"{p}: its report data is not valid JSON") from err
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise RobidError(f"{p}: report format {doc.get('format') if isinstance(doc, dict) else '?'}"
                         f", expected {FORMAT}")
    return doc


def write_html_report(out: str | Path, *, result: IdentResult | None = None,
                      diagnosis: Diagnosis | None = None,
                      elasticity: ElasticityResult | None = None,
                      tracking: Mapping[str, Any] | None = None,
                      history: Sequence[Mapping[str, Any]] | None = None,
                      robot: Robot | None = None, model_file: str | Path | None = None,
                      run: Mapping[str, Any] | None = None, title: str | None = None) -> Path:
    """Write report.html (into ``out`` when it is a folder or has no suffix) and return its
    path. ``tracking``: verification runs by phase (``{"before": Tracking.as_dict(), …}``);
    ``history``: the model file's records (``read_history``); ``model_file`` is what the
    suggested ``robid model add`` commands edit."""
    doc = report_document(result=result, diagnosis=diagnosis, elasticity=elasticity,
                          tracking=tracking, history=history, robot=robot,
                          model_file=model_file, run=run, title=title)
    return write_document(out, doc)


def write_document(out: str | Path, doc: Mapping[str, Any]) -> Path:
    """Render a report document to report.html (``out``: the file, or its folder)."""
    p = Path(out)
    if p.is_dir() or not p.suffix:
        p = p / REPORT_NAME
    p.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(p, render_html(doc).encode("utf-8"))
    return p


def add_to_report(path: str | Path, *, history: Sequence[Mapping[str, Any]] | None = None,
                  tracking: Mapping[str, Any] | None = None,
                  elasticity: Sequence[ElasticityResult] = (), robot: Robot | None = None,
                  run: Mapping[str, Any] | None = None) -> Path:
    """Render a report.html again with what came after it was written: the model file's
    error ladder as it stands now, the verification runs' tracking (by phase), the
    elasticity results of the run. Where there is no report yet (a run without an
    identification), write one of these alone (``robot`` and ``run`` name it)."""
    p = Path(path)
    if p.is_dir() or not p.suffix:
        p = p / REPORT_NAME
    if p.exists():
        doc = read_report_data(p)
        if history:
            doc["ladder"] = ladder_section(history,
                                           [f.get("sha256") or "" for f in doc["files"]])
        if tracking:
            doc["tracking"] = tracking_section(tracking, doc["robot"]["joints"])
    else:
        doc = report_document(tracking=tracking or None, history=history, robot=robot, run=run,
                              elasticity=elasticity[0] if elasticity else None)
    if elasticity:
        doc["bode"] = bode_section(list(elasticity))
    return write_document(p, doc)
