"""Scoring the candidates left after the screens: one union design (the model's base columns,
then each candidate's new ones) reduced once to per-joint, per-time-block Grams; blocked
cross-validation on sub-blocks of them, a Wald test with the long-run-variance covariance,
the practical gain on the candidate's joints, and the suggestion with its evidence."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy.stats import chi2

from robid_link.ident.data.logs import Log
from robid_link.ident.data.preprocess import Prepared
from robid_link.ident.data.sticks import smear_rows
from robid_link.ident.diagnosis.candidates import Candidate
from robid_link.ident.diagnosis.evidence import Signatures, evidence_sentence, repeats
from robid_link.ident.diagnosis.residuals import ResidualPool
from robid_link.ident.diagnosis.verdict import Suggestion
from robid_link.ident.fit.design import Design, structural_mask
from robid_link.ident.fit.estimate import (
    RANK_TOL,
    Grams,
    GramSet,
    accumulate,
    accumulate_sets,
    batch_factor,
    solve,
)
from robid_link.ident.model.effects import Block
from robid_link.ident.model.robot import Robot

__all__ = ["FOLDS", "BLOCKS", "Union", "union_design", "fold_masks", "FoldSums", "FoldCV",
           "cross_validation", "UnionGrams", "union_passes", "wald", "Score", "score_candidate",
           "given_others", "reversal_grams", "without_turns", "AT_TURNS", "suggestion",
           "one_motion_note", "rms"]

FOLDS = 5
#: time blocks of the union Grams (folds are made of them)
BLOCKS = 40


@dataclass(frozen=True)
class Union:
    """The model's base columns, then each candidate's new columns, in one design."""

    design: Design
    n_model: int  # the model's base columns, first
    blocks: list[Block]  # the candidates, in order
    positions: list[np.ndarray]  # each candidate's columns in the union design
    keep: int  # every keep-th row (after the anti-alias filter)
    block_len: int  # rows per time block at that rate
    transmission: np.ndarray | None


def union_design(robot: Robot, pool: ResidualPool, kept: Sequence[Candidate]) -> Union:
    """The union design of the model and the candidates kept, and the rate it is read at:
    rows after the anti-alias filter suffice."""
    pb, base = pool.problem, pool.base
    model_cols = list(base.independent)
    start = len(base.names)  # a candidate's standard columns follow the model's
    cand_cols: list[list[int]] = []
    for c in kept:
        cand_cols.append([start + i for i in c.new])
        start += len(c.block.param_names(robot))
    blocks = [c.block for c in kept]
    union_blocks = [*pb.blocks, *blocks]
    cols = np.array(model_cols + [c for cc in cand_cols for c in cc])
    design = Design(robot, union_blocks, cols,
                    structural_mask(robot, union_blocks, cols, pb.transmission))
    positions, pos = [], len(model_cols)
    for cc in cand_cols:
        positions.append(np.arange(pos, pos + len(cc)))
        pos += len(cc)
    fs, fc = pb.preps[0].filt.fs, pb.preps[0].filt.cutoff_hz
    keep = max(pb.interval, int(fs / (8.0 * fc)))
    block_len = max(1, pb.block_len * pb.interval // keep)
    return Union(design, len(model_cols), blocks, positions, keep, block_len, pb.transmission)


def fold_masks(k_blocks: int, folds: int) -> list[tuple[np.ndarray, np.ndarray]]:
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


@dataclass(frozen=True)
class FoldSums:
    """What the cross-validation and the Wald test read of the union Grams: each joint's
    total (n, p+2, p+2), each block's last row (n, K, p+2: counts and sums) and, per fold,
    each joint's training and held-out Grams — summed over contiguous runs of blocks (a
    fold's held-out blocks and the gap round them are one run each), never copied."""

    total: np.ndarray
    last: np.ndarray
    train: list[np.ndarray]  # per fold (n, p+2, p+2)
    held: list[np.ndarray]  # per fold (n, p+2, p+2)

    @classmethod
    def of(cls, grams: Grams, folds: Sequence[tuple[np.ndarray, np.ndarray]]) -> FoldSums:
        g, total = grams.g, grams.total()
        train, held = [], []
        for h, tr in folds:
            run, gap = np.flatnonzero(h), np.flatnonzero(~tr)
            held.append(g[:, run[0]: run[-1] + 1].sum(axis=1))
            train.append(total - g[:, gap[0]: gap[-1] + 1].sum(axis=1))
        return cls(total, g[:, :, grams.p + 1, :], train, held)

    def without(self, other: FoldSums, joints: np.ndarray) -> FoldSums:
        """These sums with ``other``'s taken off the equations of ``joints``."""
        on = np.zeros(self.total.shape[0])
        on[joints] = 1.0

        def minus(a: np.ndarray, b: np.ndarray) -> np.ndarray:
            return a - b * on.reshape((-1,) + (1,) * (a.ndim - 1))

        return FoldSums(minus(self.total, other.total), minus(self.last, other.last),
                        [minus(a, b) for a, b in zip(self.train, other.train, strict=True)],
                        [minus(a, b) for a, b in zip(self.held, other.held, strict=True)])


