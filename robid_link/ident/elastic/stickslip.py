"""Coulomb friction on the arm without the describing function's sinusoidal arm: the arm's
periodic steady state under each step's motor motion, stick-slip included, and the coupling
torque's fundamental it puts on the motor (numba; one period integrated per shooting step).

Where the drift keeps the arm one-signed the result is the linear model's; where the arm
reverses and its friction holds it for part of each period (a log without drift, strong
friction) the describing function's damper is off by tens of percent, this is not.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from robid_link.ident.elastic.models import motor_and_arm

__all__ = ["arm_stick_slip_frf"]

_STEPS = 256  # per period (RK4, events located): 2e-6 of the fundamental from 512


@numba.njit(cache=True, nogil=True)
def _motor(t: float, p: np.ndarray, hq: np.ndarray) -> tuple[float, float]:
    """The motor's position and velocity: drift·t + Σ_h Re(Q_h e^{jhωt})."""
    w = p[0]
    qm = p[1] * t
    vm = p[1]
    c1, s1 = math.cos(w * t), math.sin(w * t)
    c, s = c1, s1
    for h in range(hq.shape[0]):  # cos, sin of (h + 1)ωt by the angle-sum recurrence
        qm += hq[h, 0] * c - hq[h, 1] * s
        vm -= (h + 1) * w * (hq[h, 0] * s + hq[h, 1] * c)
        c, s = c * c1 - s * s1, s * c1 + c * s1
    return qm, vm


@numba.njit(cache=True, nogil=True)
def _force(t: float, qa: float, va: float, p: np.ndarray, hq: np.ndarray) -> float:
    """Torque on the arm but its friction; p = (w, drift, ja, k, d, ba, kg, fc)."""
    qm, vm = _motor(t, p, hq)
    return p[3] * (qm - qa) + p[4] * (vm - va) - p[5] * va - p[6] * (qa - p[1] * t)


@numba.njit(cache=True, nogil=True)
def _rk4(t: float, qa: float, va: float, h: float, s: float, p: np.ndarray, hq: np.ndarray
         ) -> tuple[float, float]:
    ja, fc = p[2], p[7]
    k1q, k1v = va, (_force(t, qa, va, p, hq) - fc * s) / ja
    k2q = va + 0.5 * h * k1v
    k2v = (_force(t + 0.5 * h, qa + 0.5 * h * k1q, k2q, p, hq) - fc * s) / ja
    k3q = va + 0.5 * h * k2v
    k3v = (_force(t + 0.5 * h, qa + 0.5 * h * k2q, k3q, p, hq) - fc * s) / ja
    k4q = va + h * k3v
    k4v = (_force(t + h, qa + h * k3q, k4q, p, hq) - fc * s) / ja
    return (qa + h * (k1q + 2 * k2q + 2 * k3q + k4q) / 6,
            va + h * (k1v + 2 * k2v + 2 * k3v + k4v) / 6)


@numba.njit(cache=True, nogil=True)
def _rk4_grid(i: int, qa: float, va: float, s: float, p: np.ndarray, dt: float,
              grid: np.ndarray) -> tuple[float, float]:
    """A whole step i of the period's grid, the motor's motion read off ``grid`` (its
    position and velocity at the half steps, computed once per period)."""
    ja, k, d, ba, kg, fc, drift = p[2], p[3], p[4], p[5], p[6], p[7], p[1]
    t = i * dt

    def acc(j: int, tt: float, q: float, v: float) -> float:
        return (k * (grid[j, 0] - q) + d * (grid[j, 1] - v) - ba * v
                - kg * (q - drift * tt) - fc * s) / ja

    k1q, k1v = va, acc(2 * i, t, qa, va)
    k2q = va + 0.5 * dt * k1v
    k2v = acc(2 * i + 1, t + 0.5 * dt, qa + 0.5 * dt * k1q, k2q)
    k3q = va + 0.5 * dt * k2v
    k3v = acc(2 * i + 1, t + 0.5 * dt, qa + 0.5 * dt * k2q, k3q)
    k4q = va + dt * k3v
    k4v = acc(2 * i + 2, t + dt, qa + dt * k3q, k4q)
    return (qa + dt * (k1q + 2 * k2q + 2 * k3q + k4q) / 6,
            va + dt * (k1v + 2 * k2v + 2 * k3v + k4v) / 6)


