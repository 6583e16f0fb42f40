"""The fleet's tasks: pure functions of their inputs (rows read from the store, a robot's
description, logs fetched by URL and checked against their hash) returning JSON-able dicts.
They run on a Dask worker or in this process alike, and never write the store.

- ``robot_trends``: one robot's identify results → each parameter's trend per model version,
  drift and wear flags with their evidence, the latest value of each parameter.
- ``type_outliers``: the latest values of the robots of one type and model version → the
  robots whose parameter leaves the type's spread (median ± k·MAD, robust to the outliers).
- ``reidentify_run``: one stored run's logs identified with another model.
"""

from __future__ import annotations

import hashlib
import math
import statistics
import tempfile
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from robid_link.exceptions import RobidError
from robid_link.ident.diagnosis import drift

__all__ = ["version_label", "robot_trends", "type_outliers", "reidentify_run",
           "OUTLIER_Z", "MAD_SCALE"]

#: a robot is an outlier of its type beyond this many robust standard deviations
OUTLIER_Z = 3.5
#: the MAD of a normal sample times this is its standard deviation
MAD_SCALE = 1.4826
#: fewest robots of a type and version for a spread to mean something
MIN_ROBOTS = 3


def version_label(row: dict[str, Any]) -> str:
    """A result's model version as the report names it: the re-identification's name (or
    ``campaign``, the run's own model) and the model's effects."""
    effects = row["record"].get("effects") or []
    return f"{row.get('model_version') or 'campaign'} [{', '.join(map(str, effects))}]"


def robot_trends(robot: str, robot_type: str, rows: Sequence[dict[str, Any]],
                 sigma: float = drift.DEFAULT_SIGMA,
                 min_change: float = drift.DEFAULT_MIN_CHANGE,
                 baseline_runs: int = drift.DEFAULT_BASELINE_RUNS) -> dict[str, Any]:
    """Trends of one robot, per model version (``rows``: its stored identify results)."""
    groups: dict[str, list[dict[str, Any]]] = {}
    for row in rows:
        if row.get("kind") == "identify" and row["record"].get("parameters"):
            groups.setdefault(version_label(row), []).append({**row, "robot": robot})
    versions = {}
    for label, group in groups.items():
        tr = drift.trend(group, robot, sigma=sigma, min_change=min_change,
                         baseline_runs=baseline_runs)
        doc = tr.as_dict()
        doc["flags"] = [_evidence(f, tr) for f in tr.flags]
        doc["latest"] = {n: {"value": v[-1][0], "std": v[-1][1]}
                         for n, v in tr.values.items() if v and v[-1] is not None}
        doc["kinds"] = {n: k[0] for n in tr.values
                        if (k := drift.parameter_kind(n, tr.expressions[n])) is not None}
        doc["relative_error"] = [row["record"].get("relative_error") for row in group]
        versions[label] = doc
    return {"robot": robot, "type": robot_type, "versions": versions}


def _evidence(flag: drift.Flag, tr: drift.Trend) -> dict[str, Any]:
    """A flag with what it rests on: the baseline runs, and the parameter run by run."""
    series = [{"run_id": run["run_id"], "value": v[0], "std": v[1]}
              for run, v in zip(tr.runs, tr.values[flag.parameter], strict=True)
              if v is not None]
    return {**flag.as_dict(),
            "evidence": {"baseline_runs": [s["run_id"] for s in series[:tr.baseline_runs]],
                         "series": series}}


