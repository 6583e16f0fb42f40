"""diagnose()'s steps, each alone: the fitted model's residual, the candidates and their two
screens, the union pass (cross-validation, Wald test, gain), transfer, verdict and ranking,
the evidence. Small inputs: arm3 with one hidden effect, or records written by hand."""

from __future__ import annotations

import warnings
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from robid_link.exceptions import ConditioningWarning, DataWarning, ExcitationWarning
from robid_link.fakes.plant import perturbed_inertials
from robid_link.ident.data.preprocess import filter_windows
from robid_link.ident.diagnosis import diagnose as diagnose_module
from robid_link.ident.diagnosis.candidates import (
    SCREEN_MIN,
    Candidate,
    ColumnSpace,
    InSample,
    Structural,
    catalog_candidates,
    coupled_sides,
    drop_slow_ripples,
    insample_screen,
    profile_candidates,
    refine_survivors,
    screen_notes,
    structural_screen,
)
from robid_link.ident.diagnosis.evidence import Signatures, evidence_sentence
from robid_link.ident.diagnosis.hyperparams import screen, screens
from robid_link.ident.diagnosis.residuals import profile_rows, residual_dict, residual_pool
from robid_link.ident.diagnosis.scoring import (
    BLOCKS,
    FOLDS,
    FoldSums,
    cross_validation,
    fold_masks,
    one_motion_note,
    reversal_grams,
    score_candidate,
    suggestion,
    union_design,
    union_passes,
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
    Verdicts,
    judge,
    not_repeating_note,
    not_transferring_note,
    one_by_one,
    rank,
    result_doubts,
    unphysical_note,
)
from robid_link.ident.fit.design import base_set_for, design_rows, with_predictions
from robid_link.ident.fit.estimate import Grams, accumulate
from robid_link.ident.fit.identify import identify, load_logs
from robid_link.ident.fit.results import ErrorStats, HeldOut
from robid_link.ident.model.effects import DEFAULT_MODEL, REGISTRY, Block, Model

from ..conftest import simulate

VISCOUS = {"name": "viscous", "fv": 2.0}
COULOMB = {"name": "coulomb", "fc": 1.5}
RIPPLE = {"name": "ripple", "joint": 1, "amplitude": 0.6, "period": 0.1}


def _quiet() -> None:
    warnings.simplefilter("ignore", ConditioningWarning)
    warnings.simplefilter("ignore", ExcitationWarning)
    warnings.filterwarnings("ignore", r".*(the a-priori model's torque|has the opposite sign of "
                            r"the a-priori model)", DataWarning)


def _block(name: str, joint: int | None, side: str | None = None, **opts) -> Block:
    return Block(REGISTRY[name], None if joint is None else joint - 1, opts, side)


def _fit(robot, path, model=DEFAULT_MODEL, validate=None, method="ols"):
    with warnings.catch_warnings():
        _quiet()
        return identify(robot, load_logs(robot, [path]), model, method=method,
                        validate=None if validate is None else load_logs(robot, [validate]))


@pytest.fixture(scope="module")
def ripple(arm3, tmp_path_factory):
    """arm3 with a cogging ripple hidden on joint 1 (0.6 N·m every 0.1 rad): the default
    model's fit, its residual pool and the profiling rows."""
    path = tmp_path_factory.mktemp("ripple") / "ripple.csv"
    simulate(arm3, path, noise=0.3, seed=5, duration=40.0, rate=250.0,
             effects=(VISCOUS, COULOMB, RIPPLE))
    result = _fit(arm3, path)
    pool = residual_pool(arm3, result)
    return SimpleNamespace(path=path, result=result, pool=pool, rows=profile_rows(arm3, pool))


@pytest.fixture(scope="module")
def union(arm3, ripple):
    """The union of the model and two candidates: offset@3 (nothing there) and ripple@1."""
    kept = [Candidate(_block("offset", 3), [0]), Candidate(_block("ripple", 1, period=0.1), [0, 1])]
    return union_design(arm3, ripple.pool, kept)


# ----------------------------------------------------------------------------- fit or reuse