class FoldCV:
    """Blocked cross-validation on sub-blocks of the union Grams.

    Per fold the model's block is factored once (column-scaled); a candidate's columns are
    added through the Schur complement, so scoring it costs O(p·k) instead of a refit.
    ``sums``: the Grams' fold sums when made already (``FoldSums.without``).
    """

    def __init__(self, grams: Grams, n_model: int, folds: list[tuple[np.ndarray, np.ndarray]],
                 sums: FoldSums | None = None) -> None:
        p = grams.p
        self.grams = grams
        self.p, self.n_model = p, n_model
        self.sums = FoldSums.of(grams, folds) if sums is None else sums
        self.train = [a.sum(axis=0) for a in self.sums.train]  # (p+2, p+2)
        self.held = self.sums.held  # (n, p+2, p+2)
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
        #: the model's own held-out RMSE per joint (no candidate)
        self.base = self.rmse(np.zeros(0, dtype=int))

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


def cross_validation(union: Union, pool: ResidualPool, grams: Grams | None = None) -> FoldCV:
    """The union Grams of the pool's rows in BLOCKS time blocks (``grams``: made already,
    ``union_passes``), split into FOLDS folds."""
    if grams is None:
        grams = accumulate(union.design, pool.pieces, union.keep, union.block_len,
                           max_blocks=BLOCKS, smooth=True)
    return FoldCV(grams, union.n_model, fold_masks(grams.g.shape[1], FOLDS))


@dataclass(frozen=True)
class UnionGrams:
    """What one pass over the pool's training rows gives the union design: the Grams of the
    cross-validation, of the rows near the velocity reversals (``reversal_grams``) and, with
    validation logs, the training Grams of the transfer scorer (two blocks)."""

    cv: Grams | None
    turns: Grams | None
    train: Grams | None


def union_passes(union: Union, pool: ResidualPool, candidates: bool, transfer: bool
                 ) -> UnionGrams:
    """The union Grams the diagnosis needs from the training rows, in one pass: with
    ``candidates`` the cross-validation's and the reversals' (each chunk's rows are built and
    filtered once, not once per set); with ``transfer`` the transfer scorer's."""
    sets = ([GramSet(BLOCKS), GramSet(BLOCKS, lambda pc: _reversal_rows(pc.prep))]
            if candidates else []) + ([GramSet(2)] if transfer else [])
    if not sets:
        return UnionGrams(None, None, None)
    grams = accumulate_sets(union.design, pool.pieces, union.keep, union.block_len, sets,
                            smooth=True)
    return UnionGrams(grams[0] if candidates else None, grams[1] if candidates else None,
                      grams[-1] if transfer else None)


