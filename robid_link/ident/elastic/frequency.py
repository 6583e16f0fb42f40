"""Frequency responses of the stepped-sine experiment: the FRF points of a joint (or a pair's
2×2) from a known schedule or from the steps found in the log, with each point's variance;
H1 and reference-based estimates for sweeps; resonance finding.

Convention: an FRF point is G(jω) = Qm(jω)/T(jω), motor position over motor torque, from the
complex amplitudes x(t) = Re(X e^{jωt}) of one step. Both amplitudes are projections on the
frequency the reference was driven at, so noise and the position loop's feedback of it average
out (the indirect / joint input-output estimate, unbiased in closed loop). The experiment and
the detection live in ``experiment`` and ``detect``; their names are re-exported here.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from robid_link.exceptions import DataError
from robid_link.ident.elastic.detect import detect_steps, log_schedule
from robid_link.ident.elastic.experiment import (
    ElasticityOptions,
    elasticity_trajectory,
    excited_axes,
    step_axes,
    stepped_sine_schedule,
)
from robid_link.ident.elastic.sines import sine_amplitudes, step_sines, without_transient

__all__ = [
    "ElasticityOptions",
    "Frf",
    "stepped_sine_schedule",
    "step_axes",
    "excited_axes",
    "elasticity_trajectory",
    "sine_amplitudes",
    "frf_from_schedule",
    "detect_steps",
    "frf_from_log",
    "log_rate",
    "log_schedule",
    "frf_h1",
    "frf_reference",
    "spectral_peaks",
]


@dataclass
class Frf:
    """Measured FRF points of one excited joint (or of a pair: ``g`` is then (K, 2, 2)).

    ``g`` motor position / motor torque (rad/(N·m)); ``coherence`` per point from the
    period-by-period blocks (1 = noise-free); ``snr`` |T| over its standard error; ``g_var``
    the variance E|ĝ − g|² of each point (each entry for a pair) from the noise the
    step's sine fit leaves at the neighbouring frequencies (None: unknown, the fit then
    weights by ``snr`` and ``coherence``); ``rate_hz`` the log's sampling rate.
    """

    joints: tuple[int, ...]
    f_hz: np.ndarray
    g: np.ndarray
    coherence: np.ndarray
    snr: np.ndarray
    source: str = "schedule"  # schedule | detected | h1 | reference
    notes: list[str] = field(default_factory=list)
    #: one joint's stepped sines: per point the torque amplitude |T| (N·m) and the motor's mean
    #: velocity over the step (rad/s, the drift); what an amplitude-dependent effect (Coulomb
    #: friction reversing on the arm) needs; None for a pair or an H1 estimate
    tau_amp: np.ndarray | None = None
    drift: np.ndarray | None = None
    g_var: np.ndarray | None = None
    rate_hz: float | None = None
    #: one joint's stepped sines: the motor position's harmonics per point (K, H), Q_1…Q_H
    #: in the log's time base (what a model of an amplitude-dependent effect is driven by)
    qm_harmonics: np.ndarray | None = None

    @property
    def accel(self) -> np.ndarray:
        """Motor acceleration over torque: (jω)²·G."""
        s2 = -(2 * np.pi * self.f_hz) ** 2
        return self.g * (s2 if self.g.ndim == 1 else s2[:, None, None])


# ----------------------------------------------------------------------------- estimation



class _Point(NamedTuple):
    """One step: amplitudes Y, U (m,) less a decaying transient's share, coherence and snr of
    the first channel, its drift, the noise at the neighbouring bins (bins, m) and the factor
    from their mean square to an amplitude's variance, the motor's harmonics."""

    y: np.ndarray
    u: np.ndarray
    coherence: float
    snr: float
    drift: float
    noise_y: np.ndarray
    noise_u: np.ndarray
    inflate: float
    harmonics: np.ndarray | None  # one joint's (a pair's fit needs none)


def _point(t: np.ndarray, qm: np.ndarray, tau: np.ndarray, f: float, periods: float) -> _Point:
    """One step window (blocks of whole periods); drift the first channel's mean velocity."""
    blocks = int(max(2, min(10, periods // 2)))
    m = qm.shape[1]
    fit = step_sines(t, np.column_stack((qm, tau)), f, blocks,  # both signals, one design
                     harmonics_of=0 if m == 1 else None)  # a pair's fit needs no harmonics
    u = fit.amplitude[m:]
    # coherence of the first channel pair from the blocks (Welch-like, 1 = noise-free)
    sy, su = fit.blocks[:, 0], fit.blocks[:, m]
    coh = float(abs(np.sum(sy * su.conj())) ** 2
                / max(np.sum(abs(sy) ** 2) * np.sum(abs(su) ** 2), 1e-300))
    spread = float(np.std(su) / math.sqrt(blocks))
    snr = float(abs(u[0]) / max(spread, 1e-300))
    tc = t - t.mean()
    drift = float(tc @ (qm[:, 0] - qm[:, 0].mean()) / max(float(tc @ tc), 1e-300))
    yu, noise, inflate = without_transient(fit.k, fit.amplitude, fit.bins)
    return _Point(yu[:m], yu[m:], coh, snr, drift, noise[:, :m], noise[:, m:], inflate,
                  fit.harmonics)


def frf_from_schedule(t: np.ndarray, q: np.ndarray, tau: np.ndarray,
                      schedule: Sequence[dict[str, Any]], joints: Sequence[int],
                      tau_model: np.ndarray | None = None, rate_hz: float | None = None
                      ) -> Frf:
    """FRF points of ``joints`` (1-based; one joint → SISO, two → the 2×2 matrix) from the
    steps of a known schedule. ``tau_model``: the identified rigid-body + friction torque to
    subtract (same shape as ``tau``); ``rate_hz`` the log's (default from t). Log times are
    those of the trajectory."""
    cols = [j - 1 for j in joints]
    if tau_model is not None:
        tau = tau - tau_model
    by_f: dict[float, list[_Point]] = {}
    for st in schedule:
        if "joint" not in st or "f_hz" not in st:
            raise DataError("schedule step without joint/f_hz: not a stepped-sine schedule")
        axes = {a[0] for a in step_axes(st)}
        if not (axes == set(joints) if len(joints) == 1 else axes <= set(joints)):
            continue  # a single axis from its own steps, a pair from its own and its axes'
        a, b = np.searchsorted(t, [st["t_measure"], st["t_end"]])
        if b - a < 8 or b > len(t) - 1:
            raise DataError(f"step at {st['f_hz']:.4g} Hz of joint {st['joint']} "
                            f"({st['t_measure']:.4g}–{st['t_end']:.4g} s) is not in the log")
        f = float(st["f_hz"])
        periods = (st["t_end"] - st["t_measure"]) * f
        by_f.setdefault(round(float(st.get("f_key", f)), 9), []).append(
            _point(t[a:b], q[a:b][:, cols], tau[a:b][:, cols], f, periods))
    frf = _assemble(tuple(joints), by_f, "schedule")
    frf.rate_hz = rate_hz if rate_hz is not None else log_rate(t)
    return frf


def log_rate(t: np.ndarray) -> float:
    """A log's sampling rate: one over its median time step."""
    return 1.0 / float(np.median(np.diff(t), overwrite_input=True))  # diff's own array


def _siso(pts: Sequence[_Point]) -> tuple[complex, float]:
    """G and its variance from one or more steps at one frequency: Σ y ū / Σ |u|²; the
    noise of y − G u (correlated in closed loop) read at the neighbouring bins."""
    y = np.array([p.y[0] for p in pts])
    u = np.array([p.u[0] for p in pts])
    uu = float(np.sum(abs(u) ** 2))
    g = complex(np.sum(y * u.conj()) / uu)
    e = [p.inflate * float(np.mean(abs(p.noise_y[:, 0] - g * p.noise_u[:, 0]) ** 2))
         for p in pts]
    return g, float(np.sum(abs(u) ** 2 * np.array(e))) / uu ** 2


def _mimo(pts: Sequence[_Point]) -> tuple[np.ndarray, np.ndarray]:
    """G = Y U⁺ from the steps at one frequency (columns: steps) and the variance of each
    entry: δG = E U⁺, E the per-step noise of y − G u."""
    ym = np.column_stack([p.y for p in pts])
    um = np.column_stack([p.u for p in pts])
    pinv = np.linalg.pinv(um)
    g = ym @ pinv
    e = np.column_stack([p.inflate * np.mean(abs(p.noise_y - p.noise_u @ g.T) ** 2, axis=0)
                         for p in pts])  # (outputs, steps)
    return g, e @ abs(pinv) ** 2


def _assemble(joints: tuple[int, ...], by_f: dict[float, list[_Point]], source: str) -> Frf:
    fs, gs, gvar, cohs, snrs, amps, drifts, harms = [], [], [], [], [], [], [], []
    for f in sorted(by_f):
        pts = by_f[f]
        g: Any
        var: Any
        if len(joints) == 1:
            g, var = _siso(pts)
            amps.append(float(np.mean([abs(p.u[0]) for p in pts])))
            drifts.append(float(min(abs(p.drift) for p in pts)))
            harms.append(max(pts, key=lambda p: abs(p.u[0])).harmonics)
        else:
            if len(pts) < len(joints):
                continue  # a 2×2 FRF needs one independent input per axis
            g, var = _mimo(pts)
        fs.append(f)
        gs.append(g)
        gvar.append(var)
        cohs.append(min(p.coherence for p in pts))
        snrs.append(min(p.snr for p in pts))
    if not fs and len(joints) > 1 and by_f:
        raise DataError(f"joints {joints[0]},{joints[1]}: a 2×2 FRF needs two independent "
                        "inputs per frequency (steps of each axis, or the pair excited "
                        f"together: robid excite --pair {joints[0]},{joints[1]})")
    if not fs:
        raise DataError(f"no steps of joint(s) {', '.join(map(str, joints))} in the log")
    single = len(joints) == 1
    return Frf(joints, np.array(fs), np.array(gs), np.array(cohs), np.array(snrs), source,
               tau_amp=np.array(amps) if single else None,
               drift=np.array(drifts) if single else None, g_var=np.array(gvar),
               qm_harmonics=np.array(harms) if single else None)


def frf_from_log(t: np.ndarray, q: np.ndarray, tau: np.ndarray, joints: Sequence[int],
                 tau_model: np.ndarray | None = None,
                 steps: Sequence[dict[str, Any]] | None = None, rate_hz: float | None = None
                 ) -> Frf:
    """As :func:`frf_from_schedule`, with the steps detected in the log alone (every axis
    looked at, so that a step of another axis is not taken for one of ``joints``), or the
    ``steps`` :func:`log_schedule` found before."""
    if tau_model is not None:
        tau = tau - tau_model
    frf = frf_from_schedule(t, q, tau, steps if steps is not None else log_schedule(t, q, tau),
                            joints, rate_hz=rate_hz)
    frf.source = "detected"
    return frf


# ----------------------------------------------------------------------------- broadband


def frf_h1(u: np.ndarray, y: np.ndarray, fs: float, nperseg: int = 4096
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """H1 = S_yu/S_uu with the coherence, for sweeps and multisines (open loop, or closed loop
    when the noise on y is small): (f, H, γ²)."""
    import scipy.signal as sig

    f, syu = sig.csd(u, y, fs=fs, nperseg=nperseg)
    _, suu = sig.welch(u, fs=fs, nperseg=nperseg)
    _, syy = sig.welch(y, fs=fs, nperseg=nperseg)
    return f, syu / suu, np.abs(syu) ** 2 / np.maximum(suu * syy, 1e-300)


def frf_reference(r: np.ndarray, u: np.ndarray, y: np.ndarray, fs: float, nperseg: int = 4096
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """G = S_yr/S_ur with the excitation r as instrument: unbiased under the position loop's
    feedback (noise is uncorrelated with r). Returns (f, G, γ²_ur)."""
    import scipy.signal as sig

    f, syr = sig.csd(r, y, fs=fs, nperseg=nperseg)
    _, sur = sig.csd(r, u, fs=fs, nperseg=nperseg)
    _, srr = sig.welch(r, fs=fs, nperseg=nperseg)
    _, suu = sig.welch(u, fs=fs, nperseg=nperseg)
    return f, syr / sur, np.abs(sur) ** 2 / np.maximum(srr * suu, 1e-300)


# ----------------------------------------------------------------------------- resonances


def spectral_peaks(f: np.ndarray, spec: np.ndarray, band: np.ndarray, *,
                   min_prominence: float = 20.0) -> tuple[float, float] | None:
    """The highest peak of a power spectrum inside ``band`` (a mask), when it stands
    ``min_prominence``× above the median of its ±50 % neighbourhood: (f_peak, prominence).
    The resonance finder of the diagnosis (a residual's spectrum)."""
    idx = np.flatnonzero(band)
    if idx.size < 20:
        return None
    k = idx[int(np.argmax(spec[idx]))]
    near = (f >= f[k] / 1.5) & (f <= f[k] * 1.5) & (np.abs(np.arange(f.size) - k) > 2)
    if k in (idx[0], idx[-1]) or not near.any():
        return None
    prominence = float(spec[k] / np.median(spec[near]))
    return (float(f[k]), prominence) if prominence > min_prominence else None
