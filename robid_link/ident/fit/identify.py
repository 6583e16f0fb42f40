"""The identification pipeline: logs + robot + model → IdentResult.

Orchestrates preprocess → regressor/effects → base set → estimate → validation → checks.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from robid_link.exceptions import ConditioningWarning, DataWarning, ExcitationWarning
from robid_link.ident.data.currents import (
    identify_current_gains,
    subtract_known_torques,
    torque_from_currents,
)
from robid_link.ident.data.logs import Log, file_sha256, load_log
from robid_link.ident.data.preprocess import Piece, Prepared, Problem, build_problem, check_counts
from robid_link.ident.fit.consistent import ConsistentFit, fit_consistent
from robid_link.ident.fit.design import Design, attach_predictions, make_design, structural_mask
from robid_link.ident.fit.estimate import Grams, accumulate, fit
from robid_link.ident.fit.results import (
    ErrorStats,
    IdentResult,
    Parameter,
    evaluate_held_out,
    parameter_unit,
)
from robid_link.ident.model.effects import Model
from robid_link.ident.model.regressor import BaseSet, rigid_regressor
from robid_link.ident.model.robot import Robot

__all__ = ["identify", "load_logs"]

#: condition number of the column-scaled base regressor above which excitation is poor
POOR_EXCITATION_COND = 1e3


def load_logs(robot: Robot, paths: Sequence[str | Path], fs: float | None = None,
              motor_side: bool = False, topic: str | None = None) -> list[Log]:
    """Read logs and bring them to the joint side: currents → torques (the robot's
    ``current_gain``; drives without one keep their current until identification), motor →
    joint side through the transmission, encoder offsets removed. ROS recordings are matched
    to the robot's joints by name (``topic``: which of their topics)."""
    logs = []
    for p in paths:
        log = torque_from_currents(robot, load_log(p, robot.n, fs, joint_names=robot.joint_names,
                                                   topic=topic,
                                                   effort_current=robot.effort_current))
        if motor_side:
            log.q, log.qd, log.qdd, log.tau = robot.to_joint_side(log.q, log.qd, log.qdd, log.tau)
        else:
            log.q = robot.remove_offsets(log.q)
        logs.append(log)
    return logs


def _profile_hypers(pb: Problem) -> dict[str, dict[str, float]]:
    """Choose free hyper-parameters by training RSS over each effect's grid."""
    chosen: dict[str, dict[str, float]] = {}
    free = [(k, b, h) for k, b in enumerate(pb.blocks) for h in b.free_hypers()]
    if not free:
        return chosen
    names = sorted({(b.effect.name, h) for _, b, h in free})
    for eff_name, hyper in names:
        targets = [(k, b) for k, b, h in free if b.effect.name == eff_name and h == hyper]
        grids = {k: b.grid(hyper, pb.robot, pb.transmission) for k, b in targets}
        size = len(next(iter(grids.values())))
        scores = np.full((size, len(pb.blocks)), np.inf)
        for gi in range(size):
            trial = list(pb.blocks)
            for k, b in targets:
                trial[k] = b.with_opts(**{hyper: grids[k][gi]})
            design, _, _ = make_design(pb.robot, trial, pb.transmission)
            f, _ = fit(design, pb.train, pb.interval, pb.block_len, warn=False)
            for k, b in targets:  # a coupled motor's friction loads several joints
                scores[gi, k] = f.rss[b.rows(pb.robot, pb.transmission)].sum()
        for k, b in targets:
            best = float(grids[k][int(np.argmin(scores[:, k]))])
            pb.blocks[k] = b.with_opts(**{hyper: best})
            chosen.setdefault(pb.blocks[k].key, {})[hyper] = best
    return chosen


