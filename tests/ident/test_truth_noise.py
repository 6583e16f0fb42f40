"""Case 2 of issue 21, on logs of the independent plant (tests/sims/arm.py): a noise estimate
that an unmodelled effect cannot inflate, and "at the noise floor" only when the residual is
white and at the estimate."""

from __future__ import annotations

import math
import os
import warnings

import numpy as np
import pytest

from robid_link.ident.data.noise import LagSums, Whiteness, noise_floor
from robid_link.ident.data.preprocess import Piece, prepare
from robid_link.ident.diagnosis.diagnose import diagnose
from robid_link.ident.fit.identify import identify, load_logs
from robid_link.ident.model.effects import DEFAULT_MODEL, Model
from robid_link.ident.model.robot import load_robot

from ..conftest import ROBOTS
from ..sims.arm import CATALOG, Noise
from ..sims.cases import BASE, hidden, plant_log, quiet

SIGMA = 0.3


def _identify(robot, path, model=DEFAULT_MODEL):
    with warnings.catch_warnings():
        quiet()
        return identify(robot, load_logs(robot, [path]), model)


def _plant(name: str, joint: int):
    """The plant's effects and the model with ``name`` hidden on ``joint`` (viscous and Coulomb
    are hidden by leaving them out of the model)."""
    if name in ("viscous", "coulomb"):
        keep = "coulomb" if name == "viscous" else "viscous"
        return ((*BASE, hidden(name, joint)), Model.parse(["rigid_body", keep]))
    return (*BASE, hidden(name, None if name == "delay" else joint)), DEFAULT_MODEL


def _noise_case(robot, tmp_path, name: str, rate: float, joint: int = 2):
    effects, model = _plant(name, joint)
    path, _ = plant_log(robot, tmp_path / f"{name}.csv", effects=effects, rate_hz=rate,
                        noise=Noise(SIGMA))
    res = _identify(robot, path, model)
    floor = res.noise_floor
    assert floor is not None
    err = np.abs(floor / SIGMA - 1.0)
    assert err.max() <= 0.10, f"{name} at {rate:g} Hz: noise read {np.round(floor, 3)}"
    return res, err.max()


@pytest.mark.parametrize("name", ["ripple", "spring", "stribeck", "delay", "coulomb"])
def test_noise_estimate_with_an_effect_hidden(arm3, tmp_path, name):
    """The short version of the matrix below (make test)."""
    res, _ = _noise_case(arm3, tmp_path, name, 250.0)
    # the effect leaves its joint's residual coloured: that joint is not at the noise floor
    assert res.at_noise_floor is not None and not res.at_noise_floor[1], res.summary()


@pytest.mark.slow
@pytest.mark.skipif(not os.environ.get("ROBID_VALIDATE"), reason="make validate")
@pytest.mark.parametrize("rate", [250.0, 1000.0, 4000.0])
@pytest.mark.parametrize("robot_name", ["arm3", "industrial6"])
def test_noise_estimate_matrix_every_catalog_effect(tmp_path, robot_name, rate):
    robot = load_robot(ROBOTS / f"{robot_name}.yaml")
    worst = {name: _noise_case(robot, tmp_path, name, rate)[1] for name in CATALOG}
    print(f"{robot_name} {rate:g} Hz: worst noise error " + ", ".join(
        f"{k} {100 * v:.1f} %" for k, v in worst.items()))


def test_ripple_hidden_on_joint_1_is_not_called_noise(arm3, tmp_path):
    """The issue's case: a ripple hidden on joint 1 read 0.41 N·m of noise against 0.3 and the
    summary put joint 1 at the noise floor."""
    path, _ = plant_log(arm3, tmp_path / "r.csv", effects=(*BASE, hidden("ripple", 1)),
                        noise=Noise(SIGMA))
    res = _identify(arm3, path)
    assert res.noise_floor[0] == pytest.approx(SIGMA, rel=0.1)
    assert res.at_noise_floor[0] is False
    text = res.summary()
    floor_line = next((ln for ln in text.splitlines() if "at the noise floor" in ln), "")
    assert "1" not in floor_line.split(":")[0], text
    doc = res.to_dict()
    assert doc["residual_whiteness"][0]["white"] is False
    assert doc["at_noise_floor"] == res.at_noise_floor


