"""The bounded fit of the linear elastic model (numba) against scipy's trust region run to full
convergence: the same minimum, inside the box, a bound held where the data push past it."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import least_squares

from robid_link.ident.elastic.bounded import fit_logged
from robid_link.ident.elastic.models import LOGGED_PARAMETERS, as_logged, motor_and_arm

F = np.geomspace(2.0, 80.0, 30)
KG = -200.0


def _measured(v: dict[str, float], hold: float, noise: float, seed: int) -> np.ndarray:
    third = None
    if "j3" in v:
        k3 = v["j3"] * (2 * math.pi * v["f3"]) ** 2
        third = (v["j3"], k3, 2 * v["z3"] * math.sqrt(k3 * v["j3"]))
    g = motor_and_arm(F, v["jm"], v["ja"], v["k"], v["d"], v["ba"], KG, third)[0]
    g = as_logged(F, g, v["jm"], delay_s=v["delay_s"], hold_s=hold)
    rng = np.random.default_rng(seed)
    return g * np.exp(noise * (rng.normal(size=F.size) + 1j * rng.normal(size=F.size)))


def _problem(names: tuple[str, ...], start: dict[str, float]
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Solver coordinates as the fits use them: logarithms of the positive parameters, Ba ≥ 0
    and the delay scaled; x0, lo, hi, is_log, scale."""
    is_log = np.array([n not in ("ba", "delay_s") for n in names])
    scale = np.array([start["d"] if n == "ba" else 1e-4 if n == "delay_s" else 1.0
                      for n in names])
    x0 = np.array([math.log(start[n]) if lg else start[n] / s
                   for n, lg, s in zip(names, is_log, scale, strict=True)])
    lo = np.where(is_log, x0 - math.log(1e3), -np.inf)
    hi = np.where(is_log, x0 + math.log(1e3), np.inf)
    lo[names.index("ba")] = 0.0
    lo[names.index("delay_s")], hi[names.index("delay_s")] = -20.0, 20.0
    if "z3" in names:
        hi[names.index("z3")] = 0.0  # damping ratio ≤ 1
    return x0, lo, hi, is_log, scale


def _scipy(meas: np.ndarray, sig: np.ndarray, hold: float, x0: np.ndarray, lo: np.ndarray,
           hi: np.ndarray, is_log: np.ndarray, scale: np.ndarray) -> np.ndarray:
    def fun(x: np.ndarray) -> np.ndarray:
        return fit_logged(2 * np.pi * F, meas, sig, KG, hold, x, lo, hi, is_log, scale,
                          max_steps=0)[1]

    def jac(x: np.ndarray) -> np.ndarray:
        return fit_logged(2 * np.pi * F, meas, sig, KG, hold, x, lo, hi, is_log, scale,
                          max_steps=0)[2]

    return least_squares(fun, x0, jac=jac, bounds=(lo, hi), method="trf", ftol=1e-15,
                         xtol=1e-15, gtol=1e-15, max_nfev=20_000).x


TRUE = {"jm": 0.8, "ja": 2.5, "k": 9000.0, "d": 6.0, "ba": 1.5, "delay_s": 1e-4}


@pytest.mark.parametrize("case", ["two masses", "three masses", "Ba at its bound"])
def test_same_minimum_as_scipy_fully_converged(case: str) -> None:
    truth = dict(TRUE)
    if case == "three masses":
        truth.update(j3=0.6, f3=40.0, z3=0.05)
    if case == "Ba at its bound":
        truth["ba"] = 0.0  # the noise pushes the unbounded optimum below 0
    names = LOGGED_PARAMETERS[:len(truth)]
    hold = 1 / 2000
    meas = _measured(truth, hold, 0.003, seed=3)
    sig = np.full(F.size, 0.003)
    start = {n: truth[n] * (1.3 if n not in ("ba", "delay_s") else 0.0) for n in names}
    start["ba"] = 0.0
    x0, lo, hi, is_log, scale = _problem(names, {**start, "d": truth["d"]})
    x, r, jac, steps = fit_logged(2 * np.pi * F, meas, sig, KG, hold, x0, lo, hi, is_log,
                                  scale)
    ref = _scipy(meas, sig, hold, x0, lo, hi, is_log, scale)
    r_ref = fit_logged(2 * np.pi * F, meas, sig, KG, hold, ref, lo, hi, is_log, scale,
                       max_steps=0)[1]
    assert 0 < steps < 5000
    assert np.all(x >= lo) and np.all(x <= hi)
    assert r @ r == pytest.approx(r_ref @ r_ref, rel=1e-10)
    np.testing.assert_allclose(x, ref, rtol=1e-6, atol=1e-7)
    values = np.where(is_log, np.exp(x), x * scale)
    for name, value in zip(names, values, strict=True):
        if case == "Ba at its bound" and name == "ba":
            assert value == 0.0
        else:
            assert value == pytest.approx(truth[name], rel=0.1, abs=2e-5), name
    # the Jacobian returned is the residuals' at x (the covariance is computed from it)
    again = fit_logged(2 * np.pi * F, meas, sig, KG, hold, x, lo, hi, is_log, scale,
                       max_steps=0)
    np.testing.assert_array_equal(again[2], jac)
