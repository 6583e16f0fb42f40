"""The two-mass fits: bounded least squares on the log of the FRF, each point weighted by its
variance, with what the log adds (the controller's hold, a torque–position delay); arm Coulomb
friction and a third mass kept only when an F-test on the weighted residuals supports them
(the third mass's many fits by the numba trust region of ``bounded``, the others by scipy's).

Parameters stay physical by construction, not by clipping: inertias, stiffness and the joint
damper are fitted as logarithms (> 0), the arm's viscous friction and Coulomb friction with a
lower bound of 0, a pair's coupled inertia as ρ·√(Ja1·Ja2) with |ρ| < 1 (the arm inertia matrix
positive definite), the delay within ±0.15 period of the highest frequency.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import numpy as np

from robid_link.exceptions import EstimationError
from robid_link.ident.elastic.bounded import fit_logged
from robid_link.ident.elastic.frequency import Frf
from robid_link.ident.elastic.models import (
    LOGGED_PARAMETERS,
    arm_coulomb_frf,
    as_logged,
    coupled_frf,
    logged_with_derivatives,
    motor_and_arm,
)
from robid_link.ident.elastic.results import CoupledElasticity, JointElasticity
from robid_link.ident.elastic.stickslip import arm_stick_slip_frf

__all__ = ["JointElasticity", "CoupledElasticity", "fit_two_mass", "fit_coupled", "arm_swing",
           "f_test", "ALPHA", "MIN_EFFECT", "SIGMA_FLOOR"]

#: significance level of the F-tests that admit arm friction or a third mass into the model
ALPHA = 1e-3
#: the least change of the fitted FRF (|Δ log G| at some point, from the two-mass fit) for which
#: an extension that passes its F-test is kept and named: smaller, it absorbs what the model
#: approximates (a plant integrated in steps, the hold's images, a transient's leftovers)
MIN_EFFECT = 0.01
#: the model's own approximations, relative (added to each point's noise in quadrature): the
#: describing function of stick-slip, the hold's images; a few 1e-4 on clean logs
SIGMA_FLOOR = 5e-4
_NAMES = ("jm", "ja", "k", "d", "ba")


# ----------------------------------------------------------------------------- start values


def _extrema(mag: np.ndarray, kind: str) -> list[int]:
    """Interior local minima/maxima standing out by ≥ 15 % from both neighbours' range."""
    out = []
    for i in range(1, mag.size - 1):
        a, b, c = mag[i - 1], mag[i], mag[i + 1]
        if kind == "min" and b < a and b < c and b < 0.87 * max(a, c):
            out.append(i)
        if kind == "max" and b > a and b > c and b > 1.15 * min(a, c):
            out.append(i)
    return out


def _peak_f(f: np.ndarray, mag: np.ndarray, i: int) -> float:
    """Parabolic interpolation in log-log around point i."""
    x, y = np.log(f[i - 1: i + 2]), np.log(mag[i - 1: i + 2])
    den = y[0] - 2 * y[1] + y[2]
    if den == 0:
        return float(f[i])
    step = 0.5 * (y[0] - y[2]) / den
    return float(np.exp(x[1] + np.clip(step, -1, 1) * (x[2] - x[0]) / 2))


