"""Diagnosis: where the model fails, which catalog effect is missing, and how much it helps.

One union design (the model's base columns plus every candidate's new columns) is reduced
once to per-joint, per-time-block Grams; each candidate is scored on sub-blocks of them by
blocked cross-validation, a Wald test and a practical-gain threshold.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.stats import chi2

from robid_link.ident.data import Log
from robid_link.ident.design import (
    Design,
    attach_predictions,
    base_set_for,
    block_columns,
    random_states,
    structural_mask,
)
from robid_link.ident.effects import REGISTRY, Block, Model, States
from robid_link.ident.estimate import RANK_TOL, Grams, accumulate, long_run_factor, solve
from robid_link.ident.identify import identify
from robid_link.ident.preprocess import Piece, Prepared, filter_windows, split
from robid_link.ident.profile import ProfileRows, profile_effect, refine_effect, screen
from robid_link.ident.results import IdentResult
from robid_link.ident.robot import Robot

__all__ = ["Suggestion", "Diagnosis", "diagnose", "GAIN_MIN", "P_MAX"]

#: a suggestion must cut its joint's held-out RMSE by at least this fraction …
GAIN_MIN = 0.05
#: … and be significant at this level (Wald test with the long-run-variance covariance)
P_MAX = 1e-3
FOLDS = 5
#: suggestions spelled out in the terminal summary (all of them go to the JSON)
SUMMARY_MAX = 5
BLOCKS = 40
#: rows (spread over the log) on which hyper-parameters are profiled
PROFILE_ROWS = 3000
#: a per-joint candidate is scored only if, in-sample on the profiling rows, it explains this
#: fraction of its joint's filtered residual (≈ half of GAIN_MIN on the RMSE)
SCREEN_MIN = 1.0 - (1.0 - GAIN_MIN / 2) ** 2


@dataclass
class Suggestion:
    effect: str
    joint: int | None  # from 1; None for a global effect
    rmse: list[float]  # held-out (CV) RMSE per joint with the effect added
    gain: float
    p_value: float
    evidence: str
    fields: dict[str, float] = field(default_factory=dict)
    hypers: dict[str, float] = field(default_factory=dict)

    def label(self) -> str:
        return self.effect if self.joint is None else f"{self.effect}@{self.joint}"

    def as_dict(self) -> dict[str, Any]:
        return {"effect": self.effect, "joint": self.joint, "rmse": self.rmse,
                "gain": self.gain, "p_value": self.p_value, "evidence": self.evidence,
                **self.fields, "hyper_parameters": self.hypers}


@dataclass
class Diagnosis:
    result: IdentResult
    effects: list[str]
    rmse_cv: list[float] | None  # None: no candidate needed scoring (no union pass)
    suggestions: list[Suggestion]
    rejected: list[Suggestion]
    absorbed: list[dict[str, Any]]
    unexplained: list[dict[str, Any]]
    notes: list[str]
    residuals: dict[str, np.ndarray] = field(default_factory=dict, repr=False)

    @property
    def verdict(self) -> str:
        return "missing_effect" if self.suggestions else "adequate"

    def to_dict(self) -> dict[str, Any]:
        return {"effects": self.effects, "joints": self.result.joints,
                "rmse": [float(x) for x in self.result.rmse], "rmse_cv": self.rmse_cv,
                "relative_error": self.result.to_dict()["relative_error"],
                "verdict": self.verdict,
                "suggestions": [s.as_dict() for s in self.suggestions],
                "not_useful": [s.as_dict() for s in self.rejected],
                "absorbed": self.absorbed, "unexplained": self.unexplained,
                "notes": self.notes}

    def summary(self) -> str:
        joints = self.result.joints
        lines = [f"robid diagnose — {self.result.robot}: model [{', '.join(self.effects)}]",
                 "  held-out RMSE per joint [N·m]: " + ", ".join(
                     f"{j['joint']}: {r:.3g}" for j, r in zip(joints, self.result.rmse,
                                                              strict=True)),
                 f"  verdict: {self.verdict}"]
        if self.suggestions:
            lines.append("  suggestions, best first:")
            for k, s in enumerate(self.suggestions[:SUMMARY_MAX], 1):
                lines.append(f"   {k}. {s.label():<22} gain {100 * s.gain:5.1f} %   {s.evidence}")
            if len(self.suggestions) > SUMMARY_MAX:
                rest = self.suggestions[SUMMARY_MAX:]
                lines.append(f"   … and {len(rest)} more, weaker ("
                             + ", ".join(s.label() for s in rest[:8])
                             + (", …" if len(rest) > 8 else "") + "; all in the JSON)")
        for u in self.unexplained:
            lines.append(f"  unexplained: {u['text']}")
        if self.absorbed:
            lines.append("  absorbed (no new information): " + ", ".join(
                f"{a['effect']} by {', '.join(a['by'][:3])}" for a in self.absorbed[:6]))
        lines += [f"  [{i}] {n}" for i, n in enumerate(self.notes, 1)]
        return "\n".join(lines)


# ----------------------------------------------------------------------------- candidates


def _candidates(robot: Robot, model: Model) -> list[Block]:
    present = {(b.effect.name, b.joint) for b in model.blocks(robot)}
    present_names = {b.effect.name for b in model.blocks(robot)}
    out = []
    for name, eff in REGISTRY.items():
        if name == "rigid_body":
            continue
        if not eff.per_joint:
            if name not in present_names:
                out.append(Block(eff, None, {}))
            continue
        for j in range(robot.n):
            if (name, j) not in present and not any(
                    (other, j) in present for other in REGISTRY
                    if name in REGISTRY[other].replaces):
                out.append(Block(eff, j, {}))
    return out


class _Novelty:
    """Which of a candidate's columns add column space to the model (structurally, on the
    same random states as the base set), and which model parameters absorb the rest."""

    def __init__(self, robot: Robot, blocks: Sequence[Block], base: Any,
                 transmission: np.ndarray | None) -> None:
        self.robot = robot
        self.names = list(base.names)
        self.base_names = base.base_names
        n_states = max(200, 4 * len(self.names))
        self.states = random_states(robot, np.random.default_rng(20260), n_states, transmission)
        w = block_columns(robot, blocks, self.states).reshape(-1, len(self.names))
        w = w[:, list(base.independent)]
        self.scale = np.linalg.norm(w, axis=0)
        self.w = w / self.scale
        self.q, _ = np.linalg.qr(self.w)

    def check(self, blk: Block) -> tuple[list[int], list[str]]:
        wc = blk.effect.columns(self.robot, self.states, blk.joint, blk.opts)
        wc = wc.reshape(-1, wc.shape[-1])
        norms = np.linalg.norm(wc, axis=0)
        new: list[int] = []
        basis = self.q
        for i in range(wc.shape[1]):
            if norms[i] <= 1e-12:
                continue
            v = wc[:, i] / norms[i]
            r = v - basis @ (basis.T @ v)
            if np.linalg.norm(r) > 1e-7:
                new.append(i)
                basis = np.column_stack((basis, r / np.linalg.norm(r)))
        by: list[str] = []
        if not new:
            coef, *_ = np.linalg.lstsq(self.w, wc / np.maximum(norms, 1e-300), rcond=None)
            big = np.abs(coef).max(axis=1) > 1e-6
            by = [self.base_names[k] for k in np.flatnonzero(big)]
        return new, by


# ----------------------------------------------------------------------------- scoring


def _fold_masks(k_blocks: int, folds: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """(held-out blocks, training blocks) with one block of gap on each side."""
    edges = np.linspace(0, k_blocks, folds + 1).round().astype(int)
    out = []
    for f in range(folds):
        held = np.zeros(k_blocks, dtype=bool)
        held[edges[f]: edges[f + 1]] = True
        gap = held.copy()
        gap[max(0, edges[f] - 1): min(k_blocks, edges[f + 1] + 1)] = True
        out.append((held, ~gap))
    return out


class _FoldCV:
    """Blocked cross-validation on sub-blocks of the union Grams.

    Per fold the model's block is factored once (column-scaled); a candidate's columns are
    added through the Schur complement, so scoring it costs O(p·k) instead of a refit.
    """

    def __init__(self, grams: Grams, n_model: int, folds: list[tuple[np.ndarray, np.ndarray]]
                 ) -> None:
        p = grams.p
        self.p, self.n_model = p, n_model
        self.train = [grams.g[:, tr].sum(axis=(0, 1)) for _, tr in folds]  # (p+2, p+2)
        self.held = [grams.g[:, held].sum(axis=1) for held, _ in folds]  # (n, p+2, p+2)
        self.counts = sum(h[:, p + 1, p + 1] for h in self.held)
        self.fact = []
        m = np.arange(n_model)
        for a in self.train:
            amm = a[np.ix_(m, m)]
            d = 1.0 / np.sqrt(np.clip(np.diag(amm), 1e-300, None))
            evals, evecs = np.linalg.eigh(amm * np.outer(d, d))
            keep = evals > evals[-1] * RANK_TOL
            inv = (evecs[:, keep] / evals[keep]) @ evecs[:, keep].T * np.outer(d, d)
            self.fact.append(inv)

    def rmse(self, cand: np.ndarray) -> np.ndarray:
        """Per-joint held-out RMSE of the model plus the union columns ``cand``."""
        p, m = self.p, np.arange(self.n_model)
        sse = np.zeros(self.held[0].shape[0])
        for a, g_held, inv in zip(self.train, self.held, self.fact, strict=True):
            b_m = a[m, p]
            if cand.size:
                a_mc = a[np.ix_(m, cand)]
                s = a[np.ix_(cand, cand)] - a_mc.T @ inv @ a_mc
                rhs = a[cand, p] - a_mc.T @ (inv @ b_m)
                theta_c = np.linalg.lstsq(s, rhs, rcond=None)[0]
                theta_m = inv @ (b_m - a_mc @ theta_c)
            else:
                theta_c, theta_m = np.zeros(0), inv @ b_m
            idx = np.concatenate((m, cand, [p]))
            v = np.concatenate((-theta_m, -theta_c, [1.0]))
            sse += np.einsum("i,jik,k->j", v, g_held[:, idx[:, None], idx[None, :]], v)
        return np.sqrt(np.maximum(sse, 0.0) / np.maximum(self.counts, 1.0))


def _wald(grams: Grams, sub: np.ndarray, cand: np.ndarray) -> tuple[float, np.ndarray]:
    """p-value that the candidate's coefficients are zero, and the full-data θ."""
    p = grams.p
    idx = np.concatenate((sub, [p, p + 1]))
    sg = Grams(grams.g[:, :, idx[:, None], idx[None, :]], grams.n_rows)
    tot = sg.total()
    s = sub.size
    theta, a_inv, _ = solve(tot[:, :s, :s].sum(0), tot[:, :s, s].sum(0), warn=False)
    kappa, var = long_run_factor(sg, theta)
    cov = a_inv @ np.einsum("j,jik->ik", kappa * var, tot[:, :s, :s]) @ a_inv
    pos = np.searchsorted(sub, cand) if np.all(np.diff(sub) > 0) else \
        np.array([int(np.flatnonzero(sub == c)[0]) for c in cand])
    beta = theta[pos]
    c_cc = cov[np.ix_(pos, pos)]
    # rank-revealing: directions the data cannot tell apart carry no degrees of freedom
    evals, evecs = np.linalg.eigh((c_cc + c_cc.T) / 2)
    keep = evals > max(evals.max(), 0.0) * 1e-10
    if not keep.any():
        return 1.0, theta
    z = evecs[:, keep].T @ beta
    stat = float(np.sum(z * z / evals[keep]))
    return float(chi2.sf(stat, int(keep.sum()))), theta


