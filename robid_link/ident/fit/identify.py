"""The identification pipeline: logs + robot + model → IdentResult, as named steps.

check and prepare (filter, split) → known torques → drive currents → the model's own torque
→ hyper-parameters → design assembly → estimate (OLS/WLS/IRLS; consistent) → data checks →
result. Each step returns new values (a new ``Problem``, ``Assembly``, ``Estimate``); none
changes what another returned.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from robid_link.exceptions import ConditioningWarning, DataError
from robid_link.ident.data.checks import data_checks
from robid_link.ident.data.currents import (
    identify_current_gains,
    torque_from_currents,
    with_currents,
    without_known_torques,
)
from robid_link.ident.data.logs import Log, file_sha256, load_log
from robid_link.ident.data.preprocess import Problem, build_problem, check_counts
from robid_link.ident.data.sticks import without_sticks
from robid_link.ident.fit.consistent import ConsistentFit, fit_consistent, pieces_by_file
from robid_link.ident.fit.design import Design, make_design, structural_mask, with_predictions
from robid_link.ident.fit.estimate import Fit, Grams, accumulate, fit
from robid_link.ident.fit.results import (
    ErrorStats,
    HeldOut,
    IdentResult,
    Parameter,
    evaluate_held_out,
    parameter_unit,
)
from robid_link.ident.model.effects import Block, Model
from robid_link.ident.model.known import KnownTorque
from robid_link.ident.model.regressor import BaseSet
from robid_link.ident.model.robot import Robot

__all__ = [
    "identify",
    "load_logs",
    # the steps, in order (each tested alone)
    "with_current_gains",
    "with_model_torque",
    "with_profiled_hypers",
    "Assembly",
    "assemble",
    "Estimate",
    "estimate",
    "estimate_consistent",
    "assemble_consistent",
    "result_of",
]

#: condition number of the column-scaled base regressor above which excitation is poor
POOR_EXCITATION_COND = 1e3
#: warnings of a step that ``identify`` calls point at identify's caller
_CALLER = 3


def identify(robot: Robot, data: Sequence[Log], model: Model, *,
             validate: Sequence[Log] | None = None, cutoff_hz: float | None = None,
             interval: int = 1, method: str = "ols", weight: str = "bisquare",
             motor_side: bool = False) -> IdentResult:
    """Identify the model's base parameters from the logs and validate on held-out data.

    With ``motor_side`` the logs were converted to the joint side through the robot's
    transmission, and friction-type effects act on the motors' velocities.
    """
    # the files' SHA-256 on a thread of their own (hashlib lets go of the GIL), beside the rest
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="robid-sha256") as pool:
        digests = pool.submit(lambda: {lg.path: file_sha256(lg.path)
                                       for lg in (*data, *(validate or ()))})
        pb = build_problem(robot, data, model, validate=validate, cutoff_hz=cutoff_hz,
                           interval=interval, motor_side=motor_side)
        pb, _ = without_sticks(pb)
        pb = without_known_torques(pb, model.known)
        pb = with_current_gains(pb, model.known)
        pb = with_model_torque(pb)
        pb, hypers = with_profiled_hypers(pb)
        if method == "consistent":
            asm, full = assemble_consistent(pb, Path(data[0].path).name)
            est = estimate_consistent(pb, asm, estimate(pb, asm, "ols"), full)
        else:
            asm = assemble(pb, Path(data[0].path).name)
            est = estimate(pb, asm, method, weight)
        notes = [*est.notes, *data_checks(pb, stacklevel=_CALLER)]
        return result_of(pb, asm, est, method=method, hypers=hypers, notes=notes,
                         files=(data, validate or ()), digests=digests.result())


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
            held = log.held
            tau_m = np.where(held, log.tau, 0.0)
            log.q, log.qd, log.qdd, log.tau = robot.to_joint_side(log.q, log.qd, log.qdd, tau_m)
            if log.tau_held is not None:  # τ_j = Σ_m T[m, j] τ_m: every motor of j logged
                assert robot.transmission is not None
                coupled = robot.transmission != 0
                log.tau_held = ~np.any(coupled & ~held[:, None], axis=0)
                log.tau[:, ~log.tau_held] = np.nan
        else:
            log.q = robot.remove_offsets(log.q)
        logs.append(log)
    return logs


def with_current_gains(pb: Problem, known: Sequence[KnownTorque]) -> Problem:
    """Drives logged as currents without a gain: the gains identified with the model's base
    parameters, every log's torque completed with them, a note per gain."""
    if not any(p.log.currents is not None for p in (*pb.preps, *pb.vpreps)):
        return pb
    partial = next((p.log for p in (*pb.preps, *pb.vpreps) if p.log.partial), None)
    if partial is not None:  # a motor's gain reads every joint its torque reaches
        raise DataError(f"{Path(partial.path).name}: drive current gains are identified from "
                        "logs that hold every joint's torque, this log holds only some; give "
                        "the gains (transmission.current_gain) or log every joint")
    design, _, _ = make_design(pb.robot, pb.blocks, pb.transmission)
    found = identify_current_gains(pb, design, known)
    if found is None:
        return pb
    return pb.with_preps([with_currents(p, found) for p in pb.preps],
                         [with_currents(p, found) for p in pb.vpreps], found.notes())