def wald(sums: FoldSums, sub: np.ndarray, cand: np.ndarray
         ) -> tuple[float, np.ndarray, np.ndarray]:
    """p-value that the candidate's coefficients are zero, the full-data θ and the
    candidate's coefficients' standard errors (the long-run-variance covariance's)."""
    p = sums.total.shape[1] - 2
    idx = np.concatenate((sub, [p, p + 1]))
    tot = sums.total[:, idx[:, None], idx[None, :]]
    s = sub.size
    theta, a_inv, _ = solve(tot[:, :s, :s].sum(0), tot[:, :s, s].sum(0), warn=False)
    kappa, var = batch_factor(sums.total, sums.last, theta, sub)
    cov = a_inv @ np.einsum("j,jik->ik", kappa * var, tot[:, :s, :s]) @ a_inv
    pos = np.searchsorted(sub, cand) if np.all(np.diff(sub) > 0) else \
        np.array([int(np.flatnonzero(sub == c)[0]) for c in cand])
    beta = theta[pos]
    c_cc = cov[np.ix_(pos, pos)]
    se = np.sqrt(np.clip(np.diag(c_cc), 0.0, None))
    # rank-revealing: directions the data cannot tell apart carry no degrees of freedom
    evals, evecs = np.linalg.eigh((c_cc + c_cc.T) / 2)
    keep = evals > max(evals.max(), 0.0) * 1e-10
    if not keep.any():
        return 1.0, theta, se
    z = evecs[:, keep].T @ beta
    stat = float(np.sum(z * z / evals[keep]))
    return float(chi2.sf(stat, int(keep.sum()))), theta, se


@dataclass(frozen=True)
class Score:
    """One candidate's figures on the training rows."""

    rmse: np.ndarray  # per joint, held out (CV), with the candidate
    p_value: float  # Wald test that its coefficients are zero
    coef: np.ndarray  # its coefficients, fitted on all the rows
    se: np.ndarray  # … and their standard errors (the Wald test's covariance)
    rows: list[int]  # the joints whose torque it loads
    before: float  # RMS over those joints of the held-out RMSE without it …
    after: float  # … and with it
    gain: float  # 1 − after / before


def score_candidate(robot: Robot, cv: FoldCV, union: Union, k: int) -> Score:
    """Candidate ``k`` of the union: cross-validated RMSE, Wald test, gain on its joints."""
    blk, cand = union.blocks[k], union.positions[k]
    sub = np.concatenate((np.arange(union.n_model), cand))
    rmse1 = cv.rmse(cand)
    p_value, theta, se = wald(cv.sums, sub, cand)
    rws = blk.rows(robot, union.transmission)  # a coupled motor's friction: several joints
    before, after = rms(cv.base[rws]), rms(rmse1[rws])
    return Score(rmse1, p_value, theta[union.n_model:], se, rws, before, after,
                 1.0 - after / max(before, 1e-300))


def given_others(robot: Robot, cv: FoldCV, union: Union, k: int, others: Sequence[int]
                 ) -> tuple[float, float]:
    """Candidate ``k``'s gain on its joints and its Wald p-value with the candidates ``others``
    already in the model (each one's columns added on the same folds)."""
    blk, cand = union.blocks[k], union.positions[k]
    held = np.concatenate([union.positions[o] for o in others]) if others else \
        np.zeros(0, dtype=int)
    rws = blk.rows(robot, union.transmission)
    before = rms(cv.rmse(held)[rws])
    after = rms(cv.rmse(np.concatenate((held, cand)))[rws])
    sub = np.sort(np.concatenate((np.arange(union.n_model), held, cand)))
    p_value, _, _ = wald(cv.sums, sub, cand)
    return 1.0 - after / max(before, 1e-300), p_value


def _reversal_rows(prep: Prepared) -> np.ndarray:
    """Rows × joints near the joint's velocity reversals (sign changes of its filtered
    velocity; as far as a stick's rows are left out: ``sticks.smear_rows``), where its torque
    still counts."""
    smear = smear_rows(prep)
    qd = prep.qd
    out = np.zeros(qd.shape, bool)
    for j in range(qd.shape[1]):
        for k in np.flatnonzero(np.sign(qd[1:, j]) != np.sign(qd[:-1, j])):
            out[max(0, k - smear): k + smear + 2, j] = True
    return out if prep.tau_mask is None else out & prep.tau_mask


def reversal_grams(union: Union, pool: ResidualPool) -> Grams:
    """The union Grams of each joint's equation on the rows near its own velocity reversals
    only, on cross_validation's time blocks (the same pieces in the same order; a pass of its
    own: ``union_passes`` gives them with the cross-validation's)."""
    pieces = [replace(pc, prep=replace(pc.prep, tau_mask=_reversal_rows(pc.prep)))
              for pc in pool.pieces]
    return accumulate(union.design, pieces, union.keep, union.block_len, max_blocks=BLOCKS,
                      smooth=True)


