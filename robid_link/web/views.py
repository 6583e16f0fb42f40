"""What the operator's page shows, read from the store: every view is one JSON-able dict that
``/api/…`` returns as it is and the HTML page renders (one query path, as Datasette does)."""

from __future__ import annotations

import math
import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from robid_link.exceptions import ConfigError, ModelError, RobidError
from robid_link.ident.fit.results import parameter_unit
from robid_link.ident.report.content import tracking_section
from robid_link.ident.report.html import REPORT_NAME, read_report_data
from robid_link.link.store import Store

__all__ = ["runs_view", "run_view", "compare_view", "trend_view", "params_view",
           "report_document_of", "RUNS_LIMIT"]

#: runs listed by default (``?limit=`` up to RUNS_MAX)
RUNS_LIMIT = 200
RUNS_MAX = 5000
JOURNAL_TAIL = 100


def _report_path(store: Store, run_id: str) -> Path | None:
    """Where the run's report.html is; None for a plant's store opened by its URL alone (the
    reports are in each cell's state dir)."""
    return store.dir / "reports" / run_id / REPORT_NAME if store.dir is not None else None


def _reported(store: Store) -> set[str]:
    """Runs whose report folder holds a report.html (one listing, not a path per run)."""
    if store.dir is None:  # a plant's store without a cell: no report here
        return set()
    try:
        with os.scandir(store.dir / "reports") as it:
            return {e.name for e in it if os.path.isfile(os.path.join(e.path, REPORT_NAME))}
    except OSError:
        return set()


def _run_row(store: Store, run: dict[str, Any], robot: str, reported: set[str]
             ) -> dict[str, Any]:
    """A run as the list shows it: state, step, progress, times, what it waits for."""
    waiting = None
    if run["state"] == "queued":
        waiting = run["created"]
    elif run["state"] == "interrupted":  # for an operator's resume since the restart
        waiting = run.get("state_since") or run["created"]
    elif run["state"] == "running":  # since the last thing the journal says happened
        tail = store.journal(run["run_id"])[-1:]
        waiting = tail[0]["time"] if tail else run["started"]
    return {"run_id": run["run_id"], "robot": robot, "campaign": run["campaign"],
            "trigger": run["trigger"], "state": run["state"], "step": run["step"],
            "error": run["error"], "created": run["created"], "started": run["started"],
            "finished": run["finished"], "waiting_since": waiting,
            "progress": run["progress"],
            "experiments": [{"exp_id": e["exp_id"], "kind": e["kind"], "state": e["state"],
                             "attempt": e["attempt"], "error": e["error"]}
                            for e in run["experiments"]],
            "report": run["run_id"] in reported}


def runs_view(store: Store, robot: str, limit: int = RUNS_LIMIT) -> dict[str, Any]:
    """The newest runs first (``limit`` of them)."""
    limit = max(1, min(int(limit), RUNS_MAX))
    reported = _reported(store)
    return {"generated": time.time(), "robot": robot,
            "runs": [_run_row(store, r, robot, reported) for r in store.runs(limit)]}


def report_document_of(store: Store, run_id: str, results: Sequence[dict[str, Any]]
                       ) -> dict[str, Any] | None:
    """The run's report document with what came after it was written: tracking of the
    verification runs, the elasticity fits (their parameters; the stored records keep no
    frequency points)."""
    path = _report_path(store, run_id)
    if path is None or not path.is_file():
        return None
    doc = read_report_data(path)
    phases = {r["kind"].removeprefix("verify_"): r["record"]["tracking"] for r in results
              if r["kind"].startswith("verify_") and "tracking" in r["record"]}
    if phases:
        doc["tracking"] = tracking_section(phases, doc["robot"]["joints"])
    fits = [e["result"] for r in results if r["kind"] == "elasticity"
            for e in r["record"].get("experiments", [])]
    if fits and not doc.get("bode"):
        doc["bode"] = {"frfs": [], "joints": [j for f in fits for j in f.get("joints", [])],
                       "notes": [n for f in fits for n in f.get("notes", [])],
                       "coupled": next((f["coupled"] for f in fits if f.get("coupled")), None)}
    return doc


def run_view(store: Store, run_id: str, robot: str) -> dict[str, Any]:
    """One run: its row, its results (records by kind), the journal's tail and its report
    document (None before the identification wrote one)."""
    run = _run_row(store, store.run(run_id), robot, _reported(store))
    results = store.results(run_id=run_id)
    return {"run": run, "results": [{"kind": r["kind"], "robot": r["robot"], "time": r["time"],
                                     "record": r["record"]} for r in results],
            "journal": store.journal(run_id)[-JOURNAL_TAIL:],
            "report": report_document_of(store, run_id, results)}


