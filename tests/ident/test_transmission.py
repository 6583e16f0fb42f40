"""Transmissions for URDF robots (``robot.transmission.yaml``), encoder offsets for MDH and
URDF robots, and drive currents with given or identified gains (issue 15, items 1 and 4)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from robid_link.exceptions import DataError, RobotError
from robid_link.fakes.plant import Plant, Truth, perturbed_inertials
from robid_link.ident.data.logs import write_log_csv
from robid_link.ident.excite.excitation import random_fourier
from robid_link.ident.fit.design import base_set_for
from robid_link.ident.fit.identify import identify, load_logs
from robid_link.ident.model.effects import DEFAULT_MODEL, Model
from robid_link.ident.model.robot import load_robot

from ..conftest import ROBOTS, mdh_to_urdf

TX_URDF = """\
# gear ratios by joint name, motor a6 also turns with joint a5, encoder zeros in degrees
transmission:
  ratios: {a1: 120, a2: 120, a3: 100, a4: 80, a5: 80, a6: 50}
  coupling: [[a5, a6, 1.0]]
  offsets: [2.0, -1.5, 0.5, 3.0, -2.0, 1.0]
"""


def _run(robot, seed, duration=20.0, rate=400.0, effects=(), inertials=None, noise=0.0):
    traj = random_fourier(robot, harmonics=5, base_hz=0.1, seed=seed)
    t = np.arange(0.0, duration, 1.0 / rate)
    q, qd, qdd = traj.evaluate(t)
    truth = Truth(perturbed_inertials(robot, seed + 100) if inertials is None else inertials,
                  effects=tuple(effects), noise_tau=noise)
    log = Plant(robot, truth).run(t, q, qd, qdd, seed=seed + 200)
    log["q_true"] = q
    return truth, log


def _true_base(robot, model, truth, friction=None):
    base, names = base_set_for(robot, model.blocks(robot))
    full = np.zeros(len(names))
    full[: 10 * robot.n] = truth.inertials
    for name, value in (friction or {}).items():
        full[names.index(name)] = value
    return base.combination @ full


def _rel_errors(res, beta):
    """Relative errors of the parameters the log determines well (std under 1 %): the
    others are noise-limited, whatever the transmission."""
    sure = np.array([p.rel_std_pct < 1.0 for p in res.parameters])
    assert sure.sum() >= 10
    return np.abs(res.theta[sure] - beta[sure]) / np.abs(beta[sure])


@pytest.fixture(scope="module")
def six_urdf(tmp_path_factory, industrial6):
    d = tmp_path_factory.mktemp("urdf")
    (d / "six.urdf").write_text(mdh_to_urdf(industrial6))
    (d / "six.transmission.yaml").write_text(TX_URDF)
    return load_robot(d / "six.urdf")


def test_urdf_transmission_file_is_found_by_name(six_urdf, industrial6):
    np.testing.assert_allclose(six_urdf.transmission, industrial6.transmission)
    np.testing.assert_allclose(np.degrees(six_urdf.encoder_offsets),
                               [2.0, -1.5, 0.5, 3.0, -2.0, 1.0])


def test_urdf_robot_with_transmission_and_offsets_identified_motor_side(six_urdf, tmp_path):
    """Motor encoders and motor torques of a coupled wrist with encoder offsets: the offsets
    matter (gravity depends on the true angle) and are removed before identification."""
    robot = six_urdf
    t_mat = robot.transmission
    truth, d = _run(robot, seed=41)
    qd_m = d["qd"] @ t_mat.T
    fv_m = np.array([0.02, 0.02, 0.015, 0.006, 0.006, 0.004])  # at the motors, N·m·s/rad
    tau_joint = d["tau_true"] + (fv_m * qd_m) @ t_mat
    # the plant's joint-side log reads q + offsets; the motor encoders read T (q + offsets)
    np.testing.assert_allclose(d["q"] - robot.encoder_offsets, d["q_true"], atol=1e-12)
    q_m, tau_m = d["q"] @ t_mat.T, tau_joint @ np.linalg.inv(t_mat)
    tau_m = tau_m + np.random.default_rng(3).normal(size=tau_m.shape) * 0.002
    path = tmp_path / "motor.csv"
    write_log_csv(path, d["t"], q_m, tau_m, qd_m, d["qdd"] @ t_mat.T)
    model = Model.parse(["rigid_body", "viscous"])
    res = identify(robot, load_logs(robot, [path], motor_side=True), model, motor_side=True)
    beta = _true_base(robot, model, truth, {f"fv_{j + 1}": fv_m[j] for j in range(6)})
    err = _rel_errors(res, beta)
    assert err.max() < 0.03, f"largest parameter error {100 * err.max():.2f} %"
    # the same log read as if the encoders had no offset: the torques are nearly as well
    # explained (an angle offset rotates the downstream links), but the parameters are off
    no_offsets = replace(robot, encoder_offsets=None)
    wrong = identify(no_offsets, load_logs(no_offsets, [path], motor_side=True), model,
                     motor_side=True)
    sure = np.array([p.rel_std_pct < 1.0 for p in res.parameters])
    wrong_err = np.abs(wrong.theta[sure] - beta[sure]) / np.abs(beta[sure])
    print(f"\nURDF motor side, coupled wrist, offsets: {err.size} well-determined parameters, "
          f"largest error {100 * err.max():.2f} % (without the offsets "
          f"{100 * wrong_err.max():.0f} %)")
    assert wrong_err.max() > 1.0  # my_2: about 300 %


def test_mdh_offsets_on_joint_side_logs(tmp_path):
    text = (ROBOTS / "arm3.yaml").read_text()
    robot_file = tmp_path / "arm3.yaml"
    robot_file.write_text(text.split("transmission:")[0]
                          + "\ntransmission: {offsets: [5.0, -3.0, 2.0]}\n")
    robot = load_robot(robot_file)
    truth, d = _run(robot, seed=42, effects=({"name": "viscous", "fv": 2.0},))
    path = tmp_path / "log.csv"
    write_log_csv(path, d["t"], d["q"], d["tau"], d["qd"], d["qdd"])
    logs = load_logs(robot, [path])
    np.testing.assert_allclose(logs[0].q, d["q"] - np.radians([5.0, -3.0, 2.0]))
    model = Model.parse(["rigid_body", "viscous"])
    res = identify(robot, logs, model)
    err = _rel_errors(res, _true_base(robot, model, truth, {f"fv_{j}": 2.0 for j in (1, 2, 3)}))
    print(f"\nMDH offsets, joint side: largest error {100 * err.max():.3f} %")
    assert err.max() < 0.03, f"largest parameter error {100 * err.max():.2f} %"


def test_motor_side_on_urdf_without_transmission_names_the_file(industrial6, tmp_path):
    urdf = tmp_path / "bare.urdf"
    urdf.write_text(mdh_to_urdf(industrial6))
    robot = load_robot(urdf)
    log = tmp_path / "log.csv"
    write_log_csv(log, np.arange(20) * 0.01, np.zeros((20, 6)), np.zeros((20, 6)))
    with pytest.raises(RobotError, match=r"--motor-side needs the gear ratios "
                                         r"\(transmission.ratios in bare.transmission.yaml\)"):
        load_logs(robot, [log], motor_side=True)


@pytest.mark.parametrize(("text", "message"), [
    ("transmission: {ratios: {a1: 100}}", "transmission.ratios: joint 'a2' missing"),
    ("transmission: {ratios: {a9: 100}}", "transmission.ratios: no joint named 'a9'"),
    ("transmission: {offsets: [1, 2]}", "transmission.offsets: expected a list of 6 values"),
    ("transmission: {current_gain: [1, 1, 1, 1, 1, 0]}", "transmission.current_gain: a gain "
                                                         "of 0"),
    ("transmission: {coupling: [[a5, a6, 1]]}", "transmission.coupling: needs "
                                                "transmission.ratios"),
    ("transmission: {gears: [1]}", "transmission: expected a mapping with keys among"),
    ("transmision: {}", "unknown key 'transmision'"),
])
def test_transmission_file_errors_name_the_key(industrial6, tmp_path, text, message):
    urdf = tmp_path / "r.urdf"
    urdf.write_text(mdh_to_urdf(industrial6))
    (tmp_path / "r.transmission.yaml").write_text(text + "\n")
    with pytest.raises(RobotError, match=r"r.transmission.yaml: " + message.replace("(", r"\(")):
        load_robot(urdf)


# ----------------------------------------------------------------------------- currents


def _arm3_with(tmp_path, extra: str):
    text = (ROBOTS / "arm3.yaml").read_text().split("transmission:")[0]
    path = tmp_path / "arm3.yaml"
    path.write_text(text + "\n" + extra + "\n")
    return load_robot(path)


def test_current_logs_with_given_gains_give_the_torque_log_parameters(tmp_path):
    gains = np.array([2.5, 1.8, 0.7])  # joint N·m per A
    robot = _arm3_with(tmp_path, f"transmission: {{current_gain: {gains.tolist()}}}")
    _, d = _run(robot, seed=43, effects=({"name": "viscous", "fv": 2.0},), noise=0.3)
    write_log_csv(tmp_path / "tau.csv", d["t"], d["q"], d["tau"], d["qd"], d["qdd"])
    write_log_csv(tmp_path / "cur.csv", d["t"], d["q"], d["tau"] / gains, d["qd"], d["qdd"],
                  current=True)
    model = Model.parse(["rigid_body", "viscous"])
    ref = identify(robot, load_logs(robot, [tmp_path / "tau.csv"]), model)
    cur = identify(robot, load_logs(robot, [tmp_path / "cur.csv"]), model)
    print(f"\ncurrent log with given gains vs torque log: largest parameter difference "
          f"{np.max(np.abs(cur.theta - ref.theta) / np.maximum(np.abs(ref.theta), 1e-9)):.1e}")
    np.testing.assert_allclose(cur.theta, ref.theta, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(cur.rmse, ref.rmse, rtol=1e-6)


def test_unknown_gain_without_known_torque_is_refused_in_one_line(tmp_path):
    robot = _arm3_with(tmp_path, "")
    _, d = _run(robot, seed=44, duration=5.0)
    write_log_csv(tmp_path / "cur.csv", d["t"], d["q"], d["tau"], d["qd"], d["qdd"],
                  current=True)
    with pytest.raises(DataError, match=r"current_gain of joint 1 \(and of 2, 3\): not "
                                        r"identifiable from these logs \(the torque scale needs "
                                        r"a known payload or known torque\); give "
                                        r"transmission.current_gain"):
        identify(robot, load_logs(robot, [tmp_path / "cur.csv"]), DEFAULT_MODEL)


def test_unknown_gain_identified_through_shared_parameters(tmp_path):
    """Joint 3's gain is left out; joints 1 and 2 are given. Link 3's parameters also load
    joint 2 (gravity, inertia), so the scale of joint 3's torque is fixed by the data."""
    gains = np.array([2.5, 1.8, 0.7])
    robot = _arm3_with(tmp_path, "transmission: {current_gain: [2.5, 1.8, null]}")
    truth, d = _run(robot, seed=45, effects=({"name": "viscous", "fv": 2.0},), noise=0.05)
    write_log_csv(tmp_path / "cur.csv", d["t"], d["q"], d["tau"] / gains, d["qd"], d["qdd"],
                  current=True)
    model = Model.parse(["rigid_body", "viscous"])
    res = identify(robot, load_logs(robot, [tmp_path / "cur.csv"]), model)
    note = next(n for n in res.notes if n.startswith("current_gain of joint 3 identified"))
    value = float(note.split("identified: ")[1].split()[0])
    err = _rel_errors(res, _true_base(robot, model, truth, {f"fv_{j}": 2.0 for j in (1, 2, 3)}))
    print(f"\ngain of joint 3 identified: {value:.5g} (truth 0.7, {100 * abs(value / 0.7 - 1):.2f} "
          f"%); largest parameter error {100 * err.max():.2f} %")
    assert value == pytest.approx(0.7, rel=0.01)
    assert err.max() < 0.03, f"largest parameter error {100 * err.max():.2f} %"