def identify(robot: Robot, data: Sequence[Log], model: Model, *,
             validate: Sequence[Log] | None = None, cutoff_hz: float | None = None,
             interval: int = 1, method: str = "ols", weight: str = "bisquare",
             motor_side: bool = False) -> IdentResult:
    """Identify the model's base parameters from the logs and validate on held-out data.

    With ``motor_side`` the logs were converted to the joint side through the robot's
    transmission, and friction-type effects act on the motors' velocities.
    """
    pb = build_problem(robot, data, model, validate=validate, cutoff_hz=cutoff_hz,
                       interval=interval, motor_side=motor_side)
    pb.notes += subtract_known_torques(pb, model.known)
    if any(p.log.currents is not None for p in (*pb.preps, *pb.vpreps)):
        design0, _, _ = make_design(robot, pb.blocks, pb.transmission)
        pb.notes += identify_current_gains(pb, design0, model.known)
    _model_torque_inputs(pb)
    hypers = _profile_hypers(pb)
    design, base, names = make_design(robot, pb.blocks, pb.transmission)
    grams = accumulate(design, pb.train, pb.interval, pb.block_len)
    check_counts(int(grams.n_rows.sum()), design.p, Path(data[0].path).name)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        f, grams = fit(design, pb.train, pb.interval, pb.block_len,
                       "ols" if method == "consistent" else method, weight,
                       base.base_names, grams)
    notes = list(pb.notes)
    for w in caught:
        notes.append(str(w.message))
        warnings.warn(str(w.message), w.category, stacklevel=2)
    nominal_beta = _nominal_base(robot, base, names)
    std = np.sqrt(np.clip(np.diag(f.cov), 0.0, None))
    params = [Parameter(nm, float(v), float(s), base.expression(k),
                        None if nominal_beta is None else nominal_beta[k],
                        *parameter_unit(nm, robot.joint_types, pb.transmission is not None))
              for k, (nm, v, s) in enumerate(zip(base.base_names, f.theta, std, strict=True))]
    least = _least_excited(grams, base)
    if f.cond > POOR_EXCITATION_COND:
        msg = (f"condition number {f.cond:.3g}: poor excitation; least excited: "
               f"{', '.join(least[:3])}")
        notes.append(msg)
        warnings.warn(msg, ConditioningWarning, stacklevel=2)
    n_rows = grams.n_rows
    ms = f.rss / np.maximum(n_rows, 1)
    var = np.maximum(ms - f.mean_res**2, 0.0)
    fit_err = ErrorStats(np.sqrt(ms), np.sqrt(var), var, int(n_rows[0]))
    cons = None
    if method == "consistent":  # issue 15 item 6 (ident/fit/consistent.py) — hook begins
        cons, params, fit_err, design = _consistent(pb, names, design, f.theta, notes,
                                                    int(n_rows[0]))
    # hook ends
    notes += _sanity_checks(pb, nominal=robot.nominal is not None)
    if pb.valid:
        notes += _extrapolation(pb)
    return IdentResult(
        robot=robot.name,
        joints=robot.mapping(),
        effects=pb.model.labels(),
        method=method,
        parameters=params,
        n_samples=int(n_rows[0]),
        condition_number=f.cond,
        fit=fit_err,
        cutoff_hz=pb.preps[0].filt.cutoff_hz,
        fs_hz=pb.preps[0].filt.fs,
        interval=pb.interval,
        rank=base.rank,
        n_standard=len(names),
        least_excited=least,
        hypers=hypers,
        data_files=[{"path": lg.path, "sha256": file_sha256(lg.path), "role": role,
                     **({"source": lg.source} if lg.source else {})}
                    for role, logs in (("data", data), ("validate", validate or ()))
                    for lg in logs],
        validation_source=pb.validation_source,
        notes=notes,
        theta=f.theta if cons is None else cons.theta,
        cov=f.cov if cons is None else cons.cov,
        problem=pb,
        design=design,
        consistent=cons,
    )


