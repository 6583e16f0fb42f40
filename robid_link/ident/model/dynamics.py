"""Rigid-body dynamics in numba on the robot's own kinematics (the regressor's frames):
inverse dynamics (RNEA) batched over samples, the joint-space mass matrix, and a Cholesky
solve — for the a-priori model's torque on long logs and the simulated plant's loop.

Pinocchio's ``rnea``/``crba`` are the reference they are tested against; these exist
because a per-sample Python call costs more than the dynamics themselves.
"""

from __future__ import annotations

import numba
import numpy as np

from robid_link.ident.model.regressor import robot_arrays
from robid_link.ident.model.robot import Robot

__all__ = ["rigid_torque", "rnea_one", "rnea_at", "placements", "mass_matrix", "cholesky",
           "cholesky_solve", "cholesky_inverse"]


@numba.njit(cache=True, nogil=True)
def placements(q, r0s, p0s, axes, revolute, rot, pos):
    """Each joint's rotation (parent → joint frame) and origin in its parent's frame at q."""
    n = q.shape[0]
    for j in range(n):
        u0, u1, u2 = axes[j, 0], axes[j, 1], axes[j, 2]
        if revolute[j]:
            c, s = np.cos(q[j]), np.sin(q[j])
        else:
            c, s = 1.0, 0.0
        t = 1.0 - c
        x00, x01, x02 = t * u0 * u0 + c, t * u0 * u1 - s * u2, t * u0 * u2 + s * u1
        x10, x11, x12 = t * u0 * u1 + s * u2, t * u1 * u1 + c, t * u1 * u2 - s * u0
        x20, x21, x22 = t * u0 * u2 - s * u1, t * u1 * u2 + s * u0, t * u2 * u2 + c
        for a in range(3):
            ra0, ra1, ra2 = r0s[j, a, 0], r0s[j, a, 1], r0s[j, a, 2]
            rot[j, a, 0] = ra0 * x00 + ra1 * x10 + ra2 * x20
            rot[j, a, 1] = ra0 * x01 + ra1 * x11 + ra2 * x21
            rot[j, a, 2] = ra0 * x02 + ra1 * x12 + ra2 * x22
        px, py, pz = p0s[j, 0], p0s[j, 1], p0s[j, 2]
        if not revolute[j]:
            px += (r0s[j, 0, 0] * u0 + r0s[j, 0, 1] * u1 + r0s[j, 0, 2] * u2) * q[j]
            py += (r0s[j, 1, 0] * u0 + r0s[j, 1, 1] * u1 + r0s[j, 1, 2] * u2) * q[j]
            pz += (r0s[j, 2, 0] * u0 + r0s[j, 2, 1] * u1 + r0s[j, 2, 2] * u2) * q[j]
        pos[j, 0], pos[j, 1], pos[j, 2] = px, py, pz


@numba.njit(cache=True, nogil=True)
def rnea_one(q, qd, qdd, r0s, p0s, axes, revolute, parents, gravity, params, use_gravity,
             vel, acc, frc, rot, pos, tau):
    """τ = M(q) q̈ + c(q, q̇) (+ g(q) when ``use_gravity``) of one sample, for standard
    parameters ``params`` (10 per link: m, mx, my, mz, xx, xy, yy, xz, yz, zz, inertia about
    the link frame's origin). Spatial vectors are [linear, angular] at the frame origin;
    vel, acc, frc (n, 6), rot (n, 3, 3), pos (n, 3) are scratch."""
    placements(q, r0s, p0s, axes, revolute, rot, pos)
    rnea_at(qd, qdd, axes, revolute, parents, gravity, params, use_gravity, vel, acc, frc,
            rot, pos, tau)


