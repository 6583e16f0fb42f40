"""Pseudo-inertias, their log-Cholesky parametrization, and the consistent fit's inner solve.

The maps of notes 1–2 of ``fit.consistent``, each written once as a per-link numba kernel;
the numpy-facing functions loop those kernels over links. The Levenberg–Marquardt solve for
one prior weight λ runs whole in one compiled call: the cross-validation makes ~10² such
solves on a clean log and ~10⁴ objective evaluations on a real robot's, where the per-call
overhead of small numpy operations was the cost.
"""

from __future__ import annotations

import numba
import numpy as np

from robid_link.ident.model.dynamics import cholesky, cholesky_solve

__all__ = ["pseudo_inertia", "standard_from_pseudo", "log_cholesky", "from_log_cholesky",
           "lm_solve", "LOGDET_GRAD", "OFF"]

#: U's entries driven by φ₄…φ₉: s₁₂, s₂₃, s₁₃, t₁, t₂, t₃
OFF = ((0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3))
_OFF = np.array(OFF, dtype=np.int64)
#: d log det J / dφ (per link): log det J = 2(4α + d₁ + d₂ + d₃)
LOGDET_GRAD = 2.0 * np.array([4.0, 1.0, 1.0, 1.0, 0, 0, 0, 0, 0, 0])


def pseudo_inertia(theta: np.ndarray) -> np.ndarray:
    """(…, 10) standard parameters in Pinocchio's order → (…, 4, 4) pseudo-inertias."""
    th = np.asarray(theta, dtype=float)
    m, h = th[..., 0], th[..., 1:4]
    xx, xy, yy, xz, yz, zz = (th[..., k] for k in range(4, 10))
    inertia = np.stack([np.stack([xx, xy, xz], -1), np.stack([xy, yy, yz], -1),
                        np.stack([xz, yz, zz], -1)], -2)
    tr = (xx + yy + zz)[..., None, None]
    out = np.zeros((*th.shape[:-1], 4, 4))
    out[..., :3, :3] = 0.5 * tr * np.eye(3) - inertia
    out[..., :3, 3] = h
    out[..., 3, :3] = h
    out[..., 3, 3] = m
    return out


@numba.njit(cache=True, nogil=True)
def _standard(j, out):
    """One 4×4 pseudo-inertia → its 10 standard parameters (m, h, Ixx, Ixy, Iyy, Ixz, Iyz,
    Izz), I = tr(Σ)·1 − Σ."""
    tr = j[0, 0] + j[1, 1] + j[2, 2]
    out[0] = j[3, 3]
    out[1] = j[0, 3]
    out[2] = j[1, 3]
    out[3] = j[2, 3]
    out[4] = tr - j[0, 0]
    out[5] = -j[0, 1]
    out[6] = tr - j[1, 1]
    out[7] = -j[0, 2]
    out[8] = -j[1, 2]
    out[9] = tr - j[2, 2]


@numba.njit(cache=True, nogil=True)
def _standard_all(j, out):
    for i in range(j.shape[0]):
        _standard(j[i], out[i])


def standard_from_pseudo(j: np.ndarray) -> np.ndarray:
    """(…, 4, 4) pseudo-inertias → (…, 10) standard parameters (inverse of the above)."""
    j = np.asarray(j, dtype=float)
    flat = np.ascontiguousarray(j.reshape(-1, 4, 4))
    out = np.empty((flat.shape[0], 10))
    _standard_all(flat, out)
    return out.reshape(*j.shape[:-2], 10)


