"""The figures of ``make bench``, one key each with its unit, its baseline (what it is compared
with, measured in the same run) and its target, written to ``build/bench.json``; the
README's performance table is rendered from that file (``benchmarks/run.py --readme``).
"""

from __future__ import annotations

import json
import math
import os
import platform
import time
from pathlib import Path
from typing import Any

__all__ = ["Figures", "readme_table"]

ROOT = Path(__file__).resolve().parent.parent
BENCH_JSON = ROOT / "build" / "bench.json"


class Figures:
    """Figures of one run of ``make bench``; ``write`` merges them into ``build/bench.json``
    (a run with ``--only`` replaces its own keys and keeps the others)."""

    def __init__(self) -> None:
        self.items: dict[str, dict[str, Any]] = {}

    def add(self, key: str, value: float | None, unit: str, *, label: str,
            baseline: tuple[str, float, str] | None = None, target: str | None = None,
            ok: bool | None = None, **extra: Any) -> None:
        """``baseline``: (what, value, unit) measured in the same run; ``ok``: the target
        holds (None: no target)."""
        entry: dict[str, Any] = {"label": label, "value": _num(value), "unit": unit}
        if baseline is not None:
            what, bval, bunit = baseline
            entry["baseline"] = {"what": what, "value": _num(bval), "unit": bunit}
        if target is not None:
            entry["target"] = target
            entry["ok"] = ok
        entry.update({k: _num(v) if isinstance(v, float) else v for k, v in extra.items()})
        self.items[key] = entry

    def write(self, path: Path = BENCH_JSON) -> Path:
        old: dict[str, Any] = {}
        if path.exists():
            try:
                old = json.loads(path.read_text()).get("figures", {})
            except (OSError, ValueError):
                old = {}
        doc = {"schema": "robid-bench/1", "machine": {
            "cpus": os.cpu_count(), "platform": platform.platform(),
            "python": platform.python_version(), "load_avg": _load()},
            "written": time.strftime("%Y-%m-%d %H:%M:%S"), "figures": {**old, **self.items}}
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(doc, indent=1, ensure_ascii=False) + "\n")
        tmp.replace(path)
        return path


def _num(x: Any) -> Any:
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _load() -> list[float] | None:
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:
        return None


def _fmt(v: float | None, unit: str) -> str:
    if v is None:
        return "—"
    digits = 3 if abs(v) < 10 else 1 if abs(v) < 1000 else 0
    text = f"{v:,.{digits}f}".rstrip("0").rstrip(".") if digits else f"{v:,.0f}"
    return f"{text} {unit}".strip() if unit not in ("×", "") else f"{text}{unit}"


def readme_table(path: Path = BENCH_JSON) -> str:
    """The README's performance table (markdown) from ``build/bench.json``."""
    doc = json.loads(path.read_text())
    lines = ["| what | figure | baseline (same run) | target |", "|---|---|---|---|"]
    for entry in doc["figures"].values():
        base = entry.get("baseline")
        btext = "" if base is None else f"{base['what']}: {_fmt(base['value'], base['unit'])}"
        mark = "" if entry.get("ok") is None else (" ✓" if entry["ok"] else " ✗")
        lines.append(f"| {entry['label']} | {_fmt(entry['value'], entry['unit'])} | {btext} | "
                     f"{entry.get('target', '')}{mark} |")
    load = doc["machine"].get("load_avg")
    lines.append("")
    lines.append(f"Measured {doc['written']} on {doc['machine']['cpus']} cores"
                 + (f", load average {load[0]:g} at the end" if load else "") + ".")
    return "\n".join(lines)
