"""Rigid-body dynamics in numba on the robot's own kinematics (the regressor's frames):
inverse dynamics (RNEA) batched over samples, the joint-space mass matrix, and a Cholesky
solve — for the a-priori model's torque on long logs and the simulated plant's loop.

Pinocchio's ``rnea``/``crba`` are the reference they are tested against; these exist
because a per-sample Python call costs more than the dynamics themselves. The per-sample
steps are inlined into their callers (a call per sample cost more than half of a batch);
the joint frames are ``spatial``'s, as the regressor's.
"""

from __future__ import annotations

import numba
import numpy as np

from robid_link.ident.model.regressor import robot_arrays
from robid_link.ident.model.robot import Robot
from robid_link.ident.model.spatial import joint_frame, joint_motion, to_child

__all__ = ["rigid_torque", "rnea_one", "rnea_at", "placements", "mass_matrix", "cholesky",
           "cholesky_solve", "cholesky_inverse"]


@numba.njit(cache=True, nogil=True, inline="always")
def placements(q, r0s, p0s, axes, revolute, rot, pos):
    """Each joint's rotation (parent → joint frame) and origin in its parent's frame at q."""
    for j in range(q.shape[0]):
        r, p = joint_frame(r0s, p0s, axes, revolute, j, q[j])
        for a in range(3):
            rot[j, a, 0], rot[j, a, 1], rot[j, a, 2] = r[3 * a], r[3 * a + 1], r[3 * a + 2]
            pos[j, a] = p[a]


@numba.njit(cache=True, nogil=True, inline="always")
def rnea_one(q, qd, qdd, r0s, p0s, axes, revolute, parents, gravity, params, use_gravity,
             vel, acc, frc, rot, pos, tau):
    """τ = M(q) q̈ + c(q, q̇) (+ g(q) when ``use_gravity``) of one sample, for standard
    parameters ``params`` (10 per link: m, mx, my, mz, xx, xy, yy, xz, yz, zz, inertia about
    the link frame's origin). Spatial vectors are [linear, angular] at the frame origin;
    vel, acc, frc (n, 6), rot (n, 3, 3), pos (n, 3) are scratch."""
    placements(q, r0s, p0s, axes, revolute, rot, pos)
    rnea_at(qd, qdd, axes, revolute, parents, gravity, params, use_gravity, vel, acc, frc,
            rot, pos, tau)


@numba.njit(cache=True, nogil=True, inline="always")
def rnea_at(qd, qdd, axes, revolute, parents, gravity, params, use_gravity, vel, acc, frc,
            rot, pos, tau):
    """``rnea_one`` with the placements (rot, pos) of q already computed."""
    n = qd.shape[0]
    for j in range(n):
        r = (rot[j, 0, 0], rot[j, 0, 1], rot[j, 0, 2], rot[j, 1, 0], rot[j, 1, 1],
             rot[j, 1, 2], rot[j, 2, 0], rot[j, 2, 1], rot[j, 2, 2])
        p = (pos[j, 0], pos[j, 1], pos[j, 2])
        par = parents[j]
        # the parent's velocity, then its acceleration, in this frame (the base: at rest,
        # −g when ``use_gravity``)
        if par < 0:
            v = to_child(r, p, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
            g0 = -gravity[0] if use_gravity else 0.0
            g1 = -gravity[1] if use_gravity else 0.0
            g2 = -gravity[2] if use_gravity else 0.0
            a = to_child(r, p, g0, g1, g2, 0.0, 0.0, 0.0)
        else:
            v = to_child(r, p, vel[par, 0], vel[par, 1], vel[par, 2], vel[par, 3],
                         vel[par, 4], vel[par, 5])
            a = to_child(r, p, acc[par, 0], acc[par, 1], acc[par, 2], acc[par, 3],
                         acc[par, 4], acc[par, 5])
        v, a = joint_motion(revolute[j], axes[j, 0], axes[j, 1], axes[j, 2], qd[j], qdd[j],
                            v, a)
        for e in range(6):
            vel[j, e] = v[e]
            acc[j, e] = a[e]
        # f = I a + v ×* (I v), I from (m, h, I_O)
        k = 10 * j
        mass, h0, h1, h2 = params[k], params[k + 1], params[k + 2], params[k + 3]
        ixx, ixy, iyy = params[k + 4], params[k + 5], params[k + 6]
        ixz, iyz, izz = params[k + 7], params[k + 8], params[k + 9]
        v0, v1, v2, v3, v4, v5 = v
        a0, a1, a2, a3, a4, a5 = a
        # momentum of v: linear m·v_l − h × ω, angular I_O ω + h × v_l
        pl0 = mass * v0 - (h1 * v5 - h2 * v4)
        pl1 = mass * v1 - (h2 * v3 - h0 * v5)
        pl2 = mass * v2 - (h0 * v4 - h1 * v3)
        pa0 = ixx * v3 + ixy * v4 + ixz * v5 + (h1 * v2 - h2 * v1)
        pa1 = ixy * v3 + iyy * v4 + iyz * v5 + (h2 * v0 - h0 * v2)
        pa2 = ixz * v3 + iyz * v4 + izz * v5 + (h0 * v1 - h1 * v0)
        fl0 = mass * a0 - (h1 * a5 - h2 * a4)
        fl1 = mass * a1 - (h2 * a3 - h0 * a5)
        fl2 = mass * a2 - (h0 * a4 - h1 * a3)
        fa0 = ixx * a3 + ixy * a4 + ixz * a5 + (h1 * a2 - h2 * a1)
        fa1 = ixy * a3 + iyy * a4 + iyz * a5 + (h2 * a0 - h0 * a2)
        fa2 = ixz * a3 + iyz * a4 + izz * a5 + (h0 * a1 - h1 * a0)
        # v ×* p: (ω × p_l, ω × p_a + v_l × p_l)
        frc[j, 0] = fl0 + (v4 * pl2 - v5 * pl1)
        frc[j, 1] = fl1 + (v5 * pl0 - v3 * pl2)
        frc[j, 2] = fl2 + (v3 * pl1 - v4 * pl0)
        frc[j, 3] = fa0 + (v4 * pa2 - v5 * pa1) + (v1 * pl2 - v2 * pl1)
        frc[j, 4] = fa1 + (v5 * pa0 - v3 * pa2) + (v2 * pl0 - v0 * pl2)
        frc[j, 5] = fa2 + (v3 * pa1 - v4 * pa0) + (v0 * pl1 - v1 * pl0)
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
