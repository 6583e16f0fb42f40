"""What the logs measure besides the model: drive currents (current → torque gains, given or
identified) and the model file's known torques (subtracted before identification).

A current gain turns a logged current into a torque on the log's side (motor torque per
ampere with ``--motor-side``, joint torque per ampere otherwise). A gain left out
(``null``) is identified with the model's parameters when the data fixes the torque's scale.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from robid_link.exceptions import DataError
from robid_link.ident.data.logs import Log
from robid_link.ident.data.preprocess import Prepared, Problem
from robid_link.ident.fit.design import Design, block_columns, design_chunks, random_states
from robid_link.ident.model.effects import Block
from robid_link.ident.model.known import KnownTorque, known_torque_total
from robid_link.ident.model.robot import Robot

__all__ = ["torque_from_currents", "without_known_torques", "CurrentGains",
           "identify_current_gains", "with_currents", "unidentifiable_gains"]


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


def without_known_torques(pb: Problem, known: Sequence[KnownTorque]) -> Problem:
    """The problem with τ − τ_known on every prepared log (raw and filtered torques alike;
    the known torque is evaluated on the filtered states, as the regressor columns are)."""
    if not known:
        return pb
    preps = [_without_known(prep, known) for prep in pb.preps]
    vpreps = [_without_known(prep, known) for prep in pb.vpreps]
    fixed = [kt.label + (f" (identified: {', '.join(kt.identify)})" if kt.identify else "")
             for kt in known]
    return pb.with_preps(preps, vpreps, [
        f"known torque(s) {'; '.join(fixed)}: subtracted from the measured torque before "
        "identification and added back in predictions"])


def _without_known(prep: Prepared, known: Sequence[KnownTorque]) -> Prepared:
    """τ − τ_known; the filtered torque follows (filtering is linear: the filter of the
    difference is the difference of the filtered torques)."""
    tk = np.zeros_like(prep.tau)
    for seg in prep.log.segments:
        if seg.stop - seg.start < 3 * prep.filt.settle:
            continue  # not prepared (too short to filter), never used
        tk[seg] = known_torque_total(tuple(known), prep.q[seg], prep.qd[seg], prep.qdd[seg])
    return replace(prep, log=replace(prep.log, tau=prep.log.tau - tk), tau_known=tk)


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


@dataclass(frozen=True)
class CurrentGains:
    """Identified current → torque gains of the drives logged without one."""

    motors: np.ndarray  # 0-based drives whose gain was identified
    gains: np.ndarray  # N·m/A on the logs' side
    std: np.ndarray
    side: str  # "motor" (motor-side logs) or "joint"

    def notes(self) -> list[str]:
        return [f"current_gain of joint {m + 1} identified: {g:.6g} N·m/A ({self.side} side, "
                f"std {100 * s / abs(g):.2g} %)"
                for m, g, s in zip(self.motors, self.gains, self.std, strict=True)]


def identify_current_gains(pb: Problem, design: Design, known: Sequence[KnownTorque]
                           ) -> CurrentGains | None:
    """Estimate the gains left out, with the model's base parameters, on the training rows
    (parallel-filtered, like the torques); ``with_currents`` then completes every log's
    torque with them. None when no log holds a current. Refused, naming the drive, when the
    data cannot fix a gain.

    The fit is in motor space with the current as the measured quantity (output error:
    i_m = (1/K_m)·(A θ − z)_m, A = M⁻¹ W): an equation-error fit (K_m·i_m = …) would put the
    current's noise into a regressor column and bias K towards zero wherever only a small
    part of the torque fixes its scale. Started from the equation-error fit, Gauss-Newton on
    per-motor Gram matrices (one pass over the data)."""
    preps = [p for p in (*pb.preps, *pb.vpreps) if p.log.currents is not None]
    if not preps:
        return None
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
    grams, rows = _motor_grams(pb, design)
    filt = pb.preps[0].filt
    # filtered rows are correlated over about fs / (2 fc) samples: fewer independent rows
    corr = max(1.0, filt.fs / pb.interval / (2.0 * filt.cutoff_hz)) if filt.active else 1.0
    _, gains, std = _fit_gains(grams, rows / corr, motors, design.p)
    return CurrentGains(motors, gains, std, "motor" if pb.transmission is not None else "joint")


def with_currents(prep: Prepared, found: CurrentGains) -> Prepared:
    """The prepared log with its logged currents turned into torque by the identified gains
    (raw and filtered torque completed); unchanged when it logs no current."""
    if prep.log.currents is None:
        return prep
    add = np.einsum("snu,u->sn", _current_columns(prep, found.motors, prep.log.currents),
                    found.gains)
    # the filtered torque follows the completed torque (filtering is linear)
    return replace(prep, log=replace(prep.log, tau=prep.log.tau + add, currents=None,
                                     current=None))


def _motor_grams(pb: Problem, design: Design) -> tuple[np.ndarray, int]:
    """Per motor m, the Gram of [A_m, i_m, z_m] over the training rows: A = M⁻¹ W (the model's
    motor torques per parameter), i the filtered current (zero where the gain is known), z
    = M⁻¹ y (the torque already known: given gains, minus known torques)."""
    n, p = pb.robot.n, design.p
    m_inv = np.eye(n) if pb.transmission is None else np.linalg.inv(pb.transmission.T)
    grams = np.zeros((n, p + 2, p + 2))
    rows = 0
    for pc in pb.train:
        prep = pc.prep
        cur = np.zeros_like(prep.tau)
        if prep.log.currents is not None:
            for seg in prep.log.segments:
                if seg.stop - seg.start >= 3 * prep.filt.settle:
                    cur[seg] = prep.filt.apply(prep.log.currents[seg])
        for c, y, idx in design_chunks(design, pc, pb.interval, chunk=8192):
            a = np.zeros((idx.size, n, p))
            for j in range(n):
                cj = c[:, design.joint_slice(j)]
                for m in np.flatnonzero(m_inv[:, j]).tolist():
                    a[:, m, design.support[j]] += m_inv[m, j] * cj
            z = y @ m_inv.T
            for m in range(n):
                x = np.column_stack((a[:, m, :], cur[idx, m], z[:, m]))
                grams[m] += x.T @ x
            rows += idx.size
    return grams, rows


def _fit_gains(grams: np.ndarray, rows: float, motors: np.ndarray, p: int
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """θ and the unknown gains K from the per-motor Grams (see identify_current_gains)."""
    u = motors.size
    unknown = {int(m): k for k, m in enumerate(motors)}
    ia, za = p, p + 1
    # equation error, the start: known rows A θ = z, unknown rows A θ − K i = z
    h = np.zeros((p + u, p + u))
    b = np.zeros(p + u)
    for m, g in enumerate(grams):
        k = unknown.get(m)
        idx = np.r_[np.arange(p), [] if k is None else [p + k]].astype(int)
        sel = np.r_[np.arange(p), [] if k is None else [ia]].astype(int)
        sign = np.r_[np.ones(p), [] if k is None else [-1.0]]
        h[np.ix_(idx, idx)] += g[np.ix_(sel, sel)] * np.outer(sign, sign)
        b[idx] += g[sel, za] * sign
    x = _solve(h, b)
    theta, gain = x[:p], x[p:]
    inv_g = 1.0 / np.where(np.abs(gain) > 1e-12, gain, 1e-12)
    for _ in range(50):  # Gauss-Newton on the output error, weights K̂² (torque units)
        h, b, rss = np.zeros((p + u, p + u)), np.zeros(p + u), 0.0
        for m, g in enumerate(grams):
            ata, ati, atz = g[:p, :p], g[:p, ia], g[:p, za]
            k = unknown.get(m)
            if k is None:
                h[:p, :p] += ata
                b[:p] += atz - ata @ theta
                rss += g[za, za] - 2 * theta @ atz + theta @ ata @ theta
                continue
            w = gain[k] ** 2
            s_i = theta @ ati - g[za, ia]
            s_s = theta @ ata @ theta - 2 * theta @ atz + g[za, za]
            ata_s = ata @ theta - atz  # Aᵀs
            gk = inv_g[k]
            h[:p, :p] += w * gk * gk * ata
            h[:p, p + k] += w * gk * ata_s
            h[p + k, :p] += w * gk * ata_s
            h[p + k, p + k] += w * s_s
            b[:p] += w * gk * (ati - gk * ata_s)
            b[p + k] += w * (s_i - gk * s_s)
            rss += w * (g[ia, ia] - 2 * gk * s_i + gk * gk * s_s)
        step = _solve(h, b)
        theta, inv_g = theta + step[:p], inv_g + step[p:]
        gain = 1.0 / inv_g
        if np.all(np.abs(step[p:]) <= 1e-10 * np.abs(inv_g)):
            break
    scale = np.sqrt(np.maximum(np.diag(h), 1e-300))
    cov = np.linalg.pinv(h / np.outer(scale, scale), rcond=1e-12) / np.outer(scale, scale)
    var_g = np.clip(np.diag(cov)[p:], 0.0, None) * max(rss, 0.0) / max(rows - p - u, 1.0)
    return theta, gain, np.sqrt(var_g) * gain**2  # std of K = std of 1/K · K²


def _solve(h: np.ndarray, b: np.ndarray) -> np.ndarray:
    scale = np.sqrt(np.maximum(np.diag(h), 1e-300))
    return np.linalg.lstsq(h / np.outer(scale, scale), b / scale, rcond=1e-12)[0] / scale
