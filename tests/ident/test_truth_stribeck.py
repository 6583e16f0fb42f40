"""Case 7 of issue 21, on logs of the independent plant (tests/sims/arm.py): a hidden Stribeck
breakaway of any shape exp(−|q̇/vs|^δ) is named with its shape exponent profiled, and the
suggestion removes ≥ 95 % of the excess error it caused."""

from __future__ import annotations

import os
import warnings

import numpy as np
import pytest

from robid_link.ident.diagnosis.diagnose import diagnose
from robid_link.ident.fit.identify import identify, load_logs
from robid_link.ident.model.effects import DEFAULT_MODEL, EffectSpec
from robid_link.ident.model.robot import load_robot

from ..conftest import ROBOTS
from ..sims.cases import BASE, hidden, plant_log, quiet


def _stribeck_case(robot, tmp_path, delta: float, joint: int, seed: int = 1
                   ) -> tuple[float, dict[str, float]]:
    """The share of the excess held-out MSE (hidden minus clean log) the top suggestion
    removes, and its hyper-parameters; asserts it is Stribeck on ``joint`` with δ within
    15 %."""
    with warnings.catch_warnings():
        quiet()
        hp, _ = plant_log(robot, tmp_path / "h.csv", seed=seed,
                          effects=(*BASE, hidden("stribeck", joint, delta=delta)))
        cp, _ = plant_log(robot, tmp_path / "c.csv", effects=BASE, seed=seed)
        logs = load_logs(robot, [hp])
        dg = diagnose(robot, logs, DEFAULT_MODEL)
        top = dg.suggestions[0]
        assert (top.effect, top.joint) == ("stribeck", joint), dg.summary()
        assert top.hypers["shape"] == pytest.approx(delta, rel=0.15), top.hypers
        assert top.fields["shape"] == pytest.approx(top.hypers["shape"], rel=1e-4)
        assert top.fields["breakaway"] > 0.0, top.evidence  # static above Coulomb friction
        spec = EffectSpec(top.effect, top.joint, tuple(sorted(top.hypers.items())))
        before = identify(robot, logs, DEFAULT_MODEL).rmse[joint - 1]
        ref = identify(robot, load_logs(robot, [cp]), DEFAULT_MODEL).rmse[joint - 1]
        after = identify(robot, logs, DEFAULT_MODEL.with_added(spec)).rmse[joint - 1]
    excess = before**2 - ref**2
    assert excess > 0
    return 1.0 - (after**2 - ref**2) / excess, top.hypers


@pytest.mark.parametrize("delta", [0.6, 1.0])
def test_stribeck_of_any_shape_is_removed(arm3, tmp_path, delta):
    """With δ fixed at 2 the δ = 0.6 breakaway was taken for friction_power, whose fit raised
    the error (−200 % of the excess removed); δ = 1 for presliding."""
    removed, _ = _stribeck_case(arm3, tmp_path, delta, joint=2)
    assert removed >= 0.95, f"δ {delta}: {100 * removed:.1f} % of the excess removed"


def test_identify_profiles_the_shape_of_a_model_stribeck(arm3, tmp_path):
    """A model file's ``stribeck@2`` without vs and shape: identify profiles both."""
    with warnings.catch_warnings():
        quiet()
        hp, _ = plant_log(arm3, tmp_path / "h.csv", duration_s=12.0,
                          effects=(*BASE, hidden("stribeck", 2, delta=0.6)))
        res = identify(arm3, load_logs(arm3, [hp]),
                       DEFAULT_MODEL.with_added(EffectSpec("stribeck", 2, ())))
    chosen = res.to_dict()["hyper_parameters"]["stribeck@2"]
    # grid values by training RSS (vs and δ trade off on a short log: the diagnosis refines
    # them); off the default δ 2, and the joint's error at the plant's 0.3 N·m noise
    assert chosen["shape"] < 2.0 and chosen["vs"] in (0.05, 0.1), chosen
    assert res.rmse[1] < 0.31, res.rmse


@pytest.mark.slow
@pytest.mark.skipif(not os.environ.get("ROBID_VALIDATE"), reason="make validate")
@pytest.mark.parametrize("robot_name,joint", [("arm3", 1), ("arm3", 3), ("industrial6", 2),
                                              ("industrial6", 5)])
def test_stribeck_matrix(tmp_path, robot_name, joint):
    robot = load_robot(ROBOTS / f"{robot_name}.yaml")
    cases = {(d, s): _stribeck_case(robot, tmp_path, d, joint, seed=s)
             for d in (0.5, 1.0, 1.5, 2.0) for s in (1, 2)}
    print(f"{robot_name} joint {joint}: " + ", ".join(
        f"δ {d} seed {s}: δ̂ {h['shape']:.3f} vs {h['vs']:.4f} {100 * v:.1f} %"
        for (d, s), (v, h) in cases.items()))
    removed = {key: v for key, (v, _) in cases.items()}
    assert min(removed.values()) >= 0.95
    assert np.isfinite(list(removed.values())).all()
