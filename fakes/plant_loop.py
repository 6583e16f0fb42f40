"""The simulated plant's closed loop compiled (numba): the same semi-implicit time stepping,
controller, elastic joints and stick-slip step as ``Plant._integrate``, for plants whose
joint effects are viscous and Coulomb friction and elasticity (what the elasticity campaign
and the closed-loop benchmarks simulate). ``Plant`` falls back to its Python loop otherwise.

Forward dynamics are M(q)⁻¹ (τ − c(q, q̇) − g(q)) from the model's own RNEA (``dynamics``),
which equals Pinocchio's ABA to rounding.
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
import pinocchio as pin

from robid_link.ident.model.dynamics import (
    cholesky,
    cholesky_inverse,
    cholesky_solve,
    mass_matrix,
    placements,
    rnea_at,
    rnea_one,
)
from robid_link.ident.model.regressor import robot_arrays
from robid_link.ident.model.robot import Robot

__all__ = ["COMPILED_EFFECTS", "integrate", "model_params"]

#: the joint effects the compiled loop simulates
COMPILED_EFFECTS = frozenset({"viscous", "coulomb", "elasticity"})


def model_params(model: pin.Model) -> np.ndarray:
    """Standard parameters (10 per link) of a Pinocchio model's bodies."""
    return np.concatenate([np.array(model.inertias[j].toDynamicParameters())
                           for j in range(1, model.njoints)])


def integrate(robot: Robot, params: np.ndarray, t: np.ndarray, sub: int,
              effects: dict[str, np.ndarray], q0: np.ndarray, v0: np.ndarray,
              controller: dict[str, Any] | None, tau_motor: np.ndarray | None
              ) -> tuple[np.ndarray, ...]:
    """Logs (q, q̇, q̈, τ) per sample, as ``Plant._integrate``: ``controller`` holds the PID
    gains and the reference (closed loop), else ``tau_motor`` is applied (open loop)."""
    r0s, p0s, axes, revolute, parents, _, gravity = robot_arrays(robot)
    n = robot.n
    if controller is not None:
        gains = np.array([controller["kp"], controller["kd"], controller["ki"]])
        ref = np.stack((controller["q"], controller["qd"], controller["qdd"]))
        nominal = np.ascontiguousarray(controller["nominal"], dtype=float)
        torques = np.zeros((1, n))
    else:
        gains = np.zeros(3)
        ref = np.zeros((3, 1, n))
        nominal = np.zeros(10 * n)
        torques = np.ascontiguousarray(tau_motor, dtype=float)
    logs = np.empty((4, t.size, n))
    _loop(r0s, p0s, axes, revolute, parents, gravity, np.ascontiguousarray(params, float),
          nominal, controller is not None, gains, ref, torques, float(t[1] - t[0]) / sub, sub,
          t.size, effects["fv"], effects["fc"], effects["elastic"], effects["k"],
          effects["d"], effects["jm"], effects["j2"], effects["k2"], effects["d2"],
          np.array(q0, dtype=float), np.array(v0, dtype=float), logs)
    return logs[0], logs[1], logs[2], logs[3]


@numba.njit(cache=True, nogil=True)
def _dynamics(q, v, arrays, params, scratch, bias, lo):
    """The bias forces RNEA(q, q̇, 0) and the Cholesky factor of M(q)."""
    r0s, p0s, axes, revolute, parents, gravity = arrays
    vel, acc, frc, rot, pos = scratch
    n = q.shape[0]
    placements(q, r0s, p0s, axes, revolute, rot, pos)
    rnea_at(v, np.zeros(n), axes, revolute, parents, gravity, params, True, vel, acc, frc,
            rot, pos, bias)
    m = np.empty((n, n))
    mass_matrix(axes, revolute, parents, gravity, params, scratch, m)
    cholesky(m, lo)


@numba.njit(cache=True, nogil=True)
def _inverse(lo, out):
    """(L Lᵀ)⁻¹ from the Cholesky factor L."""
    n = lo.shape[0]
    e = np.zeros(n)
    col = np.empty(n)
    for i in range(n):
        e[i] = 1.0
        cholesky_solve(lo, e, col)
        out[:, i] = col
        e[i] = 0.0


@numba.njit(cache=True, nogil=True)
def _solve(a, b):
    """x with a x = b for a small symmetric positive definite a."""
    inv = np.empty_like(a)
    cholesky_inverse(a, inv)
    return _matvec(inv, b)


@numba.njit(cache=True, nogil=True)
def _matvec(a, x):
    out = np.zeros(a.shape[0])
    for i in range(a.shape[0]):
        s = 0.0
        for k in range(x.size):
            s += a[i, k] * x[k]
        out[i] = s
    return out