def test_fit_or_reuse_reuses_a_result_of_the_method(arm3, ripple, monkeypatch):
    calls = []
    real = diagnose_module.identify
    monkeypatch.setattr(diagnose_module, "identify",
                        lambda *a, **k: calls.append(k["method"]) or real(*a, **k))
    logs = load_logs(arm3, [ripple.path])
    kw = {"validate": None, "cutoff_hz": None, "interval": 1, "motor_side": False}
    res = ripple.result
    assert diagnose_module.fit_or_reuse(arm3, logs, DEFAULT_MODEL, res, method="ols",
                                        **kw) is res
    assert diagnose_module.fit_or_reuse(arm3, logs, DEFAULT_MODEL, res, method="irls",
                                        **kw) is res  # scored on OLS residuals anyway
    assert calls == []
    with warnings.catch_warnings():
        _quiet()
        other = diagnose_module.fit_or_reuse(arm3, logs, DEFAULT_MODEL, res, method="wls",
                                             **kw)
    assert other.method == "wls" and calls == ["wls"]


# ----------------------------------------------------------------------------- residuals


def test_residual_pool_holds_the_models_residual_and_leaves_the_result_alone(ripple):
    pool, result = ripple.pool, ripple.result
    assert result.problem.preps[0].tau_model is None  # the result's logs untouched
    prep = pool.preps[0]
    assert prep.tau_model is not None and pool.vpieces == []
    pc = pool.pieces[0]
    first = pc.lo + (-(pc.lo - pc.ctx_lo) % pool.step)
    np.testing.assert_allclose(pool.raw[0], prep.tau[first] - prep.tau_model[first])
    np.testing.assert_allclose(pool.states.q[0], prep.q[first])
    assert pool.resid.shape == pool.raw.shape == (len(pool.states), 3)
    # the hidden ripple is joint 1's residual; the others are at the noise
    raw_rms = np.sqrt(np.mean(pool.raw**2, axis=0))
    assert raw_rms[0] > 1.2 * raw_rms[1] and raw_rms[0] > 1.2 * raw_rms[2]
    figs = residual_dict(pool)
    assert figs["r"] is pool.resid and float(figs["fs"]) == pytest.approx(250.0 / pool.step)


def test_profile_rows_are_spread_over_the_log(ripple):
    rows, pool = ripple.rows, ripple.pool
    assert 3000 <= len(rows.states) < 6000
    assert rows.states.t[-1] > 0.9 * pool.states.t[-1]
    assert rows.model_cols.shape == (len(rows.states), 3, pool.design.p)


# ----------------------------------------------------------------------------- candidates


def test_catalog_candidates_are_the_effects_not_in_the_model(arm3, industrial6):
    keys = [b.key for b in catalog_candidates(arm3, DEFAULT_MODEL, None)]
    assert not [k for k in keys if k.split("@")[0] in ("viscous", "coulomb", "rigid_body")]
    assert {"armature@1", "armature@2", "armature@3", "offset@3", "ripple@1"} <= set(keys)
    assert keys.count("delay") == 1  # a global effect once
    with_asym = Model.parse(["rigid_body", "viscous", "coulomb_asymmetric@1"])
    keys = [b.key for b in catalog_candidates(arm3, with_asym, None)]
    # coulomb_asymmetric replaces Coulomb and an offset: neither is new on joint 1
    assert "offset@1" not in keys and "coulomb@1" not in keys and "offset@2" in keys
    # the coupled wrist (motor 6 turns with joints 5 and 6): the motor's friction is new
    assert coupled_sides(industrial6, None) == [("motor", 5)]
    assert coupled_sides(industrial6, industrial6.transmission) == [("joint", 4), ("joint", 5)]
    keys = [b.key for b in catalog_candidates(industrial6, DEFAULT_MODEL, None)]
    assert {"viscous@m6", "coulomb@m6", "stribeck@m6"} <= set(keys)


def test_profile_candidates_chooses_the_ripple_period(ripple):
    armature = _block("armature", 1)
    chosen, profiled = profile_candidates(ripple.rows, [_block("ripple", 1), armature])
    assert profiled == {"ripple@1"}
    assert chosen[0].opts["period"] == pytest.approx(0.1, rel=0.02)
    assert chosen[1] is armature  # nothing to profile


