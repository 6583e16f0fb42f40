"""A synthetic plant for the fleet's tests and benchmarks: robots of a few types, each with
nightly identify results (parameters with standard errors) written through a store's own
``add_result``. Some robots wear (friction rising over the nights), one per type stands out
from its type (a parameter off by a fixed share): the answers the analysis must find."""

from __future__ import annotations

import random
import time
from dataclasses import dataclass
from typing import Any

__all__ = ["PlantSpec", "fill_store", "record"]

#: per type: parameter name → (nominal value, expression)
TYPES: dict[str, dict[str, tuple[float, str]]] = {
    "arm3": {"zz1r": (1.2, "zz_1 + yy_2"), "mx2r": (0.8, "mx_2 + 0.4·m_3"),
             "fv_1": (2.0, "fv_1"), "fv_2": (1.8, "fv_2"), "fv_3": (1.2, "fv_3"),
             "fc_1": (1.5, "fc_1"), "fc_2": (1.4, "fc_2"), "fc_3": (0.9, "fc_3")},
    "industrial6": {"zz1r": (14.0, "zz_1 + yy_2"), "mx2r": (9.5, "mx_2 + 0.4·m_3"),
                    **{f"fv_{j}": (6.0 - 0.6 * j, f"fv_{j}") for j in range(1, 7)},
                    **{f"fc_{j}": (9.0 - 0.8 * j, f"fc_{j}") for j in range(1, 7)}},
}


@dataclass(frozen=True)
class PlantSpec:
    robots: int = 12
    nights: int = 10
    types: tuple[str, ...] = ("arm3", "industrial6")
    #: every how many robots one wears (friction +30 % over the nights)
    wear_every: int = 4
    #: the share the outlier of each type is off by (its parameter 'zz1r')
    outlier: float = 0.25
    seed: int = 0


def record(kind: str, params: dict[str, tuple[float, float, str]], when: float,
           effects: tuple[str, ...] = ("viscous", "coulomb")) -> dict[str, Any]:
    """An identify record as the worker stores it (name, value, std, expression)."""
    return {"time": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(when)), "kind": "identify",
            "robot": kind, "effects": list(effects), "rmse": [0.3], "relative_error": 0.03,
            "data": [], "parameters": [{"name": n, "value": v, "std": s, "expression": e}
                                       for n, (v, s, e) in params.items()]}


def robot_names(spec: PlantSpec) -> list[tuple[str, str]]:
    """(robot, type): ``<type>-<nnn>``, types in turn."""
    return [(f"{spec.types[k % len(spec.types)]}-{k:03d}", spec.types[k % len(spec.types)])
            for k in range(spec.robots)]


def fill_store(store: Any, spec: PlantSpec) -> dict[str, Any]:
    """Write the plant's nightly results into ``store`` (a blocking ``Store``); what was
    planted: the wearing robots and each type's outlier."""
    rng = random.Random(spec.seed)
    start = time.time() - 86400.0 * spec.nights
    wearing, outliers = [], {}
    for k, (robot, kind) in enumerate(robot_names(spec)):
        wears = spec.wear_every and k % spec.wear_every == spec.wear_every - 1
        odd = kind not in outliers
        if odd:
            outliers[kind] = robot
        if wears:
            wearing.append(robot)
        own = {n: v * (1 + rng.gauss(0, 0.01)) for n, (v, _) in TYPES[kind].items()}
        if odd:
            own["zz1r"] *= 1 + spec.outlier
        for night in range(spec.nights):
            params = {}
            for n, (_, expr) in TYPES[kind].items():
                v = own[n]
                if wears and n.startswith(("fv_", "fc_")):
                    v *= 1 + 0.3 * night / max(spec.nights - 1, 1)
                std = 0.005 * abs(v)
                params[n] = (v + rng.gauss(0, std), std, expr)
            run_id = f"{robot}-n{night:03d}"
            store.add_result(run_id, robot, "identify",
                             record(kind, params, start + 86400.0 * night))
    return {"wearing": wearing, "outliers": outliers}
