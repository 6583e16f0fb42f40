"""Diagnosis: where the model fails, which catalog effect is missing, and how much it helps.

``diagnose`` is a pipeline of named steps, each in a module of this room: the fitted model's
residual (residuals.py); the catalog's candidates, their hyper-parameters, a structural and
an in-sample screen (candidates.py); one union design reduced once to per-joint, per-time-block
Grams, on which each candidate is scored by blocked cross-validation, a Wald test and a
practical gain (scoring.py); with ``validate`` logs (another motion) each candidate fitted on
all training rows and scored on them — what does not transfer is not suggested, and the
model's own effects are checked the same way (transfer.py); the verdict, its doubts and the
ranking (verdict.py); the sentence of evidence under each suggestion (evidence.py).
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from robid_link.exceptions import DataError
from robid_link.ident.data.logs import Log
from robid_link.ident.data.preprocess import Prepared
from robid_link.ident.diagnosis.candidates import (
    Candidate,
    catalog_candidates,
    drop_slow_ripples,
    insample_screen,
    profile_candidates,
    refine_survivors,
    screen_notes,
    structural_screen,
)
from robid_link.ident.diagnosis.evidence import Signatures, counterbalances
from robid_link.ident.diagnosis.hyperparams import ProfileRows, screens
from robid_link.ident.diagnosis.limits import (
    limited_candidates,
    limits_note,
    log_limits,
    within_a_sample,
    within_limits,
)
from robid_link.ident.diagnosis.residuals import (
    profile_rows,
    residual_dict,
    residual_pool,
    where_excess,
)
from robid_link.ident.diagnosis.scoring import (
    cross_validation,
    given_others,
    one_motion_note,
    score_candidate,
    suggestion,
    union_design,
    union_passes,
    without_turns,
)
from robid_link.ident.diagnosis.transfer import (
    model_transfer_doubts,
    transfer_scorer,
    with_transfer,
)
from robid_link.ident.diagnosis.verdict import (
    GAIN_MIN,
    P_MAX,
    Diagnosis,
    Suggestion,
    floor_doubts,
    judge,
    not_repeating_note,
    not_transferring_note,
    one_by_one,
    rank,
    result_doubts,
    unphysical_note,
)
from robid_link.ident.fit.design import Design
from robid_link.ident.fit.identify import identify
from robid_link.ident.fit.results import IdentResult
from robid_link.ident.model.effects import Block, Model
from robid_link.ident.model.robot import Robot
from robid_link.jobs import ResonanceHint

__all__ = ["Suggestion", "Diagnosis", "diagnose", "fit_or_reuse", "GAIN_MIN", "P_MAX"]


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
    partial = next((lg for lg in (*data, *(validate or ())) if lg.partial), None)
    if partial is not None:  # its residual pool and scores are joint × row matrices
        raise DataError(f"{Path(partial.path).name}: the diagnosis needs every joint's torque "
                        "in each log, this log holds only some (a campaign's channels: N); "
                        "identify joins such logs, diagnose does not")
    result = fit_or_reuse(robot, data, model, result, validate=validate, cutoff_hz=cutoff_hz,
                          interval=interval, method=method, motor_side=motor_side)
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="robid-diagnose") as aside:
        # what reads only the fit and the logs runs on a second core beside the candidates
        floor_f = aside.submit(getattr, result, "noise_floor")  # the raw torque's noise
        doubts_f = aside.submit(result_doubts, result)
        pool = residual_pool(robot, result)
        odd_f = aside.submit(_unexplained, pool.preps[0], pool.design, pool.theta,
                             resonance_hints)
        limits_f = aside.submit(log_limits, pool.preps[: len(pool.problem.preps)])
        notes = one_motion_note([*data, *(validate or ())])
        turns = where_excess(pool, floor_f.result())
        # the candidates: profiled, then screened (structure, then in-sample) on a few rows
        rows = profile_rows(robot, pool)
        candidates, profiled = profile_candidates(
            rows, catalog_candidates(robot, model, pool.problem.transmission), aside)
        candidates = drop_slow_ripples(candidates, pool.states)
        # the structural screen reads no rows: it runs beside every candidate's in-sample
        # screen (those it finds absorbed are dropped from that one's answer)
        structural_f = aside.submit(structural_screen, robot, pool.problem.blocks, pool.base,
                                    pool.problem.transmission, candidates)
        shares = dict(zip(map(id, candidates), screens(rows, candidates), strict=True))
        structural = structural_f.result()
        insample = insample_screen(rows, structural.new, shares)
        kept = refine_survivors(rows, insample.kept, profiled, functools.cache(
            lambda: profile_rows(robot, pool, len(pool.states))))
        kept += _shift_candidate(structural.new, kept)
        odd, doubts, limits = odd_f.result(), doubts_f.result(), limits_f.result()
    base = len(doubts)

    def with_floor(suggested: Sequence[Suggestion]) -> list[str]:
        """The doubts with each joint's floor doubt, saying where its excess sits when no
        suggestion is on that joint."""
        on = {s.joint for s in suggested}
        return doubts[:base] + floor_doubts(result, {
            j: t for j, t in turns.items() if j + 1 not in on}) + doubts[base:]

    limited = limited_candidates(kept, limits)
    # the profiling rows' dense regressor is not needed by the union pass: kept only for a
    # spring's counterbalance law, fitted once the spring is suggested
    law_rows = rows if any(k.block.effect.name == "spring" for k in kept) else None
    del rows
    notes += screen_notes(structural, insample)
    absorbed, residuals = structural.absorbed, residual_dict(pool)
    if not kept and not pool.vpieces:  # nothing can show a gain: no union pass
        notes += limits_note(limits, {})
        return Diagnosis(result, model.labels(), None, [], [], absorbed, odd, notes,
                         residuals, doubts=with_floor([]))
    union = union_design(robot, pool, kept)
    # one pass over the training rows: the cross-validation's Grams, the reversals' (should a
    # suggestion be judged away from the turns) and the transfer's
    grams = union_passes(union, pool, candidates=bool(kept), transfer=bool(pool.vpieces))
    transfer = transfer_scorer(union, pool, grams.train) if pool.vpieces else None
    if transfer is not None:
        doubts += model_transfer_doubts(robot, pool.problem, transfer, pool.base.independent)
    if not kept:  # nothing can show a gain: no candidate pass
        notes += limits_note(limits, {})
        return Diagnosis(result, model.labels(), None, [], [], absorbed, odd, notes,
                         residuals, doubts=with_floor([]))
    assert grams.cv is not None and grams.turns is not None
    cv = cross_validation(union, pool, grams.cv)
    signatures = Signatures(robot, pool.states, pool.resid)
    scored = []
    for k, blk in enumerate(union.blocks):
        score = score_candidate(robot, cv, union, k)
        sug = suggestion(blk, score, signatures)
        scored.append(sug if transfer is None else
                      with_transfer(sug, score, transfer, union.positions[k]))
    verdicts, held_back = within_limits(judge(scored), limited, limits.fs)
    at = {sug.label(): k for k, sug in enumerate(scored)}
    # a shift within a sample, when the log shows one (it passes the bar a suggestion must), is
    # the log's own timing: in the model while the others are judged, so that none is
    # suggested for what it explains
    skew = next((sug for sug in scored if sug.effect == "delay" and sug.gain >= GAIN_MIN
                 and sug.p_value <= P_MAX
                 and within_a_sample(sug.fields.get("seconds", 1.0), limits.fs)), None)
    extra = [at["delay"]] if skew is not None else []
    nuisance = "" if skew is None else (f"the log's own sample-and-hold (a shift of "
                                        f"{1e3 * skew.fields['seconds']:.2g} ms)")
    reversals = grams.turns
    ranked, explained = one_by_one(
        rank(verdicts),
        lambda sug, better: given_others(robot, cv, union, at[sug.label()],
                                         [at[b.label()] for b in better] + extra),
        lambda sug, better: without_turns(robot, cv, union, reversals, at[sug.label()],
                                          [at[b.label()] for b in better] + extra),
        nuisance)
    notes += _known_torque_pointers(ranked.suggested, law_rows, [k.block for k in kept])
    notes += explained + not_repeating_note(ranked.rejected) + unphysical_note(ranked.rejected)
    notes += not_transferring_note(ranked.not_transferring)
    notes += limits_note(limits, held_back)
    if held_back:
        doubts.append(f"the rate limits the diagnosis: {', '.join(held_back)} cut the error "
                      "but the log cannot separate them (see the notes)")
    return Diagnosis(result, model.labels(), [float(x) for x in cv.base], ranked.suggested,
                     ranked.rejected[:10], absorbed, odd, notes, residuals,
                     not_transferring=ranked.not_transferring,
                     doubts=with_floor(ranked.suggested),
                     limited=[sug for sug, _ in held_back.values()])


def _shift_candidate(new: Sequence[Candidate], kept: Sequence[Candidate]) -> list[Candidate]:
    """The delay candidate, scored whenever others are (though its in-sample share be small):
    a sub-sample shift of the torque log against the positions (a controller that logs the
    torque it holds over its tick) is what the others are judged beyond."""
    if not kept or any(c.block.effect.name == "delay" for c in kept):
        return []
    return [c for c in new if c.block.effect.name == "delay"][:1]


def _known_torque_pointers(suggested: Sequence[Suggestion], rows: ProfileRows | None,
                           kept: Sequence[Block]) -> list[str]:
    """A spring suggestion whose joint a counterbalance law fits points to ``known_torque``:
    the entry on the suggestion, the filled-in example in a note. The law is fitted on the
    profiling rows for the suggested springs' joints only (a ripple there is its rival)."""
    joints = {sug.joint - 1 for sug in suggested if sug.effect == "spring" and sug.joint}
    if rows is None or not joints:
        return []
    laws = {c.joint: c for c in counterbalances(
        rows, [b for b in kept if b.effect.name != "spring" or b.joint in joints]) if c.fits}
    out = []
    for sug in suggested:
        law = laws.get(sug.joint or 0) if sug.effect == "spring" else None
        if law is not None:
            sug.known_torque = law.entry()
            sug.evidence += "; a counterbalance law fits it: known_torque (see the notes)"
            out.append(law.note())
    return out


def fit_or_reuse(robot: Robot, data: Sequence[Log], model: Model, result: IdentResult | None,
                 *, validate: Sequence[Log] | None, cutoff_hz: float | None, interval: int,
                 method: str, motor_side: bool) -> IdentResult:
    """``result`` when it is the model identified with ``method`` and keeps its problem, else
    a new identification. Candidates are scored on OLS/WLS residuals: IRLS means OLS here."""
    method = method if method != "irls" else "ols"
    if result is None or result.method != method or result.problem is None:
        result = identify(robot, data, model, validate=validate, cutoff_hz=cutoff_hz,
                          interval=interval, method=method, motor_side=motor_side)
    return result


def _unexplained(prep: Prepared, design: Design, theta: np.ndarray,
                 hints: Mapping[int, ResonanceHint] | None = None) -> list[dict[str, Any]]:
    """Structure no catalog effect explains: a resonance in the raw residual spectrum, with
    what measures it: the caller's hint for that joint (``hints``), else the generic one."""
    import scipy.signal as sig

    out: list[dict[str, Any]] = []
    n = min(len(prep.log), 200_000)
    if prep.tau_model is not None:  # with_predictions computed it
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
