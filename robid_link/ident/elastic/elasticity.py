"""Joint elasticity from frequency responses: the two-mass fit per joint and the coupled fit of a
pair of axes (H11, H12, H21, H22 with the coupled inertia Jcop), results, summary and figures.

Model (motor side measured): Jm·q̈m + D(q̇m − q̇a) + K(qm − qa) = τ,
Ja·q̈a + Jcop·q̈a2 + Ba·q̇a + D(q̇a − q̇m) + K(qa − qm) = 0 (Ba: the joint's viscous
friction on the arm side; without it the fit loads it onto D). Fitted by weighted least
squares on the log-magnitude and phase of the complex FRF (log Ĝ − log G), started from the
antiresonance and resonance read off the measured points.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from robid_link.exceptions import DataError, EstimationError, RobidError
from robid_link.ident.data.logs import Log
from robid_link.ident.elastic.frequency import Frf, frf_from_log, frf_from_schedule, log_schedule
from robid_link.ident.model.robot import Robot

__all__ = ["two_mass_frf", "coupled_frf", "gravity_stiffness", "JointElasticity",
           "CoupledElasticity", "ElasticityResult", "fit_two_mass", "fit_coupled",
           "identify_elasticity", "elasticity_figures", "bode_cells"]

_T = TypeVar("_T")
_NAMES = ("jm", "ja", "k", "d", "ba")


def two_mass_frf(f_hz: np.ndarray, jm: float, ja: float, k: float, d: float, ba: float = 0.0,
                 kg: float = 0.0) -> np.ndarray:
    """G = qm/τ = (A + Z) / (Jm s² (A + Z) + Z A), arm A = Ja s² + Ba s + Kg, spring
    Z = D s + K; Kg the gravity stiffness ∂g/∂q of the arm at the pose (known from the rigid
    model). Ba = Kg = 0: (Ja s² + Z) / (s² (Jm Ja s² + (Jm + Ja) Z))."""
    s = 2j * np.pi * np.asarray(f_hz)
    z = d * s + k
    arm = ja * s * s + ba * s + kg
    return (arm + z) / (jm * s * s * (arm + z) + z * arm)


def _motor_and_arm(f: np.ndarray, jm: float, ja: float, k: float, d: float, ba: float,
                   kg: float) -> tuple[np.ndarray, np.ndarray]:
    """The two-mass model's motor and arm positions over the motor torque: (qm/τ, qa/τ)."""
    s = 2j * np.pi * f
    z = d * s + k
    g = two_mass_frf(f, jm, ja, k, d, ba, kg)
    return g, g * z / (ja * s * s + ba * s + kg + z)