def _consistent(pb: Problem, names: list[str], base_design: Design, beta: np.ndarray,
                notes: list[str], n: int
                ) -> tuple[ConsistentFit, list[Parameter], ErrorStats, Design]:
    """The physically consistent fit with the CAD prior on all standard columns (hook of
    ``method="consistent"``; the base-parameter OLS fit stays for conditioning and notes).
    Returns the fit, its parameters and errors, and the full design its θ belongs to (the
    result's held-out figures are computed on it)."""
    cols = np.arange(len(names))
    full = Design(pb.robot, tuple(pb.blocks), cols,
                  structural_mask(pb.robot, pb.blocks, cols, pb.transmission))
    cons = fit_consistent(full, pb.train, names, nominal=pb.robot.nominal,
                          interval=pb.interval, block_len=pb.block_len)
    val = evaluate_held_out(pb, full, cons.theta).validation
    val_ols = evaluate_held_out(pb, base_design, beta).validation
    cons.validation_ols = None if val_ols is None else val_ols.as_dict()
    std = np.sqrt(np.clip(np.diag(cons.cov), 0.0, None))
    n_rigid = cons.theta_cad.size
    params = [Parameter(nm, float(v), float(s), nm,
                        float(cons.theta_cad[k]) if k < n_rigid else None,
                        *parameter_unit(nm, pb.robot.joint_types, pb.transmission is not None))
              for k, (nm, v, s) in enumerate(zip(cons.names, cons.theta, std, strict=True))]
    ms = cons.rss / max(n, 1)
    var = np.maximum(ms - cons.mean_res**2, 0.0)
    lam = ("∞ (the CAD inertials; the data did not support moving away from them)"
           if not math.isfinite(cons.lam) else f"{cons.lam:.3g} (N·m)² ({cons.lam_rel:.3g} × "
           "the mean squared training torque)")
    notes.append(f"consistent fit: prior weight λ = {lam}, chosen by {cons.cv_scheme} on the "
                 "training data only (largest λ within one standard error of the best CV "
                 "score); every link's pseudo-inertia is positive definite (smallest "
                 f"eigenvalue {cons.min_eig.min():.3g})")
    if val is not None and val_ols is not None and val_ols.relative_error is not None:
        notes.append(f"consistent fit validates at {100 * (val.relative_error or 0):.2f} %; "
                     f"OLS of the base parameters on the same inputs at "
                     f"{100 * val_ols.relative_error:.2f} %")
    return cons, params, ErrorStats(np.sqrt(ms), np.sqrt(var), var, n), full


def _nominal_base(robot: Robot, base: BaseSet, names: list[str]) -> list[float | None] | None:
    if robot.nominal is None:
        return None
    full = np.zeros(len(names))
    full[: 10 * robot.n] = robot.nominal  # effects: unknown a priori, taken as 0
    out: list[float | None] = []
    for k in range(base.rank):
        row = base.combination[k]
        rigid_only = not np.any(row[10 * robot.n:])
        out.append(float(row @ full) if rigid_only else None)
    return out


def _least_excited(grams: Grams, base: BaseSet) -> list[str]:
    p = grams.p
    a = grams.total()[:, :p, :p].sum(axis=0)
    d = np.sqrt(np.clip(np.diag(a), 1e-300, None))
    evals, evecs = np.linalg.eigh(a / np.outer(d, d))
    v = np.abs(evecs[:, 0])
    order = np.argsort(v)[::-1]
    return [base.base_names[i] for i in order[:5] if v[i] > 0.2]


def _ranges(pieces: Sequence[Piece]) -> np.ndarray:
    lo = np.full((3, pieces[0].prep.q.shape[1]), np.inf)
    hi = -lo
    for pc in pieces:
        for k, arr in enumerate((pc.prep.q, pc.prep.qd, pc.prep.qdd)):
            a = arr[pc.lo: pc.hi]
            lo[k] = np.minimum(lo[k], a.min(axis=0))
            hi[k] = np.maximum(hi[k], a.max(axis=0))
    return np.stack((lo, hi))


def _extrapolation(pb: Problem) -> list[str]:
    tr, va = _ranges(pb.train), _ranges(pb.valid)
    span = np.maximum(tr[1] - tr[0], 1e-9)
    out = []
    for k, qty in enumerate(("q", "qd", "qdd")):
        excess = np.maximum(va[1][k] - tr[1][k], tr[0][k] - va[0][k]) / span[k]
        for j in np.flatnonzero(excess > 0.05):
            out.append(f"validation leaves the training range of {qty}{j + 1} by "
                       f"{100 * excess[j]:.0f} % of its span: the model extrapolates there")
    for msg in out:
        warnings.warn(msg, ExcitationWarning, stacklevel=3)
    return out