@numba.njit(cache=True, nogil=True)
def rnea_at(qd, qdd, axes, revolute, parents, gravity, params, use_gravity, vel, acc, frc,
            rot, pos, tau):
    """``rnea_one`` with the placements (rot, pos) of q already computed."""
    n = qd.shape[0]
    for j in range(n):
        u0, u1, u2 = axes[j, 0], axes[j, 1], axes[j, 2]
        px, py, pz = pos[j, 0], pos[j, 1], pos[j, 2]
        par = parents[j]
        for m in range(2):  # the parent's velocity, then its acceleration, in this frame
            if par < 0:
                g = use_gravity and m == 1
                s0 = -gravity[0] if g else 0.0
                s1 = -gravity[1] if g else 0.0
                s2 = -gravity[2] if g else 0.0
                s3 = s4 = s5 = 0.0
            else:
                src = vel[par] if m == 0 else acc[par]
                s0, s1, s2, s3, s4, s5 = src[0], src[1], src[2], src[3], src[4], src[5]
            l0 = s0 - (py * s5 - pz * s4)
            l1 = s1 - (pz * s3 - px * s5)
            l2 = s2 - (px * s4 - py * s3)
            dst = vel[j] if m == 0 else acc[j]
            for a in range(3):
                dst[a] = rot[j, 0, a] * l0 + rot[j, 1, a] * l1 + rot[j, 2, a] * l2
                dst[3 + a] = rot[j, 0, a] * s3 + rot[j, 1, a] * s4 + rot[j, 2, a] * s5
        vd, ad = qd[j], qdd[j]
        e0, e1, e2 = u0 * vd, u1 * vd, u2 * vd
        vl0, vl1, vl2 = vel[j, 0], vel[j, 1], vel[j, 2]
        w0, w1, w2 = vel[j, 3], vel[j, 4], vel[j, 5]
        if revolute[j]:
            acc[j, 0] += vl1 * e2 - vl2 * e1
            acc[j, 1] += vl2 * e0 - vl0 * e2
            acc[j, 2] += vl0 * e1 - vl1 * e0
            acc[j, 3] += w1 * e2 - w2 * e1 + u0 * ad
            acc[j, 4] += w2 * e0 - w0 * e2 + u1 * ad
            acc[j, 5] += w0 * e1 - w1 * e0 + u2 * ad
            vel[j, 3] += e0
            vel[j, 4] += e1
            vel[j, 5] += e2
        else:
            acc[j, 0] += w1 * e2 - w2 * e1 + u0 * ad
            acc[j, 1] += w2 * e0 - w0 * e2 + u1 * ad
            acc[j, 2] += w0 * e1 - w1 * e0 + u2 * ad
            vel[j, 0] += e0
            vel[j, 1] += e1
            vel[j, 2] += e2
        # f = I a + v ×* (I v), I from (m, h, I_O)
        p = params[10 * j: 10 * j + 10]
        mass, h0, h1, h2 = p[0], p[1], p[2], p[3]
        ixx, ixy, iyy, ixz, iyz, izz = p[4], p[5], p[6], p[7], p[8], p[9]
        v = vel[j]
        a_ = acc[j]
        # momentum of v: linear m·v_l − h × ω, angular I_O ω + h × v_l
        pl0 = mass * v[0] - (h1 * v[5] - h2 * v[4])
        pl1 = mass * v[1] - (h2 * v[3] - h0 * v[5])
        pl2 = mass * v[2] - (h0 * v[4] - h1 * v[3])
        pa0 = ixx * v[3] + ixy * v[4] + ixz * v[5] + (h1 * v[2] - h2 * v[1])
        pa1 = ixy * v[3] + iyy * v[4] + iyz * v[5] + (h2 * v[0] - h0 * v[2])
        pa2 = ixz * v[3] + iyz * v[4] + izz * v[5] + (h0 * v[1] - h1 * v[0])
        fl0 = mass * a_[0] - (h1 * a_[5] - h2 * a_[4])
        fl1 = mass * a_[1] - (h2 * a_[3] - h0 * a_[5])
        fl2 = mass * a_[2] - (h0 * a_[4] - h1 * a_[3])
        fa0 = ixx * a_[3] + ixy * a_[4] + ixz * a_[5] + (h1 * a_[2] - h2 * a_[1])
        fa1 = ixy * a_[3] + iyy * a_[4] + iyz * a_[5] + (h2 * a_[0] - h0 * a_[2])
        fa2 = ixz * a_[3] + iyz * a_[4] + izz * a_[5] + (h0 * a_[1] - h1 * a_[0])
        # v ×* p: (ω × p_l, ω × p_a + v_l × p_l)
        frc[j, 0] = fl0 + (v[4] * pl2 - v[5] * pl1)
        frc[j, 1] = fl1 + (v[5] * pl0 - v[3] * pl2)
        frc[j, 2] = fl2 + (v[3] * pl1 - v[4] * pl0)
        frc[j, 3] = fa0 + (v[4] * pa2 - v[5] * pa1) + (v[1] * pl2 - v[2] * pl1)
        frc[j, 4] = fa1 + (v[5] * pa0 - v[3] * pa2) + (v[2] * pl0 - v[0] * pl2)
        frc[j, 5] = fa2 + (v[3] * pa1 - v[4] * pa0) + (v[0] * pl1 - v[1] * pl0)
    for j in range(n - 1, -1, -1):
        f = frc[j]
        if revolute[j]:
            tau[j] = axes[j, 0] * f[3] + axes[j, 1] * f[4] + axes[j, 2] * f[5]
        else:
            tau[j] = axes[j, 0] * f[0] + axes[j, 1] * f[1] + axes[j, 2] * f[2]
        par = parents[j]
        if par >= 0:  # the child's force in the parent's frame: F = R f_l, N = R f_a + p × F
            f0 = rot[j, 0, 0] * f[0] + rot[j, 0, 1] * f[1] + rot[j, 0, 2] * f[2]
            f1 = rot[j, 1, 0] * f[0] + rot[j, 1, 1] * f[1] + rot[j, 1, 2] * f[2]
            f2 = rot[j, 2, 0] * f[0] + rot[j, 2, 1] * f[1] + rot[j, 2, 2] * f[2]
            n0 = rot[j, 0, 0] * f[3] + rot[j, 0, 1] * f[4] + rot[j, 0, 2] * f[5]
            n1 = rot[j, 1, 0] * f[3] + rot[j, 1, 1] * f[4] + rot[j, 1, 2] * f[5]
            n2 = rot[j, 2, 0] * f[3] + rot[j, 2, 1] * f[4] + rot[j, 2, 2] * f[5]
            px, py, pz = pos[j, 0], pos[j, 1], pos[j, 2]
            frc[par, 0] += f0
            frc[par, 1] += f1
            frc[par, 2] += f2
            frc[par, 3] += n0 + (py * f2 - pz * f1)
            frc[par, 4] += n1 + (pz * f0 - px * f2)
            frc[par, 5] += n2 + (px * f1 - py * f0)


