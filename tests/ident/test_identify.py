"""Identification against known truth from the simulated plant."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from robid_link.exceptions import DataError, DataWarning, ExcitationWarning
from robid_link.ident.data.logs import write_log_csv
from robid_link.ident.fit.estimate import WEIGHTS
from robid_link.ident.fit.identify import identify, load_logs
from robid_link.ident.model.effects import DEFAULT_MODEL, Model
from robid_link.ident.model.robot import load_robot

from ..conftest import mdh_to_urdf, simulate


def _chi2(res, beta):
    d = res.theta - beta
    return float(d @ np.linalg.solve(res.cov, d)), d.size


def test_mdh_robot_recovers_true_base_parameters(arm3, tmp_path):
    sim = simulate(arm3, tmp_path / "arm3.csv", noise=0.5, seed=1)
    res = identify(arm3, load_logs(arm3, [sim.path]), DEFAULT_MODEL)
    stat, dof = _chi2(res, sim.true_base(arm3, DEFAULT_MODEL))
    assert stat < chi2.ppf(0.99, dof), f"χ² {stat:.1f} with {dof} dof"
    np.testing.assert_allclose(res.rmse, 0.5, rtol=0.10)
    assert res.rank == 21 and res.validation.n_samples > 1000


def test_urdf_robot_recovers_true_base_parameters(industrial6, tmp_path):
    urdf = tmp_path / "six.urdf"
    urdf.write_text(mdh_to_urdf(industrial6))
    robot = load_robot(urdf)
    sim = simulate(robot, tmp_path / "six.csv", noise=0.8, seed=2,
                   inertials=industrial6.nominal * 1.1)
    res = identify(robot, load_logs(robot, [sim.path]), DEFAULT_MODEL)
    stat, dof = _chi2(res, sim.true_base(robot, DEFAULT_MODEL))
    assert stat < chi2.ppf(0.99, dof), f"χ² {stat:.1f} with {dof} dof"
    np.testing.assert_allclose(res.rmse, 0.8, rtol=0.10)
    # the a-priori (nominal, 10 % off and frictionless) model is much worse
    assert np.all(res.nominal.rmse > 2 * res.rmse)


def test_seven_axis_urdf_chi2(kuka_dir, tmp_path):
    robot = load_robot(kuka_dir / "kuka_lwr4.urdf")
    model = Model.parse(["rigid_body", "viscous", "coulomb", "offset"])
    sim = simulate(robot, tmp_path / "lwr.csv", noise=0.2, seed=3, rate=400.0,
                   effects=({"name": "viscous", "fv": 0.8}, {"name": "coulomb", "fc": 0.6},
                            {"name": "offset", "b": 0.1}))
    res = identify(robot, load_logs(robot, [sim.path]), model)
    stat, dof = _chi2(res, sim.true_base(robot, model))
    assert stat < chi2.ppf(0.99, dof), f"χ² {stat:.1f} with {dof} dof"
    np.testing.assert_allclose(res.rmse, 0.2, rtol=0.10)


def test_positions_only_with_quantized_encoders(arm3, tmp_path):
    """Velocities and accelerations differentiated from 20-bit encoder positions."""
    sim = simulate(arm3, tmp_path / "q.csv", noise=0.5, seed=4, derivatives=False,
                   q_resolution=2 * np.pi / 2**20, rate=1000.0)
    res = identify(arm3, load_logs(arm3, [sim.path]), DEFAULT_MODEL)
    np.testing.assert_allclose(res.rmse, 0.5, rtol=0.10)
    beta = sim.true_base(arm3, DEFAULT_MODEL)
    big = np.abs(beta) > 0.1
    np.testing.assert_allclose(res.theta[big], beta[big], rtol=0.05)


def test_wls_weights_the_noisy_joint_down(arm3, tmp_path):
    sim = simulate(arm3, tmp_path / "w.csv", seed=5, noise=0.0)
    rng = np.random.default_rng(0)
    noise = rng.normal(size=sim.data["tau"].shape) * np.array([0.2, 0.2, 3.0])
    d = sim.data
    write_log_csv(sim.path, d["t"], d["q"], d["tau_true"] + noise, d["qd"], d["qdd"])
    logs = load_logs(arm3, [sim.path])
    beta = sim.true_base(arm3, DEFAULT_MODEL)
    ols = identify(arm3, logs, DEFAULT_MODEL, method="ols")
    wls = identify(arm3, logs, DEFAULT_MODEL, method="wls")
    stat, dof = _chi2(wls, beta)
    assert stat < chi2.ppf(0.99, dof)
    # WLS parameters are more precise than OLS ones, on average over the base set
    assert np.median(np.sqrt(np.diag(wls.cov)) / np.sqrt(np.diag(ols.cov))) < 0.8


def test_irls_resists_torque_spikes(arm3, tmp_path):
    sim = simulate(arm3, tmp_path / "o.csv", seed=6, noise=0.3)
    d = sim.data
    tau = d["tau"].copy()
    rng = np.random.default_rng(1)
    hit = rng.random(tau.shape[0]) < 0.03
    tau[hit, 1] += rng.choice([-1, 1], hit.sum()) * 40.0  # one-sided sensor glitches
    write_log_csv(sim.path, d["t"], d["q"], tau, d["qd"], d["qdd"])
    logs = load_logs(arm3, [sim.path])
    beta = sim.true_base(arm3, DEFAULT_MODEL)
    ols = identify(arm3, logs, DEFAULT_MODEL, method="ols", cutoff_hz=1e9)
    irls = identify(arm3, logs, DEFAULT_MODEL, method="irls", weight="bisquare", cutoff_hz=1e9)
    err_ols = np.linalg.norm(ols.theta - beta)
    err_irls = np.linalg.norm(irls.theta - beta)
    assert err_irls < 0.3 * err_ols


@pytest.mark.parametrize("name", sorted(WEIGHTS))
def test_weight_functions_shape(name):
    w = WEIGHTS[name]
    r = np.linspace(0, 6, 61)
    vals = w(r)
    assert vals[0] == pytest.approx(1.0)
    assert np.all(np.diff(vals) <= 1e-12) and np.all(vals >= 0)
    np.testing.assert_allclose(w(-r), vals)


def test_friction_power_alpha_is_profiled(arm3, tmp_path):
    sim = simulate(arm3, tmp_path / "fp.csv", seed=7, noise=0.3,
                   effects=({"name": "friction_power", "fc": 1.0, "fv": 4.0, "alpha": 0.65,
                             "b": 0.2},))
    model = Model.parse(["rigid_body", "friction_power"])
    res = identify(arm3, load_logs(arm3, [sim.path]), model)
    assert {k: v["alpha"] for k, v in res.hypers.items()} == {
        f"friction_power@{j}": 0.65 for j in (1, 2, 3)}
    np.testing.assert_allclose(res.rmse, 0.3, rtol=0.10)
    fixed = identify(arm3, load_logs(arm3, [sim.path]),
                     Model.parse(["rigid_body", {"name": "friction_power", "alpha": 1.5}]))
    assert np.all(fixed.rmse > res.rmse)


def test_friction_power_replaces_viscous_coulomb_offset(arm3):
    blocks = Model.parse(["rigid_body", "viscous", "coulomb", "offset",
                          "friction_power@2"]).blocks(arm3)
    keys = [b.key for b in blocks]
    assert "friction_power@2" in keys and "viscous@2" not in keys and "offset@2" not in keys
    assert "viscous@1" in keys and "coulomb@3" in keys


def test_decimation_keeps_the_answer(arm3, tmp_path):
    sim = simulate(arm3, tmp_path / "d.csv", seed=8, noise=0.5, rate=1000.0)
    logs = load_logs(arm3, [sim.path])
    full = identify(arm3, logs, DEFAULT_MODEL)
    dec = identify(arm3, logs, DEFAULT_MODEL, interval=10)
    assert dec.n_samples < full.n_samples / 9
    stat, dof = _chi2(dec, sim.true_base(arm3, DEFAULT_MODEL))
    assert stat < chi2.ppf(0.99, dof)
    np.testing.assert_allclose(dec.rmse, full.rmse, rtol=0.05)


def test_validation_file_outside_training_range_warns(arm3, tmp_path):
    train = simulate(arm3, tmp_path / "t.csv", seed=9, duration=20.0)
    other = simulate(arm3, tmp_path / "v.csv", seed=10, duration=20.0)
    d = train.data
    # shrink the training motion so the other motion leaves its range
    slow = 0.5
    from robid_link.fakes.plant import Plant

    plant = Plant(arm3, train.truth)
    small = plant.run(d["t"], d["q"] * slow, d["qd"] * slow, d["qdd"] * slow, seed=1)
    write_log_csv(train.path, small["t"], small["q"], small["tau"], small["qd"], small["qdd"])
    with pytest.warns(ExcitationWarning, match="validation leaves the training range of q"):
        res = identify(arm3, load_logs(arm3, [train.path]), DEFAULT_MODEL,
                       validate=load_logs(arm3, [other.path]))
    assert res.validation_source == "files v.csv"
    assert any("extrapolates" in n for n in res.notes)


def test_sign_flip_against_the_a_priori_model_warns(arm3, tmp_path):
    sim = simulate(arm3, tmp_path / "s.csv", seed=11)
    d = sim.data
    tau = d["tau"].copy()
    tau[:, 1] *= -1
    write_log_csv(sim.path, d["t"], d["q"], tau, d["qd"], d["qdd"])
    with pytest.warns(DataWarning, match="tau2 has the opposite sign of the a-priori model"):
        identify(arm3, load_logs(arm3, [sim.path]), DEFAULT_MODEL)


def test_too_few_samples_for_the_parameters(arm3, tmp_path):
    sim = simulate(arm3, tmp_path / "short.csv", seed=12, duration=0.12)
    with pytest.raises(DataError, match="short.csv: .* training samples×joints for 21 "
                                        "parameters; need at least 105"):
        identify(arm3, load_logs(arm3, [sim.path]), DEFAULT_MODEL, cutoff_hz=100.0)


def test_motor_side_logs_with_wrist_coupling(industrial6, tmp_path):
    """Motor 6 turns with joints 5 and 6: its friction acts on its own (motor) velocity."""
    robot = industrial6
    t_mat = robot.transmission
    sim = simulate(robot, tmp_path / "joint.csv", seed=13, noise=0.0, effects=())
    d = sim.data
    qd_m = d["qd"] @ t_mat.T
    fv_m, fc_m = 0.004, 0.05  # motor-side friction, N·m at the motor
    tau_joint = d["tau_true"] + (fv_m * qd_m + fc_m * np.sign(qd_m)) @ t_mat
    q_m, tau_m = robot.to_motor_side(d["q"], tau_joint)
    sigma_m = 0.002
    tau_m = tau_m + np.random.default_rng(2).normal(size=tau_m.shape) * sigma_m
    path = tmp_path / "motor.csv"
    write_log_csv(path, d["t"], q_m, tau_m, qd_m, d["qdd"] @ t_mat.T)
    res = identify(robot, load_logs(robot, [path], motor_side=True), DEFAULT_MODEL,
                   motor_side=True)
    expected = sigma_m * np.sqrt((t_mat**2).sum(axis=0))  # noise seen on the joint side
    np.testing.assert_allclose(res.rmse, expected, rtol=0.10)
    values = {p.name: p.value for p in res.parameters}
    assert values["fv_6"] == pytest.approx(fv_m, rel=0.02)
    assert values["fc_6"] == pytest.approx(fc_m, rel=0.02)
    # modelling the same friction on joint velocities misses motor 6 on joint 5
    joint_log = tmp_path / "jointside.csv"
    write_log_csv(joint_log, d["t"], d["q"], tau_m @ t_mat, d["qd"], d["qdd"])
    plain = identify(robot, load_logs(robot, [joint_log]), DEFAULT_MODEL)
    assert plain.rmse[4] > 1.5 * res.rmse[4]
