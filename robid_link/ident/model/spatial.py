"""A joint's frame and the motion it carries, as numba helpers inlined where they are used: the
one home of the kinematics both the rigid-body regressor and inverse dynamics run.

Frames are the robot's own (``regressor.robot_arrays``): joint j sits at R0_j, p0_j in its
parent's frame and turns (or slides) about its axis u_j. Spatial motion vectors are
[linear, angular] at the frame's origin; every helper returns tuples (registers, no arrays).
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["joint_frame", "to_child", "joint_motion"]


@numba.njit(inline="always")
def joint_frame(r0s, p0s, axes, revolute, j, qj):
    """Joint j's rotation R (9-tuple, row after row) and origin p (3-tuple) in its parent's
    frame at position qj: R = R0 · Rot(u, qj) and p = p0 (revolute), R = R0 and
    p = p0 + R0 u qj (prismatic)."""
    u0, u1, u2 = axes[j, 0], axes[j, 1], axes[j, 2]
    if revolute[j]:
        c, s = np.cos(qj), np.sin(qj)
    else:
        c, s = 1.0, 0.0
    t = 1.0 - c
    x00, x01, x02 = t * u0 * u0 + c, t * u0 * u1 - s * u2, t * u0 * u2 + s * u1
    x10, x11, x12 = t * u0 * u1 + s * u2, t * u1 * u1 + c, t * u1 * u2 - s * u0
    x20, x21, x22 = t * u0 * u2 - s * u1, t * u1 * u2 + s * u0, t * u2 * u2 + c
    a00, a01, a02 = r0s[j, 0, 0], r0s[j, 0, 1], r0s[j, 0, 2]
    a10, a11, a12 = r0s[j, 1, 0], r0s[j, 1, 1], r0s[j, 1, 2]
    a20, a21, a22 = r0s[j, 2, 0], r0s[j, 2, 1], r0s[j, 2, 2]
    rot = (a00 * x00 + a01 * x10 + a02 * x20, a00 * x01 + a01 * x11 + a02 * x21,
           a00 * x02 + a01 * x12 + a02 * x22,
           a10 * x00 + a11 * x10 + a12 * x20, a10 * x01 + a11 * x11 + a12 * x21,
           a10 * x02 + a11 * x12 + a12 * x22,
           a20 * x00 + a21 * x10 + a22 * x20, a20 * x01 + a21 * x11 + a22 * x21,
           a20 * x02 + a21 * x12 + a22 * x22)
    px, py, pz = p0s[j, 0], p0s[j, 1], p0s[j, 2]
    if not revolute[j]:
        px += (a00 * u0 + a01 * u1 + a02 * u2) * qj
        py += (a10 * u0 + a11 * u1 + a12 * u2) * qj
        pz += (a20 * u0 + a21 * u1 + a22 * u2) * qj
    return rot, (px, py, pz)


@numba.njit(inline="always")
def to_child(rot, pos, s0, s1, s2, s3, s4, s5):
    """A motion vector (s0..s5) of the parent's frame in the joint's frame (``joint_frame``'s
    rot, pos): angular Rᵀ ω, linear Rᵀ (v − p × ω)."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = rot
    px, py, pz = pos
    l0 = s0 - (py * s5 - pz * s4)
    l1 = s1 - (pz * s3 - px * s5)
    l2 = s2 - (px * s4 - py * s3)
    return (r00 * l0 + r10 * l1 + r20 * l2, r01 * l0 + r11 * l1 + r21 * l2,
            r02 * l0 + r12 * l1 + r22 * l2, r00 * s3 + r10 * s4 + r20 * s5,
            r01 * s3 + r11 * s4 + r21 * s5, r02 * s3 + r12 * s4 + r22 * s5)


@numba.njit(inline="always")
def joint_motion(revolute, u0, u1, u2, vd, ad, v, a):
    """The joint's own motion added to the velocity v and acceleration a (6-tuples, its frame,
    carried from the parent): v + S q̇, a + S q̈ + v × S q̇ (v before the update)."""
    v0, v1, v2, v3, v4, v5 = v
    a0, a1, a2, a3, a4, a5 = a
    e0, e1, e2 = u0 * vd, u1 * vd, u2 * vd
    if revolute:
        a0 += v1 * e2 - v2 * e1
        a1 += v2 * e0 - v0 * e2
        a2 += v0 * e1 - v1 * e0
        a3 += v4 * e2 - v5 * e1 + u0 * ad
        a4 += v5 * e0 - v3 * e2 + u1 * ad
        a5 += v3 * e1 - v4 * e0 + u2 * ad
        v3 += e0
        v4 += e1
        v5 += e2
    else:
        a0 += v4 * e2 - v5 * e1 + u0 * ad
        a1 += v5 * e0 - v3 * e2 + u1 * ad
        a2 += v3 * e1 - v4 * e0 + u2 * ad
        v0 += e0
        v1 += e1
        v2 += e2
    return (v0, v1, v2, v3, v4, v5), (a0, a1, a2, a3, a4, a5)
