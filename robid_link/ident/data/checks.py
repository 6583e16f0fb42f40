"""The logs checked against the robot: saturation, position units and offsets, sign and scale
against the a-priori model, and validation motions outside the training ranges.

Each check returns its messages; ``data_checks`` (identify's step) warns them.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from robid_link.exceptions import DataWarning, ExcitationWarning
from robid_link.ident.data.preprocess import CHUNK, Prepared, Problem
from robid_link.ident.model.regressor import rigid_regressor
from robid_link.ident.model.robot import Robot
from robid_link.ident.model.threads import in_slots

__all__ = ["data_checks", "sanity_checks", "extrapolation"]


def data_checks(pb: Problem, stacklevel: int = 3) -> list[str]:
    """The checks' notes, each also warned (``DataWarning``, then ``ExcitationWarning``) at
    ``stacklevel`` (default: the caller of the function that calls this step). The filtered
    states are read in one pass for both kinds of checks."""
    scan = _scan(pb, ranges=bool(pb.valid))
    out = sanity_checks(pb, nominal=pb.robot.nominal is not None, scan=scan)
    for msg in out:
        warnings.warn(msg, DataWarning, stacklevel=stacklevel)
    if not pb.valid:
        return out
    outside = extrapolation(pb, scan)
    for msg in outside:
        warnings.warn(msg, ExcitationWarning, stacklevel=stacklevel)
    return out + outside


@dataclass
class _Scan:
    """What the checks read of a problem's filtered states: per data log (by position) its
    thinned rows (q, q̇, q̈, filtered τ: ``_thinned``), and the ranges (2, 3, n: min and
    max of q, q̇, q̈) over the training and the validation rows."""

    rows: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]
    ranges: dict[str, np.ndarray]


def _thinned(prep: Prepared) -> slice:
    """The rows the sanity checks read: about 4000, the filter's edges left out."""
    return slice(prep.filt.settle, len(prep.log) - prep.filt.settle,
                 max(1, len(prep.log) // 4000))


def _scan(pb: Problem, ranges: bool = True) -> _Scan:
    """One pass over the logs' filtered states, window by window in ``in_slots`` (each
    window's figures kept and combined in order): the data logs' thinned rows and, with
    ``ranges``, the state ranges of the training and validation rows."""
    roles = {"train": pb.train, "valid": pb.valid} if ranges else {}
    preps = [*pb.preps, *pb.vpreps]
    tasks = [(k, lo) for k, prep in enumerate(preps) for lo in range(0, len(prep.log), CHUNK)]
    out: list[tuple[tuple[np.ndarray, ...] | None, dict[str, np.ndarray]] | None]
    out = [None] * len(tasks)

    def work(t: int, slot: int) -> None:
        k, lo = tasks[t]
        prep = preps[k]
        hi = min(lo + CHUNK, len(prep.log))
        sl = _thinned(prep) if k < len(pb.preps) else None
        sel = None if sl is None else np.arange(*sl.indices(len(prep.log)))
        sel = None if sel is None else sel[(sel >= lo) & (sel < hi)] - lo
        spans = {role: [(max(pc.lo, lo) - lo, min(pc.hi, hi) - lo) for pc in pieces
                        if pc.prep is prep and max(pc.lo, lo) < min(pc.hi, hi)]
                 for role, pieces in roles.items()}
        if (sel is None or not sel.size) and not any(spans.values()):
            out[t] = (None, {})
            return
        kin = prep.kinematics(lo, hi)
        rows = None
        if sel is not None and sel.size:
            rows = (*(arr[sel] for arr in kin), prep.tau_f_rows(lo, hi)[sel])
        found = {}
        for role, where in spans.items():
            if where:  # extrema over the role's rows of this window, joints × rows
                cols = [np.array(arr[a:b].T, order="C") for a, b in where for arr in kin]
                found[role] = np.stack([
                    np.stack([np.min([c.min(axis=1) for c in cols[i::3]], axis=0)
                              for i in range(3)]),
                    np.stack([np.max([c.max(axis=1) for c in cols[i::3]], axis=0)
                              for i in range(3)])])
        out[t] = (rows, found)

    in_slots(range(len(tasks)), work)
    n = pb.robot.n
    thinned = []
    for k in range(len(pb.preps)):
        parts = [done[0] for (kk, _), done in zip(tasks, out, strict=True)
                 if kk == k and done is not None and done[0] is not None]
        thinned.append(tuple(np.concatenate([p[i] for p in parts]) if parts
                             else np.zeros((0, n)) for i in range(4)))
    found = {}
    for role in roles:
        lo_hi = [done[1][role] for done in out if done is not None and role in done[1]]
        found[role] = np.stack((np.min([f[0] for f in lo_hi], axis=0),
                                np.max([f[1] for f in lo_hi], axis=0)))
    return _Scan(thinned, found)  # type: ignore[arg-type]


def extrapolation(pb: Problem, scan: _Scan | None = None) -> list[str]:
    """Where the validation rows leave the training ranges of q, q̇, q̈ (> 5 % of the span)."""
    scan = _scan(pb) if scan is None else scan
    tr, va = scan.ranges["train"], scan.ranges["valid"]
    span = np.maximum(tr[1] - tr[0], 1e-9)
    out = []
    for k, qty in enumerate(("q", "qd", "qdd")):
        excess = np.maximum(va[1][k] - tr[1][k], tr[0][k] - va[0][k]) / span[k]
        for j in np.flatnonzero(excess > 0.05):
            out.append(f"validation leaves the training range of {qty}{j + 1} by "
                       f"{100 * excess[j]:.0f} % of its span: the model extrapolates there")
    return out


def sanity_checks(pb: Problem, nominal: bool, scan: _Scan | None = None) -> list[str]:
    """Torque saturation, and sign/scale of each joint against the a-priori model (``scan``:
    the problem's thinned rows, read here when not given)."""
    robot = pb.robot
    scan = _scan(pb, ranges=False) if scan is None else scan
    out = []
    for prep, thinned in zip(pb.preps, scan.rows, strict=True):
        tau = prep.log.tau
        name = Path(prep.log.path).name
        q_span = _extrema(prep.log.q)
        if pb.transmission is None:
            out += _position_checks(robot, *q_span, name)
        q, qd, qdd, meas = thinned  # no whole array of a long log
        out += _speed_check(robot, prep, qd, q_span[1] - q_span[0], name)
        low, high = _extrema(tau)
        peak = np.maximum(high, -low)  # |τ|'s peak
        flat = max(5, int(0.05 * prep.filt.fs))  # a clipped signal sits flat at its peak
        held = prep.log.held  # a partial log: no checks of torques it does not hold
        for j in np.flatnonzero(held).tolist():
            level = peak[j] - 1e-9 * max(peak[j], 1.0)
            col = tau[:, j]
            at_peak = np.abs(col) >= level
            limit = robot.limits.tau_max[j]
            if peak[j] > 0 and _longest_run(at_peak) >= flat:
                out.append(f"{name}: tau{j + 1} sits flat at {peak[j]:.3g} N·m "
                           f"({100 * at_peak.mean():.1f} % of samples): saturation?")
            elif np.isfinite(limit) and peak[j] >= 0.98 * limit:
                out.append(f"{name}: tau{j + 1} reaches {peak[j]:.3g} N·m, at or above its "
                           f"limit {limit:.3g} N·m: saturation or a wrong limit?")
        if nominal:
            pred = rigid_regressor(robot, q, qd, qdd) @ robot.nominal
            for j in np.flatnonzero(held).tolist():
                sp, sm = pred[:, j].std(), meas[:, j].std()
                if sp < 1e-9 or sm < 1e-9:
                    continue
                r = np.corrcoef(pred[:, j], meas[:, j])[0, 1]
                ratio = sm / sp
                scale, sigma = (_model_scale((qd, qdd, meas), pred, j) if r < 0
                                else (1.0, 0.0))
                if scale < -0.5 and scale < -SIGN_SIGMAS * sigma:  # the sign's evidence
                    out.append(f"{name}: tau{j + 1} has the opposite sign of the a-priori "
                               f"model (scale {scale:.3g} ± {sigma:.2g} beside friction and "
                               f"rotor inertia; correlation {r:.2f}): sign convention?")
                elif r > 0.5 and not 1 / 3 < ratio < 3:
                    out.append(f"{name}: tau{j + 1} is {ratio:.3g}× the a-priori model's "
                               f"torque: {_scale_cause(robot, (qd, qdd, meas), pred, j, ratio)}")
    return out


def _extrema(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each column's minimum and maximum (samples × joints), column by column: numpy reduces
    a (rows, n) array along its rows slowly, and a copy of a long log's is large."""
    return (np.array([x[:, j].min() for j in range(x.shape[1])]),
            np.array([x[:, j].max() for j in range(x.shape[1])]))


def _position_checks(robot: Robot, q_min: np.ndarray, q_max: np.ndarray, name: str
                     ) -> list[str]:
    """Joint positions (spanning [q_min, q_max] per joint) far outside the robot's limits,
    with the likely cause: a motor-side log (positions/ratio inside the limits), degrees, or
    an encoder offset."""
    lim = robot.limits
    ratios = (np.abs(np.diag(robot.transmission)) if robot.transmission is not None
              else np.ones(robot.n))
    out = []
    for j in range(robot.n):
        lo, hi = float(lim.q_min[j]), float(lim.q_max[j])
        if not (np.isfinite(lo) and np.isfinite(hi)) or hi <= lo:
            continue
        qmin, qmax = float(q_min[j]), float(q_max[j])
        margin = 0.05 * (hi - lo)
        if qmin >= lo - margin and qmax <= hi + margin:
            continue
        where = (f"{name}: q{j + 1} spans [{qmin:.4g}, {qmax:.4g}] against its limits "
                 f"[{lo:.4g}, {hi:.4g}]")
        ratio = float(ratios[j])
        if ratio > 1.5 and qmin / ratio >= lo - margin and qmax / ratio <= hi + margin:
            out.append(f"{where}: looks motor-side (divided by the gear ratio {ratio:.4g} it "
                       "fits): use --motor-side")
        elif math.radians(qmin) >= lo - margin and math.radians(qmax) <= hi + margin and \
                qmax - qmin > math.pi:
            out.append(f"{where}: looks like degrees (the log must be in rad)")
        elif qmax - qmin <= hi - lo + margin:
            out.append(f"{where}: the range fits but is shifted: an encoder offset "
                       "(transmission.offsets)?")
        else:
            out.append(f"{where}: wrong units or gear ratio?")
    return out


#: a motion whose every joint stays under this fraction of its speed limit crawls
CRAWL = 1e-3


def _speed_check(robot: Robot, prep: Prepared, qd: np.ndarray, span: np.ndarray, name: str
                 ) -> list[str]:
    """A motion that spans its joints' ranges (``span``: each joint's max − min position) at a
    crawl no robot excites dynamics with: the time stamps are likely not in seconds
    (milliseconds at a rate the rate check allows). ``qd``: the log's filtered velocities on
    thinned rows."""
    limit = robot.limits.qd_max
    fast = np.percentile(np.abs(qd), 95, axis=0)
    ok = np.isfinite(limit) & (limit > 0)
    if not ok.any() or np.any(fast[ok] >= CRAWL * limit[ok]) or span.max() < 0.05:
        return []
    return [f"{name}: the motion crawls (every joint under {CRAWL:g} of its speed limit over "
            f"{prep.log.t[-1] - prep.log.t[0]:.4g} s): is the time column in seconds?"]


#: a sign alarm needs the a-priori model's scale under −0.5 and this many standard errors
#: below zero
SIGN_SIGMAS = 5.0


def _model_scale(rows: tuple[np.ndarray, np.ndarray, np.ndarray], pred: np.ndarray, j: int
                 ) -> tuple[float, float]:
    """The scale of the a-priori model's torque in joint ``j``'s measured torque, fitted beside
    what it lacks (viscous and Coulomb friction, rotor inertia, an offset), and its standard
    error (the residual's lag-1 correlation widens it: the rows are filtered). A correlation
    below zero alone is no evidence of a flipped sign: friction the model lacks can make it."""
    qd, qdd, meas = (r[:, j] for r in rows)  # q̇, q̈ and the filtered torque of the rows
    cols = np.column_stack([pred[:, j], qd, np.sign(qd), qdd, np.ones_like(qd)])
    coef, *_ = np.linalg.lstsq(cols, meas, rcond=None)
    e = meas - cols @ coef
    rho = float(np.clip(np.corrcoef(e[:-1], e[1:])[0, 1], -0.99, 0.99)) if e.std() > 0 else 0.0
    var = float(e.var()) * (1 + max(rho, 0.0)) / (1 - max(rho, 0.0))
    inv = np.linalg.pinv(cols.T @ cols)
    return float(coef[0]), float(np.sqrt(max(var * inv[0, 0], 0.0)))


def _scale_cause(robot: Robot, rows: tuple[np.ndarray, np.ndarray, np.ndarray],
                 pred: np.ndarray, j: int, ratio: float) -> str:
    """Why a joint's measured torque is ``ratio``× the a-priori model's: when the model plus
    viscous and Coulomb friction and a rotor inertia (which the a-priori model lacks) explain
    the measurement, say that, not 'units'."""
    qd, qdd, meas = (r[:, j] for r in rows)  # q̇, q̈ and the filtered torque of the rows
    cols = np.column_stack([pred[:, j], qd, np.sign(qd), qdd, np.ones_like(qd)])
    coef, *_ = np.linalg.lstsq(cols, meas, rcond=None)
    r2 = 1.0 - float(np.var(meas - cols @ coef)) / max(float(np.var(meas)), 1e-300)
    if 0.5 < coef[0] < 2.0 and r2 > 0.9:
        return (f"the a-priori model lacks friction and rotor inertia (with them it explains "
                f"{100 * r2:.0f} % of the torque at scale {coef[0]:.2f}), not a unit error")
    tx = robot.transmission
    if tx is not None and abs(abs(tx[j, j]) / max(ratio, 1e-12) - 1) < 0.3 or \
            tx is not None and abs(ratio * abs(tx[j, j]) - 1) < 0.3:
        return f"near the gear ratio {abs(tx[j, j]):.4g}: a motor-side torque (--motor-side)?"
    return "gear ratio or units?"


def _longest_run(mask: np.ndarray) -> int:
    """The longest run of True in ``mask``, from its True rows (few: a torque's peak)."""
    idx = np.flatnonzero(mask)
    if not idx.size:
        return 0
    breaks = np.flatnonzero(np.diff(idx) != 1)
    ends = np.concatenate((breaks, [idx.size - 1]))
    starts = np.concatenate(([0], breaks + 1))
    return int((ends - starts).max()) + 1
