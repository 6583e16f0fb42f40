"""The error ladder: one record per identify/diagnose run, next to the model file.

The same record (model effects, per-joint RMSE, data hashes, time) is what the daemon's store
keeps for each result.
"""

from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path
from typing import Any

from robid_link.atomic import append_durable
from robid_link.exceptions import ModelError
from robid_link.safeopen import file_problem

__all__ = ["history_path", "result_record", "append_record", "read_history", "latest_hypers"]


def history_path(model_file: str | Path) -> Path:
    p = Path(model_file)
    return p.with_name(p.name + ".history.jsonl")


def result_record(kind: str, doc: dict[str, Any]) -> dict[str, Any]:
    """The shared result record from an identify or diagnose JSON document."""
    rec = {
        "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "kind": kind,
        "effects": doc.get("effects"),
        "rmse": doc.get("rmse"),
        "relative_error": doc.get("relative_error"),
        "data": [{"path": f.get("path"), "sha256": f.get("sha256")}
                 for f in doc.get("data_files", [])],
    }
    if kind == "identify":  # what drift tracking and the controller's parameter set read
        rec["parameters"] = [{k: p.get(k) for k in ("name", "value", "std", "expression")}
                             for p in doc.get("parameters", [])]
    if kind == "diagnose":
        rec["verdict"] = doc.get("verdict")
        rec["suggestions"] = [{k: s.get(k) for k in ("effect", "joint", "side", "gain",
                                                     "hyper_parameters", "seconds")}
                              for s in doc.get("suggestions", [])]
    return rec


def append_record(model_file: str | Path, record: dict[str, Any]) -> Path:
    """Append one result record. A record of a daemon run (``run_id``) is appended once per
    ``(run_id, kind)``: a run identified again after a crash adds no second line."""
    import fcntl

    path = history_path(model_file)
    if not record.get("run_id"):
        append_durable(path, (json.dumps(record) + "\n").encode())
        return path
    key = (record["run_id"], record.get("kind"))
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)  # check and append as one step between processes
        if key not in _run_keys(path):
            append_durable(path, (json.dumps(record) + "\n").encode())
    finally:
        os.close(fd)  # releases the lock
    return path


def _run_keys(path: Path) -> set[tuple[Any, Any]]:
    try:
        with open(path, "rb") as f:
            text = f.read(MAX_HISTORY_BYTES).decode("utf-8", errors="replace")
    except OSError:
        return set()
    keys = set()
    for line in text.splitlines():
        if '"run_id"' not in line:
            continue
        try:
            rec = json.loads(line)
        except ValueError:
            continue
        if isinstance(rec, dict) and rec.get("run_id"):
            keys.add((rec["run_id"], rec.get("kind")))
    return keys


#: a history grows by one short line per run
MAX_HISTORY_BYTES = 64 * 1024 * 1024


def read_history(model_file: str | Path) -> list[dict[str, Any]]:
    path = history_path(model_file)
    problem = file_problem(path)
    if problem == "not found":
        raise ModelError(f"{model_file}: no history yet ({path.name}); run identify or "
                         "diagnose with --model first")
    if problem:
        raise ModelError(f"{path}: {problem}")
    if path.stat().st_size > MAX_HISTORY_BYTES:
        raise ModelError(f"{path}: larger than the {MAX_HISTORY_BYTES} bytes allowed")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise ModelError(f"{path}: not a readable UTF-8 text file") from err
    out = []
    for i, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except (json.JSONDecodeError, RecursionError, ValueError) as err:
            raise ModelError(f"{path}: line {i} is not valid JSON") from err
        problem = _record_problem(rec)
        if problem:
            raise ModelError(f"{path}: line {i}: {problem}")
        out.append(rec)
    if not out:
        raise ModelError(f"{path}: the history is empty (no runs recorded)")
    return out


def _number_or_none(x: Any) -> bool:
    return x is None or (not isinstance(x, bool) and isinstance(x, int | float)
                         and math.isfinite(x))


def _record_problem(rec: Any) -> str | None:
    """Why a history line is not a result record, or None (fields read by history/model add)."""
    if not isinstance(rec, dict):
        return "expected a JSON object (a result record)"
    for key in ("time", "kind"):
        if not isinstance(rec.get(key), str):
            return f"'{key}' missing or not text"
    if rec.get("verdict") is not None and not isinstance(rec["verdict"], str):
        return "'verdict' must be text"
    if rec.get("effects") is not None and not (
            isinstance(rec["effects"], list) and all(isinstance(e, str) for e in rec["effects"])):
        return "'effects' must be a list of effect labels"
    if rec.get("rmse") is not None and not (
            isinstance(rec["rmse"], list) and all(_number_or_none(x) for x in rec["rmse"])):
        return "'rmse' must be a list of numbers"
    sugg = rec.get("suggestions")
    if sugg is not None and not (isinstance(sugg, list) and all(isinstance(x, dict)
                                                                for x in sugg)):
        return "'suggestions' must be a list of objects"
    for s in sugg or []:
        hyp = s.get("hyper_parameters")
        if hyp is not None and not (isinstance(hyp, dict)
                                    and all(_number_or_none(v) for v in hyp.values())):
            return "'hyper_parameters' must map names to numbers"
        if not _number_or_none(s.get("seconds")):
            return "'seconds' must be a number"
    return None


def latest_hypers(model_file: str | Path, effect: str, joint: int | None,
                  side: str | None = None) -> dict[str, float]:
    """Hyper-parameters the latest diagnosis chose for this effect (and joint), if any."""
    try:
        records = read_history(model_file)
    except ModelError:
        return {}
    for rec in reversed(records):
        for s in rec.get("suggestions") or []:
            if s.get("effect") == effect and s.get("joint") == joint and s.get("side") == side:
                hyp = dict(s.get("hyper_parameters") or {})
                if effect == "delay" and s.get("seconds") is not None:
                    hyp["seconds"] = s["seconds"]
                return hyp
    return {}
