"""The fleet report's figures, drawn from the report dict (what the tasks returned): each
robot's flagged parameters over its runs, per model version."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from robid_link.ident.diagnosis import drift
from robid_link.ident.report.figures import trend_figure

__all__ = ["trend_of", "flagged_trend_figures"]


def trend_of(robot: str, doc: dict[str, Any]) -> drift.Trend:
    """A ``drift.Trend`` back from its report form (``Trend.as_dict`` and the flags)."""
    values = {n: [None if v is None else (v["value"], v["std"]) for v in vals]
              for n, vals in doc["parameters"].items()}
    fields = drift.Flag.__dataclass_fields__
    flags = [drift.Flag(**{k: f[k] for k in fields}) for f in doc["flags"]]
    return drift.Trend(robot, doc["runs"], values, {n: "" for n in values}, flags,
                       doc["baseline_runs"])


def flagged_trend_figures(report: dict[str, Any], folder: Path) -> list[Path]:
    """``<robot>.<version>.trend.png`` for each robot and model version with drift flags."""
    out = []
    for r in report["robots"]:
        for label, doc in r["versions"].items():
            if not doc["flags"]:
                continue
            names = list(dict.fromkeys(f["parameter"] for f in doc["flags"]))
            slug = re.sub(r"[^A-Za-z0-9_.-]+", "_", label).strip("_")[:60]
            out.append(trend_figure(trend_of(r["robot"], doc), names,
                                    folder / f"{r['robot']}.{slug}.trend.png"))
    return out