def _start(frf_f: np.ndarray, acc: np.ndarray, joint: int
           ) -> tuple[np.ndarray, tuple[float, float] | None]:
    """Start values (jm, ja, k, d) from the FRF's antiresonance and resonance, and a later
    antiresonance/resonance pair when the points show one (where a third mass would start)."""
    mag = np.abs(acc)
    f_max = float(frf_f[-1])
    mins, maxs = _extrema(mag, "min"), _extrema(mag, "max")
    if not mins:
        if np.argmin(mag) == mag.size - 1 or mag[-1] < mag[0]:
            raise EstimationError(f"joint {joint}: no antiresonance below {f_max:.3g} Hz: "
                                  "extend --f-max")
        raise EstimationError(f"joint {joint}: no antiresonance between {frf_f[0]:.3g} and "
                              f"{f_max:.3g} Hz: lower --f-min or check the log's excitation")
    ia = mins[0]
    after = [i for i in maxs if i > ia]
    if not after:
        raise EstimationError(f"joint {joint}: antiresonance at {frf_f[ia]:.3g} Hz but no "
                              f"resonance below {f_max:.3g} Hz: extend --f-max")
    ir = after[0]
    fa, fr = _peak_f(frf_f, mag, ia), _peak_f(frf_f, mag, ir)
    later = [i for i in mins if i > ir]
    second = None
    if later:
        up = [i for i in maxs if i > later[0]]
        second = (_peak_f(frf_f, mag, later[0]), _peak_f(frf_f, mag, up[0]) if up
                  else 1.3 * float(frf_f[later[0]]))
    near = int(np.sum((frf_f > fa / 1.6) & (frf_f < fr * 1.6)))
    if near < 4:
        raise EstimationError(f"joint {joint}: only {near} steps between {fa / 1.6:.3g} and "
                              f"{fr * 1.6:.3g} Hz around the resonance: raise --steps")
    low = frf_f < 0.5 * fa
    j_tot = float(1.0 / np.median(mag[low])) if low.any() else float(1.0 / mag[0])
    ratio = (fa / fr) ** 2
    jm = j_tot * ratio
    ja = j_tot - jm
    k = ja * (2 * math.pi * fa) ** 2
    d = 2 * 0.05 * math.sqrt(k * ja)
    return np.array([jm, ja, k, d]), second


# ----------------------------------------------------------------------------- solver


@dataclass(frozen=True)
class _Par:
    """A fitted parameter within [lo, hi]; positive ones as logarithms (lo ≥ 0)."""

    name: str
    start: float
    log: bool = True
    lo: float = -math.inf
    hi: float = math.inf
    scale: float = 1.0  # of a linear one: the solver sees value/scale, O(1) like the logs

    def bounds(self) -> tuple[float, float]:
        if not self.log:
            return self.lo / self.scale, self.hi / self.scale
        return (math.log(self.lo) if self.lo > 0 else -math.inf,
                math.log(self.hi) if math.isfinite(self.hi) else math.inf)

    def x0(self) -> float:
        lo, hi = self.bounds()
        return min(max(math.log(self.start) if self.log else self.start / self.scale, lo), hi)

    def value(self, x: float) -> float:
        return math.exp(x) if self.log else x * self.scale


@dataclass
class _Fit:
    values: dict[str, float]
    std: dict[str, float]
    rss: float
    n: int  # residuals
    x: np.ndarray
    cov: np.ndarray
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def k(self) -> int:
        return self.x.size

    @property
    def chi2(self) -> float:
        return self.rss / max(self.n - self.k, 1)


def _lsq(pars: Sequence[_Par], resid: Callable[[dict[str, float]], np.ndarray],
         max_nfev: int | None = None, diff_step: float | None = None, what: str = "",
         jac: Callable[[dict[str, float]], np.ndarray] | None = None) -> _Fit:
    """Bounded least squares (trust region reflective) in the parametrisation of ``pars``;
    the covariance from the Jacobian scaled by the residual variance. ``jac``: the residuals'
    derivatives by each parameter's value (columns in the order of ``pars``; else finite
    differences). ``what``: the joint(s) an error names."""
    from scipy.optimize import least_squares

    def values(x: np.ndarray) -> dict[str, float]:
        return {p.name: float(p.value(v)) for p, v in zip(pars, x, strict=True)}

    def jac_x(x: np.ndarray) -> np.ndarray:  # by the solver's x: log values, scaled ones
        v = values(x)
        assert jac is not None
        return jac(v) * np.array([v[p.name] if p.log else p.scale for p in pars])

    lo, hi = np.array([p.bounds() for p in pars]).T
    x0 = np.array([p.x0() for p in pars])
    # the parametrisation is O(1) already (logarithms, scaled linear ones); the Jacobian's
    # scaling instead kept a parameter that starts on its bound (Ba = 0) from leaving it
    res = least_squares(lambda x: resid(values(x)), x0, bounds=(lo, hi), method="trf",
                        max_nfev=max_nfev, diff_step=diff_step,
                        jac="2-point" if jac is None else jac_x)
    return _fit_at(pars, res.x, res.fun, res.jac, what)


