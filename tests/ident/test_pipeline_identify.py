"""identify()'s steps, each alone on a small simulated log: what it claims to return, and that
it leaves what it was given as it was (no step changes another step's output)."""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pytest
from scipy.stats import chi2

from robid_link.exceptions import DataError, DataWarning, EstimationError, ExcitationWarning
from robid_link.fakes.plant import Plant, Truth, perturbed_inertials
from robid_link.ident.data.checks import data_checks, extrapolation, sanity_checks
from robid_link.ident.data.currents import without_known_torques
from robid_link.ident.data.logs import write_log_csv
from robid_link.ident.data.preprocess import Problem, build_problem
from robid_link.ident.excite.excitation import random_fourier
from robid_link.ident.fit.identify import (
    assemble,
    estimate,
    estimate_consistent,
    identify,
    load_logs,
    result_of,
    with_current_gains,
    with_model_torque,
    with_profiled_hypers,
)
from robid_link.ident.model.effects import DEFAULT_MODEL, REGISTRY, Model
from robid_link.ident.model.known import KnownTorque

from ..conftest import simulate

#: a counterbalance spring on joint 2 (the plant's law): outside the rigid body's columns
SPRING = {"k": 1500.0, "a": 0.15, "b": 0.2, "l0": 0.1, "phi": 0.4}
_LENGTH = "sqrt(a**2 + b**2 - 2*a*b*cos(q2 + phi))"
COUNTERBALANCE = KnownTorque("counterbalance", 2,
                             f"-k*({_LENGTH} - l0)*a*b*sin(q2 + phi)/{_LENGTH}", None,
                             tuple(SPRING.items()), ())


@pytest.fixture(scope="module")
def sim(arm3, tmp_path_factory):
    return simulate(arm3, tmp_path_factory.mktemp("pipe") / "log.csv", noise=0.5, seed=1)


@pytest.fixture
def problem(arm3, sim) -> Problem:
    return build_problem(arm3, load_logs(arm3, [sim.path]), DEFAULT_MODEL)


def _points_at_its_preps(pb: Problem) -> bool:
    preps = [*pb.preps, *pb.vpreps]
    return all(any(pc.prep is p for p in preps) for pc in (*pb.train, *pb.valid))


def _spring_log(robot, path, gains=None):
    """arm3 with the counterbalance on joint 2; with ``gains``, the torques logged as drive
    currents (τ / gain)."""
    traj = random_fourier(robot, harmonics=5, base_hz=0.1, seed=51)
    t = np.arange(0.0, 20.0, 1.0 / 400.0)
    q, qd, qdd = traj.evaluate(t)
    truth = Truth(perturbed_inertials(robot, 151), noise_tau=0.05, effects=(
        {"name": "viscous", "fv": 2.0}, {"name": "spring", "joint": 2, **SPRING}))
    log = Plant(robot, truth).run(t, q, qd, qdd, seed=251)
    tau = log["tau"] if gains is None else log["tau"] / gains
    write_log_csv(path, log["t"], log["q"], tau, log["qd"], log["qdd"],
                  current=gains is not None)
    return log


# ----------------------------------------------------------------------------- check, prepare


def test_build_problem_notes_a_lowered_cutoff_without_touching_the_log(arm3, sim):
    logs = load_logs(arm3, [sim.path])
    before = list(logs[0].notes)
    pb = build_problem(arm3, logs, DEFAULT_MODEL, interval=40)
    assert any(n.startswith("cutoff lowered to") for n in pb.notes)
    assert logs[0].notes == before  # the note is on the prepared copy, not the caller's log
    assert any(n.startswith("cutoff lowered to") for n in pb.preps[0].log.notes)
    again = build_problem(arm3, logs, DEFAULT_MODEL, interval=40)
    assert again.notes == pb.notes  # a second run does not repeat it


def test_problem_and_prepared_logs_are_frozen(problem):
    with pytest.raises(AttributeError):
        problem.notes = []  # type: ignore[misc]
    with pytest.raises(AttributeError):
        problem.preps[0].tau_model = None  # type: ignore[misc]


# ----------------------------------------------------------------------------- known torques


def test_without_known_torques_returns_a_new_problem(arm3, problem):
    known = KnownTorque("bias", 2, "0.5 + 2.0*q2", None, (), ())
    prep = problem.preps[0]
    tau, tau_f = prep.tau.copy(), prep.tau_f.copy()
    new = without_known_torques(problem, [known])
    fresh = new.preps[0]
    settle = prep.filt.settle
    rows = slice(3 * settle, -3 * settle)  # away from the filter's edges
    np.testing.assert_allclose(fresh.tau_known[:, 1], 0.5 + 2.0 * prep.q[:, 1])
    assert not fresh.tau_known[:, [0, 2]].any()
    np.testing.assert_allclose(fresh.tau, tau - fresh.tau_known)
    np.testing.assert_allclose(fresh.tau_f[rows], (tau_f - fresh.tau_known)[rows], atol=1e-6)
    assert new.notes[:-1] == problem.notes and new.notes[-1].startswith(
        "known torque(s) bias@2: subtracted from the measured torque")
    assert _points_at_its_preps(new)
    # the given problem is as it was
    assert prep.tau_known is None and np.array_equal(prep.tau, tau)
    assert np.array_equal(prep.tau_f, tau_f)
    assert all(pc.prep is prep for pc in problem.train)
    assert without_known_torques(problem, []) is problem


