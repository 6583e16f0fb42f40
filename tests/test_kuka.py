"""The real KUKA LWR4+ logs (FloBaRoID's public data): a peer reached 2.81 % on 2+3 → 1."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from robid_link.ident.effects import Model
from robid_link.ident.identify import identify, load_logs
from robid_link.ident.robot import load_robot

MODEL = Model.parse(["rigid_body", "viscous", "coulomb", "offset"])
PEER_RELATIVE_ERROR = 0.0281


def _run(kuka_dir, train, valid):
    robot = load_robot(kuka_dir / "kuka_lwr4.urdf")
    files = [kuka_dir / f"measurements_{i}.npz" for i in (*train, *valid)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # resampling of jittered stamps, sign notes
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
