"""Honest validation: the default hold-out is the end of the motion, not a robot standing
still; the noise floor of the raw torque beside the validation error; log checks that name the
likely cause (a motor-side log read as joint side, a prior without friction)."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from robid_link.fakes.plant import Plant, Truth, perturbed_inertials
from robid_link.ident.data.logs import write_log_csv
from robid_link.ident.excite.excitation import random_fourier
from robid_link.ident.fit.identify import identify, load_logs
from robid_link.ident.model.effects import load_model
from robid_link.ident.model.robot import Robot

from ..conftest import simulate

FRICTION = ({"name": "viscous", "fv": 2.0}, {"name": "coulomb", "fc": 1.5})


def _log(robot: Robot, path: Path, *, moving_s: float = 20.0, rest_s: float = 0.0,
         noise: float = 0.3, friction: tuple = FRICTION, scale_q: float = 1.0) -> Path:
    """Two periods of a rest-to-rest Fourier motion, then ``rest_s`` standing still."""
    traj = random_fourier(robot, harmonics=5, base_hz=2.0 / moving_s, seed=4)
    rate = 500.0
    t = np.arange(0.0, moving_s + rest_s, 1.0 / rate)
    q, qd, qdd = traj.evaluate(np.minimum(t, moving_s))
    qd[t > moving_s] = 0.0
    qdd[t > moving_s] = 0.0
    truth = Truth(perturbed_inertials(robot, 7), effects=friction, noise_tau=noise)
    log = Plant(robot, truth).run(t, q, qd, qdd, seed=9)
    write_log_csv(path, log["t"], log["q"] * scale_q, log["tau"])
    return path


def _identify(robot: Robot, path: Path) -> tuple:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = identify(robot, load_logs(robot, [str(path)]), load_model(None))
    return res, [str(w.message) for w in caught]


def test_holdout_is_the_end_of_the_motion_not_the_rest_after_it(arm3: Robot,
                                                                  tmp_path: Path) -> None:
    res, _ = _identify(arm3, _log(arm3, tmp_path / "rest.csv", rest_s=10.0))
    pb = res.problem
    assert pb is not None and pb.valid
    for pc in pb.valid:  # every held-out row is within the motion
        t = pc.prep.log.t
        assert t[pc.lo] >= 14.0 and t[pc.hi - 1] <= 20.01
        assert np.abs(pc.prep.qd[pc.lo:pc.hi]).max() > 0.1
    # it says which range it used, and what happened to the rest
    assert "rest.csv 1" in res.validation_source and "motion" in res.validation_source
    assert any("stands still at the end of rest.csv 10" in n for n in res.notes), res.notes
    assert any(pc.prep.log.t[pc.lo] > 20.0 for pc in pb.train)  # the rest trains
    assert res.validation is not None and res.validation.relative_error < 0.15


def test_noise_floor_is_the_plants_torque_noise(arm3: Robot, tmp_path: Path) -> None:
    sim = simulate(arm3, tmp_path / "n.csv", noise=0.5, duration=20.0)
    res, _ = _identify(arm3, sim.path)
    floor = res.noise_floor
    assert floor is not None
    np.testing.assert_allclose(floor, 0.5, rtol=0.1)
    # the validation error (raw torque) sits on the floor, the fit error (filtered) below it
    assert np.all(res.rmse < 1.2 * floor) and np.all(res.fit.rmse < 0.5 * floor)
    doc = res.to_dict()
    assert doc["noise_floor"] == pytest.approx(list(floor))
    assert "raw torque" in doc["errors_on"]["rmse"]
    assert "noise floor" in res.summary() and "noise" in res.summary().splitlines()[4]


def test_motor_side_log_read_as_joint_side_is_named(industrial6: Robot, tmp_path: Path) -> None:
    """Positions 120× too large against ±limits: 'use --motor-side', not 'units'."""
    ratios = np.abs(np.diag(industrial6.transmission))
    path = _log(industrial6, tmp_path / "m.csv", moving_s=10.0, scale_q=1.0)
    text = path.read_text().splitlines()
    head, rows = text[0], np.loadtxt(path, delimiter=",", skiprows=1)
    rows[:, 1:7] *= ratios  # motor positions in the joint columns
    np.savetxt(path, rows, delimiter=",", header=head, comments="")
    msgs = _identify(industrial6, path)[1]
    side = [m for m in msgs if "looks motor-side" in m]
    assert side and "q1" in side[0] and "--motor-side" in side[0], msgs


def test_prior_without_friction_is_not_called_a_unit_error(arm3: Robot, tmp_path: Path) -> None:
    """Rotor inertia and friction make joint 1's torque many times the a-priori (rigid, CAD)
    model's: the check says the prior lacks them instead of blaming units."""
    heavy = ({"name": "viscous", "fv": 5.0}, {"name": "coulomb", "fc": 3.0},
             {"name": "armature", "ia": 15.0})
    msgs = _identify(arm3, _log(arm3, tmp_path / "f.csv", friction=heavy, noise=0.05))[1]
    scale = [m for m in msgs if "the a-priori model's torque" in m]
    assert scale, msgs
    assert all("lacks friction and rotor inertia" in m for m in scale), scale