def test_current_columns_in_csv_and_npz(tmp_path):
    from robid_link.ident.data.logs import load_log

    t = np.arange(50) * 0.01
    q = np.zeros((50, 3))
    np.savez(tmp_path / "c.npz", t=t, q=q, current=np.ones((50, 3)))
    log = load_log(tmp_path / "c.npz", 3)
    assert log.current.all()
    (tmp_path / "mixed.csv").write_text(
        "t,q1,q2,q3,tau1,i2,tau3\n" + "".join(f"{k * 0.01},0,0,0,1,2,3\n" for k in range(50)))
    log = load_log(tmp_path / "mixed.csv", 3)
    assert log.current.tolist() == [False, True, False]
    robot = _arm3_with(tmp_path, "transmission: {current_gain: [null, 4.0, null]}")
    (converted,) = load_logs(robot, [tmp_path / "mixed.csv"])
    np.testing.assert_allclose(converted.tau[0], [1.0, 8.0, 3.0])
    assert converted.currents is None
    (tmp_path / "both.csv").write_text(
        "t,q1,q2,q3,tau1,i1,tau2,tau3\n" + "".join(f"{k * 0.01},0,0,0,1,1,2,3\n"
                                                   for k in range(50)))
    with pytest.raises(DataError, match="columns tau1 and i1 both given"):
        load_log(tmp_path / "both.csv", 3)
    np.savez(tmp_path / "two.npz", t=t, q=q, tau=q, current=q)
    with pytest.raises(DataError, match="arrays 'tau' and 'current' both given"):
        load_log(tmp_path / "two.npz", 3)
