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
from robid_link.ident.model.spatial import joint_frame, joint_motion, to_child
from robid_link.ident.model.threads import kernel_threads

__all__ = ["rigid_regressor", "reference_regressor", "BaseSet", "structural_base_set",
           "robot_arrays", "RobotArrays"]


@numba.njit(cache=True, parallel=True, nogil=True)
def _regressor_kernel(q, qd, qdd, r0s, p0s, axes, revolute, parents, anc, gravity, dest, out,
                      n_threads, zero_cols):
    """Split the samples over threads; each part has its own scratch space."""
    nsamp = q.shape[1]
    n_par = max(1, min(n_threads, nsamp // 256))
    for part in numba.prange(n_par):
        _regressor_part(q, qd, qdd, r0s, p0s, axes, revolute, parents, anc, gravity, dest, out,
                        part * nsamp // n_par, (part + 1) * nsamp // n_par, zero_cols)


@numba.njit(cache=True, nogil=True)
def _regressor_part(q, qd, qdd, r0s, p0s, axes, revolute, parents, anc, gravity, dest,  # noqa: C901
                    out, k0, k1, zero_cols):
    """Newton–Euler regressor for samples [k0, k1): entry (row i, column c) of a sample goes
    to out[k, dest[i, c]] (skipped where dest is −1); out[k, zero_cols] is set to zero.

    Each body carries, with its velocity and acceleration, the axes of its ancestor joints
    expressed in its own frame; row i of body j's block is s_iᵀ·A_j(v_j, a_j). A sample's
    frames and body regressor live in registers (``spatial``'s tuples).
    """
    n = q.shape[0]
    vel = np.zeros((n, 6))
    acc = np.zeros((n, 6))
    s_ax = np.zeros((n, n, 6))
    for k in range(k0, k1):
        for c in zero_cols:  # the dense layout: entries no joint row reaches
            out[k, c] = 0.0
        for j in range(n):
            rot, pos = joint_frame(r0s, p0s, axes, revolute, j, q[j, k])
            par = parents[j]
            # the parent's velocity, acceleration (the base: at rest, −g) and ancestor axes
            if par < 0:
                v = to_child(rot, pos, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
                a = to_child(rot, pos, -gravity[0], -gravity[1], -gravity[2], 0.0, 0.0, 0.0)
            else:
                v = to_child(rot, pos, vel[par, 0], vel[par, 1], vel[par, 2], vel[par, 3],
                             vel[par, 4], vel[par, 5])
                a = to_child(rot, pos, acc[par, 0], acc[par, 1], acc[par, 2], acc[par, 3],
                             acc[par, 4], acc[par, 5])
                for i in range(j):
                    if anc[par, i]:
                        x = to_child(rot, pos, s_ax[par, i, 0], s_ax[par, i, 1],
                                     s_ax[par, i, 2], s_ax[par, i, 3], s_ax[par, i, 4],
                                     s_ax[par, i, 5])
                        for e in range(6):
                            s_ax[j, i, e] = x[e]
            u0, u1, u2 = axes[j, 0], axes[j, 1], axes[j, 2]
            v, a = joint_motion(revolute[j], u0, u1, u2, qd[j, k], qdd[j, k], v, a)
            for e in range(6):
                vel[j, e] = v[e]
                acc[j, e] = a[e]
            if revolute[j]:
                s_ax[j, j, 0], s_ax[j, j, 1], s_ax[j, j, 2] = 0.0, 0.0, 0.0
                s_ax[j, j, 3], s_ax[j, j, 4], s_ax[j, j, 5] = u0, u1, u2
            else:
                s_ax[j, j, 0], s_ax[j, j, 1], s_ax[j, j, 2] = u0, u1, u2
                s_ax[j, j, 3], s_ax[j, j, 4], s_ax[j, j, 5] = 0.0, 0.0, 0.0
            # body regressor A (6, 10): I·a + v×*(I·v) linear in [m, h, I_O]; bRC is A[R, C]
            vl0, vl1, vl2, w0, w1, w2 = v
            a0, a1, a2 = a[3], a[4], a[5]
            c0 = a[0] + w1 * vl2 - w2 * vl1
            c1 = a[1] + w2 * vl0 - w0 * vl2
            c2 = a[2] + w0 * vl1 - w1 * vl0
            b01, b02, b03 = -(w1 * w1 + w2 * w2), w0 * w1 - a2, w0 * w2 + a1
            b11, b12, b13 = w0 * w1 + a2, -(w0 * w0 + w2 * w2), w1 * w2 - a0
            b21, b22, b23 = w0 * w2 - a1, w1 * w2 + a0, -(w0 * w0 + w1 * w1)
            b32, b33 = c2, -c1  # b31 = b42 = b53 = 0
            b41, b43 = -c2, c0
            b51, b52 = c1, -c0
            # L(a_w) + [w]× L(w); L(w) rows: (w0, w1, 0, w2, 0, 0), (0, w0, w1, 0, w2, 0),
            # (0, 0, 0, w0, w1, w2) over columns xx, xy, yy, xz, yz, zz
            b34 = a0
            b35 = a1 + (w1 * 0.0 - w2 * w0)
            b36 = -w2 * w1
            b37 = a2 + w1 * w0
            b38 = w1 * w1 - w2 * w2
            b39 = w1 * w2
            b44 = w2 * w0
            b45 = a0 + w2 * w1
            b46 = a1
            b47 = w2 * w2 - w0 * w0
            b48 = a2 - w0 * w1
            b49 = -w0 * w2
            b54 = -w1 * w0
            b55 = w0 * w0 - w1 * w1
            b56 = w0 * w1
            b57 = a0 - w1 * w2
            b58 = a1 + w0 * w2
            b59 = a2
            # row i of the block: s_iᵀ·A, over A's structural non-zeros only (the mass
            # column has no moment rows, the inertia columns no force rows): the same sums
            base = 10 * j
            for i in range(j + 1):
                if not anc[j, i]:
                    continue
                s0, s1, s2 = s_ax[j, i, 0], s_ax[j, i, 1], s_ax[j, i, 2]
                s3, s4, s5 = s_ax[j, i, 3], s_ax[j, i, 4], s_ax[j, i, 5]
                to = dest[i]
                d = to[base]
                if d >= 0:
                    out[k, d] = s0 * c0 + s1 * c1 + s2 * c2
                d = to[base + 1]
                if d >= 0:
                    out[k, d] = s0 * b01 + s1 * b11 + s2 * b21 + s4 * b41 + s5 * b51
                d = to[base + 2]
                if d >= 0:
                    out[k, d] = s0 * b02 + s1 * b12 + s2 * b22 + s3 * b32 + s5 * b52
                d = to[base + 3]
                if d >= 0:
                    out[k, d] = s0 * b03 + s1 * b13 + s2 * b23 + s3 * b33 + s4 * b43
                d = to[base + 4]
                if d >= 0:
                    out[k, d] = s3 * b34 + s4 * b44 + s5 * b54
                d = to[base + 5]
                if d >= 0:
                    out[k, d] = s3 * b35 + s4 * b45 + s5 * b55
                d = to[base + 6]
                if d >= 0:
                    out[k, d] = s3 * b36 + s4 * b46 + s5 * b56
                d = to[base + 7]
                if d >= 0:
                    out[k, d] = s3 * b37 + s4 * b47 + s5 * b57
                d = to[base + 8]
                if d >= 0:
                    out[k, d] = s3 * b38 + s4 * b48 + s5 * b58
                d = to[base + 9]
                if d >= 0:
                    out[k, d] = s3 * b39 + s4 * b49 + s5 * b59


#: r0s, p0s, axes, revolute, parents, ancestors, gravity (``robot_arrays``)
RobotArrays = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                    np.ndarray]
_ARRAYS: dict[int, tuple[Robot, RobotArrays]] = {}


def robot_arrays(robot: Robot) -> RobotArrays:
    """The kernels' view of a robot (r0s, p0s, axes, revolute, parents, ancestors, gravity),
    made once per robot object: a call on a chunk of samples should not rebuild them."""
    hit = _ARRAYS.get(id(robot))
    if hit is not None and hit[0] is robot:
        return hit[1]
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
    out = (r0s, p0s, axes, revolute, parents, anc, np.ascontiguousarray(robot.gravity))
    if len(_ARRAYS) >= 64:
        _ARRAYS.pop(next(iter(_ARRAYS)))
    _ARRAYS[id(robot)] = (robot, out)  # the reference keeps id(robot) from being reused
    return out


_DENSE: dict[int, tuple[Robot, np.ndarray, np.ndarray]] = {}


def _dense_layout(robot: Robot) -> tuple[np.ndarray, np.ndarray]:
    """The dense layout's destinations (n, 10 n) and the columns no row reaches (blocks of row
    i, body j with i no ancestor of j), made once per robot object."""
    hit = _DENSE.get(id(robot))
    if hit is not None and hit[0] is robot:
        return hit[1], hit[2]
    n = robot.n
    dest = np.arange(n * 10 * n, dtype=np.int64).reshape(n, 10 * n)
    block = np.tril(robot_arrays(robot)[5]).T  # [i, j]: the kernel writes row i of body j
    zero_cols = dest[~np.repeat(block, 10, axis=1)]
    if len(_DENSE) >= 64:
        _DENSE.pop(next(iter(_DENSE)))
    _DENSE[id(robot)] = (robot, dest, zero_cols)
    return dest, zero_cols


_NO_COLUMNS = np.zeros(0, dtype=np.int64)


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
    if dest is None:
        dest, zero_cols = _dense_layout(robot)
        if out is None:
            out = np.empty((nsamp, n, 10 * n))
        flat = out.reshape(nsamp, n * 10 * n)
    else:
        if out is None:
            raise ValueError("rigid_regressor: a compact dest needs an out array")
        flat, zero_cols = out, _NO_COLUMNS
    args = (q, qd, qdd, *robot_arrays(robot), np.ascontiguousarray(dest, np.int64), flat)
    threads = kernel_threads()
    if threads == 1 or nsamp < 512:  # one part either way: no thread launch
        _regressor_part(*args, 0, nsamp, zero_cols)
    else:
        _regressor_kernel(*args, threads, zero_cols)
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