@numba.njit(cache=True, nogil=True)
def _crossing(t: float, qa: float, va: float, h: float, s: float, p: np.ndarray,
              hq: np.ndarray) -> float:
    """Time (from t) at which the sliding arm's velocity reaches zero within h: the root of
    the cubic through v and its slope at both ends, refined by secant steps on the
    integrated solution (its velocity changes sign over the step)."""
    lo, hi = 0.0, h
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if _rk4(t, qa, va, mid, s, p, hq)[1] * s > 0:
            lo = mid
        else:
            hi = mid
    return hi


@numba.njit(cache=True, nogil=True)
def _period(x0: float, v0: float, p: np.ndarray, hq: np.ndarray, n: int
            ) -> tuple[float, float, float, float]:
    """One period from (x0 = qa − drift·t, v0) at t = 0: the end state and the coupling
    torque's fundamental (re, im of X in Re(X e^{jωt}))."""
    w, drift, k, d, fc = p[0], p[1], p[3], p[4], p[7]
    dt = 2 * math.pi / w / n
    grid = np.empty((2 * n + 1, 2))
    for j in range(2 * n + 1):
        grid[j, 0], grid[j, 1] = _motor(0.5 * j * dt, p, hq)
    qa, va = x0, v0
    f0 = _force(0.0, qa, 0.0, p, hq)
    stuck = va == 0.0 and abs(f0) <= fc
    s = 1.0 if (va > 0 or (va == 0 and f0 > 0)) else -1.0
    re = 0.0
    im = 0.0
    for i in range(n):
        t0 = i * dt
        t1 = t0 + dt
        tc = k * (grid[2 * i, 0] - qa) + d * (grid[2 * i, 1] - va)
        re += tc * math.cos(w * t0)
        im -= tc * math.sin(w * t0)
        tt = t0
        for _ in range(16):  # events within one step
            if tt >= t1 - 1e-12 * dt:
                break
            if stuck:
                if abs(_force(t1, qa, 0.0, p, hq)) <= fc:
                    tt = t1
                    break
                lo, hi = tt, t1
                for _ in range(40):
                    mid = 0.5 * (lo + hi)
                    if abs(_force(mid, qa, 0.0, p, hq)) > fc:
                        hi = mid
                    else:
                        lo = mid
                tt = hi
                stuck = False
                s = 1.0 if _force(tt, qa, 0.0, p, hq) > 0 else -1.0
                continue
            if tt == t0:
                qn, vn = _rk4_grid(i, qa, va, s, p, dt, grid)
            else:
                qn, vn = _rk4(tt, qa, va, t1 - tt, s, p, hq)
            if vn * s > 0:
                qa, va, tt = qn, vn, t1
                break
            tau = _crossing(tt, qa, va, t1 - tt, s, p, hq)
            qa = _rk4(tt, qa, va, tau, s, p, hq)[0]
            va = 0.0
            tt += tau
            fs = _force(tt, qa, 0.0, p, hq)
            if abs(fs) <= fc:
                stuck = True
            else:
                s = 1.0 if fs > 0 else -1.0
    return qa - drift * n * dt, va, 2.0 * re / n, 2.0 * im / n