#: effects whose columns read the model's own torque
_NEEDS_MODEL_TORQUE = ("load_friction", "delay")


def with_model_torque(pb: Problem) -> Problem:
    """Effects whose columns depend on the model's own torque (load friction, an estimated
    delay) get it from a first fit without them; other problems are returned as they are."""
    if not any(b.effect.name in _NEEDS_MODEL_TORQUE and b.param_names(pb.robot)
               for b in pb.blocks):
        return pb
    first = [b for b in pb.blocks if b.effect.name not in _NEEDS_MODEL_TORQUE]
    design, _, _ = make_design(pb.robot, first, pb.transmission)
    f, _ = fit(design, pb.train, pb.interval, pb.block_len, warn=False)
    return pb.with_preps(with_predictions(pb.robot, pb.preps, design, f.theta),
                         with_predictions(pb.robot, pb.vpreps, design, f.theta))


def with_profiled_hypers(pb: Problem) -> tuple[Problem, dict[str, dict[str, float]]]:
    """Free hyper-parameters chosen by training RSS over each effect's grid: the problem
    with the chosen blocks, and the choices by block key."""
    chosen: dict[str, dict[str, float]] = {}
    free = [(k, b, h) for k, b in enumerate(pb.blocks) for h in b.free_hypers()]
    if not free:
        return pb, chosen
    blocks = list(pb.blocks)
    order = sorted({(b.effect.name, list(b.effect.hypers).index(h), h) for _, b, h in free})
    several = {e for e, i, _ in order if i > 0}  # twice round for Stribeck's (vs, shape)
    order += [o for o in order if o[0] in several]
    for eff_name, _, hyper in order:  # an effect's hyper-parameters in its own order
        targets = [(k, blocks[k]) for k, b, h in free  # with the choices made so far
                   if b.effect.name == eff_name and h == hyper]
        best = _grid_choice(pb, blocks, targets, hyper)
        for k, b in targets:
            blocks[k] = b.with_opts(**{hyper: best[k]})
            chosen.setdefault(blocks[k].key, {})[hyper] = best[k]
    return replace(pb, blocks=blocks), chosen


def _grid_choice(pb: Problem, blocks: Sequence[Block], targets: Sequence[tuple[int, Block]],
                 hyper: str) -> dict[int, float]:
    """Per target block (index, block), the grid value with the least training RSS on the
    joints it loads, the other blocks as given."""
    grids = {k: b.grid(hyper, pb.robot, pb.transmission) for k, b in targets}
    size = len(next(iter(grids.values())))
    scores = np.full((size, len(blocks)), np.inf)
    for gi in range(size):
        trial = list(blocks)
        for k, b in targets:
            trial[k] = b.with_opts(**{hyper: grids[k][gi]})
        design, _, _ = make_design(pb.robot, trial, pb.transmission)
        f, _ = fit(design, pb.train, pb.interval, pb.block_len, warn=False)
        for k, b in targets:  # a coupled motor's friction loads several joints
            scores[gi, k] = f.rss[b.rows(pb.robot, pb.transmission)].sum()
    return {k: float(grids[k][int(np.argmin(scores[:, k]))]) for k, _ in targets}


@dataclass(frozen=True)
class Assembly:
    """The regressor of one problem: the compact design, the structural base set, the
    standard parameter names, and the per-joint, per-block training Grams."""

    design: Design
    base: BaseSet
    names: list[str]
    grams: Grams