def test_drop_slow_ripples_leaves_a_slow_period_to_the_spring(ripple):
    span = float(np.ptp(ripple.pool.states.q[:, 0]))
    fast, slow = _block("ripple", 1, period=0.1), _block("ripple", 1, period=0.6 * span)
    offset = _block("offset", 1)
    kept = drop_slow_ripples([fast, slow, offset], ripple.pool.states)
    assert [id(b) for b in kept] == [id(fast), id(offset)]


def test_structural_screen_reports_what_absorbs_a_candidate(arm3):
    blocks = DEFAULT_MODEL.blocks(arm3)
    base, _ = base_set_for(arm3, blocks)
    cands = [_block("armature", 1), _block("armature", 3), _block("offset", 3),
             _block("ripple", 1, period=0.1)]
    out = structural_screen(arm3, blocks, base, None, cands)
    # joint 1's rotor inertia turns with the link's: only zz_1 could tell them apart
    assert out.absorbed == [{"effect": "armature@1", "by": ["zz_1"]}]
    assert [(c.block.key, c.new) for c in out.new] == [("armature@3", [0]), ("offset@3", [0]),
                                                       ("ripple@1", [0, 1])]
    assert out.silent == []
    one_by_one = [ColumnSpace(arm3, blocks, base, None).check(b) for b in cands]
    assert ColumnSpace(arm3, blocks, base, None).check_all(cands) == one_by_one


def test_insample_screen_drops_a_candidate_that_cannot_remove_five_percent(arm3, ripple):
    offset, rip = _block("offset", 2), _block("ripple", 1, period=0.1)
    assert screen(ripple.rows, offset) < SCREEN_MIN < screen(ripple.rows, rip)
    out = insample_screen(ripple.rows, [Candidate(offset, [0]), Candidate(rip, [0, 1])])
    assert [c.block for c in out.kept] == [rip] and out.dropped == 1
    assert SCREEN_MIN == pytest.approx(1 - (1 - GAIN_MIN / 2) ** 2)


def test_screens_of_many_candidates_equal_each_screen(arm3, ripple):
    """The batched screen (the model's span joint by joint, no SVD of all the rows) gives
    what one candidate's projection off the model's basis gives."""
    blocks = [_block("offset", 2), _block("ripple", 1, period=0.1), _block("spring", 3),
              _block("coulomb_asymmetric", 3), _block("delay", None),
              _block("friction_power", 1, alpha=0.5), _block("stribeck", 3, vs=0.05)]
    np.testing.assert_allclose(screens(ripple.rows, blocks),
                               [screen(ripple.rows, b) for b in blocks], rtol=1e-6, atol=1e-9)
    # joint 2's rotor inertia is in the model's span on these rows: both shares are rounding
    # noise, far under the screen's threshold
    armature = _block("armature", 2)
    assert max(screens(ripple.rows, [armature])[0], screen(ripple.rows, armature)) < 1e-2


def test_model_span_projects_like_the_models_basis(ripple):
    rows = ripple.rows
    span, u = rows.model_span, rows.beyond_model.u
    n_rows, n, _ = rows.model_cols.shape
    cols = np.random.default_rng(0).normal(size=(n_rows, 2, 3))
    own, z = span.project_off([0, 2], cols)
    full = np.zeros((n_rows, n, 3))
    full[:, [0, 2], :] = cols
    flat = full.reshape(-1, 3)
    beyond = (flat - u @ (u.T @ flat)).reshape(n_rows, n, 3)
    np.testing.assert_allclose(own, beyond[:, [0, 2], :], atol=1e-9)
    m = rows.model_cols[:, 1, :]
    np.testing.assert_allclose(-m @ z, beyond[:, 1, :], atol=1e-9)
    np.testing.assert_allclose(span.y_perp.reshape(-1), rows.beyond_model.y, atol=1e-9)


def test_refine_survivors_moves_only_the_profiled(ripple):
    off = Candidate(_block("ripple", 1, period=0.1005), [0, 1])
    armature = Candidate(_block("armature", 3), [0])
    fine = refine_survivors(ripple.rows, [off, armature], {"ripple@1"})
    assert abs(fine[0].block.opts["period"] - 0.1) < 0.5 * abs(0.1005 - 0.1)
    assert fine[0].new == [0, 1] and fine[1] is armature
    assert off.block.opts["period"] == 0.1005  # the given candidate as it was
    assert refine_survivors(ripple.rows, [off], set())[0] is off


