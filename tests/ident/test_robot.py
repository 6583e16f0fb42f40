"""Robot descriptions: MDH and URDF, locking, transmission, and their error messages."""

from __future__ import annotations

import re

import numpy as np
import pytest

from robid_link.exceptions import RobotError
from robid_link.ident.model.regressor import rigid_regressor
from robid_link.ident.model.robot import load_robot, standard_parameter_names

from ..conftest import ROBOTS, mdh_to_urdf


def test_mdh_and_equivalent_urdf_predict_the_same_torques(industrial6, tmp_path):
    urdf = tmp_path / "industrial6.urdf"
    urdf.write_text(mdh_to_urdf(industrial6))
    other = load_robot(urdf)
    assert other.n == industrial6.n
    rng = np.random.default_rng(0)
    q, qd, qdd = (rng.uniform(-1.5, 1.5, (50, 6)) for _ in range(3))
    for k in range(50):
        np.testing.assert_allclose(other.rnea(q[k], qd[k], qdd[k]),
                                   industrial6.rnea(q[k], qd[k], qdd[k]), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(rigid_regressor(other, q, qd, qdd) @ other.nominal,
                               rigid_regressor(industrial6, q, qd, qdd) @ industrial6.nominal,
                               rtol=1e-9, atol=1e-8)


def test_mdh_limits_and_names(industrial6):
    assert industrial6.joint_names[:2] == ("a1", "a2")
    np.testing.assert_allclose(np.degrees(industrial6.limits.q_min[1]), -90)
    np.testing.assert_allclose(np.degrees(industrial6.limits.qd_max[0]), 150)
    assert industrial6.limits.tau_max[5] == 80
    assert standard_parameter_names(2)[:3] == ["m_1", "mx_1", "my_1"]
    assert industrial6.mapping()[0] == {"joint": 1, "name": "a1", "type": "revolute"}


def test_transmission_with_wrist_coupling(industrial6):
    t = industrial6.transmission
    # q_m6 = 50 (q6 + 1.0 q5)
    assert t[5, 5] == 50 and t[5, 4] == 50 and t[4, 4] == 80
    rng = np.random.default_rng(1)
    q, tau = rng.normal(size=(10, 6)), rng.normal(size=(10, 6))
    qm, taum = industrial6.to_motor_side(q, tau)
    np.testing.assert_allclose(qm[:, 5], 50 * (q[:, 5] + q[:, 4]))
    back_q, _, _, back_tau = industrial6.to_joint_side(qm, None, None, taum)
    np.testing.assert_allclose(back_q, q, atol=1e-12)
    np.testing.assert_allclose(back_tau, tau, atol=1e-12)
    # power is conserved: τ_mᵀ q̇_m = τᵀ q̇
    np.testing.assert_allclose((taum * qm).sum(axis=1), (tau * q).sum(axis=1), rtol=1e-10)


def test_urdf_lock_removes_joints(kuka_dir):
    full = load_robot(kuka_dir / "kuka_lwr4.urdf")
    locked = load_robot(kuka_dir / "kuka_lwr4.urdf", lock=["lwr_6_joint"])
    assert full.n == 7 and locked.n == 6
    assert "lwr_6_joint" not in locked.joint_names


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("joints: [{alpha: 0, a: 0, theta: 0}]", "joints[0]: missing key 'd'"),
        ("joints: [{alpha: x, a: 0, theta: 0, d: 0}]", "joints[0].alpha: expected a finite number"),
        ("joints: [{alpha: 0, a: 0, theta: 0, d: 0, type: ball}]", "joints[0].type: expected"),
        ("joints: [{alpha: 0, a: 0, theta: 0, d: 0, colour: red}]",
         "joints[0]: unknown key 'colour' (known: a, alpha, d,"),
        ("joints: [[0, 0, 0, 0]]", "joints[0]: expected a mapping, got list"),
        ("joints: []", "joints: expected a non-empty list"),
        ("joints: [{alpha: 0, a: 0, theta: 0, d: 0, limits: {q: [10, -10]}}]",
         "joints[0].limits.q: lower limit"),
        ("allow_unlimited: true\njoints: [{alpha: 0, a: 0, theta: 0, d: 0}]\n"
         "transmission: {ratios: [0]}",
         "transmission.ratios: a gear ratio of 0"),
        ("joints: [{alpha: 0, a: 0, theta: 0, d: 0,\n", "invalid YAML"),
        ("gravity: [0, 0]\njoints: [{alpha: 0, a: 0, theta: 0, d: 0, limits: {q: [-9, 9]}}]",
         "gravity: expected a list of 3 numbers"),
    ],
)
def test_bad_mdh_files_name_the_key(tmp_path, text, message):
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    with pytest.raises(RobotError, match=re.escape(message)) as e:
        load_robot(p)
    assert str(p) in str(e.value) and "\n" not in str(e.value)


def test_bad_robot_paths(tmp_path, kuka_dir):
    with pytest.raises(RobotError, match="robot description not found"):
        load_robot(tmp_path / "nope.yaml")
    (tmp_path / "r.txt").write_text("x")
    with pytest.raises(RobotError, match="unknown robot format"):
        load_robot(tmp_path / "r.txt")
    (tmp_path / "broken.urdf").write_text("<robot name='x'><link></robot>")
    with pytest.raises(RobotError, match="invalid XML at line 1"):
        load_robot(tmp_path / "broken.urdf")
    with pytest.raises(RobotError, match="--lock gripper: no joint of that name"):
        load_robot(kuka_dir / "kuka_lwr4.urdf", lock=["gripper"])
    with pytest.raises(RobotError, match="--lock applies to URDF"):
        load_robot(ROBOTS / "arm3.yaml", lock=["j1"])
