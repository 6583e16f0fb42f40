"""What the logs measure besides the model: drive currents (current → torque gains, given or
identified) and the model file's known torques (subtracted before identification).

A current gain turns a logged current into a torque on the log's side (motor torque per
ampere with ``--motor-side``, joint torque per ampere otherwise). A gain left out
(``null``) is identified with the model's parameters when the data fixes the torque's scale.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from robid_link.exceptions import DataError
from robid_link.ident.data import Log
from robid_link.ident.design import Design, block_columns, design_chunks, random_states
from robid_link.ident.effects import Block
from robid_link.ident.known import KnownTorque, known_torque_total
from robid_link.ident.preprocess import Prepared, Problem
from robid_link.ident.robot import Robot

__all__ = ["torque_from_currents", "subtract_known_torques", "identify_current_gains",
           "unidentifiable_gains"]


def _gain_key(robot: Robot) -> str:
    return ("transmission.current_gain" if robot.source.endswith((".yaml", ".yml"))
            else "transmission.current_gain (in the robot's .transmission.yaml)")


def torque_from_currents(robot: Robot, log: Log) -> Log:
    """Columns logged as currents become torques (on the log's side) through the given
    gains; drives without a gain keep their raw current in ``log.currents`` and contribute
    nothing to ``tau`` until their gain is identified."""
    if log.current is None:
        return log
    gains = robot.current_gain if robot.current_gain is not None else np.full(robot.n, math.nan)
    known = log.current & np.isfinite(gains)
    unknown = log.current & ~np.isfinite(gains)
    tau = log.tau.copy()
    tau[:, known] *= gains[known]
    currents = None
    if unknown.any():
        currents = np.zeros_like(tau)
        currents[:, unknown] = log.tau[:, unknown]
        tau[:, unknown] = 0.0
    return replace(log, tau=tau, currents=currents, current=unknown if unknown.any() else None)


def _current_columns(prep: Prepared, motors: np.ndarray, raw: np.ndarray) -> np.ndarray:
    """(N, n, u): each unknown-gain drive's current as joint torques at unit gain (τ_joint =
    Tᵀ τ_motor for motor-side logs)."""
    m = np.eye(raw.shape[1]) if prep.transmission is None else prep.transmission
    return raw[:, None, motors] * m[motors].T[None, :, :]


def subtract_known_torques(pb: Problem, known: Sequence[KnownTorque]) -> list[str]:
    """τ − τ_known on every prepared log (raw and filtered torques alike; the known torque
    is evaluated on the filtered states, as the regressor columns are)."""
    if not known:
        return []
    for prep in (*pb.preps, *pb.vpreps):
        tk = np.zeros_like(prep.tau)
        for seg in prep.log.segments:
            if seg.stop - seg.start < 3 * prep.filt.settle:
                continue  # not prepared (too short to filter), never used
            tk[seg] = known_torque_total(tuple(known), prep.q[seg], prep.qd[seg], prep.qdd[seg])
            prep.tau_f[seg] -= prep.filt.apply(tk[seg])
        prep.log = replace(prep.log, tau=prep.log.tau - tk)
        prep.tau_known = tk
    fixed = [kt.label + (f" (identified: {', '.join(kt.identify)})" if kt.identify else "")
             for kt in known]
    return [f"known torque(s) {'; '.join(fixed)}: subtracted from the measured torque before "
            "identification and added back in predictions"]


def unidentifiable_gains(robot: Robot, blocks: Sequence[Block], known: Sequence[KnownTorque],
                         motors: np.ndarray, transmission: np.ndarray | None) -> list[int]:
    """Drives (0-based) whose gain the model cannot separate from its parameters: their
    current columns, for generic parameters, lie in the model's column space together."""
    rng = np.random.default_rng(31)
    st = random_states(robot, rng, max(200, 6 * robot.n * 12), transmission)
    w = block_columns(robot, blocks, st)
    theta = rng.normal(size=w.shape[2])
    tau = np.einsum("snp,p->sn", w, theta) + known_torque_total(tuple(known), st.q, st.qd, st.qdd)
    m = np.eye(robot.n) if transmission is None else transmission
    tau_motor = tau @ np.linalg.inv(m)  # τ_joint = Tᵀ τ_motor (rows: samples)
    u = tau_motor[:, None, motors] * m[motors].T[None, :, :]
    a = np.concatenate([w.reshape(-1, w.shape[2]), u.reshape(-1, motors.size)], axis=1)
    a = a / np.maximum(np.linalg.norm(a, axis=0), 1e-300)
    _, sv, vt = np.linalg.svd(a, full_matrices=False)
    null = vt[sv < sv[0] * 1e-9]
    part = np.linalg.norm(null[:, w.shape[2]:], axis=0) if null.size else np.zeros(motors.size)
    return [int(motors[k]) for k in np.flatnonzero(part > 1e-6)]