def test_screen_notes_count_what_was_not_scored():
    notes = screen_notes(Structural([], [], ["presliding@2"]), InSample([], 2))
    assert notes == ["presliding@2: no column on the data's states at any hyper-parameter "
                     "tried (not scored)",
                     "2 candidate(s) explain under 5 % of their joint's filtered residual "
                     "even in-sample and were not scored"]
    assert screen_notes(Structural([], [], []), InSample([], 0)) == []


# ----------------------------------------------------------------------------- union pass


def test_union_design_puts_the_candidates_after_the_model(arm3, ripple, union):
    base = ripple.pool.base
    n, s = base.rank, len(base.names)
    assert union.n_model == n and union.design.p == n + 3
    assert [list(p) for p in union.positions] == [[n], [n + 1, n + 2]]
    # standard columns: the model's, then offset@3's one, then ripple@1's two
    assert list(union.design.cols[n:]) == [s, s + 1, s + 2]
    assert list(union.design.cols[:n]) == list(base.independent)
    assert union.keep >= 1 and union.block_len >= 1


def test_fold_masks_hold_out_each_block_once_with_a_gap():
    folds = fold_masks(40, FOLDS)
    held = np.array([h for h, _ in folds])
    assert np.array_equal(held.sum(axis=0), np.ones(40))
    for h, tr in folds:
        idx = np.flatnonzero(h)
        gap = {idx[0] - 1, idx[-1] + 1} & set(range(40))
        assert not (h & tr).any() and not tr[list(gap)].any()
        assert tr.sum() == 40 - h.sum() - len(gap)


def test_fold_cv_equals_a_refit_per_fold(ripple, union):
    cv = cross_validation(union, ripple.pool)
    g, p = cv.grams.g, cv.grams.p
    cand = union.positions[1]
    idx = np.concatenate((np.arange(union.n_model), cand))
    sse = np.zeros(3)
    counts = np.zeros(3)
    for h, tr in fold_masks(g.shape[1], FOLDS):
        a = g[:, tr].sum(axis=(0, 1))
        d = 1.0 / np.sqrt(np.diag(a)[idx])
        theta = d * np.linalg.lstsq(a[np.ix_(idx, idx)] * np.outer(d, d), a[idx, p] * d,
                                    rcond=None)[0]
        v = np.concatenate((-theta, [1.0]))
        held = g[:, h].sum(axis=1)
        sub = np.concatenate((idx, [p]))
        sse += np.einsum("i,jik,k->j", v, held[:, sub[:, None], sub[None, :]], v)
        counts += held[:, p + 1, p + 1]
    np.testing.assert_allclose(cv.rmse(cand), np.sqrt(sse / counts), rtol=1e-6)
    np.testing.assert_allclose(cv.base, cv.rmse(np.zeros(0, dtype=int)))


def test_fold_sums_without_the_turns_are_those_of_the_grams_without_them(ripple, union):
    """``without_turns`` scores on the fold sums less the reversals' on some joints: the
    same numbers as the fold sums of the Grams with those rows taken off."""
    made = union_passes(union, ripple.pool, candidates=True, transfer=False)
    assert made.cv is not None and made.turns is not None
    folds = fold_masks(made.cv.g.shape[1], FOLDS)
    out = np.array([0, 2])
    g = made.cv.g.copy()
    g[out] -= made.turns.g[out]
    want = FoldSums.of(Grams(g, made.cv.n_rows), folds)
    got = FoldSums.of(made.cv, folds).without(FoldSums.of(made.turns, folds), out)
    scale = np.abs(want.total).max()
    pairs = [(got.total, want.total), (got.last, want.last),
             *zip(got.train, want.train, strict=True), *zip(got.held, want.held, strict=True)]
    for a, b in pairs:
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * scale)


