"""Diagnosis: where the model fails, which catalog effect is missing, and how much it helps.

One union design (the model's base columns plus every candidate's new columns) is reduced
once to per-joint, per-time-block Grams; each candidate is scored on sub-blocks of them by
blocked cross-validation, a Wald test and a practical-gain threshold. With ``validate`` logs
(another motion) each candidate is also fitted on all training rows and scored on them: what
does not transfer is not suggested, and the model's own effects are checked the same way.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.stats import chi2

from robid_link.ident.data.logs import Log
from robid_link.ident.data.preprocess import Piece, Prepared, filter_windows, split
from robid_link.ident.diagnosis.hyperparams import (
    ProfileRows,
    profile_effect,
    refine_effect,
    screen,
)
from robid_link.ident.fit.design import (
    Design,
    attach_predictions,
    base_set_for,
    block_columns,
    random_states,
    structural_mask,
)
from robid_link.ident.fit.estimate import RANK_TOL, Grams, accumulate, long_run_factor, solve
from robid_link.ident.fit.identify import identify
from robid_link.ident.fit.results import IdentResult
from robid_link.ident.model.effects import REGISTRY, Block, Model, States, effect_label
from robid_link.ident.model.robot import Robot
from robid_link.jobs import ResonanceHint

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
#: on the validation logs a suggestion must cut its rows' RMSE by this fraction, and not raise
#: the other joints' (it shares the rigid-body parameters), else it does not transfer
TRANSFER_MIN = 0.01
#: extrapolation notes (validation outside the training ranges) that make a verdict doubtful
EXTRAPOLATION_MAX = 3
#: spring and ripple within this fraction of each other: physics decides (does it repeat?)
NEAR_EQUAL = 0.05
#: correlation of the residual with itself one period on, above which it repeats (ripple)
REPEAT_MIN = 0.5


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
    side: str | None = None  # "joint" / "motor" when the effect names its side
    #: relative cut of the validation logs' RMSE on the effect's rows (None: no such logs)
    transfer: float | None = None

    def label(self) -> str:
        return effect_label(self.effect, self.joint, self.side)

    def as_dict(self) -> dict[str, Any]:
        return {"effect": self.effect, "joint": self.joint, "side": self.side,
                "label": self.label(), "rmse": self.rmse, "gain": self.gain,
                "transfer_gain": self.transfer, "p_value": self.p_value,
                "evidence": self.evidence, **self.fields, "hyper_parameters": self.hypers}


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
    #: suggestions that won the cross-validation but not on the validation logs
    not_transferring: list[Suggestion] = field(default_factory=list)
    #: why the model cannot be called adequate though nothing is missing
    doubts: list[str] = field(default_factory=list)

    @property
    def verdict(self) -> str:
        if self.suggestions:
            return "missing_effect"
        return "doubtful" if self.doubts else "adequate"

    def to_dict(self) -> dict[str, Any]:
        return {"effects": self.effects, "joints": self.result.joints,
                "rmse": [float(x) for x in self.result.rmse], "rmse_cv": self.rmse_cv,
                "relative_error": self.result.to_dict()["relative_error"],
                "verdict": self.verdict,
                "suggestions": [s.as_dict() for s in self.suggestions],
                "not_useful": [s.as_dict() for s in self.rejected],
                "not_transferring": [s.as_dict() for s in self.not_transferring],
                "doubts": self.doubts,
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
        for s in self.not_transferring[:SUMMARY_MAX]:
            lines.append(f"  does not transfer: {s.label()} (cross-validated gain "
                         f"{100 * s.gain:.1f} %, on the validation logs "
                         f"{100 * (s.transfer or 0.0):+.1f} %)")
        for d in self.doubts:
            lines.append(f"  doubt: {d}")
        for u in self.unexplained:
            lines.append(f"  unexplained: {u['text']}")
        if self.absorbed:
            lines.append("  absorbed (no new information): " + ", ".join(
                f"{a['effect']} by {', '.join(a['by'][:3])}" for a in self.absorbed[:6]))
        lines += [f"  [{i}] {n}" for i, n in enumerate(self.notes, 1)]
        return "\n".join(lines)


# ----------------------------------------------------------------------------- candidates


def _candidates(robot: Robot, model: Model, default: np.ndarray | None) -> list[Block]:
    """Every catalog effect not in the model, on every joint; with a coupled transmission
    also the other side's friction where the coupling makes it new (joint-side logs: the
    coupled motors'; motor-side logs: the coupled joints' bearings)."""
    blocks = model.blocks(robot)

    def norm(side: str | None) -> str | None:  # a side equal to the logs' is the plain one
        return None if side == ("joint" if default is None else "motor") else side

    present = {(b.effect.name, b.joint, norm(b.side)) for b in blocks}
    present_names = {b.effect.name for b in blocks}

    def taken(name: str, j: int, side: str | None) -> bool:
        return (name, j, side) in present or any(
            (other, j, side) in present for other in REGISTRY
            if name in REGISTRY[other].replaces)

    out = []
    for name, eff in REGISTRY.items():
        if name == "rigid_body" or not eff.catalog:
            continue
        if not eff.per_joint:
            if name not in present_names:
                out.append(Block(eff, None, {}))
            continue
        out += [Block(eff, j, {}) for j in range(robot.n) if not taken(name, j, None)]
    for side, j in _coupled(robot, default):
        out += [Block(eff, j, {}, side) for name, eff in REGISTRY.items()
                if eff.sided and not taken(name, j, side)]
    return out


def _coupled(robot: Robot, default: np.ndarray | None) -> list[tuple[str, int]]:
    """(side, joint) pairs where a coupled transmission makes the other side's friction new."""
    t_mat = robot.transmission
    if t_mat is None:
        return []
    rows = [m for m in range(robot.n) if np.count_nonzero(t_mat[m]) > 1]
    if default is None:
        return [("motor", m) for m in rows]
    joints = sorted({int(i) for m in rows for i in np.flatnonzero(t_mat[m])})
    return [("joint", i) for i in joints]


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
        wc = blk.columns(self.robot, self.states)
        wc = wc.reshape(-1, wc.shape[-1])
        norms = np.linalg.norm(wc, axis=0)
        if not np.any(norms > 1e-12):
            return [], []  # no column on these states at all: nothing absorbs it
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