# ----------------------------------------------------------------------------- evidence


def _r2_binned(x: np.ndarray, r: np.ndarray, bins: int = 30) -> float:
    """How much of r a smooth function of x explains (binned means, R²)."""
    if np.ptp(x) <= 0:
        return 0.0
    edges = np.quantile(x, np.linspace(0, 1, bins + 1))
    k = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, bins - 1)
    means = np.bincount(k, weights=r, minlength=bins) / np.maximum(
        np.bincount(k, minlength=bins), 1)
    fitted = means[k]
    return float(1.0 - np.sum((r - fitted) ** 2) / max(np.sum((r - r.mean()) ** 2), 1e-300))


def _evidence(blk: Block, before: float, after: float, r2: dict[str, float],
              coef: np.ndarray) -> tuple[str, dict[str, float]]:
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
    j = blk.joint + 1
    fields.update({k: round(v, 3) for k, v in r2.items()})
    follows = max(r2, key=lambda k: r2[k])
    qty = {"r2_q": f"q{j}", "r2_qd": f"q̇{j}", "r2_qdd": f"q̈{j}", "r2_t": "time"}
    others = [k for k in ("r2_q", "r2_qd", "r2_qdd") if k != follows][:2]
    text = (f"joint {j} residual follows {qty[follows]} (R² {fields[follows]:.3g}), not "
            f"{qty[others[0]]} ({fields[others[0]]:.3g}) or {qty[others[1]]} "
            f"({fields[others[1]]:.3g}); {drop}")
    for key in ("vs", "period", "tau_s", "alpha"):
        if key in blk.opts:
            fields[key] = round(float(blk.opts[key]), 5)
            text += f"; {key} {fields[key]:.4g}"
    return text, fields