def test_union_rows_filter_only_the_blocks_that_are_not_smooth(ripple, union):
    """The union's rows: the Coulomb and ripple columns parallel-filtered as identify's are
    (the same numbers), the smooth ones (rigid body, viscous, offset) read at the kept rows
    unfiltered — what the filter leaves of them, to a small fraction of each column."""
    pc = ripple.pool.pieces[0]
    window = next(filter_windows(pc, union.keep))
    c, y, idx = design_rows(union.design, pc, window, union.keep, smooth=True)
    ref, y_ref, idx_ref = design_rows(union.design, pc, window, union.keep)
    part = union.design.fast
    assert part is not None
    assert part.at.size == 3 + 2  # each joint's Coulomb column, the ripple's two
    np.testing.assert_array_equal(c[:, part.at], ref[:, part.at])
    np.testing.assert_array_equal(y, y_ref)
    np.testing.assert_array_equal(idx, idx_ref)
    smooth = np.setdiff1d(np.arange(c.shape[1]), part.at)
    assert not np.array_equal(c[:, smooth], ref[:, smooth])
    scale = np.abs(ref[:, smooth]).max(axis=0)
    assert np.all(np.abs(c[:, smooth] - ref[:, smooth]).max(axis=0) <= 1e-3 * scale + 1e-12)


def test_predictions_between_spline_nodes(arm3, ripple):
    """The model's smooth torque on every 6th row with a spline between: the torque on every
    row to far below the noise; the Coulomb steps (not smooth) on every row as they are."""
    pb, res = ripple.result.problem, ripple.result
    every = with_predictions(arm3, pb.preps, res.design, res.theta)[0]
    spline = with_predictions(arm3, pb.preps, res.design, res.theta, every=6)[0]
    for name in ("tau_model", "tau_rigid"):
        err = np.abs(getattr(spline, name) - getattr(every, name))
        assert err.max() < 1e-3 and 0 < err.max()
    coulomb = np.flatnonzero(np.diff(np.sign(every.qd[:, 0])))  # a step there, in both
    np.testing.assert_allclose(np.diff(spline.tau_model[:, 0])[coulomb],
                               np.diff(every.tau_model[:, 0])[coulomb], atol=1e-3)


def test_union_passes_give_each_set_as_a_pass_of_its_own(ripple, union):
    """One pass, three sets of Grams: the same numbers as the cross-validation's pass, the
    reversals' and the transfer scorer's (two blocks) each made alone."""
    pool = ripple.pool
    got = union_passes(union, pool, candidates=True, transfer=True)
    alone = [accumulate(union.design, pool.pieces, union.keep, union.block_len,
                        max_blocks=BLOCKS, smooth=True), reversal_grams(union, pool),
             accumulate(union.design, pool.pieces, union.keep, union.block_len, max_blocks=2,
                        smooth=True)]
    for mine, theirs in zip((got.cv, got.turns, got.train), alone, strict=True):
        assert mine is not None
        assert np.array_equal(mine.g, theirs.g) and np.array_equal(mine.n_rows, theirs.n_rows)
    assert got.turns.n_rows.sum() < got.cv.n_rows.sum()  # the reversals' rows only
    only = union_passes(union, pool, candidates=False, transfer=True)
    assert only.cv is None and only.turns is None and np.array_equal(only.train.g, alone[2].g)


def test_score_candidate_gain_and_test(arm3, ripple, union):
    cv = cross_validation(union, ripple.pool)
    offset, rip = (score_candidate(arm3, cv, union, k) for k in (0, 1))
    assert rip.rows == [0] and rip.gain > 0.5 and rip.p_value < 1e-12
    assert rip.gain == pytest.approx(1 - rip.after / rip.before)
    assert rip.coef.shape == (2,)
    assert np.hypot(*rip.coef) == pytest.approx(0.6, rel=0.1)  # the hidden amplitude
    assert rip.se.shape == (2,) and np.all((rip.se > 0) & (rip.se < 0.05 * np.hypot(*rip.coef)))
    assert offset.rows == [2] and offset.gain < GAIN_MIN


def test_suggestion_states_its_evidence_in_its_fields(arm3, ripple, union):
    cv = cross_validation(union, ripple.pool)
    score = score_candidate(arm3, cv, union, 1)
    sig = Signatures(arm3, ripple.pool.states, ripple.pool.resid)
    sug = suggestion(union.blocks[1], score, sig)
    assert (sug.effect, sug.joint, sug.label()) == ("ripple", 1, "ripple@1")
    assert sug.gain == score.gain and sug.fields["gain"] == round(score.gain, 4)
    assert sug.fields["repeat"] > 0.5 and sug.hypers == {"period": 0.1}
    assert "the residual repeats every period" in sug.evidence
    assert f"{sug.fields['rmse_before']:.4g} → {sug.fields['rmse_after']:.4g} N·m" in sug.evidence
    assert sig.of(union.blocks[1]) is sig.of(_block("spring", 1))  # one R² per joint
    assert sig.of(_block("delay", None)) == {}