# ----------------------------------------------------------------------------- drive currents


def test_with_current_gains_completes_the_torque(arm3, tmp_path):
    gains = np.array([2.5, 1.8, 0.7])
    log = _spring_log(arm3, tmp_path / "cur.csv", gains)
    model = Model.parse(["rigid_body", "viscous"])
    pb = without_known_torques(build_problem(arm3, load_logs(arm3, [tmp_path / "cur.csv"]),
                                             model), [COUNTERBALANCE])
    currents = pb.preps[0].log.currents.copy()
    new = with_current_gains(pb, [COUNTERBALANCE])
    notes = new.notes[len(pb.notes):]
    found = np.array([float(n.split("identified: ")[1].split()[0]) for n in notes])
    assert len(notes) == 3 and all(n.startswith("current_gain of joint") for n in notes)
    np.testing.assert_allclose(found[1:], gains[1:], rtol=0.01)  # joint 1: wider (see notes)
    fresh = new.preps[0]
    assert fresh.log.currents is None and fresh.log.current is None
    measured = fresh.tau_measured[:, 1:]
    assert np.sqrt(np.mean((measured - log["tau"][:, 1:]) ** 2)) < 0.02 * np.std(log["tau"])
    assert _points_at_its_preps(new)
    np.testing.assert_array_equal(pb.preps[0].log.currents, currents)  # the input kept
    assert with_current_gains(new, [COUNTERBALANCE]) is new  # nothing left to identify


# ----------------------------------------------------------------------------- model torque


def test_with_model_torque_gives_load_friction_the_models_torque(arm3, sim):
    model = Model.parse(["rigid_body", "viscous", "coulomb", "load_friction@2"])
    pb = build_problem(arm3, load_logs(arm3, [sim.path]), model)
    new = with_model_torque(pb)
    fresh = new.preps[0]
    assert pb.preps[0].tau_model is None and pb.preps[0].tau_rigid is None
    assert fresh.tau_model.shape == fresh.tau_rigid.shape == fresh.tau_rate.shape == \
        fresh.tau.shape
    # a first fit without load friction: close to the filtered torque already
    trim = slice(fresh.filt.settle, -fresh.filt.settle)
    err = fresh.tau_f[trim] - fresh.tau_model[trim]
    assert np.all(np.sqrt(np.mean(err**2, axis=0)) < 0.1 * np.std(fresh.tau_f[trim], axis=0))
    assert _points_at_its_preps(new)
    plain = build_problem(arm3, load_logs(arm3, [sim.path]), DEFAULT_MODEL)
    assert with_model_torque(plain) is plain


# ----------------------------------------------------------------------------- hyper-parameters


def test_with_profiled_hypers_chooses_the_grid_value_of_least_rss(arm3, tmp_path):
    hidden = {"name": "stribeck", "joint": 2, "fs": 4.0, "fc": 1.5, "vs": 0.05}
    sim = simulate(arm3, tmp_path / "s.csv", noise=0.3, seed=5, duration=30.0, rate=250.0,
                   effects=({"name": "viscous", "fv": 2.0}, {"name": "coulomb", "fc": 1.5},
                            hidden))
    model = Model.parse(["rigid_body", "viscous", "coulomb", "stribeck@2"])
    pb = build_problem(arm3, load_logs(arm3, [sim.path]), model)
    new, chosen = with_profiled_hypers(pb)
    grid = np.array(REGISTRY["stribeck"].hypers["vs"].grid)
    vs = chosen["stribeck@2"]["vs"]
    assert vs in grid and 0.025 <= vs <= 0.1  # the truth is 0.05
    assert chosen["stribeck@2"]["shape"] in REGISTRY["stribeck"].hypers["shape"].grid
    assert new.blocks[-1].opts["vs"] == vs and not new.blocks[-1].free_hypers()
    assert pb.blocks[-1].free_hypers() == ["vs", "shape"]  # the given problem keeps its blocks
    assert with_profiled_hypers(new) == (new, {})


# ----------------------------------------------------------------------------- assembly


def test_assemble_builds_the_base_design_and_refuses_too_few_rows(problem):
    asm = assemble(problem, "log.csv")
    assert asm.design.p == asm.base.rank == 21  # arm3, rigid body + viscous + Coulomb
    assert len(asm.names) == 10 * 3 + 3 + 3  # standard: inertials, fv, fc
    pc = problem.train[0]
    tiny = replace(problem, train=[replace(pc, hi=pc.lo + 10)])
    with pytest.raises(DataError, match=r"^short\.csv: 30 training samples×joints for 21 "):
        assemble(tiny, "short.csv")


