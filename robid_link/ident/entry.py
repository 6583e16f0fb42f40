"""The worker process's entry point: a job record (JSON) in, a result record (JSON) out.

The link names this module (``jobs.WORKER_ENTRY``) and its child process imports it by name;
``run_job`` dispatches a record to the worker code that answers it (one table, ``HANDLERS``).
"""

from __future__ import annotations

import gc
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from robid_link import jobs as jb

if TYPE_CHECKING:
    from robid_link.ident.model.robot import Robot

__all__ = ["run", "run_job", "HANDLERS", "load_numerics"]


def run(job_json: str) -> str:
    """The child's side of the door: parse the job, run it, answer with the result's JSON.
    A job that computes loads the numerical modules first (``load_numerics``)."""
    job = jb.Job.from_json(job_json)
    if isinstance(job, NUMERICAL):
        load_numerics()
    return run_job(job).to_json()


_numerics_loaded = False


def load_numerics() -> None:
    """The worker's numerical modules and numba's compiler, loaded once per process without the
    cyclic garbage collector: their ~10^5 objects live as long as the process, and the
    collector walked them some 25 times while they loaded, for nothing (~0.2 s of a short
    identify). Frozen then, later collections skip them. The CLI's analyses and the daemon's
    worker processes call it."""
    global _numerics_loaded
    if _numerics_loaded:
        return
    enabled = gc.isenabled()
    gc.disable()
    try:
        import robid_link.ident.runner  # noqa: F401
        from robid_link.ident.data.filtering import load_compiler

        load_compiler()
        gc.freeze()
    finally:
        if enabled:
            gc.enable()
    _numerics_loaded = True


def run_job(job: jb.Job) -> jb.Record:
    """Run one job in this process; the answer is a record of ``job.RESULT``."""
    handler = HANDLERS.get(type(job))
    if handler is None:
        raise TypeError(f"no handler for {job.TYPE}")
    return handler(job)


def _robot(path: str, lock: tuple[str, ...]) -> Robot:
    from robid_link.ident.model.robot import load_robot

    return load_robot(path, lock)


def robot_info(job: jb.RobotInfoJob) -> jb.RobotInfo:
    return jb.RobotInfo.of(_robot(job.robot, job.lock))


def program(job: jb.ProgramJob) -> jb.MotionProgram:
    """Generate, check (limits) and render one experiment's program."""
    from robid_link.ident.excite import program as pg
    from robid_link.ident.excite.experiments import experiment_trajectory

    robot = _robot(job.robot, job.lock)
    traj = experiment_trajectory(robot, job.kind, job.options, Path(job.base_dir),
                                 f"experiment {job.exp_id}")
    meta: dict[str, Any] = {"kind": job.kind, "trajectory_kind": traj.kind}
    if job.reduced_speed is not None:
        traj = pg.reduced_speed(traj, job.reduced_speed)
        meta["reduced_speed"] = job.reduced_speed
    if job.log_torques is not None:
        traj = pg.with_logged_torques(robot, traj, job.log_torques, job.exp_id)
        meta["log_torques"] = list(traj.header["log_torques"])
    return pg.make_program(robot, traj, job.exp_id, meta)


def check_log(job: jb.LogCheckJob) -> jb.LogCheck:
    """Load a captured log as the identification will (columns, joint count, NaN, time)."""
    from robid_link.ident.data.logs import load_log

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        log = load_log(job.log, job.n_joints)
    return jb.LogCheck(int(log.t.size), float(log.t[-1] - log.t[0]), float(log.fs))


def _model(path: str | None, add: tuple[str, ...]) -> Any:
    from robid_link.ident.model.effects import DEFAULT_MODEL, load_model, parse_effect

    model = load_model(path) if path else DEFAULT_MODEL
    for entry in add:
        model = model.with_added(parse_effect(entry, f"add {entry}"), f"add {entry}")
    return model


def check_model(job: jb.ModelCheckJob) -> jb.ModelCheck:
    """The model a run's identification will use, built now (file, ``add:`` entries): its
    effect names. Raises the ModelError the identification would raise after the motion."""
    return jb.ModelCheck(tuple(_model(job.model, job.add).labels()))


def identify(job: jb.IdentifyJob) -> jb.IdentifyOutcome:
    """Identify (and diagnose) a run's logs; write the report; return the result records."""
    from robid_link.ident.fit.identify import load_logs
    from robid_link.ident.fit.paramset import make_parameter_set
    from robid_link.ident.runner import run_job as run_analyses

    robot = _robot(job.robot, job.lock)
    model = _model(job.model, job.add)
    out = Path(job.report_dir)
    out.mkdir(parents=True, exist_ok=True)
    analyses = ("identify", "diagnose") if job.diagnose else ("identify",)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        data = load_logs(robot, list(job.logs), None, job.motor_side)
        done = run_analyses(robot, data, model, analyses=analyses, cutoff_hz=job.cutoff_hz,
                            method=job.method, motor_side=job.motor_side,
                            json_files={k: out / f"{k}.json" for k in analyses},
                            report_dir=out, history=job.model or None, run_id=job.run_id,
                            campaign=job.campaign,
                            resonance_hints={h.joint: h for h in job.resonance_hints})
    notes = sorted({f"{w.category.__name__}: {w.message}" for w in caught})
    records, doc, summaries = done.records, done.docs["identify"], done.summaries()
    for rec in records.values():
        rec["robot"] = robot.name
        rec["run_id"] = job.run_id
        rec["warnings"] = notes
    (out / "summary.txt").write_text("\n\n".join(summaries) + "\n")
    periods = {s.joint: float(s.opts["period"]) for s in model.specs
               if s.name == "ripple" and s.joint and "period" in s.opts}
    pset_doc = doc
    if job.upload and robot.nominal is not None:
        # what a controller runs its computed torque on must be a body that can exist
        # (an inconsistent θ can make its mass matrix indefinite): the consistent fit
        from robid_link.ident.fit.identify import identify as fit

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the same notes as the fit above
            pset_doc = fit(robot, data, model, cutoff_hz=job.cutoff_hz, method="consistent",
                           motor_side=job.motor_side).to_dict()
    pset = make_parameter_set(robot, pset_doc, run_id=job.run_id, periods=periods)
    return jb.IdentifyOutcome(robot.name, records, "\n\n".join(summaries),
                              jb.ParameterSet(pset))


