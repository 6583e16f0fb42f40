"""Diagnosis: where the model fails, which catalog effect is missing, and how much it helps.

One union design (the model's base columns plus every candidate's new columns) is reduced
once to per-joint, per-time-block Grams; each candidate is scored on sub-blocks of them by
blocked cross-validation, a Wald test and a practical-gain threshold.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.stats import chi2

from robid_link.ident.data import Log
from robid_link.ident.effects import REGISTRY, Block, Model, States
from robid_link.ident.estimate import Grams, accumulate, solve
from robid_link.ident.identify import base_set_for, build_problem, identify, make_design
from robid_link.ident.preprocess import Design, Piece, design_chunks, split
from robid_link.ident.results import IdentResult
from robid_link.ident.robot import Robot

__all__ = ["Suggestion", "Diagnosis", "diagnose", "GAIN_MIN", "P_MAX"]

#: a suggestion must cut its joint's held-out RMSE by at least this fraction …
GAIN_MIN = 0.05
#: … and be significant at this level (Wald test with the long-run-variance covariance)
P_MAX = 1e-3
FOLDS = 5
BLOCKS = 40


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
    rmse_cv: list[float]
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
            for k, s in enumerate(self.suggestions, 1):
                lines.append(f"   {k}. {s.label():<22} gain {100 * s.gain:5.1f} %   {s.evidence}")
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


def _profile(robot: Robot, blk: Block, resid: np.ndarray, st: States) -> Block:
    """Choose a candidate's free hyper-parameter by how much of the current residual its
    columns explain (on decimated rows, without refitting the model)."""
    free = blk.free_hypers()
    if not free:
        return blk
    hyper = free[0]
    rows = blk.joint if blk.joint is not None else slice(None)
    y = resid[:, rows].reshape(-1)
    best, best_val = -np.inf, blk.effect.hypers[hyper].grid[0]
    for val in blk.effect.hypers[hyper].grid:
        opts = {**blk.opts, hyper: val}
        x = blk.effect.columns(robot, st, blk.joint, opts)[:, rows, :]
        x = x.reshape(-1, x.shape[-1])
        x = np.column_stack((x, np.ones(len(x))))  # the level is the model's business
        coef, *_ = np.linalg.lstsq(x, y, rcond=None)
        explained = 1.0 - np.sum((y - x @ coef) ** 2) / max(np.sum((y - y.mean()) ** 2), 1e-300)
        if explained > best:
            best, best_val = explained, val
    return Block(blk.effect, blk.joint, {**blk.opts, hyper: float(best_val)})


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


def _cv(grams: Grams, sub: np.ndarray, folds: list[tuple[np.ndarray, np.ndarray]]
        ) -> np.ndarray:
    """Per-joint held-out RMSE of the sub-model ``sub`` (column indices of the union)."""
    p = grams.p
    idx = np.concatenate((sub, [p]))
    g = grams.g[:, :, idx[:, None], idx[None, :]]  # (n, K, s+1, s+1)
    sse = np.zeros(g.shape[0])
    cnt = np.zeros(g.shape[0])
    counts = grams.g[:, :, p + 1, p + 1]
    for held, train in folds:
        tr = g[:, train].sum(axis=(0, 1))
        theta, _, _ = solve(tr[:-1, :-1], tr[:-1, -1], warn=False)
        v = np.concatenate((-theta, [1.0]))
        sse += np.einsum("i,jik,k->j", v, g[:, held].sum(axis=1), v)
        cnt += counts[:, held].sum(axis=1)
    return np.sqrt(np.maximum(sse, 0.0) / np.maximum(cnt, 1.0))


def _wald(grams: Grams, sub: np.ndarray, cand: np.ndarray) -> tuple[float, np.ndarray]:
    """p-value that the candidate's coefficients are zero, and the full-data θ."""
    from robid_link.ident.estimate import _long_run_factor

    p = grams.p
    idx = np.concatenate((sub, [p, p + 1]))
    sg = Grams(grams.g[:, :, idx[:, None], idx[None, :]], grams.n_rows)
    tot = sg.total()
    s = sub.size
    theta, a_inv, _ = solve(tot[:, :s, :s].sum(0), tot[:, :s, s].sum(0), warn=False)
    kappa, var = _long_run_factor(sg, theta)
    cov = a_inv @ np.einsum("j,jik->ik", kappa * var, tot[:, :s, :s]) @ a_inv
    pos = np.searchsorted(sub, cand) if np.all(np.diff(sub) > 0) else \
        np.array([int(np.flatnonzero(sub == c)[0]) for c in cand])
    beta = theta[pos]
    c_cc = cov[np.ix_(pos, pos)]
    try:
        stat = float(beta @ np.linalg.solve(c_cc, beta))
    except np.linalg.LinAlgError:
        return 1.0, theta
    return float(chi2.sf(stat, pos.size)), theta


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


