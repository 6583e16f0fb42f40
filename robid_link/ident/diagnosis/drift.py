"""Drift and wear across stored identifications of one robot, and two robots side by side.

Each identify record keeps its parameters (value and standard error). A parameter is flagged
when it moved away from the robot's baseline (the first runs) both beyond ``sigma`` combined
standard errors *and* by more than ``min_change`` of its baseline at the lower end of the
change's 95 % interval: with long logs every change is "significant", so a flag also needs a
practical size (the diagnosis follows the same rule).
Only parameters with a physical reading are flagged: friction rising (wear), stiffness
falling, gravity terms changing (a payload or counterbalance), rotor inertia changing.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from robid_link.exceptions import ModelError

__all__ = ["Flag", "Trend", "parameter_kind", "trend", "compare", "DEFAULT_SIGMA",
           "DEFAULT_MIN_CHANGE", "DEFAULT_BASELINE_RUNS"]

DEFAULT_SIGMA = 5.0
DEFAULT_MIN_CHANGE = 0.10
DEFAULT_BASELINE_RUNS = 3
CONFIDENCE_Z = 1.96

#: parameter name prefix → (kind, what a change means; the sign that is worrying)
_KINDS: tuple[tuple[str, str, str, int], ...] = (
    (r"^(fv|fc|fcp|fcn|fpc|fpv|fst|mu)_", "friction", "friction {dir} (wear or lubrication)",
     +1),
    (r"^k_", "stiffness", "stiffness {dir} (gearbox or belt wear)", -1),
    (r"^ia_", "rotor inertia", "rotor inertia {dir}", 0),
)
_GRAVITY = re.compile(r"^(m|mx|my|mz)_\d+$")


def parameter_kind(name: str, expression: str = "") -> tuple[str, str, int] | None:
    """(kind, message template, worrying sign) of a physically readable parameter, or None.
    A base parameter is a gravity term when its expression holds only masses and first
    moments (``mx_3 + 0.4·m_3``)."""
    for pattern, kind, text, sign in _KINDS:
        if re.match(pattern, name):
            return kind, text, sign
    terms = [t for t in re.split(r"[+\-]", expression.replace(" ", "")) if t]
    symbols = [t.split("·")[-1].split("*")[-1] for t in terms]
    if symbols and all(_GRAVITY.match(s) for s in symbols):
        return "gravity", "gravity term {dir} (payload or counterbalance changed)", 0
    return None


@dataclass(frozen=True)
class Flag:
    """One parameter that drifted: where (run), how much, in what sense."""

    run_id: str
    time: str
    parameter: str
    kind: str
    baseline: float
    value: float
    change: float        # fraction of the baseline
    sigmas: float        # change in combined standard errors
    message: str

    def as_dict(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


@dataclass
class Trend:
    """Each parameter over a robot's stored identify runs, with the drift flags."""

    robot: str
    runs: list[dict[str, Any]]                     # run_id, time
    values: dict[str, list[tuple[float, float] | None]]  # name → (value, std) per run
    expressions: dict[str, str]
    flags: list[Flag] = field(default_factory=list)
    baseline_runs: int = DEFAULT_BASELINE_RUNS

    def first_flag(self, parameter: str) -> Flag | None:
        return next((f for f in self.flags if f.parameter == parameter), None)

    def table(self, names: Sequence[str] | None = None) -> str:
        names = list(names or self.values)
        head = f"  {'run':<24}" + "".join(f"{n:>16}" for n in names)
        lines = [f"robid results — trend of {self.robot} over {len(self.runs)} runs "
                 f"(baseline: first {self.baseline_runs})", head]
        for k, run in enumerate(self.runs):
            cells = []
            for n in names:
                v = self.values[n][k]
                cells.append(f"{'—':>16}" if v is None else f"{v[0]:>9.4g} ±{v[1]:<6.2g}")
            mark = " !" if any(f.run_id == run["run_id"] for f in self.flags) else ""
            lines.append(f"  {run['run_id']:<24}" + "".join(cells) + mark)
        lines += [f"  [{i}] run {f.run_id}: {f.message}" for i, f in enumerate(self.flags, 1)]
        if not self.flags:
            lines.append("  no drift beyond the thresholds")
        return "\n".join(lines)

    def as_dict(self) -> dict[str, Any]:
        return {"robot": self.robot, "runs": self.runs, "baseline_runs": self.baseline_runs,
                "parameters": {n: [None if v is None else {"value": v[0], "std": v[1]}
                                   for v in vals] for n, vals in self.values.items()},
                "flags": [f.as_dict() for f in self.flags]}


def _params(rec: dict[str, Any]) -> dict[str, dict[str, Any]]:
    return {p["name"]: p for p in rec.get("parameters") or []
            if isinstance(p, dict) and isinstance(p.get("value"), int | float)}


