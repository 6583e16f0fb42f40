"""The rigid-body torque regressor, batched over samples, and the structural base set.

``rigid_regressor`` is a vectorized Newton–Euler regressor (Pinocchio's
``computeJointTorqueRegressor`` is the reference it is tested against).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numba
import numpy as np
import pinocchio as pin

from robid_link.ident.model.robot import Robot
from robid_link.ident.model.threads import kernel_threads

__all__ = ["rigid_regressor", "reference_regressor", "BaseSet", "structural_base_set",
           "robot_arrays"]


@numba.njit(cache=True, parallel=True, nogil=True)
def _regressor_kernel(q, qd, qdd, r0s, p0s, axes, revolute, parents, anc, gravity, dest, out,
                      n_threads, zero):
    """Split the samples over threads; each part has its own scratch space."""
    nsamp = q.shape[1]
    n_par = max(1, min(n_threads, nsamp // 256))
    for part in numba.prange(n_par):
        _regressor_part(q, qd, qdd, r0s, p0s, axes, revolute, parents, anc, gravity, dest, out,
                        part * nsamp // n_par, (part + 1) * nsamp // n_par, zero)


@numba.njit(cache=True, nogil=True)
def _regressor_part(q, qd, qdd, r0s, p0s, axes, revolute, parents, anc, gravity, dest,  # noqa: C901
                    out, k0, k1, zero):
    """Newton–Euler regressor for samples [k0, k1): entry (row i, column c) of a sample goes
    to out[k, dest[i, c]] (skipped where dest is −1).

    Each body carries, with its velocity and acceleration, the axes of its ancestor joints
    expressed in its own frame; row i of body j's block is s_iᵀ·A_j(v_j, a_j).
    """
    n = q.shape[0]
    vel = np.zeros((n, 6))
    acc = np.zeros((n, 6))
    s_ax = np.zeros((n, n, 6))
    rot = np.zeros((3, 3))
    body = np.zeros((6, 10))
    src = np.zeros(6)
    for k in range(k0, k1):
        if zero:  # the dense layout: entries no joint row reaches stay zero
            for c in range(out.shape[1]):
                out[k, c] = 0.0
        for j in range(n):
            u0, u1, u2 = axes[j, 0], axes[j, 1], axes[j, 2]
            par = parents[j]
            # R = R0 · Rot(u, q) (revolute) or R0 (prismatic); p likewise
            if revolute[j]:
                c, s = np.cos(q[j, k]), np.sin(q[j, k])
            else:
                c, s = 1.0, 0.0
            t = 1.0 - c
            rx00, rx01, rx02 = t * u0 * u0 + c, t * u0 * u1 - s * u2, t * u0 * u2 + s * u1
            rx10, rx11, rx12 = t * u0 * u1 + s * u2, t * u1 * u1 + c, t * u1 * u2 - s * u0
            rx20, rx21, rx22 = t * u0 * u2 - s * u1, t * u1 * u2 + s * u0, t * u2 * u2 + c
            for a in range(3):
                rot[a, 0] = r0s[j, a, 0] * rx00 + r0s[j, a, 1] * rx10 + r0s[j, a, 2] * rx20
                rot[a, 1] = r0s[j, a, 0] * rx01 + r0s[j, a, 1] * rx11 + r0s[j, a, 2] * rx21
                rot[a, 2] = r0s[j, a, 0] * rx02 + r0s[j, a, 1] * rx12 + r0s[j, a, 2] * rx22
            px, py, pz = p0s[j, 0], p0s[j, 1], p0s[j, 2]
            if not revolute[j]:
                dq = q[j, k]
                px += (r0s[j, 0, 0] * u0 + r0s[j, 0, 1] * u1 + r0s[j, 0, 2] * u2) * dq
                py += (r0s[j, 1, 0] * u0 + r0s[j, 1, 1] * u1 + r0s[j, 1, 2] * u2) * dq
                pz += (r0s[j, 2, 0] * u0 + r0s[j, 2, 1] * u1 + r0s[j, 2, 2] * u2) * dq
            # transform the parent's v, a and ancestor axes: ang' = Rᵀ ang, lin' = Rᵀ(lin − p×ang)
            n_vec = 2 + j
            for m in range(n_vec):
                if m >= 2 and (par < 0 or not anc[par, m - 2]):
                    continue
                if par < 0:
                    for a in range(6):
                        src[a] = 0.0
                    if m == 1:
                        src[0], src[1], src[2] = -gravity[0], -gravity[1], -gravity[2]
                elif m == 0:
                    for a in range(6):
                        src[a] = vel[par, a]
                elif m == 1:
                    for a in range(6):
                        src[a] = acc[par, a]
                else:
                    for a in range(6):
                        src[a] = s_ax[par, m - 2, a]
                l0 = src[0] - (py * src[5] - pz * src[4])
                l1 = src[1] - (pz * src[3] - px * src[5])
                l2 = src[2] - (px * src[4] - py * src[3])
                dst0 = rot[0, 0] * l0 + rot[1, 0] * l1 + rot[2, 0] * l2
                dst1 = rot[0, 1] * l0 + rot[1, 1] * l1 + rot[2, 1] * l2
                dst2 = rot[0, 2] * l0 + rot[1, 2] * l1 + rot[2, 2] * l2
                dst3 = rot[0, 0] * src[3] + rot[1, 0] * src[4] + rot[2, 0] * src[5]
                dst4 = rot[0, 1] * src[3] + rot[1, 1] * src[4] + rot[2, 1] * src[5]
                dst5 = rot[0, 2] * src[3] + rot[1, 2] * src[4] + rot[2, 2] * src[5]
                if m == 0:
                    vel[j, 0], vel[j, 1], vel[j, 2] = dst0, dst1, dst2
                    vel[j, 3], vel[j, 4], vel[j, 5] = dst3, dst4, dst5
                elif m == 1:
                    acc[j, 0], acc[j, 1], acc[j, 2] = dst0, dst1, dst2
                    acc[j, 3], acc[j, 4], acc[j, 5] = dst3, dst4, dst5
                else:
                    s_ax[j, m - 2, 0], s_ax[j, m - 2, 1], s_ax[j, m - 2, 2] = dst0, dst1, dst2
                    s_ax[j, m - 2, 3], s_ax[j, m - 2, 4], s_ax[j, m - 2, 5] = dst3, dst4, dst5
            # joint motion: v += S qd; a += S qdd + v × (S qd) (with v before the update)
            vd, ad = qd[j, k], qdd[j, k]
            vl0, vl1, vl2 = vel[j, 0], vel[j, 1], vel[j, 2]
            w0, w1, w2 = vel[j, 3], vel[j, 4], vel[j, 5]
            for a in range(6):
                s_ax[j, j, a] = 0.0
            if revolute[j]:
                e0, e1, e2 = u0 * vd, u1 * vd, u2 * vd
                acc[j, 0] += vl1 * e2 - vl2 * e1
                acc[j, 1] += vl2 * e0 - vl0 * e2
                acc[j, 2] += vl0 * e1 - vl1 * e0
                acc[j, 3] += w1 * e2 - w2 * e1 + u0 * ad
                acc[j, 4] += w2 * e0 - w0 * e2 + u1 * ad
                acc[j, 5] += w0 * e1 - w1 * e0 + u2 * ad
                vel[j, 3] += e0
                vel[j, 4] += e1
                vel[j, 5] += e2
                s_ax[j, j, 3], s_ax[j, j, 4], s_ax[j, j, 5] = u0, u1, u2
            else:
                e0, e1, e2 = u0 * vd, u1 * vd, u2 * vd
                acc[j, 0] += w1 * e2 - w2 * e1 + u0 * ad
                acc[j, 1] += w2 * e0 - w0 * e2 + u1 * ad
                acc[j, 2] += w0 * e1 - w1 * e0 + u2 * ad
                vel[j, 0] += e0
                vel[j, 1] += e1
                vel[j, 2] += e2
                s_ax[j, j, 0], s_ax[j, j, 1], s_ax[j, j, 2] = u0, u1, u2
            # body regressor A (6, 10): I·a + v×*(I·v) linear in [m, h, I_O]
            vl0, vl1, vl2 = vel[j, 0], vel[j, 1], vel[j, 2]
            w0, w1, w2 = vel[j, 3], vel[j, 4], vel[j, 5]
            a0, a1, a2 = acc[j, 3], acc[j, 4], acc[j, 5]
            c0 = acc[j, 0] + w1 * vl2 - w2 * vl1
            c1 = acc[j, 1] + w2 * vl0 - w0 * vl2
            c2 = acc[j, 2] + w0 * vl1 - w1 * vl0
            body[0, 0], body[1, 0], body[2, 0] = c0, c1, c2
            body[0, 1], body[0, 2], body[0, 3] = -(w1 * w1 + w2 * w2), w0 * w1 - a2, w0 * w2 + a1
            body[1, 1], body[1, 2], body[1, 3] = w0 * w1 + a2, -(w0 * w0 + w2 * w2), w1 * w2 - a0
            body[2, 1], body[2, 2], body[2, 3] = w0 * w2 - a1, w1 * w2 + a0, -(w0 * w0 + w1 * w1)
            body[3, 1], body[3, 2], body[3, 3] = 0.0, c2, -c1
            body[4, 1], body[4, 2], body[4, 3] = -c2, 0.0, c0
            body[5, 1], body[5, 2], body[5, 3] = c1, -c0, 0.0
            # L(a_w) + [w]× L(w); L(w) rows: (w0, w1, 0, w2, 0, 0), (0, w0, w1, 0, w2, 0),
            # (0, 0, 0, w0, w1, w2) over columns xx, xy, yy, xz, yz, zz
            body[3, 4] = a0
            body[3, 5] = a1 + (w1 * 0.0 - w2 * w0)
            body[3, 6] = -w2 * w1
            body[3, 7] = a2 + w1 * w0
            body[3, 8] = w1 * w1 - w2 * w2
            body[3, 9] = w1 * w2
            body[4, 4] = w2 * w0
            body[4, 5] = a0 + w2 * w1
            body[4, 6] = a1
            body[4, 7] = w2 * w2 - w0 * w0
            body[4, 8] = a2 - w0 * w1
            body[4, 9] = -w0 * w2
            body[5, 4] = -w1 * w0
            body[5, 5] = w0 * w0 - w1 * w1
            body[5, 6] = w0 * w1
            body[5, 7] = a0 - w1 * w2
            body[5, 8] = a1 + w0 * w2
            body[5, 9] = a2
            # row i of the block: s_iᵀ·A, over A's structural non-zeros only (the mass
            # column has no moment rows, the inertia columns no force rows): the same sums
            for i in range(j + 1):
                if not anc[j, i]:
                    continue
                s0, s1, s2 = s_ax[j, i, 0], s_ax[j, i, 1], s_ax[j, i, 2]
                s3, s4, s5 = s_ax[j, i, 3], s_ax[j, i, 4], s_ax[j, i, 5]
                base = 10 * j
                d = dest[i, base]
                if d >= 0:
                    out[k, d] = s0 * body[0, 0] + s1 * body[1, 0] + s2 * body[2, 0]
                d = dest[i, base + 1]
                if d >= 0:
                    out[k, d] = s0 * body[0, 1] + s1 * body[1, 1] + s2 * body[2, 1] \
                        + s4 * body[4, 1] + s5 * body[5, 1]
                d = dest[i, base + 2]
                if d >= 0:
                    out[k, d] = s0 * body[0, 2] + s1 * body[1, 2] + s2 * body[2, 2] \
                        + s3 * body[3, 2] + s5 * body[5, 2]
                d = dest[i, base + 3]
                if d >= 0:
                    out[k, d] = s0 * body[0, 3] + s1 * body[1, 3] + s2 * body[2, 3] \
                        + s3 * body[3, 3] + s4 * body[4, 3]
                for col in range(4, 10):
                    d = dest[i, base + col]
                    if d >= 0:
                        out[k, d] = s3 * body[3, col] + s4 * body[4, col] + s5 * body[5, col]


def robot_arrays(robot: Robot) -> tuple[np.ndarray, ...]:
    n = robot.n
    r0s = np.array([np.array(pl.rotation) for pl in robot.placements]).reshape(n, 3, 3)
    p0s = np.array([np.array(pl.translation) for pl in robot.placements]).reshape(n, 3)
    revolute = np.array([t == "revolute" for t in robot.joint_types])
    parents = np.array(robot.parents, dtype=np.int64)
    anc = np.zeros((n, n), dtype=np.bool_)
    for j in range(n):
        i = j
        while i >= 0:
            anc[j, i] = True
            i = robot.parents[i]
    axes = np.ascontiguousarray(robot.axes, dtype=float)
    return r0s, p0s, axes, revolute, parents, anc, np.ascontiguousarray(robot.gravity)


def rigid_regressor(
    robot: Robot, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, out: np.ndarray | None = None,
    dest: np.ndarray | None = None,
) -> np.ndarray:
    """Joint-torque regressor Y (N, n, 10 n) with τ = Y · π (standard parameters).

    States are (N, n) arrays; ``out`` may be a preallocated float64 array. With ``dest``
    (n, 10 n) of column indices (−1 = skip), entries go to ``out`` (N, m) instead: a compact
    layout that only computes what the caller needs.
    """
    q, qd, qdd = (np.ascontiguousarray(np.atleast_2d(x), dtype=float).T for x in (q, qd, qdd))
    n, nsamp = q.shape
    dense = dest is None
    if dest is None:
        dest = np.arange(n * 10 * n, dtype=np.int64).reshape(n, 10 * n)
        if out is None:
            out = np.empty((nsamp, n, 10 * n))
        flat = out.reshape(nsamp, n * 10 * n)
    else:
        if out is None:
            raise ValueError("rigid_regressor: a compact dest needs an out array")
        flat = out
    args = (q, qd, qdd, *robot_arrays(robot), np.ascontiguousarray(dest, np.int64), flat)
    threads = kernel_threads()
    if threads == 1 or nsamp < 512:  # one part either way: no thread launch
        _regressor_part(*args, 0, nsamp, dense)
    else:
        _regressor_kernel(*args, threads, dense)
    return out


def reference_regressor(robot: Robot, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
    """Per-sample loop over Pinocchio's ``computeJointTorqueRegressor`` (the reference)."""
    model = robot.model
    data = model.createData()
    pq = np.ascontiguousarray(robot.pin_q(q))
    qd, qdd = np.ascontiguousarray(qd, dtype=float), np.ascontiguousarray(qdd, dtype=float)
    out = np.empty((q.shape[0], robot.n, 10 * robot.n))
    for k in range(q.shape[0]):
        out[k] = pin.computeJointTorqueRegressor(model, data, pq[k], qd[k], qdd[k])
    return out


