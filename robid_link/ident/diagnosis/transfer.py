"""Transfer to the validation logs (another motion): each candidate fitted on all the training
rows and scored on the validation rows, and the model's own effects left out one at a time
(an effect whose removal lowers the validation error is a doubt about the model)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from robid_link.ident.data.preprocess import Problem
from robid_link.ident.diagnosis.residuals import ResidualPool
from robid_link.ident.diagnosis.scoring import Score, Union, rms
from robid_link.ident.diagnosis.verdict import TRANSFER_MIN, Suggestion
from robid_link.ident.fit.estimate import RANK_TOL, Grams, accumulate
from robid_link.ident.model.robot import Robot

__all__ = ["Transfer", "transfer_scorer", "with_transfer", "model_transfer_doubts"]


class Transfer:
    """Fit on all the training rows, RMSE on the validation logs' rows (Grams summed)."""

    def __init__(self, train: Grams, held: Grams, n_model: int) -> None:
        self.p = train.p
        self.n_model = n_model
        self.a = train.g.sum(axis=(0, 1))
        self.h = held.g.sum(axis=1)
        self.counts = self.h[:, self.p + 1, self.p + 1]
        #: the model's own validation RMSE per joint (its ``n_model`` base columns)
        self.base = self.rmse(np.arange(n_model))

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


def transfer_scorer(union: Union, pool: ResidualPool, train: Grams | None = None
                    ) -> Transfer:
    """The union Grams of the training rows (``train``: made already, ``union_passes``) and
    of the validation logs' rows."""
    if train is None:
        train = accumulate(union.design, pool.pieces, union.keep, union.block_len,
                           max_blocks=2, smooth=True)
    return Transfer(train, accumulate(union.design, pool.vpieces, union.keep, union.block_len,
                                      max_blocks=2, smooth=True), union.n_model)


def with_transfer(sug: Suggestion, score: Score, transfer: Transfer, cand: np.ndarray
                  ) -> Suggestion:
    """The suggestion with its figures on the validation logs. The effect shares the
    rigid-body parameters with every joint: what it does to the others counts too (each
    joint relative to itself, so none dominates)."""
    rmse_v0 = transfer.base
    rmse_v1 = transfer.rmse(np.concatenate((np.arange(transfer.n_model), cand)))
    v_before, v_after = rms(rmse_v0[score.rows]), rms(rmse_v1[score.rows])
    gain = 1.0 - rms(rmse_v1 / np.maximum(rmse_v0, 1e-300))
    fields = {**sug.fields, "validation_before": round(v_before, 4),
              "validation_after": round(v_after, 4), "transfer_gain": round(gain, 4),
              "transfer_own": round(1.0 - v_after / max(v_before, 1e-300), 4)}
    evidence = (f"{sug.evidence}; on the validation logs {fields['validation_before']:.4g} → "
                f"{fields['validation_after']:.4g} N·m (all joints: "
                f"{100 * fields['transfer_gain']:.3g} %)")
    return replace(sug, transfer=gain, fields=fields, evidence=evidence)


def model_transfer_doubts(robot: Robot, pb: Problem, transfer: Transfer,
                          independent: Sequence[int]) -> list[str]:
    """The model's own effects, each left out in turn: one whose removal lowers the
    validation logs' error raised it (a simpler model transfers better)."""
    widths = [len(b.param_names(robot)) for b in pb.blocks]
    starts = np.cumsum([0, *widths])
    owner = np.searchsorted(starts, np.asarray(independent), side="right") - 1
    full = transfer.base
    out = []
    for bi, blk in enumerate(pb.blocks):
        if blk.effect.name == "rigid_body" or not np.any(owner == bi):
            continue
        rws = blk.rows(robot, pb.transmission)
        less = transfer.rmse(np.flatnonzero(owner != bi))
        with_it, without = rms(full[rws]), rms(less[rws])
        if without < (1.0 - TRANSFER_MIN) * with_it:
            out.append(f"{blk.key} raises the validation logs' error ({without:.4g} → "
                       f"{with_it:.4g} N·m on its joints): a model without it transfers "
                       "better")
    return out