def trend(results: Sequence[dict[str, Any]], robot: str, *, sigma: float = DEFAULT_SIGMA,
          min_change: float = DEFAULT_MIN_CHANGE,
          baseline_runs: int = DEFAULT_BASELINE_RUNS) -> Trend:
    """The trend of ``robot`` from stored results (``store.results`` rows: run_id, kind,
    record, time), oldest first. The baseline of each parameter is the inverse-variance mean
    of its first ``baseline_runs`` values; each later run is compared with it."""
    rows = [r for r in results if r.get("robot") == robot and r.get("kind") == "identify"
            and _params(r["record"])]
    if not rows:
        raise ModelError(f"robot {robot}: no stored identification with parameters")
    runs = [{"run_id": r["run_id"], "time": r["record"].get("time", "")} for r in rows]
    per_run = [_params(r["record"]) for r in rows]
    names = list(dict.fromkeys(n for p in per_run for n in p))
    values = {n: [(float(p[n]["value"]), float(p[n].get("std") or 0.0)) if n in p else None
                  for p in per_run] for n in names}
    exprs = {n: next(str(p[n].get("expression") or "") for p in per_run if n in p)
             for n in names}
    out = Trend(robot, runs, values, exprs, baseline_runs=baseline_runs)
    for name in names:
        kind = parameter_kind(name, exprs[name])
        if kind is None:
            continue
        seen = [(k, v) for k, v in enumerate(values[name]) if v is not None]
        if len(seen) <= baseline_runs:
            continue
        base, base_std = _weighted_mean([v for _, v in seen[:baseline_runs]])
        for k, (value, std) in seen[baseline_runs:]:
            flag = _judge(name, kind, base, base_std, value, std, sigma, min_change, runs[k])
            if flag is not None:
                out.flags.append(flag)
                break  # the first run past the thresholds; later ones say the same
    out.flags.sort(key=lambda f: (f.time, f.run_id, f.parameter))
    return out


def _weighted_mean(vals: Sequence[tuple[float, float]]) -> tuple[float, float]:
    """Inverse-variance mean; its standard error also holds the scatter of the runs, so a
    baseline whose runs disagree beyond their standard errors is not over-trusted."""
    w = [1.0 / max(s, 1e-12) ** 2 for _, s in vals]
    mean = sum(wi * v for wi, (v, _) in zip(w, vals, strict=True)) / sum(w)
    se = math.sqrt(1.0 / sum(w))
    if len(vals) > 1:
        scatter = math.sqrt(sum((v - mean) ** 2 for v, _ in vals) / (len(vals) - 1))
        se = max(se, scatter / math.sqrt(len(vals)))
    return mean, se


def _judge(name: str, kind: tuple[str, str, int], base: float, base_std: float, value: float,
           std: float, sigma: float, min_change: float, run: dict[str, Any]) -> Flag | None:
    delta = value - base
    se = max(math.hypot(base_std, std), 1e-15)
    z = abs(delta) / se
    # practical size with its uncertainty: the change must exceed min_change even at the
    # lower end of its 95 % interval, so estimation noise near the threshold raises no flag
    rel_low = (abs(delta) - CONFIDENCE_Z * se) / max(abs(base), 1e-12)
    label, text, worry = kind
    if z < sigma or rel_low < min_change:
        return None
    if worry and math.copysign(1, delta) != worry:
        return None  # friction falling or stiffness rising is not wear
    direction = "rose" if delta > 0 else "fell"
    msg = (f"{name} {text.format(dir=direction)}: {base:.4g} → {value:.4g} "
           f"({100 * delta / abs(base):+.1f} %, {z:.1f} σ)")
    return Flag(run["run_id"], run["time"], name, label, base, value, delta / abs(base), z, msg)


def compare(results: Sequence[dict[str, Any]], robot_a: str, robot_b: str) -> str:
    """The latest identification of two robots of one type side by side (same base set)."""
    latest = {}
    for robot in (robot_a, robot_b):
        rows = [r for r in results if r.get("robot") == robot and r.get("kind") == "identify"
                and _params(r["record"])]
        if not rows:
            raise ModelError(f"robot {robot}: no stored identification with parameters")
        latest[robot] = (rows[-1]["run_id"], _params(rows[-1]["record"]))
    (run_a, pa), (run_b, pb) = latest[robot_a], latest[robot_b]
    if list(pa) != list(pb):
        raise ModelError(f"robots {robot_a} and {robot_b}: different parameter sets (other "
                         "robot type or model); nothing to compare")
    lines = [f"robid results — {robot_a} (run {run_a}) vs {robot_b} (run {run_b})",
             f"  {'parameter':<14}{robot_a:>16}{robot_b:>16}{'difference':>13}{'σ':>7}"]
    for n in pa:
        a, b = pa[n], pb[n]
        d = b["value"] - a["value"]
        z = abs(d) / max(math.hypot(a.get("std") or 0.0, b.get("std") or 0.0), 1e-15)
        rel = 100 * d / abs(a["value"]) if a["value"] else math.inf
        lines.append(f"  {n:<14}{a['value']:>16.5g}{b['value']:>16.5g}{rel:>+12.1f}%{z:>7.1f}")
    return "\n".join(lines)
