"""Re-identification of many robots' stored logs with another model, one task per run, in
parallel; the results go into the store as a new model version (the caller writes, as each
task ends), beside the runs' own, so the fleet report shows both side by side before the
model is rolled out."""

from __future__ import annotations

import fnmatch
import hashlib
import statistics
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import Any

from robid_link.exceptions import ConfigError, RobidError
from robid_link.fleet.engine import Engine
from robid_link.fleet.tasks import reidentify_run
from robid_link.safeopen import describe, read_regular

__all__ = ["plan_jobs", "reidentify", "default_version", "parse_since"]

_MODEL_BYTES = 1 << 20


def parse_since(text: str) -> float:
    """``--since``: an ISO date or date-time (local time unless it says otherwise)."""
    try:
        return datetime.fromisoformat(text).timestamp()
    except ValueError:
        raise ConfigError(f"--since {text}: expected a date like 2025-03-01 or "
                          "2025-03-01T18:00") from None


def default_version(model: Path, text: str) -> str:
    """The model version a re-identification is stored under: the file's stem and the start
    of its content's hash (the same file twice is the same version)."""
    return f"{model.stem}-{hashlib.sha256(text.encode()).hexdigest()[:8]}"


def plan_jobs(store: Any, model: Path, robots: str = "*", since: float | None = None
              ) -> list[dict[str, Any]]:
    """One job per completed run (of the robots matching the glob ``robots``, created since
    ``since``) whose logs the store knows: what ``reidentify_run`` takes."""
    try:  # never blocks on a FIFO; a model file is a few kB
        text = read_regular(model, _MODEL_BYTES).decode("utf-8", "replace")
    except OSError as err:
        raise ConfigError(f"--model {describe(err, model)}") from err
    names = [r["robot"] for r in store.robots() if fnmatch.fnmatchcase(r["robot"], robots)]
    if not names:
        raise ConfigError(f"--robot {robots}: no robot of the store matches")
    jobs = []
    for robot in names:
        runs = store.identify_inputs(robot, since)
        if not runs:
            continue
        desc_name, desc, lock = store.robot_description(robot)
        for run in runs:
            settings = run["spec"].get("identify") or {}
            jobs.append({"robot": robot, "run_id": run["run_id"], "description_name": desc_name,
                         "description": desc, "lock": lock, "logs": run["logs"],
                         "model_name": model.name, "model_text": text,
                         "method": settings.get("method", "ols"),
                         "cutoff_hz": settings.get("cutoff_hz"),
                         "motor_side": bool(settings.get("motor_side", False))})
    if not jobs:
        raise ConfigError(f"no completed run with stored logs for robot(s) {robots}"
                          + (" since then" if since is not None else ""))
    return jobs


def reidentify(engine: Engine, jobs: list[dict[str, Any]], write: Callable[..., None],
               version: str, report: Callable[[str], None] = print) -> dict[str, Any]:
    """Run the jobs on ``engine``; ``write(run_id, robot, kind, record, model_version=…)``
    stores each record as its task ends (a failed run is reported and skipped). A summary
    per robot: runs identified, failed, and the mean relative error."""
    futures = [engine.submit(reidentify_run, job) for job in jobs]
    per_robot: dict[str, dict[str, Any]] = {}
    for _, out in engine.as_completed(futures):
        robot = per_robot.setdefault(out["robot"], {"identified": 0, "failed": [],
                                                    "relative_error": []})
        if "error" in out:
            robot["failed"].append({"run_id": out["run_id"], "error": out["error"]})
            report(f"{out['robot']} run {out['run_id']}: failed: {out['error']}")
            continue
        rec = out["record"]
        write(out["run_id"], out["robot"], "identify", rec, model_version=version)
        robot["identified"] += 1
        if rec.get("relative_error") is not None:
            robot["relative_error"].append(rec["relative_error"])
        report(f"{out['robot']} run {out['run_id']}: identified, relative error "
               f"{100 * rec['relative_error']:.2f} %" if rec.get("relative_error") is not None
               else f"{out['robot']} run {out['run_id']}: identified")
    if not any(r["identified"] for r in per_robot.values()):
        raise RobidError(f"no run could be re-identified with model version {version}")
    return {"version": version, "robots": {
        name: {**r, "relative_error": statistics.fmean(r["relative_error"])
               if r["relative_error"] else None} for name, r in sorted(per_robot.items())}}
