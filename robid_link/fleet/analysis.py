"""The fleet report: every robot of a store, each parameter's trend per model version, drift and
wear flags with their evidence, and the outliers of each robot type — one ``robot_trends`` task
per robot, then one ``type_outliers`` task per (type, version) on their results. The same dict
is what ``robid fleet --json`` writes, what its text summary prints, and what a web page reads
(``fleet_view``)."""

from __future__ import annotations

import time
from typing import Any

from robid_link.exceptions import RobidError
from robid_link.fleet.engine import Engine, InlineEngine
from robid_link.fleet.tasks import OUTLIER_Z, robot_trends, type_outliers, version_label
from robid_link.ident.diagnosis import drift

__all__ = ["analyse", "fleet_view", "summary", "robot_inputs", "REPORT_FORMAT"]

REPORT_FORMAT = "robid-fleet/1"
#: the parts of an identify record the tasks read
_RECORD_KEYS = ("time", "robot", "effects", "parameters", "relative_error")


def robot_inputs(store: Any) -> list[tuple[str, str, list[dict[str, Any]]]]:
    """(robot, type, its identify results of every model version) for each robot of the
    store; the type is the robot description's name (from the directory, else the records)."""
    rows_by_robot: dict[str, list[dict[str, Any]]] = {}
    for row in store.results(model_version=None):
        if row["kind"] == "identify":
            rec = row["record"]  # what the tasks read of it: less to send to a worker
            rows_by_robot.setdefault(row["robot"], []).append({
                "run_id": row["run_id"], "kind": "identify",
                "model_version": row["model_version"],
                "record": {k: rec.get(k) for k in _RECORD_KEYS}})
    out = []
    for info in store.robots():
        rows = rows_by_robot.get(info["robot"], [])
        kind = info["type"] or next((r["record"].get("robot") for r in rows
                                     if r["record"].get("robot")), None) or info["robot"]
        out.append((info["robot"], str(kind), rows))
    return out


def analyse(store: Any, engine: Engine | None = None, *,
            sigma: float = drift.DEFAULT_SIGMA, min_change: float = drift.DEFAULT_MIN_CHANGE,
            z_limit: float = OUTLIER_Z) -> dict[str, Any]:
    """The fleet report of ``store`` (a blocking ``Store``), its tasks on ``engine`` (this
    process when None)."""
    engine = engine or InlineEngine()
    inputs = robot_inputs(store)
    if not inputs:
        raise RobidError(f"{store.where}: no robot in the store yet")
    futures = {robot: engine.submit(robot_trends, robot, kind, rows, sigma, min_change)
               for robot, kind, rows in inputs if rows}
    versions = sorted({(kind, version_label(r)) for _, kind, rows in inputs for r in rows
                       if r["record"].get("parameters")})
    by_type: dict[str, list[str]] = {}
    for robot, kind, rows in inputs:
        if rows:
            by_type.setdefault(kind, []).append(robot)
    spreads = [engine.submit(type_outliers, kind, version,
                             [futures[r] for r in by_type[kind]], z_limit)
               for kind, version in versions]
    robots = dict(zip(futures, engine.gather(list(futures.values())), strict=True))
    types = engine.gather(spreads)
    return {
        "format": REPORT_FORMAT,
        "store": store.where,
        "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "thresholds": {"sigma": sigma, "min_change": min_change, "outlier_z": z_limit},
        "robots": [{"robot": robot, "type": kind,
                    "versions": robots[robot]["versions"] if robot in robots else {}}
                   for robot, kind, _ in inputs],
        "types": types,
        "flags": [{"robot": robot, "version": v, **f} for robot, res in robots.items()
                  for v, doc in res["versions"].items() for f in doc["flags"]],
        "outliers": [{"type": t["type"], "version": t["version"], **o} for t in types
                     for o in t["outliers"]],
    }


def fleet_view(store: Any) -> dict[str, Any]:
    """The fleet report computed in this process (no cluster): what a web page shows and
    its JSON twin returns."""
    return analyse(store, InlineEngine())


def summary(report: dict[str, Any]) -> str:
    """The report as text: per robot and model version the runs and flags, then the outliers
    of each type."""
    n_robots = len(report["robots"])
    lines = [f"robid fleet — {n_robots} robot(s) in {report['store']}"]
    for r in report["robots"]:
        if not r["versions"]:
            lines.append(f"  {r['robot']} ({r['type']}): no identification stored yet")
        for label, doc in r["versions"].items():
            flags = doc["flags"]
            lines.append(f"  {r['robot']} ({r['type']}), model {label}: {len(doc['runs'])} "
                         f"run(s), {len(doc['parameters'])} parameters, "
                         f"{len(flags) or 'no'} drift flag(s)")
            for f in flags:
                lines.append(f"    ! run {f['run_id']}: {f['message']}")
    for t in report["types"]:
        if not t["spread"]:
            lines.append(f"  type {t['type']}, model {t['version']}: {len(t['robots'])} "
                         f"robot(s), too few for a spread")
            continue
        lines.append(f"  type {t['type']}, model {t['version']}: {len(t['robots'])} robots, "
                     f"{len(t['outliers']) or 'no'} outlier(s) beyond "
                     f"{report['thresholds']['outlier_z']:g} robust σ")
        lines += [f"    ! {o['message']}" for o in t["outliers"]]
    return "\n".join(lines)