# ----------------------------------------------------------------------------- diagnose


def diagnose(robot: Robot, data: Sequence[Log], model: Model, *,
             validate: Sequence[Log] | None = None, cutoff_hz: float | None = None,
             interval: int = 1, method: str = "ols", motor_side: bool = False,
             result: IdentResult | None = None) -> Diagnosis:
    """Fit the model, then score every catalog effect not in it (see the module docstring).

    ``result``: the model already identified from these inputs (``identify`` with the same
    options); its prepared logs, design and estimate are reused instead of fitting again.
    Candidates are scored on OLS/WLS residuals, so an IRLS result (or one of another method
    than ``method``) is not reused.
    """
    method = method if method != "irls" else "ols"
    if result is None or result.method != method or result.problem is None:
        result = identify(robot, data, model, validate=validate, cutoff_hz=cutoff_hz,
                          interval=interval, method=method, motor_side=motor_side)
    if result.problem is None or result.design is None:
        raise ValueError("diagnose needs a result from identify (it keeps the fitted problem)")
    logs = [*data, *(validate or ())]
    pb = result.problem
    _ = result.rmse  # the held-out figures read the fitted problem's model-torque inputs
    # copies: the model's predictions attached below must not change what the result reads
    preps = [replace(p) for p in (*pb.preps, *pb.vpreps)]
    pieces, _ = split(preps, None, holdout=0.0)
    design = result.design
    base, _ = base_set_for(robot, pb.blocks, pb.transmission)
    theta0 = np.asarray(result.theta)  # same model, same base set: identify's estimate
    attach_predictions(robot, preps, design, theta0)
    notes: list[str] = []
    if len(logs) == 1 or all(_same_motion(logs[0], lg) for lg in logs[1:]):
        notes.append("all data is one motion: candidates are scored by blocked "
                      f"cross-validation over the log ({FOLDS} folds), not on a new motion")
    # residual of the current model on decimated rows: evidence and hyper profiling
    step = max(1, sum(len(p) for p in pieces) // 12000)
    resid, raw_resid, states = _residual_with_states(pieces, step)
    absorbed: list[dict[str, Any]] = []
    kept: list[Block] = []
    cand_cols: list[list[int]] = []
    novelty = _Novelty(robot, pb.blocks, base, pb.transmission)
    n_model = len(novelty.names)
    start = n_model
    candidates = _candidates(robot, model)
    every = max(1, len(states) // PROFILE_ROWS)  # rows spread over the whole log
    sub_states = States(*(None if a is None else a[::every] for a in (
        states.q, states.qd, states.qdd, states.t)), states.transmission,
        *(None if a is None else a[::every] for a in (states.tau_rigid, states.tau_rate)))
    rows = ProfileRows(robot, sub_states, raw_resid[::every], resid[::every],
                       design.expand(design.compact(sub_states)))
    profiled = {b.key for b in candidates if b.free_hypers()}
    for name in sorted({b.effect.name for b in candidates if b.free_hypers()}):
        group = [b for b in candidates if b.effect.name == name]
        chosen = dict(zip(map(id, group), profile_effect(rows, group, refine=False),
                          strict=True))
        candidates = [chosen.get(id(b), b) for b in candidates]
    span = np.ptp(states.q, axis=0)
    candidates = [b for b in candidates if not (  # a "ripple" as slow as the motion: spring
        b.effect.name == "ripple" and b.opts.get("period", 0.0) > span[b.joint] / 2)]
    screened = 0
    for blk in candidates:
        new, by = novelty.check(blk)
        if not new:
            absorbed.append({"effect": blk.key, "by": by})
            continue
        if screen(rows, blk) < SCREEN_MIN:
            screened += 1  # cannot reach GAIN_MIN even in-sample: not worth a union column
            continue
        kept.append(blk)
        width = len(blk.effect.param_names(robot, blk.joint, blk.opts))
        cand_cols.append([start + i for i in new])
        start += width
    for name in sorted({b.effect.name for b in kept if b.key in profiled}):  # survivors only
        group = [b for b in kept if b.effect.name == name and b.key in profiled]
        fine = dict(zip(map(id, group), refine_effect(rows, group), strict=True))
        kept = [fine.get(id(b), b) for b in kept]
    del rows
    if screened:
        notes.append(f"{screened} candidate(s) explain under {100 * SCREEN_MIN:.0f} % of their "
                     "joint's filtered residual even in-sample and were not scored")
    if not kept:  # nothing can show a gain: no union pass, the verdict is adequate
        return Diagnosis(result, model.labels(), None, [], [], absorbed,
                         _unexplained(preps[0], design, theta0), notes,
                         _residual_dict(resid, states, pb.preps[0].filt.fs / step))
    union_blocks = [*pb.blocks, *kept]
    model_cols = list(base.independent)
    cols = np.array(model_cols + [c for cc in cand_cols for c in cc])
    union = Design(robot, union_blocks, cols,
                   structural_mask(robot, union_blocks, cols, pb.transmission))
    fs, fc = pb.preps[0].filt.fs, pb.preps[0].filt.cutoff_hz
    keep = max(pb.interval, int(fs / (8.0 * fc)))  # rows after the anti-alias filter suffice
    grams = accumulate(union, pieces, keep, max(1, pb.block_len * pb.interval // keep),
                       max_blocks=BLOCKS)
    folds = _fold_masks(grams.g.shape[1], FOLDS)
    base_sub = np.arange(len(model_cols))
    cv = _FoldCV(grams, len(model_cols), folds)
    rmse0 = cv.rmse(np.zeros(0, dtype=int))
    r2_cache: dict[int, dict[str, float]] = {}
    good, bad = [], []
    pos = len(model_cols)
    for blk, cc in zip(kept, cand_cols, strict=True):
        cand = np.arange(pos, pos + len(cc))
        pos += len(cc)
        sub = np.concatenate((base_sub, cand))
        rmse1 = cv.rmse(cand)
        p_value, theta = _wald(grams, sub, cand)
        if blk.joint is None:
            gain = 1.0 - math.sqrt(np.mean(rmse1**2) / max(np.mean(rmse0**2), 1e-300))
            before, after = float(np.sqrt(np.mean(rmse0**2))), float(np.sqrt(np.mean(rmse1**2)))
            r2: dict[str, float] = {}
        else:
            j = blk.joint
            gain = 1.0 - float(rmse1[j] / max(rmse0[j], 1e-300))
            before, after = float(rmse0[j]), float(rmse1[j])
            if j not in r2_cache:
                r2_cache[j] = {"r2_q": _r2_binned(states.q[:, j], resid[:, j]),
                               "r2_qd": _r2_binned(states.qd[:, j], resid[:, j]),
                               "r2_qdd": _r2_binned(states.qdd[:, j], resid[:, j])}
            r2 = r2_cache[j]
        text, fields = _evidence(blk, before, after, r2, theta[len(base_sub):])
        sug = Suggestion(blk.effect.name, None if blk.joint is None else blk.joint + 1,
                         [float(x) for x in rmse1], float(gain), p_value, text,
                         {"gain": round(float(gain), 4), **fields},
                         {k: float(v) for k, v in blk.opts.items()})
        (good if gain >= GAIN_MIN and p_value <= P_MAX else bad).append(sug)
    good.sort(key=lambda s: -s.gain)
    good = _prefer_simpler(good)
    bad.sort(key=lambda s: -s.gain)
    return Diagnosis(result, model.labels(), [float(x) for x in rmse0], good, bad[:10],
                     absorbed, _unexplained(preps[0], design, theta0), notes,
                     _residual_dict(resid, states, pb.preps[0].filt.fs / step))


def _residual_dict(resid: np.ndarray, states: States, fs: float) -> dict[str, np.ndarray]:
    """What the residual figures plot."""
    return {"r": resid, "q": states.q, "qd": states.qd, "qdd": states.qdd, "t": states.t,
            "fs": np.array(fs)}


def _prefer_simpler(good: list[Suggestion]) -> list[Suggestion]:
    """Among near-equal explanations on one joint, the one with fewer parameters first."""
    order = {"offset": 1, "viscous": 1, "coulomb": 1, "armature": 1, "load_friction": 1,
             "stribeck": 1, "coulomb_asymmetric": 2, "ripple": 2, "friction_drift": 2,
             "friction_power": 3, "spring": 9, "delay": 1}
    out = list(good)
    swapped = True
    while swapped:  # bubble until stable: equivalents may come in any order
        swapped = False
        for i in range(len(out) - 1):
            a, b = out[i], out[i + 1]
            close = abs(a.fields["rmse_after"] - b.fields["rmse_after"]) <= 0.01 * max(
                a.fields["rmse_after"], 1e-12)  # equivalent: the same error left, within 1 %
            if a.joint == b.joint and close and order.get(b.effect, 9) < order.get(a.effect, 9):
                out[i], out[i + 1] = b, a
                swapped = True
    return out


def _same_motion(a: Log, b: Log) -> bool:
    n = min(len(a), len(b))
    return bool(n > 10 and np.abs(a.q[:n] - b.q[:n]).max() < 0.02)


def _residual_with_states(pieces: Sequence[Piece], step: int
                          ) -> tuple[np.ndarray, np.ndarray, States]:
    """The model's residual on decimated rows, of the filtered and of the raw torque, with
    the states of those rows. Filtering is linear, so filtering the raw residual (τ − Xθ with
    the model's prediction from ``attach_predictions``) equals the parallel-filtered residual
    τ_f − X_f·θ, at the cost of n columns instead of the design's."""
    res: list[np.ndarray] = []
    raw: list[np.ndarray] = []
    parts: dict[str, list[np.ndarray]] = {k: [] for k in ("q", "qd", "qdd", "t", "tr", "rate")}
    for pc in pieces:
        prep = pc.prep
        for a, b, ca, cb, at_edge in filter_windows(pc, step):
            filtered = prep.filt.apply(prep.tau[ca:cb] - prep.tau_model[ca:cb], edges=at_edge)
            idx = np.arange(a, b, step)
            res.append(filtered[a - ca: b - ca: step])
            raw.append(prep.tau[idx] - prep.tau_model[idx])
            parts["q"].append(prep.q[idx])
            parts["qd"].append(prep.qd[idx])
            parts["qdd"].append(prep.qdd[idx])
            parts["t"].append(prep.log.t[idx] - prep.log.t[0])
            if prep.tau_rigid is not None and prep.tau_rate is not None:
                parts["tr"].append(prep.tau_rigid[idx])
                parts["rate"].append(prep.tau_rate[idx])
    cat = {k: np.concatenate(v) if v else None for k, v in parts.items()}
    st = States(cat["q"], cat["qd"], cat["qdd"], cat["t"], pieces[0].prep.transmission,
                cat["tr"], cat["rate"])
    return np.concatenate(res), np.concatenate(raw), st


def _unexplained(prep: Prepared, design: Design, theta: np.ndarray) -> list[dict[str, Any]]:
    """Structure no catalog effect explains: a resonance in the raw residual spectrum."""
    import scipy.signal as sig

    out: list[dict[str, Any]] = []
    n = min(len(prep.log), 200_000)
    if prep.tau_model is not None:  # attach_predictions computed it
        r = prep.tau[:n] - prep.tau_model[:n]
    else:
        r = prep.tau[:n] - design.predict(design.compact(prep.states(0, n)), theta)
    fs = prep.filt.fs
    nper = int(min(n // 4, 4 * fs))
    if nper < 64:
        return out
    f, pxx = sig.welch(r, fs=fs, nperseg=nper, axis=0)
    motion_hz = _motion_bandwidth(prep.q[:n], fs)
    band = (f > max(2.0, 3.0 * motion_hz)) & (f < 0.45 * fs)
    idx = np.flatnonzero(band)
    for j in range(design.robot.n):
        if idx.size < 20:
            break
        spec = pxx[:, j]
        k = idx[int(np.argmax(spec[idx]))]
        lo_f, hi_f = f[k] / 1.5, f[k] * 1.5
        near = (f >= lo_f) & (f <= hi_f) & (np.abs(np.arange(f.size) - k) > 2)
        if k in (idx[0], idx[-1]) or not near.any():
            continue
        prominence = float(spec[k] / np.median(spec[near]))
        if prominence > 20:
            fr = float(f[k])
            out.append({"joint": j + 1, "kind": "resonance", "frequency_hz": round(fr, 3),
                        "peak_over_floor": round(prominence, 1),
                        "text": f"joint {j + 1} residual has a resonance at {fr:.3g} Hz "
                                f"({prominence:.3g}× its neighbourhood): joint elasticity? "
                                f"Add an elasticity experiment for joint {j + 1}: "
                                "campaigns.<name>.experiments: [{kind: elasticity, "
                                f"joints: [{j + 1}]}}] (or robid excite --kind elasticity "
                                f"--joint {j + 1})"})
    return out


def _motion_bandwidth(q: np.ndarray, fs: float) -> float:
    """Frequency below which 99 % of the positions' variation lies."""
    spec = np.abs(np.fft.rfft(q - q.mean(axis=0), axis=0)) ** 2
    cum = np.cumsum(spec.sum(axis=1))
    k = int(np.searchsorted(cum, 0.99 * cum[-1]))
    return float(k * fs / q.shape[0])
