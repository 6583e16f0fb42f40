"""The real KUKA LWR4+ logs (FloBaRoID's public data): a peer reached 2.81 % on 2+3 → 1."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from robid_link.exceptions import ConditioningWarning, DataWarning, ExcitationWarning
from robid_link.ident.fit.identify import identify, load_logs
from robid_link.ident.model.effects import Model
from robid_link.ident.model.robot import load_robot

MODEL = Model.parse(["rigid_body", "viscous", "coulomb", "offset"])
PEER_RELATIVE_ERROR = 0.0281


def _expected_kuka_warnings() -> None:
    """What these logs are known to raise: jittered stamps resampled, two joints logged with
    the opposite sign of the URDF's a-priori model, validation motions outside the training
    range, weak excitation of some parameters. Anything else still fails the test."""
    warnings.filterwarnings("ignore", r".*time step varies by up to", DataWarning)
    warnings.filterwarnings("ignore", r".*has the opposite sign of the a-priori model",
                            DataWarning)
    warnings.filterwarnings("ignore", r"validation leaves the training range", ExcitationWarning)
    warnings.filterwarnings("ignore", category=ConditioningWarning)


def _run(kuka_dir, train, valid):
    robot = load_robot(kuka_dir / "kuka_lwr4.urdf")
    files = [kuka_dir / f"measurements_{i}.npz" for i in (*train, *valid)]
    with warnings.catch_warnings():
        _expected_kuka_warnings()
        data = load_logs(robot, files[: len(train)])
        val = load_logs(robot, files[len(train):])
        return identify(robot, data, MODEL, validate=val)


@pytest.mark.kuka
def test_beats_the_peer_on_a_repeated_trajectory(kuka_dir):
    res = _run(kuka_dir, (2, 3), (1,))
    assert res.validation.relative_error < PEER_RELATIVE_ERROR
    assert res.validation.abs_error < 0.72  # the peer's absolute error, N·m
    assert res.nominal.relative_error > 3 * res.validation.relative_error
    assert res.joints[0]["name"] == "lwr_0_joint" and len(res.joints) == 7


@pytest.mark.kuka
def test_unseen_motion_is_reported_with_the_cad_model(kuka_dir):
    res = _run(kuka_dir, (1, 2), (3,))
    rel, cad = res.validation.relative_error, res.nominal.relative_error
    # honest figures (closing note): ~12.8 % identified vs ~11.7 % CAD on the unseen motion;
    # the training motion does not span file 3's velocities, and the check says so
    assert 0.0 < rel < 0.25 and 0.0 < cad < 0.25
    assert any("leaves the training range of qd" in n for n in res.notes)
    assert np.all(np.isfinite(res.rmse))


@pytest.mark.kuka
def test_diagnosis_on_real_data_and_its_effect_on_the_unseen_motion(kuka_dir):
    """Diagnose the default model on files 1+2; add the top suggestion; validate on file 3."""
    from robid_link.ident.diagnosis.diagnose import diagnose
    from robid_link.ident.model.effects import DEFAULT_MODEL, EffectSpec

    robot = load_robot(kuka_dir / "kuka_lwr4.urdf")
    with warnings.catch_warnings():
        _expected_kuka_warnings()
        data = load_logs(robot, [kuka_dir / f"measurements_{i}.npz" for i in (1, 2)])
        val = load_logs(robot, [kuka_dir / "measurements_3.npz"])
        dg = diagnose(robot, data, DEFAULT_MODEL)
        top = dg.suggestions[0]
        before = identify(robot, data, DEFAULT_MODEL, validate=val)
        after = identify(robot, data, DEFAULT_MODEL.with_added(
            EffectSpec(top.effect, top.joint, tuple(sorted(top.hypers.items())))), validate=val)
    # honest figures (closing note): the residual of joint 1 (the vertical axis) is the worst;
    # the top suggestion concerns it and lowers the unseen motion's error a little
    assert dg.verdict == "missing_effect" and top.joint == 1
    assert any("one motion" in n for n in dg.notes)  # files 1 and 2 repeat one trajectory
    assert after.rmse[0] < 0.8 * before.rmse[0]
    assert after.validation.relative_error < before.validation.relative_error