def _sanity_checks(pb: Problem, nominal: bool) -> list[str]:
    """Torque saturation, and sign/scale of each joint against the a-priori model."""
    robot = pb.robot
    out = []
    for prep in pb.preps:
        tau = prep.log.tau
        name = Path(prep.log.path).name
        if pb.transmission is None:
            out += _position_checks(robot, prep.log.q, name)
        peak = np.abs(tau).max(axis=0)
        flat = max(5, int(0.05 * prep.filt.fs))  # a clipped signal sits flat at its peak
        for j in range(robot.n):
            at_peak = np.abs(tau[:, j]) >= peak[j] - 1e-9 * max(peak[j], 1.0)
            limit = robot.limits.tau_max[j]
            if peak[j] > 0 and _longest_run(at_peak) >= flat:
                out.append(f"{name}: tau{j + 1} sits flat at {peak[j]:.3g} N·m "
                           f"({100 * at_peak.mean():.1f} % of samples): saturation?")
            elif np.isfinite(limit) and peak[j] >= 0.98 * limit:
                out.append(f"{name}: tau{j + 1} reaches {peak[j]:.3g} N·m, at or above its "
                           f"limit {limit:.3g} N·m: saturation or a wrong limit?")
        if nominal:
            step = max(1, len(prep.log) // 4000)
            trim = prep.filt.settle
            sl = slice(trim, len(prep.log) - trim, step)
            pred = rigid_regressor(robot, prep.q[sl], prep.qd[sl], prep.qdd[sl]) @ robot.nominal
            meas = prep.tau_f[sl]
            for j in range(robot.n):
                sp, sm = pred[:, j].std(), meas[:, j].std()
                if sp < 1e-9 or sm < 1e-9:
                    continue
                r = np.corrcoef(pred[:, j], meas[:, j])[0, 1]
                ratio = sm / sp
                if r < -0.5:
                    out.append(f"{name}: tau{j + 1} has the opposite sign of the a-priori model "
                               f"(correlation {r:.2f}): sign convention?")
                elif r > 0.5 and not 1 / 3 < ratio < 3:
                    out.append(f"{name}: tau{j + 1} is {ratio:.3g}× the a-priori model's "
                               f"torque: {_scale_cause(robot, prep, sl, pred, j, ratio)}")
    for msg in out:
        warnings.warn(msg, DataWarning, stacklevel=3)
    return out


def _position_checks(robot: Robot, q: np.ndarray, name: str) -> list[str]:
    """Joint positions far outside the robot's limits, with the likely cause: a motor-side
    log (positions/ratio inside the limits), degrees, or an encoder offset."""
    lim = robot.limits
    ratios = (np.abs(np.diag(robot.transmission)) if robot.transmission is not None
              else np.ones(robot.n))
    out = []
    for j in range(robot.n):
        lo, hi = float(lim.q_min[j]), float(lim.q_max[j])
        if not (np.isfinite(lo) and np.isfinite(hi)) or hi <= lo:
            continue
        qmin, qmax = float(q[:, j].min()), float(q[:, j].max())
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


def _scale_cause(robot: Robot, prep: Prepared, sl: slice, pred: np.ndarray, j: int,
                 ratio: float) -> str:
    """Why a joint's measured torque is ``ratio``× the a-priori model's: when the model plus
    viscous and Coulomb friction and a rotor inertia (which the a-priori model lacks) explain
    the measurement, say that, not 'units'."""
    qd, qdd, meas = prep.qd[sl, j], prep.qdd[sl, j], prep.tau_f[sl, j]
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
    if not mask.any():
        return 0
    edges = np.diff(np.concatenate(([0], mask.astype(np.int8), [0])))
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return int((stops - starts).max())


_NEEDS_MODEL_TORQUE = ("load_friction", "delay")


def _model_torque_inputs(pb: Problem) -> None:
    """Effects whose columns depend on the model's own torque (load friction, an estimated
    delay) get it from a first fit without them."""
    if not any(b.effect.name in _NEEDS_MODEL_TORQUE and b.param_names(pb.robot)
               for b in pb.blocks):
        return
    first = [b for b in pb.blocks if b.effect.name not in _NEEDS_MODEL_TORQUE]
    design, _, _ = make_design(pb.robot, first, pb.transmission)
    f, _ = fit(design, pb.train, pb.interval, pb.block_len, warn=False)
    attach_predictions(pb.robot, [*pb.preps, *pb.vpreps], design, f.theta)