def test_clean_log_sits_at_the_floor(arm3, tmp_path):
    path, _ = plant_log(arm3, tmp_path / "c.csv", noise=Noise(SIGMA))
    res = _identify(arm3, path)
    assert res.at_noise_floor == [True, True, True], res.summary()
    assert "1, 2, 3: validation error at the noise floor, residual white" in res.summary()


def test_coloured_noise_is_not_claimed_white(arm3, tmp_path):
    """Coloured sensor noise has fewer high frequencies: the estimate (white noise) reads low,
    and the residual's autocorrelation says it is not white."""
    path, _ = plant_log(arm3, tmp_path / "k.csv", noise=Noise(SIGMA, colour=0.6))
    res = _identify(arm3, path)
    assert np.all(res.noise_floor < SIGMA)
    assert res.at_noise_floor == [False, False, False]
    assert "not white" in res.summary()


def test_quantised_torque_and_encoders(arm3, tmp_path):
    """A 12-bit-like torque step and encoder counts: still within 10 %."""
    path, _ = plant_log(arm3, tmp_path / "q.csv",
                        noise=Noise(SIGMA, tau_lsb=0.25, q_lsb=2 * math.pi / 2**20))
    res = _identify(arm3, path)
    true = math.sqrt(SIGMA**2 + 0.25**2 / 12)  # the step adds its uniform rounding noise
    np.testing.assert_allclose(res.noise_floor, true, rtol=0.1)


def test_diagnosis_of_a_spring_left_unnamed_is_not_adequate(arm3, tmp_path):
    """A residual at twice the noise that is not white is not 'adequate', whatever the catalog
    says: the verdict names the joint, the noise estimate and the whiteness figures."""
    path, _ = plant_log(arm3, tmp_path / "s.csv", effects=(*BASE, hidden("ripple", 2)),
                        noise=Noise(SIGMA))
    model = Model.parse(["rigid_body", "viscous", "coulomb"])
    with warnings.catch_warnings():
        quiet()
        logs = load_logs(arm3, [path])
        res = identify(arm3, logs, model)
        dg = diagnose(arm3, logs, model, result=res)
    assert dg.verdict != "adequate"
    joint2 = [d for d in dg.doubts if d.startswith("joint 2")]
    assert joint2 and "noise" in joint2[0] and "not white" in joint2[0], dg.doubts


# -- the steps alone


def _pieces(tau: np.ndarray, fs: float = 500.0) -> list[Piece]:
    from robid_link.ident.data.logs import Log

    t = np.arange(tau.shape[0]) / fs
    log = Log("x.csv", t, np.zeros_like(tau), tau, segments=[slice(0, t.size)])
    prep = prepare(log, None)
    return [Piece(prep, 100, t.size - 100, 0, t.size)]


def test_noise_floor_ignores_smooth_torque_and_steps():
    rng = np.random.default_rng(0)
    t = np.arange(20000) / 500.0
    smooth = 50 * np.sin(2 * np.pi * 0.7 * t) + 3 * np.sin(2 * np.pi * 15 * t)
    steps = 2.0 * np.sign(np.sin(2 * np.pi * 0.3 * t))  # Coulomb reversals
    tau = (smooth + steps)[:, None] + rng.normal(0, 0.4, (t.size, 1))
    assert noise_floor(_pieces(tau))[0] == pytest.approx(0.4, rel=0.03)
    assert noise_floor([]) is None


def test_lag_sums_equal_the_direct_autocorrelation():
    rng = np.random.default_rng(1)
    e = rng.normal(size=(3000, 2)) + 0.3
    e[:, 1] = np.convolve(e[:, 1], np.ones(4) / 4, "same")
    acc = LagSums(2, lags=5)
    acc.add(e)
    white = acc.result()
    assert white is not None
    x = e - e.mean(axis=0)
    for k in range(1, 6):
        direct = (x[:-k] * x[k:]).mean(axis=0) / (x * x).mean(axis=0)
        np.testing.assert_allclose(white.acf[k - 1], direct, atol=5e-3)
    assert white.white.tolist() == [True, False]
    assert "not white" in white.sentence(1) and white.joint(0)["white"] is True


def test_whiteness_of_a_tiny_colour_on_a_long_log_is_immaterial():
    """On 10⁶ samples a coloured part of 1 % of the variance is significant but immaterial."""
    acf = np.full((25, 1), 0.01)
    w = Whiteness(acf, 1_000_000)
    assert w.q_stat[0] > w.q_bound and bool(w.white[0])