def test_every_parameter_says_its_unit_and_side(industrial6: Robot, tmp_path: Path) -> None:
    from robid_link.ident.fit.results import parameter_unit

    assert parameter_unit("zz_1", ("revolute",), False) == ("kg·m²", "joint")
    assert parameter_unit("fv_2", ("revolute", "revolute"), True) == ("N·m·s/rad", "motor")
    assert parameter_unit("mx_2", ("revolute", "revolute"), True) == ("kg·m", "joint")
    assert parameter_unit("fc_1", ("prismatic",), False) == ("N", "joint")
    assert parameter_unit("spr2s_1", ("revolute",), False) == ("N·m", "joint")
    assert parameter_unit("fv_m2", ("revolute", "prismatic"), False) == ("N·s/m", "motor")
    assert parameter_unit("fc_j1", ("revolute",), True) == ("N·m", "joint")
    res, _ = _identify(industrial6, _log(industrial6, tmp_path / "u.csv", moving_s=10.0))
    doc = res.to_dict()["parameters"]
    assert all(p["unit"] and p["side"] == "joint" for p in doc), doc


def test_parameter_set_keeps_motor_friction_apart(arm3: Robot, tmp_path: Path) -> None:
    """A controller feeds the set's joint friction forward: a motor's friction (motor units)
    goes to ``friction_motor``, never into the joints' lists."""
    from robid_link.ident.fit.paramset import make_parameter_set

    res, _ = _identify(arm3, _log(arm3, tmp_path / "p.csv", moving_s=10.0))
    doc = res.to_dict()
    joint_set = make_parameter_set(arm3, doc, run_id="r1")
    assert joint_set["friction"]["viscous"][0] == pytest.approx(2.0, rel=0.1)
    assert joint_set["friction_motor"]["viscous"] == [0.0, 0.0, 0.0]
    for p in doc["parameters"]:  # as if joint 1's friction had been identified on its motor
        if p["name"] in ("fv_1", "fc_1"):
            p["name"] = p["name"].replace("_1", "_m1")
    motor_set = make_parameter_set(arm3, doc, run_id="r2")
    assert motor_set["friction"]["viscous"][0] == 0.0
    assert motor_set["friction_motor"]["viscous"][0] == pytest.approx(2.0, rel=0.1)
    assert motor_set["friction"]["viscous"][1:] == joint_set["friction"]["viscous"][1:]


def test_cad_figures_are_the_a_priori_inverse_dynamics_on_the_held_out_rows(
        industrial6: Robot, tmp_path: Path) -> None:
    """The held-out pass predicts the a-priori model from the base columns it has made; the
    figures are those of the robot's own inverse dynamics (RNEA) on the same rows."""
    from robid_link.ident.fit.results import StatsAccumulator, row_mask
    from robid_link.ident.model.dynamics import rigid_torque

    res, _ = _identify(industrial6, _log(industrial6, tmp_path / "cad.csv", moving_s=10.0))
    acc = StatsAccumulator(industrial6.n)
    for pc in res.problem.valid:
        st = pc.prep.states(pc.lo, pc.hi)
        tau = pc.prep.tau[pc.lo: pc.hi]
        pred = rigid_torque(industrial6, st.q, st.qd, st.qdd, industrial6.nominal)
        acc.add(tau - pred, tau, row_mask(pc.prep, pc.lo, pc.hi))
    rnea = acc.stats()
    assert rnea is not None and res.nominal is not None
    np.testing.assert_allclose(res.nominal.rmse, rnea.rmse, rtol=1e-10)
    assert res.nominal.relative_error == pytest.approx(rnea.relative_error, rel=1e-10)