def test_signatures_read_a_sided_effect_against_its_motor_whatever_came_first(arm3):
    """Review: on a motor-side log the first candidate scored on a joint set the velocity every
    other candidate's evidence was read against (a spring's 'q̇m1' or a friction's 'q̇1',
    depending on the order). A sided effect reads its motor's velocity, the others the
    joint's, in either order."""
    from robid_link.ident.model.effects import States

    rng = np.random.default_rng(3)
    q, qd, qdd = (rng.normal(size=(400, 3)) for _ in range(3))
    coupled = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
    states = States(q, qd, qdd, transmission=coupled)
    resid = rng.normal(size=(400, 3))
    for order in (("spring", "coulomb"), ("coulomb", "spring")):
        sig = Signatures(arm3, states, resid)
        labels = {name: sig.of(_block(name, 2))["r2_qd"][0] for name in order}
        assert labels == {"spring": "q̇2", "coulomb": "q̇m2"}, order


def test_evidence_sentence_of_an_offset_and_a_delay():
    text, fields = evidence_sentence(_block("offset", 3), 0.5, 0.4, {}, np.array([0.8]))
    assert text == ("joint 3: a constant torque; cross-validated RMSE of the filtered torque "
                    "0.5 → 0.4 N·m")
    assert fields == {"rmse_before": 0.5, "rmse_after": 0.4}
    text, fields = evidence_sentence(_block("delay", None), 0.5, 0.2, {}, np.array([0.01]))
    assert text.startswith("the torque log is shifted by 10 ms") and fields["seconds"] == 0.01


# ----------------------------------------------------------------------------- transfer


@pytest.fixture(scope="module")
def springs(arm3, tmp_path_factory):
    """A model with a spring the robot has not, fitted on one motion, validated on another."""
    d = tmp_path_factory.mktemp("springs")
    train, valid = d / "a.csv", d / "b.csv"
    inertials = perturbed_inertials(arm3, 105)  # one robot, two motions
    simulate(arm3, train, noise=0.3, seed=5, duration=30.0, rate=250.0, inertials=inertials)
    simulate(arm3, valid, noise=0.3, seed=8, duration=20.0, rate=250.0, inertials=inertials)
    model = Model.parse(["rigid_body", "viscous", "coulomb", "spring@1"])
    pool = residual_pool(arm3, _fit(arm3, train, model, validate=valid))
    return pool, union_design(arm3, pool, [Candidate(_block("offset", 3), [0])])


def test_model_transfer_doubts_name_an_effect_that_raises_the_validation_error(arm3, springs):
    pool, union = springs
    assert pool.vpieces and all(any(pc.prep is p for p in pool.preps[1:])
                                for pc in pool.vpieces)
    transfer = transfer_scorer(union, pool)
    doubts = model_transfer_doubts(arm3, pool.problem, transfer, pool.base.independent)
    assert len(doubts) == 1 and doubts[0].startswith("spring@1 raises the validation logs' "
                                                     "error")


def test_with_transfer_adds_the_validation_figures(arm3, springs):
    pool, union = springs
    transfer = transfer_scorer(union, pool)
    score = score_candidate(arm3, cross_validation(union, pool), union, 0)
    sug = suggestion(union.blocks[0], score, Signatures(arm3, pool.states, pool.resid))
    out = with_transfer(sug, score, transfer, union.positions[0])
    assert sug.transfer is None and "validation_before" not in sug.fields  # not changed
    f = out.fields
    assert list(f)[-4:] == ["validation_before", "validation_after", "transfer_gain",
                            "transfer_own"]
    assert out.transfer == pytest.approx(f["transfer_gain"], abs=5e-5)
    assert f["transfer_own"] == pytest.approx(
        1 - f["validation_after"] / f["validation_before"], abs=1e-3)
    assert out.evidence.startswith(sug.evidence + "; on the validation logs ")