# ----------------------------------------------------------------------------- base set

#: Order in which columns of one link are offered to the greedy selection: parameters
#: listed last are the ones regrouped away (the classical YY, MZ, M eliminations).
_PREFERENCE = ("xx", "xy", "xz", "yz", "zz", "mx", "my", "yy", "mz", "m")


@dataclass(frozen=True)
class BaseSet:
    """The structural base set: β = K · θ, with θ the full column vector of the model."""

    names: tuple[str, ...]  # full (standard + effect) parameter names
    independent: tuple[int, ...]  # column indices kept, in the order of β
    combination: np.ndarray  # K (r, P)
    absorbed: dict[int, tuple[int, ...]]  # dependent column -> base indices it loads onto

    @property
    def rank(self) -> int:
        return len(self.independent)

    @property
    def base_names(self) -> list[str]:
        return [self.names[i] for i in self.independent]

    def expression(self, k: int, digits: int = 4) -> str:
        """``zz_2 + 0.0506·m_3 − …``: what base parameter k stands for."""
        row = self.combination[k]
        lead = self.independent[k]
        terms = [self.names[lead]]
        for i in np.flatnonzero(row):
            if i == lead:
                continue
            c = row[i]
            mag = f"{abs(c):.{digits}g}"
            coef = "" if mag == "1" else f"{mag}·"
            terms.append(f"{'-' if c < 0 else '+'} {coef}{self.names[i]}")
        return " ".join(terms)