@numba.njit(cache=True, nogil=True)
def _stick_slip(v_free, bound, minv, h):
    """Velocity after one step of Coulomb friction with bounds F (≥ 0) per joint: as the
    plant's ``_stick_slip`` (active set on the sticking joints, a few sweeps)."""
    n = v_free.size
    stick = np.zeros(n, dtype=np.bool_)
    direction = -np.sign(v_free)
    v_new = v_free.copy()
    for _ in range(2 * n + 2):
        force = np.where(stick, 0.0, direction * bound)
        if stick.any():
            s_idx = np.flatnonzero(stick)
            rhs_all = -(v_free + h * _matvec(minv, force))
            rhs = rhs_all[s_idx] / h
            sub = np.empty((s_idx.size, s_idx.size))
            for a in range(s_idx.size):
                for b in range(s_idx.size):
                    sub[a, b] = minv[s_idx[a], s_idx[b]]
            sol = _solve(sub, rhs)
            for a in range(s_idx.size):
                force[s_idx[a]] = sol[a]
        v_new = v_free + h * _matvec(minv, force)
        crossed = ~stick & (bound > 0) & (np.sign(v_new) != -direction)
        released = stick & (np.abs(force) > bound * (1 + 1e-9))
        if not crossed.any() and not released.any():
            return np.where(stick, 0.0, v_new)
        stick = (stick | crossed) & ~released
        direction = np.where(released, np.sign(force), direction)
    return np.where(stick, 0.0, v_new)


@numba.njit(cache=True, nogil=True)
def _loop(r0s, p0s, axes, revolute, parents, gravity, params, nominal, closed, gains, ref,
          torques, h, sub, n_samples, fv, fc, elastic, k_el, d_el, jm, j2, k2, d2, q0, v0,
          logs):
    n = q0.size
    arrays = (r0s, p0s, axes, revolute, parents, gravity)
    scratch = (np.empty((n, 6)), np.empty((n, 6)), np.empty((n, 6)), np.empty((n, 3, 3)),
               np.empty((n, 3)))
    minv, lo = np.empty((n, n)), np.empty((n, n))
    bias = np.empty(n)
    q, v = q0.copy(), v0.copy()
    th, thd = q.copy(), v.copy()  # motor side of elastic joints (joint units)
    th2, thd2 = q.copy(), v.copy()  # third masses
    rel_prev = np.zeros(n)
    integral = np.zeros(n)
    acc = np.empty(n)
    cmd_acc = np.empty(n)
    tau_cmd = np.empty(n)
    tau_third = np.zeros(n)
    kp, kd, ki = gains[0], gains[1], gains[2]
    for k in range(n_samples):
        for step in range(sub):
            q_meas = np.where(elastic, th, q)
            qd_meas = np.where(elastic, thd, v)
            if closed:  # computed-torque PID on the a-priori model
                for j in range(n):
                    err = ref[0, k, j] - q_meas[j]
                    integral[j] += h * err
                    cmd_acc[j] = (ref[2, k, j] + kp * err + kd * (ref[1, k, j] - qd_meas[j])
                                  + ki * integral[j])
                rnea_one(q_meas, qd_meas, cmd_acc, r0s, p0s, axes, revolute, parents, gravity,
                         nominal, True, scratch[0], scratch[1], scratch[2], scratch[3],
                         scratch[4], tau_cmd)
            else:
                tau_cmd[:] = torques[k]
            tau_arm = tau_cmd.copy()
            for j in range(n):
                if elastic[j]:  # the arm feels the spring, the motor drives it
                    rel = thd[j] - v[j]
                    tau_arm[j] = k_el[j] * (th[j] - q[j]) + d_el[j] * (1.5 * rel
                                                                         - 0.5 * rel_prev[j])
                    rel_prev[j] = rel
            for j in range(n):
                if elastic[j] and j2[j] > 0:
                    tau_third[j] = k2[j] * (q[j] - th2[j]) + d2[j] * (v[j] - thd2[j])
                    tau_arm[j] -= tau_third[j]
            f_smooth = fv * v
            # fast path: every joint keeps slipping the way it moves
            _dynamics(q, v, arrays, params, scratch, bias, lo)
            cholesky_solve(lo, tau_arm - f_smooth - fc * np.sign(v) - bias, acc)
            v_new = v + h * acc
            crossing = (fc > 0) & ((v == 0) | (np.sign(v_new) != np.sign(v)))
            if crossing.any():  # exact step: active set with the full M⁻¹
                cholesky_solve(lo, tau_arm - f_smooth - bias, acc)
                v_free = v + h * acc
                _inverse(lo, minv)
                v_new = _stick_slip(v_free, fc, minv, h)
            for j in range(n):
                if elastic[j]:
                    thd[j] += h * (tau_cmd[j] - tau_arm[j]) / jm[j]
                    th[j] += h * thd[j]
                    if j2[j] > 0:
                        thd2[j] += h * tau_third[j] / j2[j]
                        th2[j] += h * thd2[j]
            if step == 0:
                logs[0, k] = q_meas
                logs[1, k] = qd_meas
                logs[2, k] = (v_new - v) / h
                logs[3, k] = tau_cmd
            v = v_new
            q = q + h * v