def type_outliers(robot_type: str, version: str, robots: Sequence[dict[str, Any]],
                  z_limit: float = OUTLIER_Z) -> dict[str, Any]:
    """Robots of ``robot_type`` whose latest value of a parameter (model ``version``) leaves
    the type's spread: ``|x − median| > z_limit · scale``, scale = 1.4826·MAD, but never
    below the median standard error (no robot stands out by estimation noise alone).
    ``robots``: results of ``robot_trends``."""
    latest = {r["robot"]: r["versions"][version]["latest"] for r in robots
              if r["type"] == robot_type and version in r["versions"]}
    names = sorted({n for values in latest.values() for n in values})
    spread, outliers = {}, []
    for name in names:
        have = {robot: vals[name] for robot, vals in latest.items() if name in vals}
        if len(have) < MIN_ROBOTS:
            continue
        xs = [v["value"] for v in have.values()]
        med = statistics.median(xs)
        mad = statistics.median(abs(x - med) for x in xs)
        scale = max(MAD_SCALE * mad, statistics.median(v["std"] for v in have.values()),
                    1e-12 * max(abs(med), 1.0))
        spread[name] = {"median": med, "mad": mad, "scale": scale, "robots": len(have)}
        for robot, v in sorted(have.items()):
            z = (v["value"] - med) / scale
            if abs(z) > z_limit:
                outliers.append({"robot": robot, "parameter": name, "value": v["value"],
                                 "std": v["std"], "median": med, "scale": scale,
                                 "robust_z": z,
                                 "message": f"{robot}: {name} {v['value']:.4g} vs the "
                                            f"{robot_type} median {med:.4g} ({z:+.1f} robust σ "
                                            f"over {len(have)} robots)"})
    return {"type": robot_type, "version": version, "robots": sorted(latest),
            "spread": spread, "outliers": outliers}


def _fetch(url: str, sha: str) -> bytes:
    """A stored log's bytes (a folder path or an fsspec URL), checked against its hash."""
    try:
        if "://" in url:
            import fsspec  # type: ignore[import-untyped]

            with fsspec.open(url, "rb") as fh:
                data = fh.read()
        else:
            data = Path(url).read_bytes()
    except (OSError, ValueError) as err:
        raise RobidError(f"{url}: stored log unreadable ({err})") from err
    got = hashlib.sha256(data).hexdigest()
    if got != sha:
        raise RobidError(f"{url}: stored log damaged (sha256 {got[:12]}…)")
    return bytes(data)


def reidentify_run(job: dict[str, Any]) -> dict[str, Any]:
    """Identify one stored run's logs with another model: ``job`` holds the robot's name,
    description (file name, bytes, locked joints), the run id, the logs (``sha256``, ``url``),
    the model file (name, text) and the run's identification settings (``method``,
    ``cutoff_hz``, ``motor_side``). The identify record, or the error in one line."""
    out = {"robot": job["robot"], "run_id": job["run_id"]}
    try:
        out["record"] = _identify(job)
    except (RobidError, ValueError, ArithmeticError) as err:
        out["error"] = str(err).splitlines()[0] if str(err) else type(err).__name__
    return out


def _identify(job: dict[str, Any]) -> dict[str, Any]:
    from robid_link.ident.fit.identify import load_logs
    from robid_link.ident.model.effects import load_model
    from robid_link.ident.model.robot import load_robot
    from robid_link.ident.runner import run_job

    with tempfile.TemporaryDirectory(prefix="robid-fleet-") as tmp:
        folder = Path(tmp)
        desc = folder / Path(job["description_name"]).name
        desc.write_bytes(job["description"])
        model_file = folder / Path(job["model_name"]).name
        model_file.write_text(job["model_text"])
        paths = []
        for k, log in enumerate(job["logs"]):
            p = folder / f"log{k}-{log['sha256'][:12]}.csv"
            p.write_bytes(_fetch(log["url"], log["sha256"]))
            paths.append(p)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            robot = load_robot(desc, tuple(job["lock"]))
            model = load_model(model_file)
            data = load_logs(robot, paths, None, bool(job.get("motor_side")))
            done = run_job(robot, data, model, analyses=("identify",),
                           cutoff_hz=job.get("cutoff_hz"), method=job.get("method") or "ols",
                           motor_side=bool(job.get("motor_side")), run_id=job["run_id"])
    rec = done.records["identify"]
    urls = {log["sha256"]: log["url"] for log in job["logs"]}
    rec["data"] = [{"path": urls.get(d.get("sha256"), d.get("path")), "sha256": d.get("sha256")}
                   for d in rec.get("data", [])]
    rec["robot"] = robot.name
    rec["warnings"] = sorted({f"{w.category.__name__}: {w.message}" for w in caught})
    rec["model_file"] = job["model_name"]
    if rec.get("relative_error") is not None and not math.isfinite(rec["relative_error"]):
        rec["relative_error"] = None
    return dict(rec)