def _evidence(blk: Block, j_rows: Sequence[int], before: float, after: float, gain: float,
              r2: dict[str, float], coef: np.ndarray) -> tuple[str, dict[str, float]]:
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
             interval: int = 1, method: str = "ols", motor_side: bool = False) -> Diagnosis:
    """Fit the model, then score every catalog effect not in it (see the module docstring)."""
    result = identify(robot, data, model, validate=validate, cutoff_hz=cutoff_hz,
                      interval=interval, method=method if method != "irls" else "ols",
                      motor_side=motor_side)
    logs = [*data, *(validate or ())]
    pb = build_problem(robot, logs, model, cutoff_hz=cutoff_hz, interval=interval,
                       motor_side=motor_side)
    pieces, _ = split(pb.preps, None, holdout=0.0)
    design, base, _ = make_design(robot, pb.blocks, pb.transmission)
    g0 = accumulate(design, pieces, pb.interval, pb.block_len, max_blocks=BLOCKS)
    tot = g0.total()
    theta0, _, _ = solve(tot[:, :design.p, :design.p].sum(0), tot[:, :design.p, design.p].sum(0),
                         warn=False)
    attach_predictions(robot, pb.preps, design, theta0)
    notes: list[str] = []
    if len(logs) == 1 or all(_same_motion(logs[0], lg) for lg in logs[1:]):
        notes.append("all data is one motion: candidates are scored by blocked "
                      f"cross-validation over the log ({FOLDS} folds), not on a new motion")
    # residual of the current model on decimated rows: evidence and hyper profiling
    step = max(1, sum(len(p) for p in pieces) // 20000)
    resid, states = _residual_with_states(design, theta0, pieces, step)
    absorbed: list[dict[str, Any]] = []
    kept: list[Block] = []
    for blk in _candidates(robot, model):
        if blk.free_hypers():
            blk = _profile(robot, blk, resid, states)
        trial = [*pb.blocks, blk]
        bset, names = base_set_for(robot, trial, pb.transmission)
        width = len(blk.effect.param_names(robot, blk.joint, blk.opts))
        new = [i for i in range(len(names) - width, len(names)) if i in bset.independent]
        if not new:
            by = sorted({bset.names[bset.independent[k]] for i in range(len(names) - width,
                         len(names)) for k in bset.absorbed.get(i, ())})
            absorbed.append({"effect": blk.key, "by": by})
            continue
        kept.append(blk)
    union_blocks = [*pb.blocks, *kept]
    ubase, unames = base_set_for(robot, union_blocks, pb.transmission)
    n_model = sum(len(b.effect.param_names(robot, b.joint, b.opts)) for b in pb.blocks)
    model_cols = list(base.independent)
    cand_cols: list[list[int]] = []
    start = n_model
    for blk in kept:
        width = len(blk.effect.param_names(robot, blk.joint, blk.opts))
        trial_base, _ = base_set_for(robot, [*pb.blocks, blk], pb.transmission)
        cand_cols.append([start + i - n_model for i in range(n_model, n_model + width)
                          if i in trial_base.independent])
        start += width
    cols = np.array(model_cols + [c for cc in cand_cols for c in cc])
    from robid_link.ident.identify import _random_states  # structural mask on these columns
    from robid_link.ident.preprocess import block_columns

    w = block_columns(robot, union_blocks,
                      _random_states(robot, np.random.default_rng(7), 64, pb.transmission))
    mask = np.abs(w[:, :, cols]).max(axis=0) > 0
    union = Design(robot, union_blocks, cols, mask)
    grams = accumulate(union, pieces, pb.interval, pb.block_len, max_blocks=BLOCKS)
    folds = _fold_masks(grams.g.shape[1], FOLDS)
    base_sub = np.arange(len(model_cols))
    rmse0 = _cv(grams, base_sub, folds)
    good, bad = [], []
    pos = len(model_cols)
    for blk, cc in zip(kept, cand_cols, strict=True):
        cand = np.arange(pos, pos + len(cc))
        pos += len(cc)
        sub = np.concatenate((base_sub, cand))
        rmse1 = _cv(grams, sub, folds)
        p_value, theta = _wald(grams, sub, cand)
        if blk.joint is None:
            gain = 1.0 - math.sqrt(np.mean(rmse1**2) / max(np.mean(rmse0**2), 1e-300))
            before, after = float(np.sqrt(np.mean(rmse0**2))), float(np.sqrt(np.mean(rmse1**2)))
            r2: dict[str, float] = {}
        else:
            j = blk.joint
            gain = 1.0 - float(rmse1[j] / max(rmse0[j], 1e-300))
            before, after = float(rmse0[j]), float(rmse1[j])
            r2 = {"r2_q": _r2_binned(states.q[:, j], resid[:, j]),
                  "r2_qd": _r2_binned(states.qd[:, j], resid[:, j]),
                  "r2_qdd": _r2_binned(states.qdd[:, j], resid[:, j])}
        text, fields = _evidence(blk, [], before, after, gain, r2, theta[len(base_sub):])
        sug = Suggestion(blk.effect.name, None if blk.joint is None else blk.joint + 1,
                         [float(x) for x in rmse1], float(gain), p_value, text,
                         {"gain": round(float(gain), 4), **fields},
                         {k: float(v) for k, v in blk.opts.items()})
        (good if gain >= GAIN_MIN and p_value <= P_MAX else bad).append(sug)
    good.sort(key=lambda s: -s.gain)
    good = _prefer_simpler(good)
    bad.sort(key=lambda s: -s.gain)
    return Diagnosis(result, model.labels(), [float(x) for x in rmse0], good, bad[:10],
                     absorbed, _unexplained(pb, design, theta0), notes,
                     {"r": resid, "q": states.q, "qd": states.qd, "qdd": states.qdd,
                      "t": states.t, "fs": np.array(pb.preps[0].filt.fs / step)})


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


def attach_predictions(robot: Robot, preps: Sequence[Any], design: Design,
                       theta: np.ndarray) -> None:
    """The current model's rigid torque and torque rate on every sample (candidates use them)."""
    blocks = design.blocks
    n_rigid = 10 * robot.n if blocks and blocks[0].effect.name == "rigid_body" else 0
    rigid_theta = theta.copy()
    rigid_theta[np.asarray(design.cols) >= n_rigid] = 0.0
    for prep in preps:
        n = len(prep.log)
        full = np.zeros((n, robot.n))
        rigid = np.zeros((n, robot.n))
        for a in range(0, n, 65536):
            b = min(a + 65536, n)
            c = design.compact(prep.states(a, b))
            full[a:b] = design.predict(c, theta)
            rigid[a:b] = design.predict(c, rigid_theta)
        prep.tau_rigid = rigid
        prep.tau_rate = np.gradient(full, 1.0 / prep.filt.fs, axis=0)


def _residual_with_states(design: Design, theta: np.ndarray, pieces: Sequence[Piece],
                          step: int) -> tuple[np.ndarray, States]:
    """The model's residual on decimated (filtered) rows, with the states of those rows."""
    res: list[np.ndarray] = []
    parts: dict[str, list[np.ndarray]] = {k: [] for k in ("q", "qd", "qdd", "t", "tr", "rate")}
    for pc in pieces:
        prep = pc.prep
        for c, y, idx in design_chunks(design, pc, step):
            res.append(y - design.predict(c, theta))
            parts["q"].append(prep.q[idx])
            parts["qd"].append(prep.qd[idx])
            parts["qdd"].append(prep.qdd[idx])
            parts["t"].append(prep.log.t[idx])
            if prep.tau_rigid is not None and prep.tau_rate is not None:
                parts["tr"].append(prep.tau_rigid[idx])
                parts["rate"].append(prep.tau_rate[idx])
    cat = {k: np.concatenate(v) if v else None for k, v in parts.items()}
    st = States(cat["q"], cat["qd"], cat["qdd"], cat["t"], pieces[0].prep.transmission,
                cat["tr"], cat["rate"])
    return np.concatenate(res), st


def _unexplained(pb: Any, design: Design, theta: np.ndarray) -> list[dict[str, Any]]:
    """Structure no catalog effect explains: a resonance in the raw residual spectrum."""
    import scipy.signal as sig

    out: list[dict[str, Any]] = []
    prep = pb.preps[0]
    n = min(len(prep.log), 200_000)
    c = design.compact(prep.states(0, n))
    r = prep.tau[:n] - design.predict(c, theta)
    fs = prep.filt.fs
    nper = int(min(n // 4, 4 * fs))
    if nper < 64:
        return out
    f, pxx = sig.welch(r, fs=fs, nperseg=nper, axis=0)
    band = (f > 2.0) & (f < 0.45 * fs)
    for j in range(pb.robot.n):
        spec = pxx[band, j]
        if spec.size < 20:
            continue
        k = int(np.argmax(spec))
        floor = float(np.median(spec))
        if spec[k] > 30 * floor:
            fr = float(f[band][k])
            out.append({"joint": j + 1, "kind": "resonance", "frequency_hz": round(fr, 3),
                        "peak_over_floor": round(float(spec[k] / floor), 1),
                        "text": f"joint {j + 1} residual has a resonance at {fr:.3g} Hz "
                                f"({spec[k] / floor:.3g}× the spectral floor): joint "
                                "elasticity? Run a stepped-sine experiment around a pose"})
    return out