@numba.njit(cache=True, nogil=True)
def _link(phi, u, du, theta, dtheta, jbuf, tbuf):
    """One link's φ → U, dU/dφ (10, 4, 4), θ = θ(UUᵀ) and dθ/dφ (10 θ × 10 φ)."""
    scale = np.exp(phi[0])
    u[:] = 0.0
    for k in range(3):
        u[k, k] = scale * np.exp(phi[1 + k])
    for k in range(6):
        u[_OFF[k, 0], _OFF[k, 1]] = scale * phi[4 + k]
    u[3, 3] = scale
    du[:] = 0.0
    du[0] = u
    for k in range(3):
        du[1 + k, k, k] = u[k, k]
    for k in range(6):
        du[4 + k, _OFF[k, 0], _OFF[k, 1]] = scale
    for a in range(4):  # J = U Uᵀ
        for b in range(4):
            s = 0.0
            for c in range(4):
                s += u[a, c] * u[b, c]
            jbuf[a, b] = s
    _standard(jbuf, theta)
    for k in range(10):  # dJ = dU Uᵀ + U dUᵀ
        for a in range(4):
            for b in range(4):
                s = 0.0
                for c in range(4):
                    s += du[k, a, c] * u[b, c] + u[a, c] * du[k, b, c]
                jbuf[a, b] = s
        _standard(jbuf, tbuf)
        for r in range(10):
            dtheta[r, k] = tbuf[r]


@numba.njit(cache=True, nogil=True)
def _links(phi, u, du, theta, dtheta):
    """``_link`` over the (n, 10) φ of n links; False when any entry is not finite."""
    jbuf = np.empty((4, 4))
    tbuf = np.empty(10)
    ok = True
    for i in range(phi.shape[0]):
        _link(phi[i], u[i], du[i], theta[i], dtheta[i], jbuf, tbuf)
        for r in range(10):
            if not np.isfinite(theta[i, r]):
                ok = False
            for k in range(10):
                if not np.isfinite(dtheta[i, r, k]):
                    ok = False
    return ok