# ----------------------------------------------------------------------------- verdict


def _sug(effect="offset", joint=1, gain=0.2, p=1e-6, after=0.3, transfer=None, **fields):
    f = {"rmse_after": after, **fields}
    if transfer is not None:
        f.setdefault("transfer_own", transfer)
    return Suggestion(effect, joint, [after], gain, p, "", f, {}, None, transfer)


def test_judge_needs_the_gain_the_test_and_the_transfer():
    good, small, weak = _sug(), _sug(gain=GAIN_MIN / 2), _sug(p=10 * P_MAX)
    lost, lost_own = _sug(transfer=-0.01), _sug(transfer=0.2, transfer_own=0.005)
    v = judge([good, small, weak, lost, lost_own])
    assert v.suggested == [good] and v.rejected == [small, weak]
    assert v.not_transferring == [lost, lost_own]
    assert not_transferring_note([lost]) == [
        "offset@1 won the cross-validation but did not cut the error on the validation "
        "logs: not suggested"]
    assert not_transferring_note([]) == []


def test_a_stribeck_with_a_negative_breakaway_is_not_suggested():
    """Static below Coulomb friction is friction rising with speed: no Stribeck curve; a
    breakaway within 2σ of zero, or another effect's coefficients, are not judged by sign."""
    rising = _sug("stribeck", 2, gain=0.595, breakaway=-3.82, breakaway_sigma=0.058)
    faint = _sug("stribeck", 3, gain=0.2, breakaway=-0.05, breakaway_sigma=0.03)
    real = _sug("stribeck", 1, gain=0.8, breakaway=2.5, breakaway_sigma=0.015)
    power = _sug("friction_power", 2, gain=0.587)
    v = judge([rising, faint, real, power])
    assert v.suggested == [faint, real, power] and v.rejected == [rising]
    assert unphysical_note(v.rejected) == [
        "stribeck@2 cuts the error (gain 59.5 %) but its fitted breakaway fst_2 = -3.82 ± "
        "0.058 N·m is negative: the friction rises with speed from standstill, not a Stribeck "
        "curve (a velocity-dependent law such as friction_power describes it): not suggested"]
    assert unphysical_note([_sug("stribeck", 2, gain=0.01, breakaway=-3.0,
                                 breakaway_sigma=0.1)]) == []  # not worth a word


def test_rank_prefers_transfer_then_physics_then_fewer_parameters():
    a, b = _sug(gain=0.3, transfer=0.1), _sug(gain=0.2, transfer=0.4)
    assert rank(judge([a, b])).suggested == [b, a]  # by transfer when there is one
    asym = _sug("coulomb_asymmetric", 3, gain=0.3, after=0.300)
    offset = _sug("offset", 3, gain=0.29, after=0.302)  # the same error left, within 1 %
    assert rank(judge([asym, offset])).suggested == [offset, asym]
    spring = _sug("spring", 1, gain=0.4, after=0.30)
    cogging = _sug("ripple", 1, gain=0.39, after=0.31, repeat=0.9)
    assert rank(judge([spring, cogging])).suggested == [cogging, spring]  # it repeats
    smooth = _sug("ripple", 1, gain=0.41, after=0.30, repeat=0.1)
    # a ripple whose residual does not repeat one period on is no cogging: not suggested
    assert rank(judge([smooth, spring])).suggested == [spring]
    assert not_repeating_note([smooth]) == [
        "ripple@1 (gain 41 %, correlation one period on 0.1) cut the error, but the residual "
        "does not repeat along the angle one period on (correlation under 0.5): not cogging or "
        "meshing, not suggested"]
    assert rank(judge([_sug(gain=0.01), _sug(gain=0.03)])).rejected[0].gain == 0.03


