"""The evidence under a suggestion: how much of its joint's residual a smooth function of the
quantity the effect depends on explains (R², binned), whether it repeats one period on (a
ripple), and the sentence whose numbers are also the suggestion's fields.

A counterbalance behind a ``spring`` suggestion: when a joint's residual follows its angle
the way a strut between a base point and a link point pushes or pulls (τ = F(l)·a·b·sin ψ / l,
l² = a² + b² − 2ab·cos ψ, ψ = q + φ, the force a quadratic in the length: F = f0 + f1·l +
f2·l², a linear spring f2 = 0, a gas strut's polytropic force close to it over its stroke), the
suggestion points to ``known_torque`` with that law filled in for the joint: a/b and φ fitted
to the residual's shape, f0, f1, f2 left for identification (they enter linearly). The law is
offered only when it explains nearly what the spring's angle series does, and more than a
ripple on that joint. Whether the log fixes that shape is a likelihood-ratio test over the
(a/b, φ) grid: when shapes far from the fitted one explain the residual as well, the note says
so and asks for the strut's measured a, b and φ (the part of a strut's torque that is a sine of
the angle is taken by the joint's gravity parameters, so what is left to fit the shape to can
be small)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import minimize

from robid_link.ident.diagnosis.hyperparams import Beyond, ProfileRows
from robid_link.ident.model.effects import REGISTRY, Block, States
from robid_link.ident.model.robot import Robot

__all__ = ["Signatures", "r2_binned", "signature_r2", "evidence_sentence", "repeats",
           "Counterbalance", "counterbalances", "LAW_SHARE_MIN", "known_torque_entry"]


def r2_binned(x: np.ndarray, r: np.ndarray, bins: int = 30) -> float:
    """How much of r a smooth function of x explains (binned means, R²)."""
    if np.ptp(x) <= 0:
        return 0.0
    edges = np.quantile(x, np.linspace(0, 1, bins + 1))
    k = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, bins - 1)
    means = np.bincount(k, weights=r, minlength=bins) / np.maximum(
        np.bincount(k, minlength=bins), 1)
    fitted = means[k]
    return float(1.0 - np.sum((r - fitted) ** 2) / max(np.sum((r - r.mean()) ** 2), 1e-300))


#: what each effect is a function of: the quantity its evidence is stated against
_SIGNATURE = {"spring": "q", "ripple": "q", "armature": "qdd", "friction_drift": "t"}


def signature_r2(robot: Robot, blk: Block, states: States, resid: np.ndarray
                  ) -> dict[str, tuple[str, float]]:
    """R² of the block's primary row's residual against q, the block's velocity (a motor's
    for a motor-side effect), its acceleration and time: key → (label, R²)."""
    j = blk.joint
    assert j is not None
    st = blk.states(robot, states)
    on_motor = blk.effect.sided and st.transmission is not None
    if on_motor:
        assert st.transmission is not None
        v, a, tag = st.qd @ st.transmission[j], st.qdd @ st.transmission[j], f"m{j + 1}"
    else:
        v, a, tag = states.qd[:, j], states.qdd[:, j], f"{j + 1}"
    r = resid[:, j]
    out = {"r2_q": (f"q{j + 1}", r2_binned(states.q[:, j], r)),
           "r2_qd": (f"q̇{tag}", r2_binned(v, r)),
           "r2_qdd": (f"q̈{tag}", r2_binned(a, r))}
    if blk.effect.name == "friction_drift" and states.t is not None:
        # only a drift is weighed against time: at a slow motion's pace, binned time follows
        # everything the motion does
        out["r2_t"] = ("time", r2_binned(states.t, r))
    return out


class Signatures:
    """``signature_r2`` of the residual rows, computed once per joint and the velocity read
    (the motor's or the joint's: the first candidate there stands for the others)."""

    def __init__(self, robot: Robot, states: States, resid: np.ndarray) -> None:
        self.robot, self.states, self.resid = robot, states, resid
        self._cache: dict[str, dict[str, tuple[str, float]]] = {}

    def of(self, blk: Block) -> dict[str, tuple[str, float]]:
        """key → (label, R²); empty for a global effect."""
        if blk.joint is None:
            return {}
        # the velocity a block's signature is read against: its motor's for a sided effect
        # on a log with a transmission, else the joint's (as ``signature_r2`` decides)
        on_motor = blk.effect.sided and blk.states(self.robot, self.states).transmission is not None
        tag = f"{blk.joint}{on_motor}{blk.effect.name == 'friction_drift'}"
        if tag not in self._cache:
            self._cache[tag] = signature_r2(self.robot, blk, self.states, self.resid)
        return self._cache[tag]


def evidence_sentence(blk: Block, before: float, after: float,
              r2: dict[str, tuple[str, float]], coef: np.ndarray) -> tuple[str, dict[str, float]]:
    """The sentence under a suggestion, stated against the quantity the effect is a function
    of (a friction's velocity, a spring's angle …), so that it cannot contradict it."""
    name = blk.effect.name
    fields = {"rmse_before": round(before, 4), "rmse_after": round(after, 4)}
    drop = (f"cross-validated RMSE of the filtered torque {fields['rmse_before']:.4g} → "
            f"{fields['rmse_after']:.4g} N·m")
    if blk.joint is None:
        if name == "delay":
            secs = float(coef[0]) if coef.size else 0.0
            fields["seconds"] = round(secs, 5)
            return (f"the torque log is shifted by {1e3 * fields['seconds']:.4g} ms against "
                    f"the positions; {drop}", fields)
        return f"{drop}", fields
    fields.update({k: round(v, 3) for k, (_, v) in r2.items()})
    own = "r2_" + _SIGNATURE.get(name, "qd")
    where = f"joint {blk.joint + 1}" if blk.side != "motor" else f"motor {blk.joint + 1}"
    if name == "offset":
        text = f"{where}: a constant torque"
    else:
        others = [k for k in ("r2_q", "r2_qd", "r2_qdd") if k != own]
        text = (f"{where} residual against {r2[own][0]}: R² {fields[own]:.3g} ("
                + ", ".join(f"{r2[k][0]} {fields[k]:.3g}" for k in others) + ")")
        best = max(r2, key=lambda k: r2[k][1])
        if best != own and r2[best][1] > r2[own][1] + 0.05:
            text += (f"; it follows {r2[best][0]} more closely, and the effect still cuts "
                     "the held-out error")
    text += f"; {drop}"
    for key in ("vs", "shape", "vp", "period", "tau_s", "alpha"):
        if key in blk.opts:
            fields[key] = round(float(blk.opts[key]), 5)
            text += f"; {key} {fields[key]:.4g}"
    return text, fields


def repeats(q: np.ndarray, r: np.ndarray, period: float) -> float:
    """Correlation of the residual's mean over the angle with itself one period on: near 1
    for cogging or meshing (it repeats), low for a spring (smooth over the travel)."""
    per = 16
    width = period / per
    k = np.floor((q - q.min()) / width).astype(np.int64)
    counts = np.bincount(k)
    means = np.bincount(k, weights=r) / np.maximum(counts, 1)
    ok = (counts[:-per] > 0) & (counts[per:] > 0)
    if ok.sum() < per:
        return 0.0
    a, b = means[:-per][ok], means[per:][ok]
    if a.std() <= 0 or b.std() <= 0:
        return 0.0
    return float(np.corrcoef(a, b)[0, 1])


# ------------------------------------------------------- a counterbalance behind a spring

#: the law must explain this fraction of what the spring's angle series explains
LAW_SHARE_MIN = 0.8
#: χ² quantile (2 degrees of freedom, 95 %) of the (a/b, φ) profile's likelihood-ratio region
_CHI2_2_95 = 5.991
#: the shape counts as fixed by the log when its 95 % region holds at most this share of the
#: grid's (a/b, φ) cells
SHAPE_REGION_MAX = 0.1
_RATIOS = np.geomspace(0.05, 0.95, 14)
_PHASES = np.linspace(-math.pi, math.pi, 48, endpoint=False)


@dataclass(frozen=True)
class Counterbalance:
    """The spring law fitted to one joint's residual (from 1): shape constants, and the
    in-sample shares of the joint's filtered residual (its own model row and friction
    refitted alongside) that the law, the angle series and a ripple explain — each a share of
    the whole residual, so at most 1."""

    joint: int
    ratio: float  # a / b
    phi: float  # rad
    law_share: float
    series_share: float
    ripple_share: float
    #: the 95 % profile region of the shape: its share of the grid's cells, the a/b range and
    #: the share of the turn its φ cover
    region_share: float = 0.0
    ratio_range: tuple[float, float] = (0.0, 0.0)
    phi_cover: float = 0.0

    @property
    def shape_fixed(self) -> bool:
        """Whether the log fixes a/b and φ (its 95 % region is a small part of the grid)."""
        return self.region_share <= SHAPE_REGION_MAX

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
        # each share is of the joint's whole filtered residual: at most 100 %; the law and the
        # angle series span different columns, so either may explain more than the other
        shape = ("" if self.shape_fixed else
                 f"; the log does not fix the strut's shape: every a/b from "
                 f"{self.ratio_range[0]:.2g} to {self.ratio_range[1]:.2g} with φ over "
                 f"{100 * self.phi_cover:.0f} % of the turn explains it as well (95 % "
                 f"likelihood-ratio region over the (a/b, φ) grid: {100 * self.region_share:.0f} "
                 "% of it), so the a/b and φ below are placeholders — measure a, b and φ on the "
                 "arm (the strut's mounting points and the angle between them at q = 0)")
        return (f"spring@{self.joint}: joint {self.joint}'s residual follows its angle like a "
                f"counterbalance (in-sample, of its filtered residual with its friction and its "
                f"model row refitted, a strut law with a/b {self.ratio:.3g} and φ "
                f"{self.phi:.3g} rad explains {100 * self.law_share:.3g} %, the angle series "
                f"(a Fourier series of order 4) {100 * self.series_share:.3g} %, a ripple "
                f"{100 * self.ripple_share:.3g} %{shape}): "
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


@dataclass(frozen=True)
class _Region:
    """The (a/b, φ) grid cells whose law the likelihood-ratio test cannot tell from the best:
    their share of the grid, their a/b range, the share of the turn their φ cover."""

    share: float
    ratios: tuple[float, float]
    phi_cover: float


def _region(beyond: Beyond, grid: np.ndarray, best: float, ratio: float) -> _Region:
    """The 95 % profile region of the shape on ``grid`` (shares, ratios × phases): Gaussian
    residuals of N rows give 2·Δlog L = N·ln(RSS/RSS_best), with RSS what is left beyond the
    helpers and the law, N the rows' independent count (the residual is filtered: its rows
    are correlated, ``_independent_rows``)."""
    left = float(beyond.y @ beyond.y) / beyond.yy  # share left beyond the helpers
    n = _independent_rows(beyond.y)
    rss = np.maximum(left - grid, 1e-300)
    inside = n * np.log(rss / max(left - best, 1e-300)) <= _CHI2_2_95
    if not inside.any():  # the refined best stands alone: no cell of the grid is as good
        return _Region(0.0, (ratio, ratio), 0.0)
    ratios = _RATIOS[inside.any(axis=1)]
    return _Region(float(inside.mean()), (float(ratios.min()), float(ratios.max())),
                   float(inside.any(axis=0).mean()))


def _independent_rows(y: np.ndarray) -> float:
    """How many independent rows a correlated series holds: N / (1 + 2 Σ ρ_k), the sum over
    the lags up to its autocorrelation's first crossing of zero (Bartlett's effective size)."""
    y = y - y.mean()
    var = float(y @ y)
    if var <= 0 or y.size < 4:
        return float(y.size)
    total = 0.0
    for k in range(1, min(y.size // 4, 500)):
        rho = float(y[:-k] @ y[k:]) / var
        if rho <= 0:
            break
        total += rho
    return y.size / (1.0 + 2.0 * total)


def _fit(beyond: Beyond, q: np.ndarray) -> tuple[float, float, float, _Region]:
    """(a/b, φ, share, the shape's 95 % region): the grid's best, refined by Nelder–Mead in
    (log a/b, φ)."""
    grid = np.array([[beyond.share(_law_columns(q, r, p)) for p in _PHASES] for r in _RATIOS])
    k = int(np.argmax(grid))  # the first of equal bests, as max() over the grid's order
    best = (float(grid.flat[k]), float(_RATIOS[k // _PHASES.size]),
            float(_PHASES[k % _PHASES.size]))

    def cost(x: np.ndarray) -> float:
        r = float(np.clip(math.exp(x[0]), 1e-3, 0.999))
        return -beyond.share(_law_columns(q, r, float(x[1])))

    res = minimize(cost, [math.log(best[1]), best[2]], method="Nelder-Mead",
                   options={"xatol": 1e-4, "fatol": 1e-7, "maxiter": 300})
    if -res.fun > best[0]:
        r = float(np.clip(math.exp(res.x[0]), 1e-3, 0.999))
        phi = float((res.x[1] + math.pi) % (2 * math.pi) - math.pi)
        return r, phi, float(-res.fun), _region(beyond, grid, float(-res.fun), r)
    return best[1], best[2], best[0], _region(beyond, grid, best[0], best[1])


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
        ratio, phi, share, region = _fit(beyond, rows.states.q[:, j])
        out.append(Counterbalance(j + 1, ratio, phi, share, beyond.share(series), rshare,
                                  region.share, region.ratios, region.phi_cover))
    return out