def identify_current_gains(pb: Problem, design: Design, known: Sequence[KnownTorque]
                           ) -> list[str]:
    """Estimate the gains left out, with the model's base parameters, by least squares on
    the training rows (parallel-filtered, like the torques); then every log's torque is
    completed with them. Refused, naming the drive, when the data cannot fix a gain."""
    preps = [p for p in (*pb.preps, *pb.vpreps) if p.log.currents is not None]
    if not preps:
        return []
    masks = [(p in pb.preps, p.log.current) for p in preps if p.log.current is not None]
    motors = np.flatnonzero(np.any([m for _, m in masks], axis=0))
    trained = np.any([m for tr, m in masks if tr] or [np.zeros(pb.robot.n, bool)], axis=0)
    if not trained[motors].all():
        j = int(motors[~trained[motors]][0]) + 1
        raise DataError(f"current_gain of joint {j}: the --validate logs hold its current but "
                        f"the data logs do not, so nothing identifies it; give "
                        f"{_gain_key(pb.robot)}")
    bad = unidentifiable_gains(pb.robot, pb.blocks, known, motors, pb.transmission)
    if bad:
        j = bad[0] + 1
        others = f" (and of {', '.join(str(b + 1) for b in bad[1:])})" if bad[1:] else ""
        raise DataError(f"current_gain of joint {j}{others}: not identifiable from these logs "
                        "(the torque scale needs a known payload or known torque); give "
                        f"{_gain_key(pb.robot)}")
    p, u = design.p, motors.size
    gram = np.zeros((p + u, p + u))
    rhs = np.zeros(p + u)
    yy, rows = 0.0, 0
    filtered: dict[int, np.ndarray] = {}
    for pc in pb.train:
        prep = pc.prep
        if prep.log.currents is None:
            cur = None
        else:
            if id(prep) not in filtered:
                raw = np.zeros_like(prep.log.currents)
                for seg in prep.log.segments:
                    if seg.stop - seg.start >= 3 * prep.filt.settle:
                        raw[seg] = prep.filt.apply(prep.log.currents[seg])
                filtered[id(prep)] = raw
            cur = filtered[id(prep)]
        for c, tau, idx in design_chunks(design, pc, pb.interval):
            ucols = (np.zeros((idx.size, pb.robot.n, u)) if cur is None
                     else _current_columns(prep, motors, cur[idx]))
            for j in range(pb.robot.n):
                sup = np.concatenate((design.support[j], p + np.arange(u)))
                x = np.concatenate((c[:, design.joint_slice(j)], -ucols[:, j, :]), axis=1)
                gram[np.ix_(sup, sup)] += x.T @ x
                rhs[sup] += x.T @ tau[:, j]
                yy += float(tau[:, j] @ tau[:, j])
                rows += idx.size
    scale = np.sqrt(np.maximum(np.diag(gram), 1e-300))
    g_s = gram / np.outer(scale, scale)
    sol_s = np.linalg.lstsq(g_s, rhs / scale, rcond=1e-12)[0]
    sol = sol_s / scale
    rss = max(yy - 2 * sol @ rhs + sol @ gram @ sol, 0.0)
    cov = np.linalg.pinv(g_s, rcond=1e-12) / np.outer(scale, scale) * rss / max(rows - p - u, 1)
    gains = sol[p:]
    std = np.sqrt(np.clip(np.diag(cov)[p:], 0.0, None))
    for prep in (*pb.preps, *pb.vpreps):
        if prep.log.currents is None:
            continue
        cols = _current_columns(prep, motors, prep.log.currents)
        add = np.einsum("snu,u->sn", cols, gains)
        for seg in prep.log.segments:
            if seg.stop - seg.start >= 3 * prep.filt.settle:
                prep.tau_f[seg] += prep.filt.apply(add[seg])
        prep.log = replace(prep.log, tau=prep.log.tau + add, currents=None, current=None)
    side = "motor" if pb.transmission is not None else "joint"
    return [f"current_gain of joint {m + 1} identified: {g:.6g} N·m/A ({side} side, std "
            f"{100 * s / abs(g) if g else math.inf:.2g} %)" for m, g, s in zip(motors, gains, std,
                                                                            strict=True)]