def assemble(pb: Problem, where: str) -> Assembly:
    """Design and training Grams; refused (naming ``where``) with too few rows."""
    design, base, names = make_design(pb.robot, pb.blocks, pb.transmission)
    grams = accumulate(design, pb.train, pb.interval, pb.block_len)
    check_counts(int(grams.n_rows.sum()), design.p, where)
    return Assembly(design, base, names, grams)


@dataclass(frozen=True)
class FullAssembly:
    """The consistent fit's design (every standard column) and its Grams per file."""

    design: Design
    grams: list[Grams]


def assemble_consistent(pb: Problem, where: str) -> tuple[Assembly, FullAssembly]:
    """``assemble`` for the consistent fit: one pass over the rows with every standard
    column, per file; the base design's columns are a subset of them, so with one file its
    Grams are read out of the full ones instead of a second pass."""
    design, base, names = make_design(pb.robot, pb.blocks, pb.transmission)
    cols = np.arange(len(names))
    full = Design(pb.robot, tuple(pb.blocks), cols,
                  structural_mask(pb.robot, pb.blocks, cols, pb.transmission))
    _, per_file = pieces_by_file(pb.train)
    grams = [accumulate(full, pcs, pb.interval, pb.block_len) for pcs in per_file]
    if len(grams) == 1:
        sel = np.concatenate((design.cols, [full.p, full.p + 1]))
        base_grams = Grams(grams[0].g[:, :, sel[:, None], sel], grams[0].n_rows.copy())
    else:  # blocks span the files together: the base Grams take their own pass
        base_grams = accumulate(design, pb.train, pb.interval, pb.block_len)
    check_counts(int(base_grams.n_rows.sum()), design.p, where)
    return Assembly(design, base, names, base_grams), FullAssembly(full, grams)


@dataclass(frozen=True)
class Estimate:
    """An estimator's answer: θ of ``design``'s columns with its covariance, the parameter
    table, the errors on the training rows, and the notes so far."""

    theta: np.ndarray
    cov: np.ndarray
    parameters: list[Parameter]
    fit: ErrorStats
    condition_number: float
    least_excited: list[str]
    n_samples: int
    design: Design
    notes: list[str]
    consistent: ConsistentFit | None = None
    held_out: HeldOut | None = None  # the held-out figures, when a step computed them


