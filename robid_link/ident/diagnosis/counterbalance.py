"""A counterbalance behind a ``spring`` suggestion: when a joint's residual follows its angle
the way a strut between a base point and a link point pushes or pulls (τ = F(l)·a·b·sin ψ / l,
l² = a² + b² − 2ab·cos ψ, ψ = q + φ, the force a quadratic in the length: F = f0 + f1·l +
f2·l², a linear spring f2 = 0, a gas strut's polytropic force close to it over its stroke), the
suggestion points to ``known_torque`` with that law filled in for the joint: a/b and φ fitted
to the residual's shape, f0, f1, f2 left for identification (they enter linearly). The law is
offered only when it explains nearly what the spring's angle series does, and more than a
ripple on that joint."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import minimize

from robid_link.ident.diagnosis.hyperparams import Beyond, ProfileRows
from robid_link.ident.model.effects import REGISTRY, Block

__all__ = ["Counterbalance", "counterbalances", "LAW_SHARE_MIN", "known_torque_entry"]

#: the law must explain this fraction of what the spring's angle series explains
LAW_SHARE_MIN = 0.8
_RATIOS = np.geomspace(0.05, 0.95, 14)
_PHASES = np.linspace(-math.pi, math.pi, 48, endpoint=False)


@dataclass(frozen=True)
class Counterbalance:
    """The spring law fitted to one joint's residual (from 1): shape constants, and the
    in-sample shares of the residual (beyond the joint's own model row and friction) that the
    law, the angle series and a ripple explain."""

    joint: int
    ratio: float  # a / b
    phi: float  # rad
    law_share: float
    series_share: float
    ripple_share: float

    @property
    def fits(self) -> bool:
        return (self.law_share >= LAW_SHARE_MIN * self.series_share
                and self.law_share > self.ripple_share)

    def entry(self) -> dict[str, Any]:
        return known_torque_entry(self.joint, self.ratio, self.phi)

    def note(self) -> str:
        e = self.entry()
        flow = (f"{{name: {e['name']}, joint: {e['joint']}, expression: \"{e['expression']}\", "
                f"constants: {{a: {e['constants']['a']}, b: 1.0, phi: {e['constants']['phi']}}}"
                ", identify: [f0, f1, f2]}")
        series = max(self.series_share, 1e-300)
        return (f"spring@{self.joint}: joint {self.joint}'s residual follows its angle like a "
                f"counterbalance (in-sample, a strut law with a/b {self.ratio:.3g} and φ "
                f"{self.phi:.3g} rad explains {100 * self.law_share / series:.3g} % of what "
                "the angle series does, a ripple "
                f"{100 * self.ripple_share / series:.3g} %): "
                "if the arm has a spring or gas strut there, give its law in the model file — "
                f"known_torque: [{flow}] — with its measured a, b (only their ratio is fitted "
                "here) and the force's f0, f1, f2 identified")


def known_torque_entry(joint: int, ratio: float, phi: float) -> dict[str, Any]:
    """A ``known_torque`` entry of the spring law on ``joint`` (from 1), b = 1."""
    psi = f"q{joint} + phi"
    length = f"sqrt(a**2 + b**2 - 2*a*b*cos({psi}))"
    return {"name": f"counterbalance{joint}", "joint": joint,
            "expression": f"(f0 + f1*{length} + f2*{length}**2)*a*b*sin({psi})/{length}",
            "constants": {"a": round(float(ratio), 4), "b": 1.0, "phi": round(float(phi), 4)},
            "identify": ["f0", "f1", "f2"]}


def _law_columns(q: np.ndarray, ratio: float, phi: float) -> np.ndarray:
    psi = q + phi
    s = np.sin(psi)
    length = np.sqrt(1.0 + ratio**2 - 2.0 * ratio * np.cos(psi))
    return np.column_stack([ratio * s / length, ratio * s, ratio * s * length])


def _fit(beyond: Beyond, q: np.ndarray) -> tuple[float, float, float]:
    """(a/b, φ, share): the grid's best, refined by Nelder–Mead in (log a/b, φ)."""
    best = max((beyond.share(_law_columns(q, r, p)), r, p) for r in _RATIOS for p in _PHASES)

    def cost(x: np.ndarray) -> float:
        r = float(np.clip(math.exp(x[0]), 1e-3, 0.999))
        return -beyond.share(_law_columns(q, r, float(x[1])))

    res = minimize(cost, [math.log(best[1]), best[2]], method="Nelder-Mead",
                   options={"xatol": 1e-4, "fatol": 1e-7, "maxiter": 300})
    if -res.fun > best[0]:
        r = float(np.clip(math.exp(res.x[0]), 1e-3, 0.999))
        phi = float((res.x[1] + math.pi) % (2 * math.pi) - math.pi)
        return r, phi, float(-res.fun)
    return float(best[1]), float(best[2]), float(best[0])


def counterbalances(rows: ProfileRows, candidates: Sequence[Block]) -> list[Counterbalance]:
    """The law fitted on each joint with a ``spring`` candidate among ``candidates`` (a ripple
    candidate on the joint, when there is one, is the law's rival)."""
    out = []
    for blk in candidates:
        if blk.effect.name != "spring" or blk.joint is None:
            continue
        j = blk.joint
        beyond = Beyond(rows.helper_basis([j]), rows.resid_filtered[:, j])
        series = REGISTRY["spring"].columns(rows.robot, rows.states, j, blk.opts)[:, j, :]
        ripple = next((c for c in candidates if c.effect.name == "ripple" and c.joint == j),
                      None)
        rshare = 0.0 if ripple is None else beyond.share(
            ripple.columns(rows.robot, rows.states)[:, j, :])
        ratio, phi, share = _fit(beyond, rows.states.q[:, j])
        out.append(Counterbalance(j + 1, ratio, phi, share, beyond.share(series), rshare))
    return out
