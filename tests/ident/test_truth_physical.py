"""Case 5 of issue 21, on logs of the independent plant (tests/sims/arm.py): a fit that
validates worse than CAD or is physically impossible gets a doubt naming it and the consistent
estimator, and its parameter set is marked unfit (the link then refuses to upload it unless
forced: tests/link/test_unfit_set.py); no sign alarm without the sign's evidence."""

from __future__ import annotations

import warnings
from types import SimpleNamespace

import numpy as np
import pytest

from robid_link.exceptions import DataWarning
from robid_link.ident.fit.identify import identify, load_logs
from robid_link.ident.fit.paramset import make_parameter_set
from robid_link.ident.fit.physics import fit_doubts, impossible_parameters
from robid_link.ident.fit.results import Parameter
from robid_link.ident.model.effects import DEFAULT_MODEL

from ..sims.arm import Effect, Noise
from ..sims.cases import BASE, plant_log, quiet

#: the 6-axis example's truth: heavy friction and a strong balancing spring on axis 2 that the
#: default model does not know (its nightly campaign identifies without it)
NIGHTLY = (Effect("viscous", p={"b": 6.0}), Effect("coulomb", p={"fc": 12.0}),
           Effect("spring", 2, {"k": 20000.0, "a": 0.15, "b": 0.2, "l0": 0.3, "phi": 0.4}))


@pytest.fixture(scope="module")
def nightly(industrial6, tmp_path_factory):
    path, _ = plant_log(industrial6, tmp_path_factory.mktemp("n") / "nightly.csv",
                        effects=NIGHTLY, rate_hz=500.0, noise=Noise(1.0))
    with warnings.catch_warnings():
        quiet()
        logs = load_logs(industrial6, [path])
        return logs, identify(industrial6, logs, DEFAULT_MODEL)


def test_worse_than_cad_is_a_doubt_with_the_remedy(industrial6, nightly):
    _, res = nightly
    doubts = res.doubts
    assert any("validate worse than the CAD model" in d and "--method consistent" in d
               for d in doubts), doubts
    assert res.to_dict()["doubts"] == doubts
    assert "  doubt: " in res.summary()
    pset = make_parameter_set(industrial6, res.to_dict(), run_id="nightly")
    assert pset["uploadable"] is False and pset["unfit"][:len(doubts)] == doubts


def test_clean_fit_has_no_doubt(arm3, tmp_path):
    path, _ = plant_log(arm3, tmp_path / "c.csv", rate_hz=500.0, seed=2, motion_seed=4)
    with warnings.catch_warnings():
        quiet()
        res = identify(arm3, load_logs(arm3, [path]), DEFAULT_MODEL)
    assert res.doubts == []
    pset = make_parameter_set(arm3, res.to_dict(), run_id="clean")
    assert pset["uploadable"] is True and pset["unfit"] == []


def test_a_consistent_fit_is_never_impossible(industrial6, nightly):
    logs, _ = nightly
    with warnings.catch_warnings():
        quiet()
        res = identify(industrial6, logs, DEFAULT_MODEL, method="consistent")
    assert impossible_parameters(res) == []
    pset = make_parameter_set(industrial6, res.to_dict(), run_id="c")
    assert pset["physically_consistent"] is True
    assert not any("describe no body" in u for u in pset["unfit"])


def test_impossible_base_parameter_is_named():
    """zz_1 + yy_2 + 0.16·m_3 cannot be negative; xx_2 − yy_2 can."""
    from robid_link.ident.model.robot import load_robot

    from ..conftest import ROBOTS

    robot = load_robot(ROBOTS / "arm3.yaml")
    from robid_link.ident.fit.design import base_set_for

    base, _ = base_set_for(robot, DEFAULT_MODEL.blocks(robot))
    params = [Parameter(nm, -1.0 if nm in ("zz_1", "xx_2") else 1.0, 0.1, "")
              for nm in base.base_names]
    pb = SimpleNamespace(robot=robot, blocks=DEFAULT_MODEL.blocks(robot), transmission=None)
    res = SimpleNamespace(problem=pb, method="ols", parameters=params, joints=[],
                          validation=None, nominal=None)
    assert [p[0] for p in impossible_parameters(res)] == ["zz_1"]
    (doubt,) = fit_doubts(res)
    assert doubt.startswith("physically impossible: zz_1 = -1 ± 0.1") and "consistent" in doubt


def test_no_sign_alarm_without_the_signs_evidence(industrial6, nightly):
    """Friction the a-priori model lacks can turn a joint's correlation with it negative; the
    model's scale beside friction is then positive and no alarm fires."""
    logs, res = nightly
    assert not any("opposite sign" in n for n in res.notes), res.notes


def test_a_flipped_torque_is_still_named(arm3, tmp_path):
    path, rec = plant_log(arm3, tmp_path / "f.csv", effects=BASE, duration_s=20.0)
    rec.tau[:, 1] *= -1.0
    from ..sims.arm import write_csv

    write_csv(path, rec)
    with pytest.warns(DataWarning, match=r"tau2 has the opposite sign of the a-priori model "
                                         r"\(scale -"):
        identify(arm3, load_logs(arm3, [path]), DEFAULT_MODEL)
    assert np.isfinite(rec.tau).all()