@numba.njit(cache=True, nogil=True)
def _rnea_batch(q, qd, qdd, r0s, p0s, axes, revolute, parents, gravity, params, out):
    n = q.shape[1]
    vel, acc, frc = np.empty((n, 6)), np.empty((n, 6)), np.empty((n, 6))
    rot, pos = np.empty((n, 3, 3)), np.empty((n, 3))
    for k in range(q.shape[0]):
        rnea_one(q[k], qd[k], qdd[k], r0s, p0s, axes, revolute, parents, gravity, params, True,
                 vel, acc, frc, rot, pos, out[k])


def rigid_torque(robot: Robot, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray,
                 params: np.ndarray) -> np.ndarray:
    """Inverse dynamics (N, n) of the rigid body with standard parameters ``params`` (10 n):
    Y(q, q̇, q̈)·params without the regressor (N, n, 10 n)."""
    q, qd, qdd = (np.ascontiguousarray(np.atleast_2d(x), dtype=float) for x in (q, qd, qdd))
    out = np.empty(q.shape)
    r0s, p0s, axes, revolute, parents, _, gravity = robot_arrays(robot)
    _rnea_batch(q, qd, qdd, r0s, p0s, axes, revolute, parents, gravity,
                np.ascontiguousarray(params, dtype=float), out)
    return out


@numba.njit(cache=True, nogil=True)
def mass_matrix(axes, revolute, parents, gravity, params, scratch, m_out):
    """M(q) (n, n) at the placements in ``scratch`` (``placements``), column by column: RNEA
    without gravity at rest with q̈ = e_i."""
    vel, acc, frc, rot, pos = scratch
    n = axes.shape[0]
    zero = np.zeros(n)
    e = np.zeros(n)
    col = np.empty(n)
    for i in range(n):
        e[i] = 1.0
        rnea_at(zero, e, axes, revolute, parents, gravity, params, False, vel, acc, frc, rot,
                pos, col)
        m_out[:, i] = col
        e[i] = 0.0
    for i in range(n):  # symmetric to rounding: take the mean
        for k in range(i + 1, n):
            v = 0.5 * (m_out[i, k] + m_out[k, i])
            m_out[i, k] = v
            m_out[k, i] = v


@numba.njit(cache=True, nogil=True)
def cholesky(m, lo):
    """Lower Cholesky factor of a symmetric positive definite matrix into lo."""
    n = m.shape[0]
    lo[:] = 0.0
    for i in range(n):
        for k in range(i + 1):
            s = m[i, k]
            for p in range(k):
                s -= lo[i, p] * lo[k, p]
            lo[i, k] = np.sqrt(s) if i == k else s / lo[k, k]


@numba.njit(cache=True, nogil=True)
def cholesky_solve(lo, b, x):
    """x with L Lᵀ x = b."""
    n = b.size
    for i in range(n):
        s = b[i]
        for p in range(i):
            s -= lo[i, p] * x[p]
        x[i] = s / lo[i, i]
    for i in range(n - 1, -1, -1):
        s = x[i]
        for p in range(i + 1, n):
            s -= lo[p, i] * x[p]
        x[i] = s / lo[i, i]


@numba.njit(cache=True, nogil=True)
def cholesky_inverse(m, out):
    """M⁻¹ of a symmetric positive definite matrix (Cholesky)."""
    n = m.shape[0]
    lo = np.empty((n, n))
    cholesky(m, lo)
    e = np.zeros(n)
    col = np.empty(n)
    for i in range(n):
        e[i] = 1.0
        cholesky_solve(lo, e, col)
        out[:, i] = col
        e[i] = 0.0
