"""The fitted model's residual where a diagnosis looks: the prepared logs with the model's own
torque, the rows candidates are profiled and scored on, and the residual on decimated rows
(evidence, profiling, the residual figures)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from robid_link.ident.data.preprocess import Piece, Prepared, Problem, filter_windows, split
from robid_link.ident.diagnosis.hyperparams import ProfileRows
from robid_link.ident.fit.design import Design, base_set_for, with_predictions
from robid_link.ident.fit.results import IdentResult
from robid_link.ident.model.effects import States
from robid_link.ident.model.regressor import BaseSet
from robid_link.ident.model.robot import Robot

__all__ = ["ResidualPool", "residual_pool", "residual_rows", "profile_rows", "residual_dict",
           "where_excess", "Where", "SPLINE_NODES", "PROFILE_ROWS", "RESIDUAL_ROWS",
           "TURN_SHARE_MIN", "TURN_CONCENTRATION", "FAST_MARGIN"]

#: the model's smooth torque is evaluated on this many rows per period of the cutoff, a
#: cubic spline between (``with_predictions``): the rate the union Grams are read at
SPLINE_NODES = 8
#: rows (spread over the log) on which hyper-parameters are profiled
PROFILE_ROWS = 3000
#: about this many decimated rows carry the residual (evidence and profiling)
RESIDUAL_ROWS = 12000
#: a joint's residual sits at its turns when at least this share of its filtered excess over
#: the noise lies within one period of the cutoff of its velocity reversals …
TURN_SHARE_MIN = 0.5
#: … and that share is this many times the share of rows there
TURN_CONCENTRATION = 3.0
#: a filtered residual within this factor of the noise through the filter: the excess of the
#: raw one is faster than the cutoff
FAST_MARGIN = 1.1


@dataclass(frozen=True)
class ResidualPool:
    """The fitted model and its residual, where the candidates are profiled and scored."""

    problem: Problem
    design: Design
    base: BaseSet  # the model's structural base set (identify's)
    theta: np.ndarray  # identify's estimate of the base parameters
    preps: list[Prepared]  # the training, then the validation logs, with the model's torque
    pieces: list[Piece]  # rows candidates are profiled and cross-validated on
    vpieces: list[Piece]  # the validation logs' rows (transfer); empty without
    step: int  # decimation of the residual rows
    resid: np.ndarray  # (rows, n): the residual of the filtered torque …
    raw: np.ndarray  # … and of the raw torque
    states: States  # the states of those rows


def residual_pool(robot: Robot, result: IdentResult) -> ResidualPool:
    """The model's predictions on copies of the result's prepared logs, and its residual.
    With validation logs, candidates are profiled and cross-validated on the training logs
    and then scored on the validation logs (a new motion); without, all the data is one
    pool."""
    pb, design = result.problem, result.design
    if pb is None or design is None:
        raise ValueError("diagnose needs a result from identify (it keeps the fitted problem)")
    base, _ = base_set_for(robot, pb.blocks, pb.transmission)
    theta = np.asarray(result.theta)  # same model, same base set: identify's estimate
    for prep in (*pb.preps, *pb.vpreps):  # every pass below reads all the states' rows
        prep.keep_kinematics()
    filt = pb.preps[0].filt
    preps = with_predictions(robot, [*pb.preps, *pb.vpreps], design, theta,
                             every=max(1, int(filt.fs / (SPLINE_NODES * filt.cutoff_hz))))
    pieces, _ = split(preps[: len(pb.preps)] if pb.vpreps else preps, None, holdout=0.0)
    vpieces = split(preps[len(pb.preps):], None, holdout=0.0)[0] if pb.vpreps else []
    step = max(1, sum(len(p) for p in pieces) // RESIDUAL_ROWS)
    resid, raw, states = residual_rows(pieces, step)
    return ResidualPool(pb, design, base, theta, preps, pieces, vpieces, step, resid, raw,
                        states)


def residual_rows(pieces: Sequence[Piece], step: int
                  ) -> tuple[np.ndarray, np.ndarray, States]:
    """The model's residual on decimated rows, of the filtered and of the raw torque, with
    the states of those rows. Filtering is linear, so filtering the raw residual (τ − Xθ with
    the model's prediction from ``with_predictions``) equals the parallel-filtered residual
    τ_f − X_f·θ, at the cost of n columns instead of the design's."""
    res: list[np.ndarray] = []
    raw: list[np.ndarray] = []
    parts: dict[str, list[np.ndarray]] = {k: [] for k in ("q", "qd", "qdd", "t", "tr", "rate")}
    for pc in pieces:
        prep, model = pc.prep, pc.prep.tau_model
        if model is None:
            raise ValueError("residual_rows needs the model's torque on the logs "
                             "(with_predictions)")
        for a, b, ca, cb, at_edge in filter_windows(pc, step):
            filtered = prep.filt.apply(prep.tau[ca:cb] - model[ca:cb], edges=at_edge)
            idx = np.arange(a, b, step)
            # rows without a joint's torque (partial logs, sticks) show no residual there
            keep = 1.0 if prep.tau_mask is None else prep.tau_mask[idx]
            res.append(filtered[a - ca: b - ca: step] * keep)
            raw.append((prep.tau[idx] - model[idx]) * keep)
            parts["q"].append(prep.q[idx])
            parts["qd"].append(prep.qd[idx])
            parts["qdd"].append(prep.qdd[idx])
            parts["t"].append(prep.log.t[idx] - prep.log.t[0])
            if prep.tau_rigid is not None and prep.tau_rate is not None:
                parts["tr"].append(prep.tau_rigid[idx])
                parts["rate"].append(prep.tau_rate[idx])
    cat = {k: np.concatenate(v) for k, v in parts.items() if v}
    st = States(cat["q"], cat["qd"], cat["qdd"], cat["t"], pieces[0].prep.transmission,
                cat.get("tr"), cat.get("rate"))
    return np.concatenate(res), np.concatenate(raw), st


def profile_rows(robot: Robot, pool: ResidualPool, count: int = PROFILE_ROWS) -> ProfileRows:
    """About ``count`` of the residual rows, spread over the whole log, with the model's
    dense regressor on them: where hyper-parameters are profiled and candidates screened
    (PROFILE_ROWS), or where a shape is refined (every residual row)."""
    states = pool.states
    every = max(1, len(states) // count)
    sub_states = states.rows(slice(None, None, every))
    return ProfileRows(robot, sub_states, pool.raw[::every], pool.resid[::every],
                       pool.design.expand(pool.design.compact(sub_states)))


def residual_dict(pool: ResidualPool) -> dict[str, np.ndarray]:
    """What the residual figures plot."""
    st = pool.states
    assert st.t is not None  # the pool's rows carry their times (``residual_pool``)
    return {"r": pool.resid, "q": st.q, "qd": st.qd, "qdd": st.qdd, "t": st.t,
            "fs": np.array(pool.problem.preps[0].filt.fs / pool.step)}


@dataclass(frozen=True)
class Where:
    """Where a joint's excess over the noise sits, said in its floor doubt: at its velocity
    reversals (``energy``: the share of the filtered residual's excess over the noise within
    ``window_s`` of them; ``rows``: the share of the rows there), or above the cutoff (the
    filtered residual ``filtered`` at ``floor``, what the noise leaves through the filter)."""

    kind: str  # "turns" | "fast"
    energy: float
    rows: float
    window_s: float
    cutoff_hz: float
    filtered: float = 0.0
    floor: float = 0.0

    def sentence(self) -> str:
        if self.kind == "fast":
            return (f"its filtered residual ({self.filtered:.2g} N·m) is what the noise leaves "
                    f"through the {self.cutoff_hz:.3g} Hz filter ({self.floor:.2g} N·m): the "
                    "excess is faster than the cutoff (the loop's own torque, a resonance), "
                    "where no catalog effect at the motion's pace reaches")
        return (f"{100 * self.energy:.0f} % of its filtered residual's excess over the noise "
                f"lies within {self.window_s:.2g} s of its velocity reversals "
                f"({100 * self.rows:.2g} % of the rows): structure at the turns that no catalog "
                f"effect explains — friction that changes there faster than the "
                f"{self.cutoff_hz:.3g} Hz cutoff resolves (a stick, a closed loop's Coulomb "
                "switch)")


def where_excess(pool: ResidualPool, noise: np.ndarray | None) -> dict[int, Where]:
    """Per joint (from 0), where its excess sits, when the residual says: at its velocity
    reversals (at least TURN_SHARE_MIN of the filtered residual's excess over the noise within
    one period of the cutoff of them, TURN_CONCENTRATION times the share of rows there; rows
    left out of the joint's equation count for neither), or above the cutoff (the filtered
    residual within FAST_MARGIN of the noise ``noise`` through the filter)."""
    filt = pool.problem.preps[0].filt
    window = 1.0 / filt.cutoff_hz
    impulse = np.zeros(8 * int(filt.fs / filt.cutoff_hz) + 1)
    impulse[impulse.size // 2] = 1.0
    gain = float(np.sqrt(np.sum(filt.apply(impulse) ** 2)))  # white noise's rms through it
    st, out = pool.states, {}
    assert st.t is not None
    for j in range(pool.resid.shape[1]):
        r2 = pool.resid[:, j] ** 2
        live = r2 > 0
        turns = st.t[np.flatnonzero(np.sign(st.qd[1:, j]) != np.sign(st.qd[:-1, j]))]
        if not live.any():
            continue
        floor2 = 0.0 if noise is None else (gain * noise[j]) ** 2
        if turns.size:
            pos = np.searchsorted(turns, st.t)
            gap = np.minimum(np.abs(st.t - turns[np.clip(pos - 1, 0, turns.size - 1)]),
                             np.abs(turns[np.clip(pos, 0, turns.size - 1)] - st.t))
            near = (gap <= window) & live
            # the excess over what the noise leaves through the filter, near the turns
            excess = float(r2[live].sum() - floor2 * live.sum())
            at = float(r2[near].sum() - floor2 * near.sum())
            energy, rows = at / max(excess, 1e-300), float(near.sum() / live.sum())
            if excess > 0 and energy >= TURN_SHARE_MIN and energy >= TURN_CONCENTRATION * rows:
                out[j] = Where("turns", min(energy, 1.0), rows, window, filt.cutoff_hz)
                continue
        rms_f = float(np.sqrt(r2[live].mean()))
        if noise is not None and rms_f <= FAST_MARGIN * gain * noise[j]:
            out[j] = Where("fast", 0.0, 0.0, window, filt.cutoff_hz, rms_f, gain * noise[j])
    return out