def _fit_at(pars: Sequence[_Par], x: np.ndarray, fun: np.ndarray, jac: np.ndarray,
            what: str) -> _Fit:
    """The fit at the solver's x: the covariance from the Jacobian by x and the residuals."""
    rss = float(fun @ fun)
    n = fun.size
    try:
        cov = np.linalg.inv(jac.T @ jac) * rss / max(n - x.size, 1)
    except np.linalg.LinAlgError as err:
        raise EstimationError(f"{what + ': ' if what else ''}elasticity fit: singular "
                              "Jacobian (too few or too noisy FRF points)") from err
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    vals = {p.name: float(p.value(v)) for p, v in zip(pars, x, strict=True)}
    std = {p.name: float(vals[p.name] * s if p.log else s * p.scale)
           for p, s in zip(pars, sd, strict=True)}
    return _Fit(vals, std, rss, n, x, cov)


def f_test(small: _Fit, big: _Fit) -> tuple[float, float]:
    """F statistic and p-value of the extended fit ``big`` against the nested ``small``."""
    from scipy.special import betainc  # F's tail by its incomplete beta: no scipy.stats import

    extra = big.k - small.k
    dof = max(big.n - big.k, 1)
    if big.rss >= small.rss or extra <= 0:
        return 0.0, 1.0
    stat = (small.rss - big.rss) / extra / (big.rss / dof)
    return float(stat), float(betainc(0.5 * dof, 0.5 * extra, dof / (dof + extra * stat)))


def _sigma_log(frf: Frf) -> np.ndarray:
    """Standard deviation of the real and of the imaginary part of log ĝ per point (per
    entry for a pair): from the point's variance, else from its snr and coherence; with the
    model's floor in quadrature."""
    g = frf.g
    if frf.g_var is not None:
        s2 = np.asarray(frf.g_var, dtype=float) / (2 * np.maximum(np.abs(g) ** 2, 1e-300))
    else:
        coh = np.clip(frf.coherence, 1e-6, 1.0)
        s2 = 0.5 / np.maximum(frf.snr, 1.0) ** 2 + (1 - coh) / (20 * coh)
        if g.ndim == 3:
            s2 = np.broadcast_to(s2[:, None, None], g.shape)
    return np.sqrt(s2 + SIGMA_FLOOR ** 2)


def _logres(model: np.ndarray, meas: np.ndarray, sig: np.ndarray) -> np.ndarray:
    r = np.log(model / meas) / sig
    return np.concatenate((r.real.ravel(), r.imag.ravel()))


def _delay_bound(frf: Frf) -> float:
    return 0.15 / float(frf.f_hz[-1])


# ----------------------------------------------------------------------------- one joint


def _siso_pars(start: dict[str, float], frf: Frf, *, fc: bool = False,
               third: bool = False) -> list[_Par]:
    tau = _delay_bound(frf)
    pars = [_Par(n, start[n], lo=1e-3 * start[n], hi=1e3 * start[n])
            for n in ("jm", "ja", "k", "d")]
    pars += [_Par("ba", max(start.get("ba", 0.0), 0.0), log=False, lo=0.0,
                  scale=start["d"]),
             _Par("delay_s", start.get("delay_s", 0.0), log=False, lo=-tau, hi=tau,
                  scale=tau / 10)]
    if fc:
        pars.append(_Par("fc", max(start["fc"], 0.0), log=False, lo=0.0,
                         scale=float(np.median(frf.tau_amp)) if frf.tau_amp is not None
                         else 1.0))
    if third:  # its own frequency on a held arm inside the band's reach, damping ratio ≤ 1
        f = frf.f_hz
        pars += [_Par("j3", start["j3"], lo=1e-3 * start["ja"], hi=10 * start["ja"]),
                 _Par("f3", start["f3"], lo=0.5 * float(f[0]), hi=3 * float(f[-1])),
                 _Par("z3", start["z3"], lo=1e-3, hi=1.0)]
    return pars