def arm_coulomb_frf(f_hz: np.ndarray, jm: float, ja: float, k: float, d: float, ba: float,
                    kg: float, fc: float, tau_amp: np.ndarray, drift: np.ndarray
                    ) -> np.ndarray:
    """G with Coulomb friction ``fc`` on the arm, as its describing function at each step's
    torque amplitude and drift: the arm's velocity v0 + V sin ωt reverses when V > |v0|, and
    fc·sign(v) then has the fundamental (4 fc/π)·√(1 − (v0/V)²) in phase with the velocity:
    a damper c = (4 fc/(π V))·√(1 − (v0/V)²) on the arm, zero while the drift keeps it one-
    signed. V = ω·|qa/τ|·|T| depends on c: solved per step by bisection (c = c(V(c)))."""
    f = np.asarray(f_hz, dtype=float)
    w = 2 * np.pi * f
    v0 = np.maximum(np.abs(np.asarray(drift, dtype=float)), 1e-9)
    amp = np.asarray(tau_amp, dtype=float)

    def gap(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        g, arm = _motor_and_arm(f, jm, ja, k, d, ba + c, kg)
        v = w * np.abs(arm) * amp
        r = np.clip(v0 / np.maximum(v, 1e-300), 0.0, 1.0)
        return 4 * fc / np.pi * np.sqrt(1.0 - r * r) / np.maximum(v, 1e-300) - c, g

    # c(V) peaks at 2 fc/(π v0) (where V = √2 v0): the root lies below
    lo, hi = np.zeros_like(f), 2 * max(fc, 0.0) / (np.pi * v0) * 1.001 + 1e-12
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        up = gap(mid)[0] > 0
        lo, hi = np.where(up, mid, lo), np.where(up, hi, mid)
    return gap(0.5 * (lo + hi))[1]


def coupled_frf(f_hz: np.ndarray, jm: Sequence[float], ja: Sequence[float], jcop: float,
                k: Sequence[float], d: Sequence[float], ba: Sequence[float] = (0.0, 0.0),
                kg: np.ndarray | None = None) -> np.ndarray:
    """2×2 G (K, 2, 2): [Jm s² + Z − Z (A + Z)⁻¹ Z]⁻¹, A = [[Ja1, Jcop], [Jcop, Ja2]] s²
    + diag(Ba) s + Kg (2×2 gravity stiffness), Z = diag(D s + K)."""
    s = 2j * np.pi * np.asarray(f_hz)[:, None, None]
    eye = np.eye(2)
    z = (np.asarray(d)[None, :] * s[:, :, 0] + np.asarray(k)[None, :])[:, :, None] * eye
    jam = np.array([[ja[0], jcop], [jcop, ja[1]]])
    kgm = np.zeros((2, 2)) if kg is None else np.asarray(kg, dtype=float)
    arm = np.linalg.solve(jam * s * s + np.asarray(ba) * eye * s + kgm + z, z)
    dyn = np.asarray(jm)[:, None] * eye * s * s + z - z @ arm
    return np.linalg.inv(dyn)


@dataclass(frozen=True)
class JointElasticity:
    """Two-mass parameters of one joint (units of the log's side)."""

    joint: int
    jm: float
    ja: float
    k: float
    d: float
    std: dict[str, float]
    fit_rms: float  # RMS of the weighted log-FRF residual (≈ relative error)
    measures: str | None = None  # the campaign entry that measures it (set by the daemon)
    ba: float = 0.0  # viscous friction on the arm side (N·m·s/rad)
    kg: float = 0.0  # gravity stiffness of the arm at the pose (known, not fitted)
    fc: float | None = None  # Coulomb friction on the arm side (N·m); None: not fitted

    @property
    def f_res_hz(self) -> float:
        return math.sqrt(self.k * (self.jm + self.ja) / (self.jm * self.ja)) / (2 * math.pi)

    @property
    def f_antires_hz(self) -> float:
        return math.sqrt(self.k / self.ja) / (2 * math.pi)

    def as_dict(self) -> dict[str, Any]:
        return {"joint": self.joint, "jm": self.jm, "ja": self.ja, "k": self.k, "d": self.d,
                "ba": self.ba, "fc_arm": self.fc, "kg": self.kg, "f_res_hz": self.f_res_hz,
                "f_antires_hz": self.f_antires_hz,
                "std": dict(self.std), "fit_rms": self.fit_rms, "measures": self.measures}


@dataclass(frozen=True)
class CoupledElasticity:
    joints: tuple[int, int]
    jcop: float
    std: dict[str, float]
    fit_rms: float
    kg: tuple[tuple[float, float], tuple[float, float]] = ((0.0, 0.0), (0.0, 0.0))

    def as_dict(self) -> dict[str, Any]:
        return {"joints": list(self.joints), "jcop": self.jcop, "std": dict(self.std),
                "fit_rms": self.fit_rms}


@dataclass
class ElasticityResult:
    """What ``robid elasticity`` reports; keeps the FRFs it was fitted on (for the figures)."""

    robot: str
    joints: list[JointElasticity]
    frfs: list[Frf]
    coupled: CoupledElasticity | None = None
    side: str = "joint"
    notes: list[str] = field(default_factory=list)
    data_files: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        doc: dict[str, Any] = {"robot": self.robot, "side": self.side,
                               "joints": [j.as_dict() for j in self.joints],
                               "notes": list(self.notes), "data_files": list(self.data_files)}
        if self.coupled is not None:
            doc["coupled"] = self.coupled.as_dict()
        return doc

    def summary(self) -> str:
        unit = "kg·m²" if self.side == "joint" else "kg·m² (motor side)"
        lines = [f"Elasticity of {self.robot} ({len(self.joints)} joint(s), inertias in {unit}, "
                 "K in N·m/rad, D in N·m·s/rad)",
                 f"  {'joint':>5} {'Jm':>10} {'Ja':>10} {'K':>11} {'D':>9} {'f_res Hz':>9} "
                 f"{'f_anti Hz':>9} {'Ba':>8} {'fit rms':>8}"]
        for j in self.joints:
            lines.append(f"  {j.joint:>5} {j.jm:>10.4g} {j.ja:>10.4g} {j.k:>11.5g} {j.d:>9.4g} "
                         f"{j.f_res_hz:>9.4g} {j.f_antires_hz:>9.4g} {j.ba:>8.3g} "
                         f"{j.fit_rms:>8.3g}")
            lines.append(f"  {'±':>5} {j.std['jm']:>10.2g} {j.std['ja']:>10.2g} "
                         f"{j.std['k']:>11.2g} {j.std['d']:>9.2g} {'':>9} {'':>9} "
                         f"{j.std['ba']:>8.2g}")
        if self.coupled is not None:
            c = self.coupled
            lines.append(f"  coupled {c.joints[0]}–{c.joints[1]}: Jcop {c.jcop:.4g} "
                         f"± {c.std['jcop']:.2g}, fit rms {c.fit_rms:.3g}")
        lines += [f"  [{i}] {n}" for i, n in enumerate(self.notes, 1)]
        return "\n".join(lines)


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


def _start_and_band(frf_f: np.ndarray, acc: np.ndarray, joint: int, notes: list[str]
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Start values (jm, ja, k, d) from the FRF's antiresonance and resonance, and the mask of
    points to fit (below a second resonance, which is flagged)."""
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
    band = np.ones(frf_f.size, dtype=bool)
    later = [i for i in mins if i > ir]
    if later:
        second = [i for i in maxs if i > later[0]]
        f2 = _peak_f(frf_f, mag, second[0]) if second else None
        band = frf_f < frf_f[later[0]]
        if f2 is not None:
            notes.append(f"joint {joint}: a second resonance at {f2:.3g} Hz (antiresonance near "
                         f"{frf_f[later[0]]:.3g} Hz): a three-mass model is needed; the two-mass "
                         f"fit uses the points below {frf_f[later[0]]:.3g} Hz")
    fa, fr = _peak_f(frf_f, mag, ia), _peak_f(frf_f, mag, ir)
    near = int(np.sum((frf_f > fa / 1.6) & (frf_f < fr * 1.6) & band))
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
    return np.array([jm, ja, k, d, 0.0]), band


# ----------------------------------------------------------------------------- fits


def _weights(frf: Frf) -> np.ndarray:
    """Per-point weight: coherence over the relative noise (1/snr), capped so that a few
    very clean points do not carry the fit."""
    rel = 1.0 / np.maximum(frf.snr, 1.0)
    w = np.sqrt(np.clip(frf.coherence, 0.0, 1.0)) / np.sqrt(rel**2 + 0.01**2)
    return w / np.median(w)


def _logres(model: np.ndarray, meas: np.ndarray) -> np.ndarray:
    r = np.log(model / meas)
    return np.concatenate((r.real.ravel(), r.imag.ravel()))


def _solve(fun: Any, x0: np.ndarray, names: Sequence[str], log_scale: Sequence[bool],
           what: str) -> tuple[np.ndarray, dict[str, float], float]:
    from scipy.optimize import least_squares

    res = least_squares(fun, x0, method="lm", x_scale="jac")
    dof = max(res.fun.size - x0.size, 1)
    s2 = float(res.fun @ res.fun) / dof
    try:
        cov = np.linalg.inv(res.jac.T @ res.jac) * s2
    except np.linalg.LinAlgError as err:
        raise EstimationError(f"{what}: elasticity fit: singular Jacobian (too few or too "
                              "noisy FRF points)") from err
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    vals = np.where(log_scale, np.exp(res.x), res.x)
    std = {n: float(v * s if lg else s) for n, v, s, lg in zip(names, vals, sd, log_scale,
                                                              strict=True)}
    return vals, std, math.sqrt(s2)


def fit_two_mass(frf: Frf, notes: list[str] | None = None, kg: float = 0.0
                 ) -> JointElasticity:
    """Two-mass fit of one joint's FRF (weighted LS on log-magnitude and phase); ``kg`` the
    arm's known gravity stiffness at the pose. With the steps' torque amplitudes and drifts
    (stepped sines) and an arm whose sine outruns the drift, the arm's Coulomb friction is
    fitted too (:func:`arm_coulomb_frf`): reversing, it damps amplitude-dependently, which a
    constant D and Ba would absorb wrongly."""
    notes = notes if notes is not None else []
    joint = frf.joints[0]
    if frf.f_hz.size < 6:
        raise EstimationError(f"joint {joint}: {frf.f_hz.size} FRF points, need at least 6: "
                              "raise --steps")
    n_notes = len(notes)
    x0, band = _start_and_band(frf.f_hz, frf.accel, joint, notes)
    flagged = len(notes) > n_notes  # the second resonance stood out in the points already
    while True:
        f, g, w = frf.f_hz[band], frf.g[band], _weights(frf)[band]

        def fun(x: np.ndarray, f: np.ndarray = f, g: np.ndarray = g, w: np.ndarray = w
                ) -> np.ndarray:
            return np.tile(w, 2) * _logres(two_mass_frf(f, *np.exp(x[:4]), x[4], kg), g)

        vals, std, rms = _solve(fun, np.r_[np.log(x0[:4]), x0[4]], _NAMES,
                                [True] * 4 + [False], f"joint {joint}")
        p = JointElasticity(joint, *map(float, vals[:4]), std=std, fit_rms=rms,
                            ba=float(vals[4]), kg=float(kg))
        if frf.tau_amp is not None and frf.drift is not None:
            p = _with_arm_coulomb(frf, band, p, notes)
        cut = None if flagged else _second_mode(frf, p)
        if cut is None:
            return p
        flagged = True
        f2, f_cut = cut
        keep = frf.f_hz < f_cut
        if keep.sum() < 6:
            notes.append(f"joint {joint}: a second resonance near {f2:.3g} Hz: a three-mass "
                         "model is needed (too few points below it to refit without it)")
            return p
        notes.append(f"joint {joint}: a second resonance near {f2:.3g} Hz (the two-mass model "
                     f"misses the points from {f_cut:.3g} Hz): a three-mass model is needed; "
                     f"the two-mass fit uses the points below {f_cut:.3g} Hz")
        band = keep
        x0 = np.r_[p.jm, p.ja, p.k, p.d, p.ba]


def arm_swing(frf: Frf, p: JointElasticity) -> np.ndarray:
    """Per FRF point the arm's sine velocity amplitude over the step's drift, by the fitted
    linear model (above 1 the arm reverses and its Coulomb friction acts at the step's
    frequency)."""
    assert frf.tau_amp is not None and frf.drift is not None
    arm = _motor_and_arm(frf.f_hz, p.jm, p.ja, p.k, p.d, p.ba, p.kg)[1]
    return (2 * np.pi * frf.f_hz * np.abs(arm) * frf.tau_amp
            / np.maximum(np.abs(frf.drift), 1e-12))


def _with_arm_coulomb(frf: Frf, band: np.ndarray, p: JointElasticity, notes: list[str]
                      ) -> JointElasticity:
    """Where the linear fit ``p`` says the arm reverses (its sine outruns the drift), the fit
    again with the arm's Coulomb friction (started from a few friction levels, the best
    kept; the linear fit stays when friction explains nothing), and a note."""
    assert frf.tau_amp is not None and frf.drift is not None
    swing = arm_swing(frf, p)[band]
    if not np.any(swing > 1.0):
        return p
    f, g, w = frf.f_hz[band], frf.g[band], _weights(frf)[band]
    amp, drift = frf.tau_amp[band], frf.drift[band]
    kg = p.kg
    worst = int(np.argmax(swing))
    notes.append(f"joint {p.joint}: the arm's sine outruns the drift at {int(np.sum(swing > 1))} "
                 f"step(s) (×{swing[worst]:.2g} at {f[worst]:.3g} Hz): its friction reverses "
                 "there, fitted as Coulomb friction on the arm (describing function); a "
                 "faster drift or a smaller sine keeps it out")

    def fun(x: np.ndarray) -> np.ndarray:
        jm, ja, k, d = np.exp(x[:4])
        model = arm_coulomb_frf(f, jm, ja, k, d, x[4], kg, float(np.exp(x[5])), amp, drift)
        return np.tile(w, 2) * _logres(model, g)

    best = None
    scale = float(np.median(amp))
    for frac in (0.01, 0.1, 1.0):
        x0 = np.r_[np.log([p.jm, p.ja, p.k, p.d]), p.ba, math.log(frac * scale)]
        try:
            fit = _solve(fun, x0, (*_NAMES, "fc"), [True] * 4 + [False, True],
                         f"joint {p.joint}")
        except EstimationError:
            continue
        if best is None or fit[2] < best[2]:
            best = fit
    if best is None or best[2] >= p.fit_rms:
        return p
    vals, std, rms = best
    return JointElasticity(p.joint, *map(float, vals[:4]), std=std, fit_rms=rms,
                           ba=float(vals[4]), kg=kg, fc=float(vals[5]))


def _second_mode(frf: Frf, p: JointElasticity) -> tuple[float, float] | None:
    """A second mode the two-mass fit misses: above the antiresonance, a run of ≥ 2
    neighbouring points whose misfit stands well above their noise (and above 1.5 %: what
    the model's own approximations leave). Returns (frequency of the worst point, the
    frequency from which the misfit starts) or None."""
    model = two_mass_frf(frf.f_hz, p.jm, p.ja, p.k, p.d, p.ba, p.kg)
    miss = np.abs(np.log(model / frf.g))
    sigma = np.hypot(1.0 / np.maximum(frf.snr, 1.0), 0.005)
    bad = (miss > 4 * sigma) & (miss > 0.015) & (frf.f_hz > p.f_antires_hz)
    idx = np.flatnonzero(bad)
    runs = np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1) if idx.size else []
    runs = [r for r in runs if r.size >= 2]
    if not runs:
        return None
    worst = max(runs, key=lambda r: float(miss[r].max()))
    k = int(worst[np.argmax(miss[worst])])
    start = int(worst[0])
    return float(frf.f_hz[k]), float(frf.f_hz[max(start - 1, 0)])


def fit_coupled(frf: Frf, notes: list[str] | None = None, kg: np.ndarray | None = None
                ) -> tuple[list[JointElasticity], CoupledElasticity]:
    """Coupled fit of a pair's 2×2 FRF: Jm, Ja, K, D, Ba per axis and the coupled inertia
    Jcop; ``kg`` the arms' known 2×2 gravity stiffness at the pose."""
    notes = notes if notes is not None else []
    j1, j2 = frf.joints
    singles = []
    for i, j in enumerate((j1, j2)):
        sub = Frf((j,), frf.f_hz, frf.g[:, i, i], frf.coherence, frf.snr, frf.source)
        # a diagonal term shows both of the pair's modes: no second-resonance note from it
        singles.append(_start_and_band(sub.f_hz, sub.accel, j, [])[0])
    # Jcop from the low-frequency inertia matrix: (s² G)⁻¹ → Jm + Ja (2×2)
    low = frf.f_hz < 0.5 * frf.f_hz[np.argmin(np.abs(frf.accel[:, 0, 0]))]
    inert = np.linalg.inv(frf.accel[low if low.any() else slice(0, 1)]).real.mean(axis=0)
    jcop0 = float(0.5 * (inert[0, 1] + inert[1, 0]))
    x0 = np.array([*np.log(singles[0][:4]), 0.0, *np.log(singles[1][:4]), 0.0, jcop0])
    w = _weights(frf)
    g = frf.g
    # off-diagonal terms relative to the diagonal's scale (they cross zero: no logarithm)
    norm = np.sqrt(np.abs(g[:, 0, 0] * g[:, 1, 1]))

    def fun(x: np.ndarray) -> np.ndarray:
        a, b = np.exp(x[:4]), np.exp(x[5:9])
        model = coupled_frf(frf.f_hz, (a[0], b[0]), (a[1], b[1]), x[10], (a[2], b[2]),
                            (a[3], b[3]), (x[4], x[9]), kg)
        diag = [_logres(model[:, i, i], g[:, i, i]) for i in range(2)]
        off = [(model[:, i, 1 - i] - g[:, i, 1 - i]) / norm for i in range(2)]
        offr = [np.concatenate((o.real, o.imag)) for o in off]
        return np.tile(w, 8) * np.concatenate(diag + offr)

    names = [f"{n}{i}" for i in (1, 2) for n in _NAMES] + ["jcop"]
    vals, std, rms = _solve(fun, x0, names, ([True] * 4 + [False]) * 2 + [False],
                            f"joints {frf.joints[0]},{frf.joints[1]}")
    joints = [JointElasticity(j, *map(float, vals[5 * i: 5 * i + 4]),
                              std={n: std[f"{n}{i + 1}"] for n in _NAMES}, fit_rms=rms,
                              ba=float(vals[5 * i + 4]),
                              kg=0.0 if kg is None else float(np.asarray(kg)[i, i]))
              for i, j in enumerate((j1, j2))]
    kgt = tuple(tuple(map(float, r)) for r in (np.zeros((2, 2)) if kg is None else kg))
    return joints, CoupledElasticity((j1, j2), float(vals[10]), {"jcop": std["jcop"]}, rms,
                                     kgt)  # type: ignore[arg-type]


# ----------------------------------------------------------------------------- job


def identify_elasticity(robot: Robot, logs: Sequence[Log], *, joints: Sequence[int] = (),
                        pair: tuple[int, int] | None = None,
                        schedule: Sequence[dict[str, Any]] | None = None,
                        tau_model: Sequence[np.ndarray] | None = None,
                        side: str = "joint", inertials: np.ndarray | None = None
                        ) -> ElasticityResult:
    """Elasticity of ``joints`` (1-based, each its own two-mass fit) and/or a coupled ``pair``
    from stepped-sine logs. ``schedule``: the steps from the trajectory header (else detected
    in each log); ``tau_model``: per log, the identified rigid-body + friction torque;
    ``inertials``: standard parameters for the arm's gravity stiffness at the logs' pose
    (default the robot's nominal ones)."""
    if not logs:
        raise EstimationError("elasticity: no logs")
    for j in (*joints, *(pair or ())):
        if not 1 <= j <= robot.n:
            raise EstimationError(f"elasticity: joint {j} not in 1..{robot.n}")
    notes: list[str] = []
    frfs: list[Frf] = []
    fitted: list[JointElasticity] = []
    coupled = None
    targets: list[tuple[int, ...]] = [(j,) for j in joints] + ([tuple(pair)] if pair else [])
    kg = _gravity_stiffness_of_logs(robot, logs, side, inertials, notes)
    found = None if schedule is not None else [
        _named(log.path, log_schedule, log.t, log.q, log.tau) for log in logs]
    for target in targets:
        frf = _merged_frf(logs, target, schedule, tau_model, found)
        frfs.append(frf)
        cols = [j - 1 for j in target]
        if len(target) == 1:
            fitted.append(fit_two_mass(frf, notes, float(kg[cols[0], cols[0]])))
        else:
            pj, coupled = fit_coupled(frf, notes, kg[np.ix_(cols, cols)])
            fitted += pj
    if schedule is None:
        notes.append("steps detected from the log alone (no schedule given)")
    return ElasticityResult(robot.name, fitted, frfs, coupled, side, notes,
                            [log.path for log in logs])


def gravity_stiffness(robot: Robot, q: np.ndarray, inertials: np.ndarray) -> np.ndarray:
    """∂g/∂q (n×n, symmetrized) at the pose q: the stiffness gravity adds to the arm side
    (negative where it pulls the arm away), by central differences of Y(q, 0, 0)·π."""
    from robid_link.ident.model.regressor import rigid_regressor

    n = robot.n
    eps = 1e-5
    qs = np.repeat(np.asarray(q, dtype=float)[None], 2 * n, axis=0)
    for j in range(n):
        qs[2 * j, j] += eps
        qs[2 * j + 1, j] -= eps
    zeros = np.zeros_like(qs)
    g = rigid_regressor(robot, qs, zeros, zeros) @ inertials
    kg = ((g[0::2] - g[1::2]) / (2 * eps)).T  # column j: ∂g/∂q_j
    return 0.5 * (kg + kg.T)


def _gravity_stiffness_of_logs(robot: Robot, logs: Sequence[Log], side: str,
                               inertials: np.ndarray | None, notes: list[str]) -> np.ndarray:
    theta = inertials if inertials is not None else robot.nominal
    if theta is None or side != "joint" or not np.any(robot.gravity):
        if theta is None and np.any(robot.gravity):
            notes.append("no inertials for the arm's gravity stiffness: K is the spring plus "
                         "gravity's ∂g/∂q at the pose (give the robot's inertials)")
        return np.zeros((robot.n, robot.n))
    pose = np.median(np.concatenate([log.q for log in logs]), axis=0)
    return gravity_stiffness(robot, pose, np.asarray(theta, dtype=float))


def _named(path: str, analysis: Callable[..., _T], *args: Any) -> _T:
    """The frequency analysis works on arrays: its data errors get the log's name here."""
    try:
        return analysis(*args)
    except DataError as err:
        raise DataError(f"{path}: {err}") from err


def _merged_frf(logs: Sequence[Log], target: tuple[int, ...],
                schedule: Sequence[dict[str, Any]] | None,
                tau_model: Sequence[np.ndarray] | None,
                found: Sequence[Sequence[dict[str, Any]]] | None) -> Frf:
    parts = []
    for i, log in enumerate(logs):
        tm = tau_model[i] if tau_model is not None else None
        try:
            if schedule is not None:
                parts.append(_named(log.path, frf_from_schedule, log.t, log.q, log.tau,
                                    schedule, target, tm))
            else:
                parts.append(_named(log.path, frf_from_log, log.t, log.q, log.tau, target, tm,
                                    found[i] if found else None))
        except RobidError as err:  # one log without this joint's steps is fine if another has
            if len(logs) == 1:
                raise
            last = err
    if not parts:
        raise last
    order = np.argsort(np.concatenate([p.f_hz for p in parts]))
    f, g, coh, snr = (np.concatenate([getattr(p, a) for p in parts])[order]
                      for a in ("f_hz", "g", "coherence", "snr"))
    amps = [p.tau_amp for p in parts if p.tau_amp is not None]
    drifts = [p.drift for p in parts if p.drift is not None]
    whole = len(amps) == len(drifts) == len(parts)
    return Frf(target, f, g, coh, snr, source=parts[0].source,
               tau_amp=np.concatenate(amps)[order] if whole else None,
               drift=np.concatenate(drifts)[order] if whole else None)


# ----------------------------------------------------------------------------- figures


def bode_cells(res: ElasticityResult, frf: Frf
               ) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
    """(model frequencies, [(measured, model)] per cell): motor acceleration over torque of one
    fitted FRF, measured at its points and of the fit on 400 log-spaced frequencies; one cell
    for a joint, H11, H12, H21, H22 (row major) for a pair."""
    by_joint = {j.joint: j for j in res.joints}
    fine = np.geomspace(frf.f_hz[0], frf.f_hz[-1], 400)
    s2 = -(2 * np.pi * fine) ** 2
    if len(frf.joints) == 1:
        p = by_joint[frf.joints[0]]
        return fine, [(frf.accel, s2 * two_mass_frf(fine, p.jm, p.ja, p.k, p.d, p.ba, p.kg))]
    a, b = (by_joint[j] for j in frf.joints)
    assert res.coupled is not None
    model = s2[:, None, None] * coupled_frf(fine, (a.jm, b.jm), (a.ja, b.ja), res.coupled.jcop,
                                            (a.k, b.k), (a.d, b.d), (a.ba, b.ba),
                                            np.array(res.coupled.kg))
    return fine, [(frf.accel[:, r, c], model[:, r, c]) for r in range(2) for c in range(2)]


def elasticity_figures(res: ElasticityResult, out_dir: str | Path) -> list[Path]:
    """Bode magnitude and phase of q̈m/τ per fitted FRF: measured circles shaded by coherence,
    the model as a line, parameters and resonances under the plot; the 2×2 grid for a pair."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullFormatter

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    by_joint = {j.joint: j for j in res.joints}
    paths = []
    for frf in res.frfs:
        fine, pairs = bode_cells(res, frf)
        cells = dict(zip([(0, 0)] if len(pairs) == 1 else [(0, 0), (0, 1), (1, 0), (1, 1)],
                         pairs, strict=True))
        text = _param_text([by_joint[j] for j in frf.joints])
        if len(frf.joints) == 2:
            assert res.coupled is not None
            text += f"\nJcop {res.coupled.jcop:.4g}"
        nr, nc = (1, 1) if len(cells) == 1 else (2, 2)
        fig = plt.figure(figsize=(6.5 * nc, 5.5 * nr))
        grid = fig.add_gridspec(2 * nr, nc, height_ratios=[2, 1] * nr, hspace=0.6)
        for (r, c), (meas, line) in cells.items():
            am = fig.add_subplot(grid[2 * r, c])
            ap = fig.add_subplot(grid[2 * r + 1, c], sharex=am)
            shade = np.clip(frf.coherence, 0, 1)
            am.loglog(fine, np.abs(line), "-", color="C0", label="model")
            am.scatter(frf.f_hz, np.abs(meas), c=shade, cmap="Greys", vmin=0, vmax=1,
                       edgecolors="C3", label="measured")
            ap.semilogx(fine, np.degrees(np.angle(line)), "-", color="C0")
            ap.scatter(frf.f_hz, np.degrees(np.angle(meas)), c=shade, cmap="Greys", vmin=0,
                       vmax=1, edgecolors="C3")
            name = (f"H{frf.joints[r]}{frf.joints[c]}" if len(frf.joints) == 2
                    else f"joint {frf.joints[0]}")
            am.set_title(f"{name}: motor acceleration / motor torque")
            am.set_ylabel("|q̈m/τ|")
            ap.set_ylabel("phase (deg)")
            ap.set_xlabel("frequency (Hz)")
            for ax in (am, ap):  # log axes: label the decades only
                ax.xaxis.set_minor_formatter(NullFormatter())
            am.legend(fontsize=8)
        fig.text(0.02, 0.005, text, fontsize=8, family="monospace", va="bottom")
        fig.subplots_adjust(bottom=0.2 if nr == 1 else 0.12)
        path = out / f"elasticity_{'_'.join(map(str, frf.joints))}.png"
        fig.savefig(path, dpi=90)
        plt.close(fig)
        paths.append(path)
    return paths


def _param_text(params: Sequence[JointElasticity]) -> str:
    return "\n".join(f"joint {p.joint}: Jm {p.jm:.4g}  Ja {p.ja:.4g}  K {p.k:.5g}  D {p.d:.4g}  "
                     f"Ba {p.ba:.3g}  "
                     f"f_res {p.f_res_hz:.4g} Hz  f_antires {p.f_antires_hz:.4g} Hz"
                     for p in params)