def _log(path: str, robot: Robot) -> Any:
    from robid_link.ident.data.logs import load_log

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # resampling notes: the log itself was checked
        return load_log(path, robot.n)


def verify(job: jb.VerifyJob) -> jb.VerifyOutcome:
    """Tracking of each verification log against the path it was given."""
    from robid_link.ident.excite.excitation import Trajectory
    from robid_link.ident.excite.verify import tracking

    robot = _robot(job.robot, job.lock)
    records: list[dict[str, Any]] = []
    for run_ in job.runs:
        tr = run_.program.trajectory()
        ref = Trajectory(tr.t - tr.t[0], tr.q, tr.rate_hz, tr.kind, tr.robot, dict(tr.header))
        log = _log(run_.log, robot)
        res = tracking(robot, ref, log.t, log.q, f"verification log {run_.log}")
        records.append({"kind": "verify", "experiment": run_.exp_id, "phase": run_.phase,
                        "robot": robot.name, "tracking": res.as_dict()})
    if job.report_dir:
        from robid_link.ident.report.html import add_to_report

        add_to_report(job.report_dir, robot=robot, run=_run(job),
                      tracking={r["phase"]: r["tracking"] for r in records})
    return jb.VerifyOutcome(robot.name, tuple(records))


def _run(job: jb.VerifyJob | jb.ElasticityJob) -> dict[str, Any] | None:
    return {"run_id": job.run_id, "campaign": job.campaign} if job.run_id else None


def elasticity(job: jb.ElasticityJob) -> jb.ElasticityOutcome:
    """Elasticity of each stepped-sine log, from the schedule its program carried."""
    from robid_link.ident.elastic.elasticity import identify_elasticity
    from robid_link.ident.elastic.frequency import excited_axes

    robot = _robot(job.robot, job.lock)
    results, fits = [], []
    for run_ in job.runs:
        schedule = run_.program.trajectory().header.get("schedule")
        joints, pairs = excited_axes(schedule or [])
        log = _log(run_.log, robot)
        res = identify_elasticity(robot, [log], joints=joints,
                                  pair=pairs[0] if pairs else None, schedule=schedule)
        doc = res.to_dict()
        for j in doc.get("joints", []):
            j["measures"] = {"experiment": run_.exp_id, "kind": "elasticity"}
        results.append({"experiment": run_.exp_id, "result": doc})
        fits.append(res)
    if job.report_dir and fits:
        from robid_link.ident.report.html import add_to_report

        add_to_report(job.report_dir, robot=robot, run=_run(job), elasticity=fits)
    return jb.ElasticityOutcome(robot.name, tuple(results))


def feedforward(job: jb.FeedforwardJob) -> jb.FeedforwardTable:
    """The set's model torque along the setpoints (what a motion-master driver streams)."""
    import numpy as np

    from robid_link.exceptions import ModelError
    from robid_link.ident.fit.paramset import feedforward as set_feedforward
    from robid_link.ident.fit.paramset import setpoint_torque

    robot = _robot(job.robot, job.lock)
    pset = job.parameter_set
    if pset.robot not in (None, robot.name):
        raise ModelError(f"parameter set {pset.sha256[:12]} is for robot {pset.robot}, not "
                         f"{robot.name}")
    q = np.asarray(job.q, dtype=float).reshape(len(job.q), -1)
    if q.shape[1] != robot.n or not np.all(np.isfinite(q)):
        raise ModelError(f"feed-forward setpoints: {q.shape[1]} joints or non-finite values; "
                         f"robot {robot.name} has {robot.n} joints")
    tau = setpoint_torque(robot, set_feedforward(pset.doc, robot.n), q, job.period_s)
    return jb.FeedforwardTable(pset.sha256, job.period_s, tuple(map(tuple, tau.tolist())))


def drift(job: jb.DriftJob) -> jb.DriftReport:
    """Drift flags of a robot's stored identifications (no identification yet: none)."""
    from robid_link.exceptions import ModelError
    from robid_link.ident.diagnosis.drift import trend

    try:
        tr = trend([dict(r) for r in job.results], job.robot)
    except ModelError:  # no identification with parameters yet
        return jb.DriftReport(())
    return jb.DriftReport(tuple(
        jb.DriftFlag(f.run_id, f.parameter, f.kind, float(f.change), float(f.sigmas), f.message)
        for f in tr.flags if job.run_id is None or f.run_id == job.run_id))


#: job record type → the worker code that answers it
HANDLERS: dict[type[jb.Job], Callable[[Any], jb.Record]] = {
    jb.RobotInfoJob: robot_info,
    jb.ProgramJob: program,
    jb.LogCheckJob: check_log,
    jb.ModelCheckJob: check_model,
    jb.IdentifyJob: identify,
    jb.VerifyJob: verify,
    jb.ElasticityJob: elasticity,
    jb.FeedforwardJob: feedforward,
    jb.DriftJob: drift,
}
#: the jobs that identify or simulate (the others read a file or render a program)
NUMERICAL = (jb.IdentifyJob, jb.VerifyJob, jb.ElasticityJob, jb.FeedforwardJob, jb.DriftJob)