# ----------------------------------------------------------------------------- estimate


def test_estimate_recovers_the_true_base_parameters(arm3, sim, problem):
    asm = assemble(problem, "log.csv")
    est = estimate(problem, asm, "ols")
    d = est.theta - sim.true_base(arm3, DEFAULT_MODEL)
    assert float(d @ np.linalg.solve(est.cov, d)) < chi2.ppf(0.99, d.size)
    assert est.design is asm.design and est.consistent is None
    assert est.notes[: len(problem.notes)] == problem.notes
    assert [p.name for p in est.parameters] == asm.base.base_names
    # on the filtered torque: the white noise's share below the 10 Hz cutoff (500 Hz log)
    np.testing.assert_allclose(est.fit.rmse, 0.5 * np.sqrt(10.0 / 250.0), rtol=0.15)
    assert est.n_samples == int(asm.grams.n_rows[0])
    with pytest.raises(EstimationError, match="unknown method 'bogus'"):
        estimate(problem, asm, "bogus")


def test_estimate_consistent_starts_from_ols_and_keeps_it(arm3, sim, problem):
    asm = assemble(problem, "log.csv")
    ols = estimate(problem, asm, "consistent")  # the base-parameter OLS fit first
    est = estimate_consistent(problem, asm, ols)
    assert est.consistent is not None and np.all(est.consistent.min_eig > 0)
    assert est.design.p == len(asm.names)  # θ of every standard column
    assert est.theta.shape == (len(asm.names),)
    assert est.condition_number == ols.condition_number  # conditioning: the OLS fit's
    assert est.notes[: len(ols.notes)] == ols.notes
    assert est.notes[len(ols.notes)].startswith("consistent fit: prior weight λ")
    assert ols.design is asm.design and ols.consistent is None  # the OLS estimate kept


# ----------------------------------------------------------------------------- data checks


def test_data_checks_note_a_clipped_torque(arm3, sim):
    logs = load_logs(arm3, [sim.path])
    tau = logs[0].tau.copy()
    peak = 0.6 * np.abs(tau[:, 0]).max()
    tau[:, 0] = np.clip(tau[:, 0], -peak, peak)
    pb = build_problem(arm3, [replace(logs[0], tau=tau)], DEFAULT_MODEL)
    assert any("tau1 sits flat" in n for n in sanity_checks(pb, nominal=False))
    with pytest.warns(DataWarning, match="tau1 sits flat"):
        notes = data_checks(pb)
    assert any("saturation?" in n for n in notes)


def test_data_checks_note_validation_outside_the_training_ranges(problem):
    assert extrapolation(problem) == []  # the held-out end moves like the rest
    pc = problem.train[0]
    narrow = replace(problem, train=[replace(pc, hi=pc.lo + (pc.hi - pc.lo) // 10)])
    outside = extrapolation(narrow)
    assert outside and all("the model extrapolates there" in n for n in outside)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        notes = data_checks(narrow)
    assert notes[-len(outside):] == outside
    assert {w.category for w in caught} == {ExcitationWarning}


# ----------------------------------------------------------------------------- result


def test_result_of_keeps_what_it_was_fitted_on(arm3, sim, problem):
    asm = assemble(problem, "log.csv")
    est = estimate(problem, asm, "ols")
    logs = load_logs(arm3, [sim.path])
    res = result_of(problem, asm, est, method="ols", hypers={}, notes=["a note"],
                    files=(logs, ()))
    assert res.problem is problem and res.design is est.design and res.theta is est.theta
    assert res.notes == ["a note"] and res.rank == 21 and res.n_standard == len(asm.names)
    assert [f["role"] for f in res.data_files] == ["data"]
    assert len(res.data_files[0]["sha256"]) == 64
    assert res.validation is not None and res.validation.n_samples > 1000


def test_identify_leaves_its_inputs_as_they_were(arm3, tmp_path):
    _spring_log(arm3, tmp_path / "s.csv")
    logs = load_logs(arm3, [tmp_path / "s.csv"])
    arrays = {k: getattr(logs[0], k).copy() for k in ("t", "q", "tau")}
    notes = list(logs[0].notes)
    model = replace(Model.parse(["rigid_body", "viscous", "load_friction@3"]),
                    known=(COUNTERBALANCE,))
    res = identify(arm3, logs, model, interval=20)  # 400 Hz: the cutoff is lowered
    for k, a in arrays.items():
        np.testing.assert_array_equal(getattr(logs[0], k), a)
    assert logs[0].notes == notes
    assert any(n.startswith("cutoff lowered") for n in res.notes)
    assert res.problem.preps[0].tau_known is not None  # the problem holds what the steps made
    assert res.problem.preps[0].tau_model is not None
