"""Bounded trust-region fits of the linear (two- or three-mass) model as logged, residuals and
Jacobian from one numba evaluation: the F-test of a third mass takes a dozen fits per joint, and
a step costs a few microseconds here where scipy's trust region spends a tenth of a millisecond.

The problem is that of ``fitting._lsq`` with the model's analytic Jacobian: weighted residuals
of log G (real and imaginary parts), parameters in the solver's coordinates (logarithms, scaled
linear values) within a box. A step minimises the linearised residuals within ‖D h‖ ≤ radius
(D the largest column norms of J seen, Moré's scaling; the Levenberg–Marquardt λ by Moré's
Newton iteration) over the parameters a bound does not hold, moves none by more than 1, and is
projected on the box; the radius follows the ratio of the actual to the predicted decrease. It
runs to convergence (the cost falls by less than 1e-15 of itself, the step is at rounding, the
gradient vanishes on the box) or for ``max_steps``.
"""

from __future__ import annotations

import cmath
import math

import numba
import numpy as np

from robid_link.exceptions import EstimationError
from robid_link.ident.elastic.models import logged_kernel
from robid_link.ident.model.dynamics import cholesky_solve

__all__ = ["fit_logged"]


def fit_logged(w: np.ndarray, meas: np.ndarray, sig: np.ndarray, kg: float, hold_s: float,
               x0: np.ndarray, lo: np.ndarray, hi: np.ndarray, is_log: np.ndarray,
               scale: np.ndarray, max_steps: int = 5000
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Least squares of r = [Re, Im](log(G(x)/meas)/sig) over lo ≤ x ≤ hi, x in the order of
    ``models.LOGGED_PARAMETERS`` (6 for two masses, 9 with the third), a parameter's value
    exp(x) where ``is_log`` else x·scale; w the points' angular frequencies. Returns (x, r,
    ∂r/∂x, steps taken)."""
    n = x0.size
    m = 2 * w.size
    x = np.empty(n)
    r = np.empty(m)
    jac = np.empty((m, n))
    steps = _solve(np.ascontiguousarray(w, dtype=float), np.ascontiguousarray(meas, dtype=complex),
                   np.ascontiguousarray(sig, dtype=float), float(kg), float(hold_s),
                   np.asarray(x0, dtype=float), np.asarray(lo, dtype=float),
                   np.asarray(hi, dtype=float), np.asarray(is_log, dtype=np.bool_),
                   np.asarray(scale, dtype=float), max_steps, x, r, jac)
    if steps < 0:
        raise EstimationError("elasticity fit: the model is not finite at the start values")
    return x, r, jac, int(steps)


@numba.njit(cache=True, nogil=True)
def _evaluate(x, w, meas, sig, kg, hold, is_log, scale, g, dlog, r, jac):
    """Residuals and Jacobian at x; False where the model is not finite there."""
    n = x.size
    v = np.empty(9)
    v[6:] = 0.0
    for p in range(n):
        v[p] = math.exp(x[p]) if is_log[p] else x[p] * scale[p]
    logged_kernel(w, hold, v[0], v[1], v[2], v[3], v[4], kg, n == 9, v[7], v[8], v[6], v[5],
                   g, dlog)
    k = w.size
    for i in range(k):
        z = cmath.log(g[i] / meas[i]) / sig[i]
        r[i], r[k + i] = z.real, z.imag
        for p in range(n):
            c = dlog[i, p] * ((v[p] if is_log[p] else scale[p]) / sig[i])
            jac[i, p], jac[k + i, p] = c.real, c.imag
    for i in range(2 * k):
        if not math.isfinite(r[i]):
            return False
    return True


@numba.njit(cache=True, nogil=True)
def _solve(w, meas, sig, kg, hold, x0, lo, hi, is_log, scale, max_steps, x, r, jac):
    n, m = x0.size, 2 * w.size
    g = np.empty(w.size, dtype=np.complex128)
    dlog = np.empty((w.size, n), dtype=np.complex128)
    r_try, jac_try = np.empty(m), np.empty((m, n))
    gram, grad = np.empty((n, n)), np.empty(n)
    x[:] = np.minimum(np.maximum(x0, lo), hi)
    if not _evaluate(x, w, meas, sig, kg, hold, is_log, scale, g, dlog, r, jac):
        return -1
    cost = 0.5 * (r @ r)
    _normal(jac, r, gram, grad)
    dscale = np.full(n, 1e-150)
    for p in range(n):  # Moré's scaling: the largest column norm seen
        dscale[p] = max(dscale[p], math.sqrt(gram[p, p]))
    radius = max(math.sqrt(np.sum((dscale * x) ** 2)), 1.0)
    steps = 0
    while steps < max_steps:
        steps += 1
        # the parameters a bound holds (the gradient pushes outward) keep their value
        free = np.flatnonzero(~(((x <= lo) & (grad > 0)) | ((x >= hi) & (grad < 0))))
        if free.size == 0 or np.max(np.abs(grad[free]) / dscale[free]) \
                <= 1e-12 * math.sqrt(2 * cost + 1e-300):
            break  # stationary on the box
        h = _trust_step(gram, grad, free, dscale, radius)
        # no parameter moves by more than 1 (a factor e of a positive one) in a step: the
        # residuals hardly see some (a third mass's frequency far from the band), and a full
        # step along them would leave the model's linear reach and stall against a bound
        h *= min(1.0, 1.0 / max(np.max(np.abs(h)), 1e-300))
        x_try = np.minimum(np.maximum(x + h, lo), hi)
        step = x_try - x
        size = math.sqrt(np.sum((dscale * step) ** 2))
        if size <= 1e-15 * (math.sqrt(np.sum((dscale * x) ** 2)) + 1e-300):
            break  # the step is at rounding
        ok = _evaluate(x_try, w, meas, sig, kg, hold, is_log, scale, g, dlog, r_try, jac_try)
        new = 0.5 * (r_try @ r_try) if ok else np.inf
        predicted = -(grad @ step) - 0.5 * (step @ (gram @ step))
        ratio = (cost - new) / predicted if predicted > 0 else -1.0
        if ratio < 0.25:
            radius = 0.25 * size
        elif ratio > 0.75 and size > 0.95 * radius:
            radius *= 2.0
        if new < cost:
            done = cost - new <= 1e-15 * cost
            x[:] = x_try
            r[:] = r_try
            jac[:] = jac_try
            cost = new
            _normal(jac, r, gram, grad)
            for p in range(n):
                dscale[p] = max(dscale[p], math.sqrt(gram[p, p]))
            if done:
                break
    return steps


@numba.njit(cache=True, nogil=True)
def _normal(jac, r, gram, grad):
    """JᵀJ and Jᵀr (loops: BLAS calls cost more than these small products)."""
    m, n = jac.shape
    for p in range(n):
        acc = 0.0
        for i in range(m):
            acc += jac[i, p] * r[i]
        grad[p] = acc
        for t in range(p + 1):
            acc = 0.0
            for i in range(m):
                acc += jac[i, p] * jac[i, t]
            gram[p, t] = gram[t, p] = acc


@numba.njit(cache=True, nogil=True)
def _trust_step(gram, grad, free, dscale, radius):
    """argmin ‖J h + r‖ over ‖D h‖ ≤ radius, h zero off ``free`` (from JᵀJ and Jᵀr): the
    Gauss–Newton step if it fits, else the λ of (JᵀJ + λ D²) h = −Jᵀr with ‖D h‖ = radius
    (to 0.1 %) by Newton's method on 1/radius − 1/‖D h(λ)‖ within its bracket, a Cholesky
    factor per trial λ (Moré's algorithm; the systems are at most 9 × 9)."""
    k = free.size
    b, gs = np.empty((k, k)), np.empty(k)
    for q in range(k):  # in the scaled parameters D h: columns of unit size at most
        gs[q] = grad[free[q]] / dscale[free[q]]
        for t in range(k):
            b[q, t] = gram[free[q], free[t]] / (dscale[free[q]] * dscale[free[t]])
    low = np.empty((k, k))
    p, qv = np.empty(k), np.empty(k)
    if _cholesky_solve(b, 0.0, gs, low, p, qv):
        if math.sqrt(p @ p) <= radius:
            return _scatter(p, free, dscale)
    lower, upper = 0.0, math.sqrt(gs @ gs) / radius
    lam = 1e-3 * upper
    for _ in range(30):
        if not lower < lam < upper:
            lam = max(1e-3 * upper, math.sqrt(lower * upper))
        if not _cholesky_solve(b, lam, gs, low, p, qv):
            lower = lam
            continue
        norm = math.sqrt(p @ p)
        if abs(norm - radius) <= 1e-3 * radius:
            break
        if norm < radius:
            upper = lam
        else:
            lower = lam
        lam += (norm / math.sqrt(qv @ qv)) ** 2 * (norm - radius) / radius
    return _scatter(p, free, dscale)


@numba.njit(cache=True, nogil=True)
def _cholesky_solve(b, lam, gs, low, p, qv):
    """p = −(b + λI)⁻¹ gs and qv = L⁻¹ p (L the Cholesky factor); False where b + λI is not
    positive definite to working precision."""
    k = gs.size
    top = 0.0
    for q in range(k):
        top = max(top, b[q, q] + lam)
    for q in range(k):
        for t in range(q + 1):
            acc = b[q, t] + (lam if q == t else 0.0)
            for j in range(t):
                acc -= low[q, j] * low[t, j]
            if q == t:
                if acc <= 1e-14 * top:
                    return False
                low[q, q] = math.sqrt(acc)
            else:
                low[q, t] = acc / low[t, t]
    cholesky_solve(low, -gs, p)
    for q in range(k):  # L qv = p
        acc = p[q]
        for j in range(q):
            acc -= low[q, j] * qv[j]
        qv[q] = acc / low[q, q]
    return True


@numba.njit(cache=True, nogil=True)
def _scatter(scaled, free, dscale):
    h = np.zeros(dscale.size)
    for q in range(free.size):
        h[free[q]] = scaled[q] / dscale[free[q]]
    return h
