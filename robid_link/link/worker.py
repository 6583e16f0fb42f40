"""What the daemon hands to its worker processes: program generation, log checks and the
identification (+ diagnosis) of a run. Plain functions of picklable arguments, run under a
forkserver/spawn pool so the event loop never blocks on numerical work."""

from __future__ import annotations

import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

from robid_link.exceptions import RobidError, WorkerError
from robid_link.link.driver import MotionProgram

__all__ = ["generate_program", "check_log", "check_model", "identify_run"]


def _robot(robot_path: str, lock: tuple[str, ...]) -> Any:
    from robid_link.ident.model.robot import load_robot

    return load_robot(robot_path, lock)


def generate_program(robot_path: str, lock: tuple[str, ...], exp_id: str, kind: str,
                     options: dict[str, Any], base_dir: str,
                     reduced_speed: float | None = None) -> MotionProgram:
    """Generate, check (limits) and render one experiment's program."""
    from robid_link.ident.excite.experiments import experiment_trajectory
    from robid_link.link import program as pg

    robot = _robot(robot_path, lock)
    traj = experiment_trajectory(robot, kind, options, Path(base_dir))
    meta: dict[str, Any] = {"kind": kind, "trajectory_kind": traj.kind}
    if reduced_speed is not None:
        traj = pg.reduced_speed(traj, reduced_speed)
        meta["reduced_speed"] = reduced_speed
    return pg.make_program(robot, traj, exp_id, meta)


def check_log(n_joints: int, log_path: str) -> dict[str, Any]:
    """Load a captured log as the identification will (columns, joint count, NaN, time)."""
    from robid_link.ident.data.logs import load_log

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        log = load_log(log_path, n_joints)
    return {"samples": int(log.t.size), "duration_s": float(log.t[-1] - log.t[0]),
            "rate_hz": float(log.fs)}


def check_model(model_path: str | None, add: list[str]) -> list[str]:
    """The model a run's identification will use, built now (file, ``add:`` entries): its
    effect names. Raises the ModelError the identification would raise after the motion."""
    from robid_link.ident.model.effects import DEFAULT_MODEL, load_model, parse_effect

    model = load_model(model_path) if model_path else DEFAULT_MODEL
    for entry in add:
        model = model.with_added(parse_effect(entry, f"add {entry}"), f"add {entry}")
    return [str(e) for e in getattr(model, "effects", ())]


def identify_run(job: dict[str, Any]) -> dict[str, Any]:
    """Identify (and diagnose) a run's logs; write the report; return the result records."""
    from robid_link.ident.fit.identify import load_logs
    from robid_link.ident.model.effects import DEFAULT_MODEL, load_model, parse_effect
    from robid_link.ident.runner import run_job

    robot = _robot(job["robot"], tuple(job["lock"]))
    model = load_model(job["model"]) if job.get("model") else DEFAULT_MODEL
    for entry in job.get("add", ()):
        model = model.with_added(parse_effect(entry, f"add {entry}"), f"add {entry}")
    out = Path(job["report_dir"])
    out.mkdir(parents=True, exist_ok=True)
    analyses = ("identify", "diagnose") if job.get("diagnose") else ("identify",)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        data = load_logs(robot, job["logs"], None, job.get("motor_side", False))
        done = run_job(robot, data, model, analyses=analyses, cutoff_hz=job.get("cutoff_hz"),
                       method=job.get("method", "ols"), motor_side=job.get("motor_side", False),
                       json_files={k: out / f"{k}.json" for k in analyses}, report_dir=out,
                       history=job.get("model") or None, run_id=job["run_id"],
                       campaign=job.get("campaign"),
                       elasticity_entries={int(j): str(e) for j, e in
                                           job.get("elasticity_entries", {}).items()})
    notes = sorted({f"{w.category.__name__}: {w.message}" for w in caught})
    records, doc, summaries = done.records, done.docs["identify"], done.summaries()
    for rec in records.values():
        rec["robot"] = robot.name
        rec["run_id"] = job["run_id"]
        rec["warnings"] = notes
    (out / "summary.txt").write_text("\n\n".join(summaries) + "\n")
    from robid_link.ident.fit.paramset import make_parameter_set

    periods = {s.joint: float(s.opts["period"]) for s in model.specs
               if s.name == "ripple" and s.joint and "period" in s.opts}
    pset_doc = doc
    if job.get("upload") and robot.nominal is not None:
        # what a controller runs its computed torque on must be a body that can exist
        # (an inconsistent θ can make its mass matrix indefinite): the consistent fit
        from robid_link.ident.fit.identify import identify

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the same notes as the fit above
            pset_doc = identify(robot, data, model, cutoff_hz=job.get("cutoff_hz"),
                                method="consistent",
                                motor_side=job.get("motor_side", False)).to_dict()
    pset = make_parameter_set(robot, pset_doc, run_id=job["run_id"], periods=periods)
    return {"records": records, "summary": "\n\n".join(summaries),
            "parameters": doc.get("parameters", []), "robot": robot.name,
            "parameter_set": pset}