def test_one_by_one_keeps_what_still_helps_names_twins_and_drops_the_rest():
    """Each suggestion after the first is judged with the better ones in the model (``given``)
    and without the other joints' turns (``apart``)."""
    top = _sug("ripple", 1, gain=0.8, after=0.05, repeat=0.97)
    leak = _sug("spring", 2, gain=0.09, after=0.045)  # lives on what ripple@1 leaves
    real = _sug("offset", 3, gain=0.3, after=0.03)
    twin = _sug("friction_power", 1, gain=0.79, after=0.0502)  # explains what ripple@1 does
    turns = _sug("stribeck", 3, gain=0.07, after=0.029)  # lives on the other joints' turns
    given = {"spring@2": (0.01, 1e-6), "offset@3": (0.29, 1e-9),
             "friction_power@1": (0.0, 0.5), "stribeck@3": (0.06, 1e-6)}
    apart = {"ripple@1": (0.8, 0.0), "offset@3": (0.28, 1e-9), "stribeck@3": (0.01, 0.2)}
    v, notes = one_by_one(Verdicts([top, twin, real, leak, turns], [], []),
                          lambda s, better: given[s.label()], lambda s, better: apart[s.label()])
    assert v.suggested == [top, real]
    assert top.alternatives == ["friction_power@1"] and "the log cannot tell them apart" in \
        top.evidence and top.as_dict()["alternatives"] == ["friction_power@1"]
    assert [s.label() for s in v.rejected] == ["spring@2", "stribeck@3"]
    assert notes[0] == ("spring@2 (gain 9 % alone, 1 % with ripple@1, offset@3 in the model) "
                        "explains only what those leave: not suggested")
    assert notes[1].startswith("stribeck@3 (gain 7 %) keeps 1 % when the rows near the "
                               "velocity reversals are left out")
    # the log's own sample-and-hold, when the callables hold it in the model, judges the first
    first = _sug("spring", 2, gain=0.13, after=0.0166)
    v, notes = one_by_one(Verdicts([first], [], []), lambda s, better: (0.012, 1e-4),
                          lambda s, better: (0.1, 1e-9), "the log's own sample-and-hold")
    assert v.suggested == [] and notes == [
        "spring@2 (gain 13 % alone, 1.2 % with the log's own sample-and-hold in the model) "
        "explains only what that leaves: not suggested"]
    assert real.fields["gain_given"] == 0.29 and real.fields["gain_apart"] == 0.28


def test_verdict_is_doubtful_when_the_validation_error_is_above_cads(arm3, ripple):
    res = replace(ripple.result, notes=[])
    res.held_out = HeldOut(ErrorStats(np.ones(3), np.ones(3), np.ones(3), 10, 0.12),
                           ErrorStats(np.ones(3), np.ones(3), np.ones(3), 10, 0.10), [])
    doubts = result_doubts(res)
    assert len(doubts) == 1 and doubts[0].startswith(
        "held-out relative error 12 % is above the a-priori (CAD) model's 10 %; refit with "
        "--method consistent"), doubts
    dg = Diagnosis(res, ["rigid_body"], None, [], [], [], [], [], doubts=doubts)
    assert dg.verdict == "doubtful" and dg.to_dict()["doubts"] == doubts
    assert Diagnosis(res, [], None, [_sug()], [], [], [], [], doubts=doubts).verdict == \
        "missing_effect"
    res.held_out = HeldOut(res.held_out.nominal, res.held_out.validation, [])  # below CAD
    assert result_doubts(res) == []
    assert Diagnosis(res, [], None, [], [], [], [], []).verdict == "adequate"


def test_three_extrapolation_warnings_make_a_doubt(ripple):
    warn = "validation leaves the training range of q1 by 9 % of its span: the model " \
           "extrapolates there"
    res = replace(ripple.result, notes=[warn] * 3)
    res.held_out = HeldOut(None, None, [])
    assert result_doubts(res) == ["3 extrapolation warnings: the validation motion leaves "
                                  "the training ranges, so its error says little about the "
                                  "model"]
    assert result_doubts(replace(res, notes=[warn] * 2)) == []


def test_one_motion_note(arm3, ripple, tmp_path):
    logs = load_logs(arm3, [ripple.path])
    note = [f"all data is one motion: candidates are scored by blocked cross-validation over "
            f"the log ({FOLDS} folds), not on a new motion"]
    assert one_motion_note(logs) == note and one_motion_note(logs * 2) == note
    other = simulate(arm3, tmp_path / "o.csv", seed=6, duration=5.0, rate=250.0)
    assert one_motion_note([*logs, *load_logs(arm3, [other.path])]) == []