#: what each effect is a function of: the quantity its evidence is stated against
_SIGNATURE = {"spring": "q", "ripple": "q", "armature": "qdd", "friction_drift": "t"}


def _signature_r2(robot: Robot, blk: Block, states: States, resid: np.ndarray
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
    out = {"r2_q": (f"q{j + 1}", _r2_binned(states.q[:, j], r)),
           "r2_qd": (f"q̇{tag}", _r2_binned(v, r)),
           "r2_qdd": (f"q̈{tag}", _r2_binned(a, r))}
    if blk.effect.name == "friction_drift" and states.t is not None:
        # only a drift is weighed against time: at a slow motion's pace, binned time follows
        # everything the motion does
        out["r2_t"] = ("time", _r2_binned(states.t, r))
    return out


def _evidence(blk: Block, before: float, after: float,
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
    for key in ("vs", "vp", "period", "tau_s", "alpha"):
        if key in blk.opts:
            fields[key] = round(float(blk.opts[key]), 5)
            text += f"; {key} {fields[key]:.4g}"
    return text, fields


# ----------------------------------------------------------------------------- diagnose


def diagnose(robot: Robot, data: Sequence[Log], model: Model, *,
             validate: Sequence[Log] | None = None, cutoff_hz: float | None = None,
             interval: int = 1, method: str = "ols", motor_side: bool = False,
             result: IdentResult | None = None,
             resonance_hints: Mapping[int, ResonanceHint] | None = None) -> Diagnosis:
    """Fit the model, then score every catalog effect not in it (see the module docstring).

    ``resonance_hints`` (joint → what the caller tells of an unexplained resonance there: the
    daemon names its campaign experiment that measures the joint, or the entry to add)
    replace the generic advice (``robid excite --kind elasticity``).

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
    # with validation logs, candidates are profiled and cross-validated on the training logs
    # and then scored on the validation logs (a new motion); without, all the data is one pool
    pieces, _ = split(preps[: len(pb.preps)] if pb.vpreps else preps, None, holdout=0.0)
    vpieces = split(preps[len(pb.preps):], None, holdout=0.0)[0] if pb.vpreps else []
    design = result.design
    base, _ = base_set_for(robot, pb.blocks, pb.transmission)
    theta0 = np.asarray(result.theta)  # same model, same base set: identify's estimate
    attach_predictions(robot, preps, design, theta0)
    odd = _unexplained(preps[0], design, theta0, resonance_hints)
    notes: list[str] = []
    if len(logs) == 1 or all(_same_motion(logs[0], lg) for lg in logs[1:]):
        notes.append("all data is one motion: candidates are scored by blocked "
                      f"cross-validation over the log ({FOLDS} folds), not on a new motion")
    doubts = _doubts(result)
    # residual of the current model on decimated rows: evidence and hyper profiling
    step = max(1, sum(len(p) for p in pieces) // 12000)
    resid, raw_resid, states = _residual_with_states(pieces, step)
    absorbed: list[dict[str, Any]] = []
    kept: list[Block] = []
    cand_cols: list[list[int]] = []
    novelty = _Novelty(robot, pb.blocks, base, pb.transmission)
    n_model = len(novelty.names)
    start = n_model
    candidates = _candidates(robot, model, pb.transmission)
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
    silent: list[str] = []
    for blk in candidates:
        new, by = novelty.check(blk)
        if not new:
            if by:
                absorbed.append({"effect": blk.key, "by": by})
            else:
                silent.append(blk.key)
            continue
        if screen(rows, blk) < SCREEN_MIN:
            screened += 1  # cannot reach GAIN_MIN even in-sample: not worth a union column
            continue
        kept.append(blk)
        width = len(blk.param_names(robot))
        cand_cols.append([start + i for i in new])
        start += width
    for name in sorted({b.effect.name for b in kept if b.key in profiled}):  # survivors only
        group = [b for b in kept if b.effect.name == name and b.key in profiled]
        fine = dict(zip(map(id, group), refine_effect(rows, group), strict=True))
        kept = [fine.get(id(b), b) for b in kept]
    del rows
    if silent:
        notes.append(f"{', '.join(silent[:6])}: no column on the data's states at any "
                     "hyper-parameter tried (not scored)")
    if screened:
        notes.append(f"{screened} candidate(s) explain under {100 * SCREEN_MIN:.0f} % of their "
                     "joint's filtered residual even in-sample and were not scored")
    residuals = _residual_dict(resid, states, pb.preps[0].filt.fs / step)
    if not kept and not vpieces:  # nothing can show a gain: no union pass
        return Diagnosis(result, model.labels(), None, [], [], absorbed,
                         odd, notes, residuals,
                         doubts=doubts)
    union_blocks = [*pb.blocks, *kept]
    model_cols = list(base.independent)
    cols = np.array(model_cols + [c for cc in cand_cols for c in cc])
    union = Design(robot, union_blocks, cols,
                   structural_mask(robot, union_blocks, cols, pb.transmission))
    fs, fc = pb.preps[0].filt.fs, pb.preps[0].filt.cutoff_hz
    keep = max(pb.interval, int(fs / (8.0 * fc)))  # rows after the anti-alias filter suffice
    block_len = max(1, pb.block_len * pb.interval // keep)
    transfer = None
    if vpieces:
        transfer = _Transfer(accumulate(union, pieces, keep, block_len, max_blocks=2),
                             accumulate(union, vpieces, keep, block_len, max_blocks=2))
        doubts += _model_transfer(robot, pb, transfer, len(model_cols), base.independent)
    if not kept:  # nothing can show a gain: no candidate pass
        return Diagnosis(result, model.labels(), None, [], [], absorbed,
                         odd, notes, residuals,
                         doubts=doubts)
    grams = accumulate(union, pieces, keep, block_len, max_blocks=BLOCKS)
    folds = _fold_masks(grams.g.shape[1], FOLDS)
    base_sub = np.arange(len(model_cols))
    cv = _FoldCV(grams, len(model_cols), folds)
    rmse0 = cv.rmse(np.zeros(0, dtype=int))
    rmse_v0 = transfer.rmse(base_sub) if transfer is not None else None
    r2_cache: dict[str, dict[str, tuple[str, float]]] = {}
    good, bad, lost = [], [], []
    pos = len(model_cols)
    for blk, cc in zip(kept, cand_cols, strict=True):
        cand = np.arange(pos, pos + len(cc))
        pos += len(cc)
        sub = np.concatenate((base_sub, cand))
        rmse1 = cv.rmse(cand)
        p_value, theta = _wald(grams, sub, cand)
        rws = blk.rows(robot, pb.transmission)  # a coupled motor's friction: several joints
        before, after = _rms(rmse0[rws]), _rms(rmse1[rws])
        gain = 1.0 - after / max(before, 1e-300)
        r2: dict[str, tuple[str, float]] = {}
        if blk.joint is not None:
            tag = f"{blk.joint}{blk.side}{blk.effect.name == 'friction_drift'}"
            if tag not in r2_cache:
                r2_cache[tag] = _signature_r2(robot, blk, states, resid)
            r2 = r2_cache[tag]
        text, fields = _evidence(blk, before, after, r2, theta[len(base_sub):])
        if blk.effect.name == "ripple" and blk.joint is not None:
            fields["repeat"] = round(_repeats(states.q[:, blk.joint], resid[:, blk.joint],
                                              float(blk.opts["period"])), 3)
            text += f"; the residual repeats every period (correlation {fields['repeat']:.3g})"
        sug = Suggestion(blk.effect.name, None if blk.joint is None else blk.joint + 1,
                         [float(x) for x in rmse1], float(gain), p_value, text,
                         {"gain": round(float(gain), 4), **fields},
                         {k: float(v) for k, v in blk.opts.items()}, blk.side)
        if transfer is not None and rmse_v0 is not None:
            rmse_v1 = transfer.rmse(sub)
            v_before, v_after = _rms(rmse_v0[rws]), _rms(rmse_v1[rws])
            # the effect shares the rigid-body parameters with every joint: what it does to
            # the others counts too (each joint relative to itself, so none dominates)
            sug.transfer = 1.0 - _rms(rmse_v1 / np.maximum(rmse_v0, 1e-300))
            sug.fields.update({"validation_before": round(v_before, 4),
                               "validation_after": round(v_after, 4),
                               "transfer_gain": round(sug.transfer, 4),
                               "transfer_own": round(1.0 - v_after / max(v_before, 1e-300), 4)})
            sug.evidence += (f"; on the validation logs {sug.fields['validation_before']:.4g} → "
                             f"{sug.fields['validation_after']:.4g} N·m (all joints: "
                             f"{100 * sug.fields['transfer_gain']:.3g} %)")
        if gain >= GAIN_MIN and p_value <= P_MAX:
            if sug.transfer is not None and (sug.transfer <= 0.0 or
                                             sug.fields["transfer_own"] < TRANSFER_MIN):
                lost.append(sug)
            else:
                good.append(sug)
        else:
            bad.append(sug)
    # rank by what transfers to the validation logs when there are some, else by the CV gain
    good.sort(key=lambda s: -(s.transfer if s.transfer is not None else s.gain))
    good = _prefer_simpler(_physics_order(good))
    bad.sort(key=lambda s: -s.gain)
    lost.sort(key=lambda s: -s.gain)
    if lost:
        notes.append(f"{', '.join(s.label() for s in lost[:6])} won the cross-validation but "
                     "did not cut the error on the validation logs: not suggested")
    return Diagnosis(result, model.labels(), [float(x) for x in rmse0], good, bad[:10],
                     absorbed, odd, notes, residuals,
                     not_transferring=lost, doubts=doubts)


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


class _Transfer:
    """Fit on all the training rows, RMSE on the validation logs' rows (Grams summed)."""

    def __init__(self, train: Grams, held: Grams) -> None:
        self.p = train.p
        self.a = train.g.sum(axis=(0, 1))
        self.h = held.g.sum(axis=1)
        self.counts = self.h[:, self.p + 1, self.p + 1]

    def rmse(self, cols: np.ndarray) -> np.ndarray:
        p = self.p
        a, b = self.a[np.ix_(cols, cols)], self.a[cols, p]
        d = 1.0 / np.sqrt(np.clip(np.diag(a), 1e-300, None))
        evals, evecs = np.linalg.eigh(a * np.outer(d, d))
        keep = evals > evals[-1] * RANK_TOL
        theta = d * (evecs[:, keep] @ ((evecs[:, keep].T @ (b * d)) / evals[keep]))
        idx = np.concatenate((cols, [p]))
        v = np.concatenate((-theta, [1.0]))
        sse = np.einsum("i,jik,k->j", v, self.h[:, idx[:, None], idx[None, :]], v)
        return np.sqrt(np.maximum(sse, 0.0) / np.maximum(self.counts, 1.0))


def _model_transfer(robot: Robot, pb: Any, transfer: _Transfer, n_model: int,
                    independent: Sequence[int]) -> list[str]:
    """The model's own effects, each left out in turn: one whose removal lowers the
    validation logs' error raised it (a simpler model transfers better)."""
    widths = [len(b.param_names(robot)) for b in pb.blocks]
    starts = np.cumsum([0, *widths])
    owner = np.searchsorted(starts, np.asarray(independent), side="right") - 1
    full = transfer.rmse(np.arange(n_model))
    out = []
    for bi, blk in enumerate(pb.blocks):
        if blk.effect.name == "rigid_body" or not np.any(owner == bi):
            continue
        rws = blk.rows(robot, pb.transmission)
        less = transfer.rmse(np.flatnonzero(owner != bi))
        with_it, without = _rms(full[rws]), _rms(less[rws])
        if without < (1.0 - TRANSFER_MIN) * with_it:
            out.append(f"{blk.key} raises the validation logs' error ({without:.4g} → "
                       f"{with_it:.4g} N·m on its joints): a model without it transfers "
                       "better")
    return out


def _doubts(result: IdentResult) -> list[str]:
    """Why a model with nothing missing still cannot be called adequate."""
    out = []
    extrap = [n for n in result.notes if "the model extrapolates" in n]
    if len(extrap) >= EXTRAPOLATION_MAX:
        out.append(f"{len(extrap)} extrapolation warnings: the validation motion leaves the "
                   "training ranges, so its error says little about the model")
    try:
        val, nom = result.validation, result.nominal
    except (AttributeError, ValueError):  # no held-out rows
        return out
    if (val is not None and nom is not None and val.relative_error is not None
            and nom.relative_error is not None and val.relative_error > nom.relative_error):
        out.append(f"held-out relative error {100 * val.relative_error:.3g} % is above the "
                   f"a-priori (CAD) model's {100 * nom.relative_error:.3g} %")
    return out


def _repeats(q: np.ndarray, r: np.ndarray, period: float) -> float:
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


def _physics_order(good: list[Suggestion]) -> list[Suggestion]:
    """A spring and a ripple on one joint within NEAR_EQUAL of each other: what physics says
    of each decides — cogging repeats along the angle, a spring does not."""
    out = list(good)
    for i, a in enumerate(out):
        for k in range(i + 1, len(out)):
            b = out[k]
            if a.joint != b.joint or {a.effect, b.effect} != {"spring", "ripple"}:
                continue
            near = abs(a.fields["rmse_after"] - b.fields["rmse_after"]) <= NEAR_EQUAL * max(
                a.fields["rmse_after"], b.fields["rmse_after"], 1e-12)
            ripple = a if a.effect == "ripple" else b
            repeats = ripple.fields.get("repeat", 0.0) >= REPEAT_MIN
            if near and (a is ripple) != repeats:
                out[i], out[k] = b, a
            break
    return out


def _residual_dict(resid: np.ndarray, states: States, fs: float) -> dict[str, np.ndarray]:
    """What the residual figures plot."""
    return {"r": resid, "q": states.q, "qd": states.qd, "qdd": states.qdd, "t": states.t,
            "fs": np.array(fs)}


def _prefer_simpler(good: list[Suggestion]) -> list[Suggestion]:
    """Among near-equal explanations on one joint, the one with fewer parameters first."""
    order = {"offset": 1, "viscous": 1, "friction": 1, "coulomb": 1, "armature": 1,
             "load_friction": 1, "stribeck": 1, "presliding": 1, "coulomb_asymmetric": 2,
             "ripple": 2, "friction_drift": 2, "friction_power": 3, "spring": 9, "delay": 1}
    out = list(good)
    swapped = True
    while swapped:  # bubble until stable: equivalents may come in any order
        swapped = False
        for i in range(len(out) - 1):
            a, b = out[i], out[i + 1]
            close = abs(a.fields["rmse_after"] - b.fields["rmse_after"]) <= 0.01 * max(
                a.fields["rmse_after"], 1e-12)  # equivalent: the same error left, within 1 %
            if {a.effect, b.effect} == {"spring", "ripple"}:
                continue  # physics decides those (_physics_order)
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


def _unexplained(prep: Prepared, design: Design, theta: np.ndarray,
                 hints: Mapping[int, ResonanceHint] | None = None) -> list[dict[str, Any]]:
    """Structure no catalog effect explains: a resonance in the raw residual spectrum, with
    what measures it: the caller's hint for that joint (``hints``), else the generic one."""
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
            hint = (hints or {}).get(j + 1)
            entry = hint.measured_by if hint is not None else None
            todo = hint.todo if hint is not None else (
                f"measure it with an elasticity experiment for joint {j + 1} (robid excite "
                f"--kind elasticity --joint {j + 1})")
            out.append({"joint": j + 1, "kind": "resonance", "frequency_hz": round(fr, 3),
                        "peak_over_floor": round(prominence, 1), "measured_by": entry,
                        "text": f"joint {j + 1} residual has a resonance at {fr:.3g} Hz "
                                f"({prominence:.3g}× its neighbourhood): joint elasticity? "
                                f"{todo[0].upper()}{todo[1:]}"})
    return out


def _motion_bandwidth(q: np.ndarray, fs: float) -> float:
    """Frequency below which 99 % of the positions' variation lies."""
    spec = np.abs(np.fft.rfft(q - q.mean(axis=0), axis=0)) ** 2
    cum = np.cumsum(spec.sum(axis=1))
    k = int(np.searchsorted(cum, 0.99 * cum[-1]))
    return float(k * fs / q.shape[0])