def _third(v: dict[str, float]) -> tuple[float, float, float] | None:
    """(j3, k3, d3) from the fitted j3, f3 (√(k3/j3)/2π) and z3 (damping ratio)."""
    if "j3" not in v:
        return None
    k3 = v["j3"] * (2 * math.pi * v["f3"]) ** 2
    return v["j3"], k3, 2 * v["z3"] * math.sqrt(k3 * v["j3"])


def _siso_model(frf: Frf, v: dict[str, float], kg: float, hold: float,
                warm: dict[str, np.ndarray] | None = None, friction: str = "stick-slip"
                ) -> np.ndarray:
    """The FRF as logged; arm friction ``friction``: ``stick-slip`` integrated under the
    logged motor motion (two masses only) or ``df``, its describing function."""
    f = frf.f_hz
    third = _third(v)
    if "fc" in v:
        assert frf.tau_amp is not None and frf.drift is not None
        if third is None and friction == "stick-slip":
            qm = (frf.qm_harmonics if frf.qm_harmonics is not None
                  else np.abs(frf.g) * frf.tau_amp)
            g = arm_stick_slip_frf(f, v["jm"], v["ja"], v["k"], v["d"], v["ba"], kg,
                                   v["fc"], qm, frf.drift, warm)
        else:
            g = arm_coulomb_frf(f, v["jm"], v["ja"], v["k"], v["d"], v["ba"], kg, v["fc"],
                                frf.tau_amp, frf.drift, third)
    else:
        g = motor_and_arm(f, v["jm"], v["ja"], v["k"], v["d"], v["ba"], kg, third)[0]
    return as_logged(f, g, v["jm"], delay_s=v["delay_s"], hold_s=hold)