def estimate(pb: Problem, asm: Assembly, method: str, weight: str = "bisquare") -> Estimate:
    """OLS, WLS or IRLS of the base parameters (``consistent`` starts from OLS). The fit's
    warnings become notes and are warned again, with poor excitation, to identify's caller."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        f, grams = fit(asm.design, pb.train, pb.interval, pb.block_len,
                       "ols" if method == "consistent" else method, weight,
                       asm.base.base_names, asm.grams)
    notes = list(pb.notes)
    for w in caught:
        notes.append(str(w.message))
        warnings.warn(str(w.message), w.category, stacklevel=_CALLER)
    params = _parameters(pb, asm, f)
    least = _least_excited(grams, asm.base)
    if f.cond > POOR_EXCITATION_COND:
        msg = (f"condition number {f.cond:.3g}: poor excitation; least excited: "
               f"{', '.join(least[:3])}")
        notes.append(msg)
        warnings.warn(msg, ConditioningWarning, stacklevel=_CALLER)
    n_rows = grams.n_rows
    ms = f.rss / np.maximum(n_rows, 1)
    var = np.maximum(ms - f.mean_res**2, 0.0)
    # partial logs, sticking rows: joints have rows of their own; the count is the largest
    fit_err = ErrorStats(np.sqrt(ms), np.sqrt(var), var, int(n_rows.max()))
    return Estimate(f.theta, f.cov, params, fit_err, f.cond, least, int(n_rows.max()),
                    asm.design, notes)


def _parameters(pb: Problem, asm: Assembly, f: Fit) -> list[Parameter]:
    nominal_beta = _nominal_base(pb.robot, asm.base, asm.names)
    std = np.sqrt(np.clip(np.diag(f.cov), 0.0, None))
    return [Parameter(nm, float(v), float(s), asm.base.expression(k),
                      None if nominal_beta is None else nominal_beta[k],
                      *parameter_unit(nm, pb.robot.joint_types, pb.transmission is not None))
            for k, (nm, v, s) in enumerate(zip(asm.base.base_names, f.theta, std,
                                               strict=True))]


def estimate_consistent(pb: Problem, asm: Assembly, est: Estimate,
                        fa: FullAssembly | None = None) -> Estimate:
    """The physically consistent fit with the CAD prior on all standard columns; the
    base-parameter OLS estimate ``est`` stays for conditioning and notes. Its θ belongs to
    the full design (the result's held-out figures are computed on it). ``fa``: the full
    design and its Grams from ``assemble_consistent`` (else built here)."""
    if fa is None:
        cols = np.arange(len(asm.names))
        full = Design(pb.robot, tuple(pb.blocks), cols,
                      structural_mask(pb.robot, pb.blocks, cols, pb.transmission))
    else:
        full = fa.design
    cons = fit_consistent(full, pb.train, asm.names, nominal=pb.robot.nominal,
                          interval=pb.interval, block_len=pb.block_len,
                          grams=None if fa is None else fa.grams)
    held = evaluate_held_out(pb, full, cons.theta)
    val = held.validation
    val_ols = evaluate_held_out(pb, asm.design, est.theta).validation
    cons.validation_ols = None if val_ols is None else val_ols.as_dict()
    std = np.sqrt(np.clip(np.diag(cons.cov), 0.0, None))
    n_rigid = cons.theta_cad.size
    params = [Parameter(nm, float(v), float(s), nm,
                        float(cons.theta_cad[k]) if k < n_rigid else None,
                        *parameter_unit(nm, pb.robot.joint_types, pb.transmission is not None))
              for k, (nm, v, s) in enumerate(zip(cons.names, cons.theta, std, strict=True))]
    ms = cons.rss / max(est.n_samples, 1)
    var = np.maximum(ms - cons.mean_res**2, 0.0)
    notes = [*est.notes, _consistent_note(cons)]
    if val is not None and val_ols is not None and val_ols.relative_error is not None:
        notes.append(f"consistent fit validates at {100 * (val.relative_error or 0):.2f} %; "
                     f"OLS of the base parameters on the same inputs at "
                     f"{100 * val_ols.relative_error:.2f} %")
    return replace(est, theta=cons.theta, cov=cons.cov, parameters=params,
                   fit=ErrorStats(np.sqrt(ms), np.sqrt(var), var, est.n_samples),
                   design=full, notes=notes, consistent=cons, held_out=held)


def _consistent_note(cons: ConsistentFit) -> str:
    lam = ("∞ (the CAD inertials; the data did not support moving away from them)"
           if not math.isfinite(cons.lam) else f"{cons.lam:.3g} (N·m)² ({cons.lam_rel:.3g} × "
           "the mean squared training torque)")
    return (f"consistent fit: prior weight λ = {lam}, chosen by {cons.cv_scheme} on the "
            "training data only (largest λ within one standard error of the best CV "
            "score); every link's pseudo-inertia is positive definite (smallest "
            f"eigenvalue {cons.min_eig.min():.3g})")


def result_of(pb: Problem, asm: Assembly, est: Estimate, *, method: str,
              hypers: dict[str, dict[str, float]], notes: list[str],
              files: tuple[Sequence[Log], Sequence[Log]],
              digests: Mapping[str, str] | None = None) -> IdentResult:
    """The result, keeping the problem and design it was fitted on (held-out figures are
    computed from them on first use); ``files``: the data and the validation logs, with
    their SHA-256 by path in ``digests`` (else read here)."""
    robot = pb.robot
    res = IdentResult(
        robot=robot.name,
        joints=robot.mapping(),
        effects=pb.model.labels(),
        method=method,
        parameters=est.parameters,
        n_samples=est.n_samples,
        condition_number=est.condition_number,
        fit=est.fit,
        cutoff_hz=pb.preps[0].filt.cutoff_hz,
        fs_hz=pb.preps[0].filt.fs,
        interval=pb.interval,
        rank=asm.base.rank,
        n_standard=len(asm.names),
        least_excited=est.least_excited,
        hypers=hypers,
        data_files=[{"path": lg.path,
                     "sha256": (digests or {}).get(lg.path) or file_sha256(lg.path),
                     "role": role,
                     **({"source": lg.source} if lg.source else {})}
                    for role, logs in zip(("data", "validate"), files, strict=True)
                    for lg in logs],
        validation_source=pb.validation_source,
        notes=notes,
        theta=est.theta,
        cov=est.cov,
        problem=pb,
        design=est.design,
        consistent=est.consistent,
    )
    if est.held_out is not None:  # computed on the same problem, design and θ: not again
        res.__dict__["held_out"] = est.held_out
    return res


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