def verify_run(job: dict[str, Any]) -> dict[str, Any]:
    """Tracking of each verification log against the path it was given."""
    from robid_link.ident.data.logs import load_log
    from robid_link.ident.excite.excitation import Trajectory
    from robid_link.ident.excite.verify import tracking
    from robid_link.link.driver import MotionProgram

    robot = _robot(job["robot"], tuple(job["lock"]))
    records = []
    for run in job["runs"]:
        tr = MotionProgram(run["exp_id"], run["files"], 0.0).trajectory()
        ref = Trajectory(tr.t - tr.t[0], tr.q, tr.rate_hz, tr.kind, tr.robot, dict(tr.header))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # resampling notes: the log itself was checked
            log = load_log(run["log"], robot.n)
        res = tracking(robot, ref, log.t, log.q)
        records.append({"kind": "verify", "experiment": run["exp_id"], "phase": run["phase"],
                        "robot": robot.name, "tracking": res.as_dict()})
    return {"robot": robot.name, "records": records}


def elasticity_run(job: dict[str, Any]) -> dict[str, Any]:
    """Elasticity of each stepped-sine log, from the schedule its program carried."""
    from robid_link.ident.data.logs import load_log
    from robid_link.ident.elastic.elasticity import identify_elasticity
    from robid_link.ident.elastic.frequency import excited_axes
    from robid_link.link.driver import MotionProgram

    robot = _robot(job["robot"], tuple(job["lock"]))
    results = []
    for run in job["runs"]:
        head = MotionProgram(run["exp_id"], run["files"], 0.0).trajectory().header
        schedule = head.get("schedule")
        joints, pairs = excited_axes(schedule or [])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # resampling notes: the log itself was checked
            log = load_log(run["log"], robot.n)
        res = identify_elasticity(robot, [log], joints=joints,
                                  pair=pairs[0] if pairs else None, schedule=schedule)
        doc = res.to_dict()
        for j in doc.get("joints", []):
            j["measures"] = {"experiment": run["exp_id"], "kind": "elasticity"}
        results.append({"experiment": run["exp_id"], "result": doc})
    return {"robot": robot.name, "results": results}


# ----------------------------------------------------------------------------- process runner


def _error_name(err: BaseException) -> str:
    cls = type(err)
    return f"{cls.__module__}:{cls.__qualname__}"


def _error_class(name: str) -> type[RobidError]:
    """The RobidError subclass a worker named (``module:Class``); RobidError itself for a
    name that is not one (the pipe carries names, never code)."""
    import importlib
    import sys

    module_name, _, qualname = name.partition(":")
    if module_name not in sys.modules and not module_name.startswith("robid_link."):
        return RobidError
    try:
        obj: Any = importlib.import_module(module_name)
        for part in qualname.split("."):
            obj = getattr(obj, part)
    except (ImportError, AttributeError):
        return RobidError
    return obj if isinstance(obj, type) and issubclass(obj, RobidError) else RobidError


def _tie_to_daemon(daemon_pid: int) -> None:
    """Die with the daemon: the kernel's parent-death signal (the parent is the daemon, or
    the fork server, which exits with it), and a thread that waits on a pidfd of the daemon
    itself and ends this process when the daemon is gone (whatever the parent is)."""
    import ctypes
    import os
    import signal
    import threading

    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # not Linux: the watchdog thread alone
        pass
    try:
        fd = os.pidfd_open(daemon_pid)
    except ProcessLookupError:
        os._exit(1)  # the daemon died before we got here
    except (OSError, AttributeError):
        return

    def watch() -> None:
        import select

        poller = select.poll()
        poller.register(fd, select.POLLIN)
        poller.poll()  # readable when the daemon has exited (even before it is reaped)
        os._exit(1)

    threading.Thread(target=watch, name="robid-daemon-watch", daemon=True).start()


def _child(conn: Any, func: Any, args: tuple[Any, ...], daemon_pid: int | None = None
           ) -> None:
    if daemon_pid is not None:
        _tie_to_daemon(daemon_pid)
    try:
        result: tuple[str, Any, str] = ("ok", func(*args), "")
    except RobidError as err:
        result = ("error", _error_name(err), str(err))
    except Exception as err:  # a bug: report it with where it happened; the daemon lives on
        import traceback

        where = traceback.extract_tb(err.__traceback__)[-1]
        result = ("error", _error_name(WorkerError()), f"worker {func.__name__} crashed: "
                  f"{type(err).__name__}: {err} ({Path(where.filename).name}:{where.lineno})")
    conn.send(result)
    conn.close()


async def run_in_worker(ctx: Any, func: Any, *args: Any,
                        on_start: Callable[[], None] | None = None) -> Any:
    """Run ``func(*args)`` in a fresh process of the multiprocessing context ``ctx``; a
    cancelled caller terminates the process. A RobidError comes back as its own class
    (``UnsafeProgramError`` stays one); a crash or a dead process as WorkerError. The child
    dies with the daemon (``_tie_to_daemon``); ``on_start`` runs once it was started."""
    import asyncio

    recv, send = ctx.Pipe(duplex=False)
    import os

    proc = ctx.Process(target=_child, args=(send, func, args, os.getpid()),
                       name=f"robid-{func.__name__}",
                       daemon=True)
    proc.start()
    send.close()
    if on_start is not None:
        on_start()
    try:
        try:
            status, value, message = await asyncio.to_thread(recv.recv)
        except EOFError:
            await asyncio.to_thread(proc.join, 5.0)
            raise WorkerError(f"worker process {func.__name__} died (exit code "
                              f"{proc.exitcode})") from None
    finally:
        if proc.is_alive():
            proc.terminate()
        await asyncio.to_thread(proc.join, 5.0)
        recv.close()
    if status != "ok":
        cls = _error_class(value)
        try:
            error = cls(message)
        except TypeError:  # a subclass with another constructor: keep the message
            error = RobidError(message)
        raise error
    return value