def structural_base_set(
    names: Sequence[str],
    sample_columns: Callable[[np.random.Generator, int], np.ndarray],
    n_samples: int = 400,
    seed: int = 20260,
    preference: Sequence[int] | None = None,
    tol: float = 1e-8,
) -> BaseSet:
    """Greedy column selection on a regressor of random states (same result on every log).

    ``sample_columns(rng, n)`` returns the stacked regressor (rows, P) for n random states.
    Columns are offered in ``preference`` order; a column whose distance to the span of the
    columns before it is below ``tol`` (after normalisation) is dependent.
    """
    rng = np.random.default_rng(seed)
    w = sample_columns(rng, n_samples)
    p = w.shape[1]
    order = list(preference) if preference is not None else list(range(p))
    norms = np.linalg.norm(w, axis=0)
    live = [i for i in order if norms[i] > tol * max(1.0, norms.max())]
    wn = w[:, live] / norms[live]
    r = np.linalg.qr(wn, mode="r")
    diag = np.abs(np.diag(r))
    indep = [live[k] for k in range(len(live)) if diag[k] > 1e-7]
    dep = [i for i in range(p) if i not in indep]
    k_mat = np.zeros((len(indep), p))
    k_mat[np.arange(len(indep)), indep] = 1.0
    absorbed: dict[int, tuple[int, ...]] = {}
    if dep:
        coef, *_ = np.linalg.lstsq(w[:, indep], w[:, dep], rcond=None)
        coef[np.abs(coef) < 1e-9 * max(1.0, np.abs(coef).max())] = 0.0
        k_mat[:, dep] = coef
        for col, i in enumerate(dep):
            absorbed[i] = tuple(int(b) for b in np.flatnonzero(coef[:, col]))
    # keep β in the order of the full column vector, which reads best
    perm = np.argsort(indep)
    new_pos = np.empty_like(perm)
    new_pos[perm] = np.arange(perm.size)
    absorbed = {i: tuple(sorted(int(new_pos[k]) for k in ks)) for i, ks in absorbed.items()}
    return BaseSet(
        names=tuple(names),
        independent=tuple(int(indep[i]) for i in perm),
        combination=k_mat[perm],
        absorbed=absorbed,
    )


def preference_order(n_links: int, n_extra: int) -> list[int]:
    """Rigid columns base to tip in ``_PREFERENCE`` order within a link, then the effects."""
    from robid_link.ident.model.robot import STANDARD_NAMES

    pos = {nm: k for k, nm in enumerate(STANDARD_NAMES)}
    order = [10 * j + pos[nm] for j in range(n_links) for nm in _PREFERENCE]
    return order + list(range(10 * n_links, 10 * n_links + n_extra))
