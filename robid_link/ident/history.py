"""The error ladder: one record per identify/diagnose run, next to the model file.

The same record (model effects, per-joint RMSE, data hashes, time) is what the daemon's store
keeps for each result.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from robid_link.atomic import append_durable
from robid_link.exceptions import ModelError

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
    if kind == "diagnose":
        rec["verdict"] = doc.get("verdict")
        rec["suggestions"] = [{k: s.get(k) for k in ("effect", "joint", "gain",
                                                     "hyper_parameters", "seconds")}
                              for s in doc.get("suggestions", [])]
    return rec


def append_record(model_file: str | Path, record: dict[str, Any]) -> Path:
    path = history_path(model_file)
    append_durable(path, (json.dumps(record) + "\n").encode())
    return path


def read_history(model_file: str | Path) -> list[dict[str, Any]]:
    path = history_path(model_file)
    if not path.is_file():
        raise ModelError(f"{model_file}: no history yet ({path.name}); run identify or "
                         "diagnose with --model first")
    out = []
    for i, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError as err:
            raise ModelError(f"{path}: line {i} is not valid JSON") from err
    return out


def latest_hypers(model_file: str | Path, effect: str, joint: int | None) -> dict[str, float]:
    """Hyper-parameters the latest diagnosis chose for this effect (and joint), if any."""
    try:
        records = read_history(model_file)
    except ModelError:
        return {}
    for rec in reversed(records):
        for s in rec.get("suggestions") or []:
            if s.get("effect") == effect and s.get("joint") == joint:
                hyp = dict(s.get("hyper_parameters") or {})
                if effect == "delay" and s.get("seconds") is not None:
                    hyp["seconds"] = s["seconds"]
                return hyp
    return {}