#: effects whose evidence lies at the turns too — friction laws of the velocity, and a delay
#: (a late torque log shows the Coulomb switch late): their own joints' rows near the velocity
#: reversals stay when their gain is checked away from the turns
AT_TURNS = frozenset({"viscous", "coulomb", "friction", "friction_power", "coulomb_asymmetric",
                      "stribeck", "presliding", "friction_drift", "load_friction", "delay"})


def without_turns(robot: Robot, cv: FoldCV, union: Union, turns: Grams, k: int,
                  others: Sequence[int] = ()) -> tuple[float, float]:
    """Candidate ``k``'s gain on its joints and its Wald p-value (with the candidates
    ``others`` in the model) when the rows near the joints' velocity reversals are left out of
    their equations — the other joints' for an effect whose evidence lies at the turns too
    (AT_TURNS; none for a delay, which loads every joint), every joint's for anything else. A
    closed loop's friction at a turn (a stick, the kink of a Coulomb switch) is finer than the
    filter resolves; what the model misses there recurs wherever the motion turns again (at
    the same angles in a repeated motion) and biases the parameters the joints share, so a
    candidate that lives on it loses its gain here."""
    blk, cand = union.blocks[k], union.positions[k]
    held = np.concatenate([union.positions[o] for o in others]) if others else \
        np.zeros(0, dtype=int)
    own = blk.rows(robot, union.transmission)
    out = np.arange(robot.n)
    if blk.effect.name in AT_TURNS:
        out = np.setdiff1d(out, own)
    folds = fold_masks(cv.grams.g.shape[1], FOLDS)
    sums = cv.sums.without(FoldSums.of(turns, folds), out)
    fold = FoldCV(cv.grams, union.n_model, folds, sums)
    before = rms(fold.rmse(held)[own])
    after = rms(fold.rmse(np.concatenate((held, cand)))[own])
    sub = np.sort(np.concatenate((np.arange(union.n_model), held, cand)))
    p_value, _, _ = wald(sums, sub, cand)
    return 1.0 - after / max(before, 1e-300), p_value


def suggestion(blk: Block, score: Score, signatures: Signatures) -> Suggestion:
    """The candidate as a suggestion: its figures, its evidence sentence and fields (with a
    ripple, whether the residual repeats one period on; with a Stribeck curve, its fitted
    breakaway and σ, which ``verdict.judge`` reads)."""
    text, fields = evidence_sentence(blk, score.before, score.after, signatures.of(blk),
                                     score.coef)
    if blk.effect.name == "stribeck" and score.coef.size:
        fields["breakaway"] = float(f"{score.coef[0]:.4g}")
        fields["breakaway_sigma"] = float(f"{score.se[0]:.3g}")
        text += (f"; breakaway {blk.param_names(signatures.robot)[0]} "
                 f"{fields['breakaway']:.4g} ± {fields['breakaway_sigma']:.3g} N·m")
    if blk.effect.name == "ripple" and blk.joint is not None:
        fields["repeat"] = round(repeats(signatures.states.q[:, blk.joint],
                                         signatures.resid[:, blk.joint],
                                         float(blk.opts["period"])), 3)
        text += f"; the residual repeats every period (correlation {fields['repeat']:.3g})"
    gain = float(score.gain)
    return Suggestion(blk.effect.name, None if blk.joint is None else blk.joint + 1,
                      [float(x) for x in score.rmse], gain, score.p_value, text,
                      {"gain": round(gain, 4), **fields},
                      {k: float(v) for k, v in blk.opts.items()}, blk.side)


def one_motion_note(logs: Sequence[Log]) -> list[str]:
    """When every log repeats one motion, the scores come from the cross-validation alone."""
    if len(logs) == 1 or all(_same_motion(logs[0], lg) for lg in logs[1:]):
        return ["all data is one motion: candidates are scored by blocked "
                f"cross-validation over the log ({FOLDS} folds), not on a new motion"]
    return []


def _same_motion(a: Log, b: Log) -> bool:
    n = min(len(a), len(b))
    return bool(n > 10 and np.abs(a.q[:n] - b.q[:n]).max() < 0.02)


def rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))