@numba.njit(cache=True, nogil=True)
def _steady(x0: float, v0: float, p: np.ndarray, hq: np.ndarray, n: int
            ) -> tuple[float, float, float, float]:
    """The periodic state, then its coupling torque's fundamental: period by period, with a
    Newton step on the period map (finite differences) where it gets closer (sticking makes
    the map non-smooth there; plain periods then converge, a stuck arm forgets its start)."""
    x, v = x0, v0
    scale_x = math.hypot(hq[0, 0], hq[0, 1]) + 1e-12
    scale_v = scale_x * p[0] + abs(p[1]) + 1e-12
    x1, v1, _, _ = _period(x, v, p, hq, n)
    best, stalled, newton = math.inf, 0, 0
    done = False
    for _ in range(40):
        gx, gv = x1 - x, v1 - v
        gap = math.hypot(gx / scale_x, gv / scale_v)
        # tight: a fit differentiates this numerically; at rounding level it stalls
        stalled = stalled + 1 if gap > 0.5 * best else 0
        best = min(best, gap)
        if gap < 1e-12 or (gap < 1e-9 and stalled >= 3):
            done = True
            break
        if newton <= 0:
            ex, ev = 1e-6 * scale_x, 1e-6 * scale_v
            ax, av, _, _ = _period(x + ex, v, p, hq, n)
            bx, bv, _, _ = _period(x, v + ev, p, hq, n)
            j11, j21 = (ax - x1) / ex - 1.0, (av - v1) / ex
            j12, j22 = (bx - x1) / ev, (bv - v1) / ev - 1.0
            det = j11 * j22 - j12 * j21
            if abs(det) > 1e-14:
                xn = x - (j22 * gx - j12 * gv) / det
                vn = v - (-j21 * gx + j11 * gv) / det
                yn, wn, _, _ = _period(xn, vn, p, hq, n)
                if math.hypot((yn - xn) / scale_x, (wn - vn) / scale_v) < 0.5 * gap:
                    x, v, x1, v1 = xn, vn, yn, wn
                    continue
            newton = 8  # plain periods before the next try
        newton -= 1
        x, v = x1, v1
        x1, v1, _, _ = _period(x, v, p, hq, n)
    if done:
        _, _, re, im = _period(x, v, p, hq, n)
        return re, im, x, v
    # no fixed point: a subharmonic orbit (stick-slip can lock every few periods), or one
    # still settling; the log's sine fit averages the periods, so does this
    re = im = 0.0
    for _ in range(12):
        x, v, a, b = _period(x, v, p, hq, n)
        re += a / 12
        im += b / 12
    return re, im, x, v


@numba.njit(cache=True, nogil=True)
def _coupling(w: np.ndarray, drift: np.ndarray, arm: np.ndarray, shape: np.ndarray,
              x0: np.ndarray, v0: np.ndarray, n: int) -> np.ndarray:
    out = np.empty((w.size, 4))
    p = np.empty(8)
    for i in range(w.size):
        p[0], p[1] = w[i], drift[i]
        p[2:] = arm
        out[i, 0], out[i, 1], out[i, 2], out[i, 3] = _steady(x0[i], v0[i], p, shape[i], n)
    return out


def arm_stick_slip_frf(f_hz: np.ndarray, jm: float, ja: float, k: float, d: float,
                       ba: float, kg: float, fc: float, qm: np.ndarray, drift: np.ndarray,
                       warm: dict[str, np.ndarray] | None = None) -> np.ndarray:
    """G = qm/τ of the two-mass joint with Coulomb friction ``fc`` on the arm, per step: the
    motor moves as the log shows, drift·t + Σ_h Re(Q_h e^{jhωt}) (``qm``: (K,) the
    fundamental Q_1, or (K, H) with its harmonics), the arm's periodic motion under it is
    integrated with stick-slip, and the fundamental Tc of the coupling torque
    K(qm − qa) + D(q̇m − q̇a) closes the motor's equation: G = 1/(Jm s² + Tc/Q_1).
    ``warm``: a dict the arm's periodic states are kept in, each call starting from the last
    (a fit's next parameters are close: the shooting then needs a step or two)."""
    f = np.asarray(f_hz, dtype=float)
    w = 2 * np.pi * f
    harm = np.asarray(qm, dtype=complex).reshape(f.size, -1)
    q1 = np.where(np.abs(harm[:, 0]) > 0, harm[:, 0], 1e-300)
    v_drift = np.asarray(drift, dtype=float) * np.ones_like(f)
    # start from the linear arm (no friction) under the motor's fundamental
    g, garm = motor_and_arm(f, jm, ja, k, d, ba, kg)
    qa = q1 * garm / g
    x0 = qa.real
    v0 = v_drift + (1j * w * qa).real
    if warm is not None and warm.get("x", np.empty(0)).shape == f.shape:
        x0, v0 = warm["x"], warm["v"]
    arm = np.array([ja, k, d, ba, kg, max(fc, 0.0)])
    shape = np.ascontiguousarray(np.stack((harm.real, harm.imag), axis=-1))
    tc = _coupling(w, v_drift, arm, shape, np.ascontiguousarray(x0),
                   np.ascontiguousarray(v0), _STEPS)
    if warm is not None:
        warm["x"], warm["v"] = tc[:, 2].copy(), tc[:, 3].copy()
    s = 1j * w
    return 1.0 / (jm * s * s + (tc[:, 0] + 1j * tc[:, 1]) / q1)