def _fit_siso(frf: Frf, start: dict[str, float], kg: float, hold: float, sig: np.ndarray,
              *, fc: bool = False, third: bool = False, friction: str = "stick-slip",
              max_nfev: int = 200) -> _Fit:
    friction = "df" if third else friction  # the stick-slip kernel has two masses
    warm: dict[str, np.ndarray] = {}
    pars = _siso_pars(start, frf, fc=fc, third=third)
    if not fc:  # the Jacobian's columns are the parameters'
        assert tuple(p.name for p in pars) == LOGGED_PARAMETERS[:len(pars)]
    if third and not fc:  # the extension's many fits: by ``bounded`` (numba), max_nfev steps
        lo, hi = np.array([p.bounds() for p in pars]).T
        x, fun, jac_x, _ = fit_logged(2 * np.pi * frf.f_hz, frf.g, sig, kg, hold,
                                      np.array([p.x0() for p in pars]), lo, hi,
                                      np.array([p.log for p in pars]),
                                      np.array([p.scale for p in pars]), max_nfev)
        fit = _fit_at(pars, x, fun, jac_x, f"joint {frf.joints[0]}")
        fit.extra.update(hold_s=hold, friction=None)
        return fit
    last: dict[tuple[float, ...], tuple[np.ndarray, np.ndarray]] = {}

    def linear(v: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
        """The linear model and its derivatives, once per point (residual, then Jacobian)."""
        key = tuple(v.values())
        if key not in last:
            last.clear()
            last[key] = logged_with_derivatives(
                frf.f_hz, v["jm"], v["ja"], v["k"], v["d"], v["ba"], kg,
                (v["f3"], v["z3"], v["j3"]) if third else None, delay_s=v["delay_s"],
                hold_s=hold)
        return last[key]

    def resid(v: dict[str, float]) -> np.ndarray:
        model = (linear(v)[0] if not fc else _siso_model(frf, v, kg, hold, warm, friction))
        return _logres(model, frf.g, sig)

    def jac(v: dict[str, float]) -> np.ndarray:  # the linear model's, analytic
        cols = linear(v)[1] / sig[:, None]
        return np.concatenate((cols.real, cols.imag))

    # an extension the data do not need is ill-determined: its fit only has to show that
    fit = _lsq(pars, resid, max_nfev=max_nfev if fc or third else None,
               diff_step=1e-4 if fc and friction == "stick-slip" else None,  # integrated
               what=f"joint {frf.joints[0]}", jac=None if fc else jac)
    fit.extra.update(hold_s=hold, friction=friction if fc else None)
    return fit


def fit_two_mass(frf: Frf, notes: list[str] | None = None, kg: float = 0.0
                 ) -> JointElasticity:
    """Two-mass fit of one joint's FRF; ``kg`` the arm's known gravity stiffness at the pose.

    The log's hold (a controller at the log's rate) or none, whichever fits better, and the
    torque–position delay are fitted with the plant. Then two extensions, each kept only when
    an F-test on the weighted residuals says the data need it (p < ``ALPHA``), with a note
    giving F and p: Coulomb friction on the arm (its describing function at each step's
    amplitude and drift; only where the arm's sine can outrun the drift) and a third mass on
    the arm (a second resonance inside the measured band)."""
    notes = notes if notes is not None else []
    joint = frf.joints[0]
    if frf.f_hz.size < 6:
        raise EstimationError(f"joint {joint}: {frf.f_hz.size} FRF points, need at least 6: "
                              "raise --steps")
    x0, second = _start(frf.f_hz, frf.accel, joint)
    sig = _sigma_log(frf)
    start = dict(zip(("jm", "ja", "k", "d"), map(float, x0), strict=True))
    holds = [0.0] + ([1.0 / frf.rate_hz] if frf.rate_hz else [])
    fits = [_fit_siso(frf, start, kg, h, sig) for h in holds]
    best = min(fits, key=lambda fit: fit.rss)
    hold = best.extra["hold_s"]
    tests: dict[str, dict[str, Any]] = {}
    if frf.tau_amp is not None and frf.drift is not None:
        best = _try_arm_coulomb(frf, best, kg, hold, sig, tests, notes)
    best = _try_third_mass(frf, best, kg, hold, sig, second, tests, notes)
    if "fc" in best.values or "j3" in best.values:  # the hold was chosen on the two masses
        for other in holds:
            if other != hold:
                fit = _fit_siso(frf, best.values, kg, other, sig, fc="fc" in best.values,
                                third="j3" in best.values, max_nfev=2000,
                                friction=best.extra["friction"] or "stick-slip")
                best = fit if fit.rss < best.rss else best
    return _joint(joint, frf, best, kg, sig, tests)


def _joint(joint: int, frf: Frf, fit: _Fit, kg: float, sig: np.ndarray,
           tests: dict[str, dict[str, Any]]) -> JointElasticity:
    v = fit.values
    model = _siso_model(frf, v, kg, fit.extra["hold_s"], friction=fit.extra["friction"])
    rms = float(np.sqrt(np.mean(np.abs(np.log(model / frf.g)) ** 2)))
    third = _third(v)
    return JointElasticity(joint, v["jm"], v["ja"], v["k"], v["d"], std=dict(fit.std),
                           fit_rms=rms, ba=v["ba"], kg=float(kg), fc=v.get("fc"),
                           delay_s=v["delay_s"], hold_s=float(fit.extra["hold_s"]),
                           third=third, chi2=fit.chi2, tests=tests)


def arm_swing(frf: Frf, p: JointElasticity | dict[str, float]) -> np.ndarray:
    """Per FRF point the arm's sine velocity amplitude over the step's drift, by the fitted
    linear model (above 1 the arm reverses and its Coulomb friction acts at the step's
    frequency)."""
    assert frf.tau_amp is not None and frf.drift is not None
    if isinstance(p, JointElasticity):
        arm = motor_and_arm(frf.f_hz, p.jm, p.ja, p.k, p.d, p.ba, p.kg, p.third)[1]
    else:
        arm = motor_and_arm(frf.f_hz, p["jm"], p["ja"], p["k"], p["d"], p["ba"],
                            p.get("kg", 0.0), _third(p))[1]
    return (2 * np.pi * frf.f_hz * np.abs(arm) * frf.tau_amp
            / np.maximum(np.abs(frf.drift), 1e-12))


def _try_arm_coulomb(frf: Frf, base: _Fit, kg: float, hold: float, sig: np.ndarray,
                     tests: dict[str, dict[str, Any]], notes: list[str]) -> _Fit:
    """The arm's Coulomb friction, where the linear fit says the arm's sine outruns the drift
    at some step (elsewhere it is a constant torque, invisible at the step's frequency),
    kept when the F-test supports it. Screened by the describing function (cheap); where it
    may matter, fitted with the arm's stick-slip integrated under the logged motor motion."""
    assert frf.tau_amp is not None
    swing = arm_swing(frf, {**base.values, "kg": kg})
    if not np.any(swing > 1.0):
        return base
    start = {**base.values, "fc": 0.1 * float(np.median(frf.tau_amp))}
    try:
        best = _fit_siso(frf, start, kg, hold, sig, fc=True, friction="df")
    except EstimationError:
        return base
    stat, p = f_test(base, best)
    if p < 100 * ALPHA and frf.qm_harmonics is not None:
        try:
            best = _fit_siso(frf, best.values, kg, hold, sig, fc=True)
            stat, p = f_test(base, best)
        except EstimationError:
            pass
    effect = _effect(frf, best, base, kg)
    kept = p < ALPHA and effect > MIN_EFFECT
    tests["arm_coulomb"] = {"F": stat, "p": p, "df": [best.k - base.k, best.n - best.k],
                            "effect": effect, "model": best.extra["friction"],
                            "kept": bool(kept)}
    if not kept:
        return base
    worst = int(np.argmax(swing))
    v = best.values
    how = ("its stick-slip under the logged motor motion" if best.extra["friction"] ==
           "stick-slip" else "its describing function")
    notes.append(f"joint {frf.joints[0]}: Coulomb friction on the arm, {v['fc']:.3g} ± "
                 f"{best.std['fc']:.2g} N·m: the arm's sine outruns the drift at "
                 f"{int(np.sum(swing > 1))} of {swing.size} steps (×{swing[worst]:.2g} at "
                 f"{frf.f_hz[worst]:.3g} Hz), where its friction reverses; {how} fits "
                 f"better than the linear model (F = {stat:.3g}, p = {p:.2g}) and is in the "
                 "fit (a faster drift or a smaller sine keeps it out)")
    return best


def _effect(frf: Frf, ext: _Fit, base: _Fit, kg: float) -> float:
    """How much the extended fit moves the fitted FRF at the measured points from the base
    fit (largest |Δ log G|): below ``MIN_EFFECT`` it only absorbs what the model approximates
    (a plant integrated in discrete steps, the hold's images, a transient's leftovers)."""
    a = _siso_model(frf, ext.values, kg, ext.extra["hold_s"], friction=ext.extra["friction"])
    b = _siso_model(frf, base.values, kg, base.extra["hold_s"])
    return float(np.max(np.abs(np.log(a / b))))


def _second_mode_hz(v: dict[str, float], kg: float) -> tuple[float, float]:
    """The undamped modes of motor – arm – third mass: (first, second) resonance in Hz."""
    j3, k3, _ = _third(v) or (0.0, 0.0, 0.0)
    m = np.diag([v["jm"], v["ja"], j3])
    k = v["k"]
    stiff = np.array([[k, -k, 0.0], [-k, k + k3 + kg, -k3], [0.0, -k3, k3]])
    lam = np.sort(np.linalg.eigvals(np.linalg.solve(m, stiff)).real)
    w = np.sqrt(np.maximum(lam[-2:], 0.0))
    return float(w[0] / (2 * math.pi)), float(w[1] / (2 * math.pi))


def _try_third_mass(frf: Frf, base: _Fit, kg: float, hold: float, sig: np.ndarray,
                    second: tuple[float, float] | None, tests: dict[str, dict[str, Any]],
                    notes: list[str]) -> _Fit:
    """A third mass on the arm (a second resonance), started from the second antiresonance
    the points show or from a few frequencies above the first resonance; kept when the
    F-test supports it and its second resonance lies inside the measured band."""
    v = base.values
    if "fc" in v:  # the stick-slip kernel has two masses, the describing function is off
        tests["third_mass"] = {"skipped": "arm friction in the model", "kept": False}
        return base
    f_res = math.sqrt(v["k"] * (v["jm"] + v["ja"]) / (v["jm"] * v["ja"])) / (2 * math.pi)
    f_top = float(frf.f_hz[-1])
    if f_top < 1.3 * f_res or frf.f_hz.size < base.k + 6:
        return base
    # started at the second antiresonance the points show, else where the two-mass fit
    # misses most above the resonance
    if second:
        f2 = second[0]
    else:
        miss = np.abs(np.log(_siso_model(frf, v, kg, hold) / frf.g)) / sig
        above = np.flatnonzero(frf.f_hz > 1.2 * f_res)
        f2 = float(frf.f_hz[above[np.argmax(miss[above])]]) if above.size else 0.9 * f_top
    best = None
    for f_start in dict.fromkeys((f2, min(1.5 * f2, f_top))):  # f2 may be the band's top
        for share in (0.2, 0.5):
            j3 = share * v["ja"]
            start = {**v, "ja": v["ja"] - j3, "j3": j3, "f3": f_start, "z3": 0.05}
            try:  # a short look from each start, then the best one to the end
                fit = _fit_siso(frf, start, kg, hold, sig, third=True, max_nfev=40)
            except EstimationError:
                continue
            if best is None or fit.rss < best.rss:
                best = fit
    if best is None:
        return base
    try:
        best = _fit_siso(frf, best.values, kg, hold, sig, third=True, max_nfev=2000)
    except EstimationError:
        return base
    stat, p = f_test(base, best)
    f2 = _second_mode_hz(best.values, kg)[1]
    effect = _effect(frf, best, base, kg)
    # a mode of its own: apart from the first resonance (a tiny mass tuned to it only
    # reshapes the resonance a transient left in the points) and inside the band
    kept = p < ALPHA and effect > MIN_EFFECT and 1.25 * f_res < f2 < 1.05 * f_top
    tests["third_mass"] = {"F": stat, "p": p, "df": [best.k - base.k, best.n - best.k],
                           "f_hz": f2, "effect": effect, "kept": bool(kept)}
    if not kept:
        return base
    b = best.values
    k3 = (_third(b) or (0.0, 0.0, 0.0))[1]
    notes.append(f"joint {frf.joints[0]}: a second resonance near {f2:.3g} Hz: a three-mass "
                 f"model (a third mass {b['j3']:.3g} on {k3:.4g} N·m/rad behind the arm) "
                 f"fits better than the two-mass model (F = {stat:.3g}, p = {p:.2g}); the "
                 "parameters are the three-mass fit's")
    return best


# ----------------------------------------------------------------------------- a pair


def fit_coupled(frf: Frf, notes: list[str] | None = None, kg: np.ndarray | None = None
                ) -> tuple[list[JointElasticity], CoupledElasticity]:
    """Coupled fit of a pair's 2×2 FRF: Jm, Ja, K, D, Ba and the torque delay per axis and
    the coupled inertia Jcop = ρ·√(Ja1·Ja2) (|ρ| < 1); ``kg`` the arms' known 2×2 gravity
    stiffness at the pose. The log's hold or none, whichever fits better."""
    notes = notes if notes is not None else []
    j1, j2 = frf.joints
    singles = []
    for i, j in enumerate((j1, j2)):
        sub = Frf((j,), frf.f_hz, frf.g[:, i, i], frf.coherence, frf.snr, frf.source)
        singles.append(_start(sub.f_hz, sub.accel, j)[0])
    # Jcop from the low-frequency inertia matrix: (s² G)⁻¹ → Jm + Ja (2×2)
    low = frf.f_hz < 0.5 * frf.f_hz[np.argmin(np.abs(frf.accel[:, 0, 0]))]
    inert = np.linalg.inv(frf.accel[low if low.any() else slice(0, 1)]).real.mean(axis=0)
    rho0 = 0.5 * (inert[0, 1] + inert[1, 0]) / math.sqrt(singles[0][1] * singles[1][1])
    tau = _delay_bound(frf)
    pars: list[_Par] = []
    for i, s in enumerate(singles, 1):
        pars += [_Par(f"{n}{i}", float(x), lo=1e-3 * float(x), hi=1e3 * float(x))
                 for n, x in zip(("jm", "ja", "k", "d"), s, strict=True)]
        pars += [_Par(f"ba{i}", 0.0, log=False, lo=0.0, scale=float(s[3])),
                 _Par(f"delay_s{i}", 0.0, log=False, lo=-tau, hi=tau, scale=tau / 10)]
    pars.append(_Par("rho", float(np.clip(rho0, -0.9, 0.9)), log=False, lo=-0.999, hi=0.999))
    sig = _sigma_log(frf)
    g = frf.g
    norm = np.sqrt(np.abs(g[:, 0, 0] * g[:, 1, 1]))
    # the off-diagonal terms cross zero: no logarithm, relative to the diagonal's scale
    sig_off = [sig[:, i, 1 - i] if frf.g_var is None else
               np.sqrt(frf.g_var[:, i, 1 - i] / (2 * norm ** 2) + SIGMA_FLOOR ** 2)
               for i in range(2)]
    kgm = np.zeros((2, 2)) if kg is None else np.asarray(kg, dtype=float)

    def model(v: dict[str, float], hold: float) -> np.ndarray:
        jcop = v["rho"] * math.sqrt(v["ja1"] * v["ja2"])
        gm = coupled_frf(frf.f_hz, (v["jm1"], v["jm2"]), (v["ja1"], v["ja2"]), jcop,
                         (v["k1"], v["k2"]), (v["d1"], v["d2"]), (v["ba1"], v["ba2"]), kgm)
        return as_logged(frf.f_hz, gm, (v["jm1"], v["jm2"]),
                         delay_s=(v["delay_s1"], v["delay_s2"]), hold_s=hold)

    def resid(v: dict[str, float], hold: float) -> np.ndarray:
        m = model(v, hold)
        diag = [_logres(m[:, i, i], g[:, i, i], sig[:, i, i]) for i in range(2)]
        off = [(m[:, i, 1 - i] - g[:, i, 1 - i]) / norm / sig_off[i] for i in range(2)]
        return np.concatenate(diag + [np.concatenate((o.real, o.imag)) for o in off])

    holds = [0.0] + ([1.0 / frf.rate_hz] if frf.rate_hz else [])
    fits = []
    for hold in holds:
        fit = _lsq(pars, partial(resid, hold=hold), what=f"joints {j1},{j2}")
        fit.extra["hold_s"] = hold
        fits.append(fit)
    fit = min(fits, key=lambda x: x.rss)
    v, hold = fit.values, fit.extra["hold_s"]
    jcop = v["rho"] * math.sqrt(v["ja1"] * v["ja2"])
    # its standard error through ρ and the two arm inertias (log-parametrised)
    names = [p.name for p in pars]
    grad = np.zeros(len(names))
    grad[names.index("ja1")] = grad[names.index("ja2")] = 0.5 * jcop
    grad[names.index("rho")] = math.sqrt(v["ja1"] * v["ja2"])
    jcop_sd = float(math.sqrt(max(grad @ fit.cov @ grad, 0.0)))
    m = model(v, hold)
    rms = float(np.sqrt(np.mean(np.abs(np.log(m[:, [0, 1], [0, 1]] / g[:, [0, 1], [0, 1]]))
                                ** 2)))
    joints = []
    for i, j in enumerate((j1, j2), 1):
        std = {n: fit.std[f"{n}{i}"] for n in (*_NAMES, "delay_s")}
        joints.append(JointElasticity(j, v[f"jm{i}"], v[f"ja{i}"], v[f"k{i}"], v[f"d{i}"],
                                      std=std, fit_rms=rms, ba=v[f"ba{i}"],
                                      kg=float(kgm[i - 1, i - 1]), delay_s=v[f"delay_s{i}"],
                                      hold_s=float(hold), chi2=fit.chi2))
    kgt = tuple(tuple(map(float, r)) for r in kgm)
    return joints, CoupledElasticity((j1, j2), jcop, {"jcop": jcop_sd}, rms,
                                     kgt)  # type: ignore[arg-type]