def _identify_of(store: Store, ref: str) -> dict[str, Any]:
    """The identification a comparison side names: a run id, or ``robot:NAME`` (its newest)."""
    if ref.startswith("robot:"):
        rows = [r for r in store.results(ref.removeprefix("robot:")) if r["kind"] == "identify"]
        if not rows:
            raise ConfigError(f"robot {ref.removeprefix('robot:')}: no stored identification")
        return rows[-1]
    rows = [r for r in store.results(run_id=ref) if r["kind"] == "identify"]
    if not rows:
        store.run(ref)  # names a run that is not in the store
        raise ConfigError(f"run {ref}: no identification stored (yet)")
    return rows[-1]


def compare_view(store: Store, a: str, b: str) -> dict[str, Any]:
    """Two identifications side by side: errors per joint, parameters, their differences
    (also in combined standard errors)."""
    sides = [_identify_of(store, ref) for ref in (a, b)]
    recs = [s["record"] for s in sides]
    params = [{p["name"]: p for p in r.get("parameters") or []} for r in recs]
    names = list(dict.fromkeys([*params[0], *params[1]]))
    rows = []
    for n in names:
        pa, pb = params[0].get(n), params[1].get(n)
        row: dict[str, Any] = {"name": n, "a": pa, "b": pb, "delta": None, "sigmas": None}
        if pa and pb:
            row["delta"] = pb["value"] - pa["value"]
            s = math.hypot(pa.get("std") or 0.0, pb.get("std") or 0.0)
            row["sigmas"] = abs(row["delta"]) / s if s > 0 else None
        rows.append(row)
    rmse = [r.get("rmse") or [] for r in recs]
    return {"sides": [{"ref": ref, "run_id": s["run_id"], "robot": s["robot"], "time": s["time"],
                       "effects": r.get("effects"), "rmse": r.get("rmse"),
                       "relative_error": r.get("relative_error")}
                      for ref, s, r in zip((a, b), sides, recs, strict=True)],
            "rmse_delta": [None if x is None or y is None else y - x
                           for x, y in zip(rmse[0], rmse[1], strict=False)],
            "parameters": rows}


def trend_view(store: Store, robot: str) -> dict[str, Any]:
    """Each parameter of ``robot`` over its runs (oldest first), each run labelled with its
    model version (a new set of effects starts a new version), and the drift flags."""
    from robid_link.ident.diagnosis.drift import trend

    rows = store.results(robot)
    try:
        tr = trend(rows, robot)
    except ModelError:
        return {"robot": robot, "runs": [], "parameters": {}, "flags": [], "versions": []}
    doc = tr.as_dict()
    ident = {r["run_id"]: r for r in rows if r["kind"] == "identify"}
    versions: list[tuple[str, ...]] = []
    for run in doc["runs"]:
        row = ident[run["run_id"]]
        eff = tuple(row["record"].get("effects") or ())
        if eff not in versions:
            versions.append(eff)
        run.update(version=versions.index(eff) + 1, time_s=row["time"],
                   rmse=row["record"].get("rmse"))
    doc["versions"] = [list(v) for v in versions]
    doc["expressions"] = tr.expressions
    doc["units"] = {n: parameter_unit(n, (), False)[0] for n in doc["parameters"]}
    return doc


def params_view(store: Store, robots: Sequence[str]) -> dict[str, Any]:
    """The parameter sets of each robot: version, origin, approval, and which one the
    controller runs (and would roll back to)."""
    out = []
    for robot in robots:
        active = store.active_param_sets(robot)
        sets = [{"version": s["version"], "sha256": s["sha256"], "run_id": s["run_id"],
                 "created": s["created"], "approved": s["approved"],
                 "approved_by": s["approved_by"],
                 "in_use": bool(active) and s["sha256"] == active[-1],
                 "rollback_target": len(active) > 1 and s["sha256"] == active[-2]}
                for s in store.param_sets(robot)]
        out.append({"robot": robot, "sets": sets})
    return {"robots": out}


def robots_in(store: Store, default: str) -> list[str]:
    """Robots with stored results, the config's first."""
    try:
        found = {r["robot"] for r in store.results()}
    except RobidError:
        found = set()
    return [default, *sorted(found - {default})]


def fleet_page_view(store: Store) -> dict[str, Any]:
    """The plant's robots in this store (``robid fleet``'s report, computed here): per robot
    and model version its runs, latest parameters and drift flags; outliers per robot type.
    A store without robots yet gives an empty report, not an error."""
    from robid_link.fleet.analysis import fleet_view

    try:
        return fleet_view(store)
    except RobidError as err:
        return {"format": None, "store": store.where, "robots": [], "types": [], "flags": [],
                "outliers": [], "empty": str(err)}