def from_log_cholesky(phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n, 10) log-Cholesky φ → standard parameters (n, 10) and dθ/dφ (n, 10, 10)."""
    phi = np.ascontiguousarray(phi, dtype=float)
    n = phi.shape[0]
    theta, d = np.empty((n, 10)), np.empty((n, 10, 10))
    _links(phi, np.empty((n, 4, 4)), np.empty((n, 10, 4, 4)), theta, d)
    return theta, d


def log_cholesky(j: np.ndarray) -> np.ndarray:
    """(n, 4, 4) positive definite pseudo-inertias → (n, 10) φ with J = U Uᵀ, U upper."""
    flip = np.eye(4)[::-1]
    low = np.linalg.cholesky(flip @ j @ flip)
    u = flip @ low @ flip  # upper triangular, U Uᵀ = J
    alpha = np.log(u[:, 3, 3])
    v = u / u[:, 3, 3][:, None, None]
    phi = np.empty((j.shape[0], 10))
    phi[:, 0] = alpha
    for k in range(3):
        phi[:, 1 + k] = np.log(v[:, k, k])
    for k, (r, c) in enumerate(OFF):
        phi[:, 4 + k] = v[:, r, c]
    return phi


# ----------------------------------------------------------------------- the inner solve

@numba.njit(cache=True, nogil=True)
def _objective(a, b, lam, w, pi, phi):
    """πᵀAπ − 2bᵀπ + λ(wᵀπ − Σ log det J) (the constant terms left out)."""
    p = pi.size
    quad = 0.0
    lin = 0.0
    for r in range(p):
        s = 0.0
        for c in range(p):
            s += a[r, c] * pi[c]
        quad += pi[r] * s
        lin += (lam * w[r] - 2.0 * b[r]) * pi[r]
    logdet = 0.0
    for i in range(phi.shape[0]):
        for k in range(4):
            logdet += LOGDET_GRAD[k] * phi[i, k]
    return quad + lin - lam * logdet


@numba.njit(cache=True, nogil=True)
def _normal_equations(a, b, lam, w, l0_inv, pi, phi, d, du, hess, grad):
    """Gauss–Newton Hessian 2(DᵀAD + λ JᵤᵀJᵤ) and gradient Dᵀ(2(Aπ − b) + λw) − λ∇log det,
    D = dπ/dφ block-diagonal (10 × 10 per link)."""
    n = phi.shape[0]
    p = 10 * n
    ad = np.zeros((p, p))  # A D
    for r in range(p):
        for j in range(n):
            for k in range(10):
                s = 0.0
                for m in range(10):
                    s += a[r, 10 * j + m] * d[j, m, k]
                ad[r, 10 * j + k] = s
    for i in range(n):  # Dᵀ (A D)
        for k in range(10):
            for c in range(p):
                s = 0.0
                for m in range(10):
                    s += d[i, m, k] * ad[10 * i + m, c]
                hess[10 * i + k, c] = 2.0 * s
    ju = np.empty((4, 4, 10))
    for i in range(n):  # the prior's ‖L₀⁻¹U‖²: Jᵤ = L₀⁻¹ dU/dφ
        for x in range(4):
            for y in range(4):
                for k in range(10):
                    s = 0.0
                    for z in range(4):
                        s += l0_inv[i, x, z] * du[i, k, z, y]
                    ju[x, y, k] = s
        for k in range(10):
            for m in range(10):
                s = 0.0
                for x in range(4):
                    for y in range(4):
                        s += ju[x, y, k] * ju[x, y, m]
                hess[10 * i + k, 10 * i + m] += 2.0 * lam * s
    res = np.empty(p)
    for r in range(p):
        s = 0.0
        for c in range(p):
            s += a[r, c] * pi[c]
        res[r] = 2.0 * (s - b[r]) + lam * w[r]
    for i in range(n):
        for k in range(10):
            s = 0.0
            for m in range(10):
                s += d[i, m, k] * res[10 * i + m]
            grad[10 * i + k] = s - lam * LOGDET_GRAD[k]


@numba.njit(cache=True, nogil=True)
def _damped_solve(hess, diag, mu, grad, lo, step):
    """step with (H + μ diag) step = −grad by Cholesky; False when not positive definite (a
    pivot ≤ 0 or NaN: its square root is NaN)."""
    m = hess.copy()
    for r in range(grad.size):
        m[r, r] += mu * diag[r]
    cholesky(m, lo)
    for r in range(grad.size):
        if not lo[r, r] > 0.0:
            return False
    cholesky_solve(lo, -grad, step)
    return True


@numba.njit(cache=True, nogil=True)
def lm_solve(a, b, lam, w, l0_inv, phi0, tol, max_iter):
    """Levenberg–Marquardt in φ for one λ on the reduced normal equations (note 2 of
    ``fit.consistent``). Stops when an accepted step lowers the objective by less than
    ``tol`` (absolute) or no damping gives a decrease. Returns φ, π (10 n) and the number
    of objective evaluations."""
    n = phi0.shape[0]
    p = 10 * n
    phi = phi0.copy()
    u, du = np.empty((n, 4, 4)), np.empty((n, 10, 4, 4))
    theta, d = np.empty((n, 10)), np.empty((n, 10, 10))
    _links(phi, u, du, theta, d)
    pi = theta.ravel().copy()
    f = _objective(a, b, lam, w, pi, phi)
    t_u, t_du = np.empty((n, 4, 4)), np.empty((n, 10, 4, 4))
    t_theta, t_d = np.empty((n, 10)), np.empty((n, 10, 10))
    hess, grad = np.empty((p, p)), np.empty(p)
    diag, lo, step = np.empty(p), np.empty((p, p)), np.empty(p)
    trial = np.empty((n, 10))
    mu, nfev = 1e-4, 1
    for _ in range(max_iter):
        _normal_equations(a, b, lam, w, l0_inv, pi, phi, d, du, hess, grad)
        top = 0.0
        for r in range(p):
            top = max(top, hess[r, r])
        floor = 1e-12 * max(top, 1e-300)
        for r in range(p):
            diag[r] = max(hess[r, r], floor)
        improved = False
        f_new = f
        for _ in range(30):
            if not _damped_solve(hess, diag, mu, grad, lo, step):
                mu *= 10.0
                continue
            for i in range(n):
                for k in range(10):
                    trial[i, k] = phi[i, k] + step[10 * i + k]
            finite = _links(trial, t_u, t_du, t_theta, t_d)
            f_new = _objective(a, b, lam, w, t_theta.ravel(), trial)
            nfev += 1
            if finite and np.isfinite(f_new) and f_new <= f:
                improved = True
                break
            mu *= 4.0
        if not improved:
            break
        decrease = f - f_new
        phi[:] = trial
        u[:] = t_u
        du[:] = t_du
        d[:] = t_d
        pi[:] = t_theta.ravel()
        f = f_new
        mu = max(mu / 3.0, 1e-12)
        if decrease <= tol:
            break
    return phi, pi, nfev
