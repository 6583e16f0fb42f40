"""``robid identify``, ``diagnose``, ``history``, ``model add``, ``elasticity``: the model from
logs, what it misses, its error ladder, and the joints' elasticity."""

from __future__ import annotations

import argparse
import contextlib
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from robid_link.cli.types import (
    Command,
    axes_of,
    axis_pair,
    bounded_int,
    figure_path,
    output_path,
    positive_float,
    rate_hz,
    refuse_given,
    robot_options,
)
from robid_link.exceptions import ConfigError, DataError, RobidError
from robid_link.ident.entry import load_numerics

__all__ = ["COMMANDS", "IRLS_WEIGHTS"]

#: the weight functions of ``--method irls`` (``ident.fit.estimate.WEIGHTS``; listed here so
#: that ``robid --help`` starts without numpy)
IRLS_WEIGHTS = ("andrews", "bisquare", "cauchy", "fair", "huber", "logistic", "talwar",
                "welsch")


def _shared_inputs(p: argparse.ArgumentParser) -> None:
    robot_options(p)
    p.add_argument("--data", action="append", required=True, metavar="LOG",
                   help="log (.csv, .npz, .mat, a ROS 2 bag folder, .mcap, a ROS 1 .bag); "
                        "repeat to identify on several")
    p.add_argument("--validate", action="append", metavar="LOG",
                   help="held-out log(s); default: the last 20 %% of each --data file")
    p.add_argument("--fs", type=rate_hz(1e6), metavar="HZ",
                   help="sampling rate in Hz of .mat logs (the others carry time stamps)")
    _topic_option(p)
    p.add_argument("--cutoff", type=positive_float(1e6), metavar="HZ",
                   help="zero-phase low-pass cutoff (default 10 Hz, at most 40 %% of Nyquist)")
    p.add_argument("--interval", type=bounded_int(1, 100_000), default=1, metavar="K",
                   help="keep every K-th sample after anti-alias filtering (default 1)")
    p.add_argument("--motor-side", action="store_true",
                   help="logs are on the motor side; convert through the robot's transmission")
    p.add_argument("--model", help="model file (YAML with effects:); default "
                   "[rigid_body, viscous, coulomb]")
    p.add_argument("--add", action="append", default=[], metavar="EFFECT[@J]",
                   help="add an effect to the model for this run; repeatable")


def _topic_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--topic", metavar="NAME",
                   help="ROS bags: the joint-state (or controller-state) topic to read; "
                        "default the bag's JointState topic (/joint_states among several)")


def _load_model(args: argparse.Namespace) -> Any:
    from robid_link.ident.model.effects import DEFAULT_MODEL, load_model, parse_effect, save_model

    if args.model and not Path(args.model).exists():
        save_model(args.model, DEFAULT_MODEL)  # the error ladder starts at the default model
        print(f"created {args.model} with the default model [{', '.join(DEFAULT_MODEL.labels())}]")
    model = load_model(args.model)
    for entry in args.add:
        model = model.with_added(parse_effect(entry, f"--add {entry}"), f"--add {entry}")
    return model


@contextlib.contextmanager
def _digests_ahead(args: argparse.Namespace) -> Iterator[None]:
    """The logs' SHA-256 (the result records them) read on a thread while the numerical
    modules load, when a core is idle; a file that cannot be read is the command's own error
    to report, where it reads the log."""
    from robid_link.ident.data.logs import file_sha256

    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="robid-sha256") as pool:
        for path in [*args.data, *(args.validate or [])]:
            if Path(path).is_file():  # a bag's folder is read when identify asks
                pool.submit(file_sha256, path)
        yield


def _inputs(args: argparse.Namespace) -> tuple[Any, Any, Any, Any]:
    """The shared inputs of identify and diagnose: robot, model, data and validation logs."""
    from robid_link.ident.fit.identify import load_logs
    from robid_link.ident.model.robot import load_robot

    robot = load_robot(args.robot, args.lock, allow_unlimited=args.allow_unlimited)
    model = _load_model(args)
    data = load_logs(robot, args.data, args.fs, args.motor_side, topic=args.topic)
    valid = (load_logs(robot, args.validate, args.fs, args.motor_side, topic=args.topic)
             if args.validate else None)
    return robot, model, data, valid


# ------------------------------------------------------------------------------- identify

def _identify_options(p: argparse.ArgumentParser) -> None:
    _shared_inputs(p)
    p.add_argument("--method", choices=("ols", "wls", "irls", "consistent"), default="ols",
                   help="least squares: ols (default), wls (per-joint weights), irls (robust) "
                   "or consistent (standard parameters kept physically realizable, with the "
                   "CAD inertials as prior, weight chosen by cross-validation)")
    p.add_argument("--export-urdf", metavar="FILE", type=output_path("file"),
                   help="with --method consistent: write the robot's URDF with the "
                   "identified inertials")
    p.add_argument("--weight", choices=IRLS_WEIGHTS, metavar="NAME",
                   help="with --method irls: the weight function, one of "
                        f"{', '.join(IRLS_WEIGHTS)} (default bisquare)")
    p.add_argument("--json", metavar="FILE", type=output_path("file", create_parents=True),
                   help="write the result as JSON")
    p.add_argument("--out", metavar="DIR", type=output_path("dir"),
                   help="write report.html, figures, parameter table and YAML")


def _fs_check(args: argparse.Namespace) -> None:
    """``--fs`` sets the rate of .mat logs only: with none among the logs it would be
    ignored."""
    logs = [*args.data, *(getattr(args, "validate", None) or [])]
    if args.fs is not None and not any(Path(x).suffix.lower() == ".mat" for x in logs):
        raise ConfigError(f"--fs {args.fs:g}: applies to .mat logs only (the others carry "
                          "their time stamps)")


def _identify_check(args: argparse.Namespace) -> None:
    if args.export_urdf and args.method != "consistent":
        raise ConfigError("--export-urdf needs --method consistent (standard parameters)")
    if args.method != "irls":
        refuse_given(args, ["--weight"], f"applies to --method irls only, not {args.method}")
    _fs_check(args)


def _identify(args: argparse.Namespace) -> int:
    with _digests_ahead(args):
        load_numerics()
        return _identify_loaded(args)


def _identify_loaded(args: argparse.Namespace) -> int:
    from robid_link.ident.runner import run_job

    robot, model, data, valid = _inputs(args)
    job = run_job(robot, data, model, validate=valid, cutoff_hz=args.cutoff,
                  interval=args.interval, method=args.method,
                  weight=args.weight or "bisquare",
                  motor_side=args.motor_side, json_files={"identify": args.json} if args.json
                  else None, report_dir=args.out, history=args.model or None)
    print(job.result.summary())
    if args.out:
        print(f"\n  wrote {len(job.report_files['identify'])} files to {args.out}; report: "
              f"{job.report_html}")
    if args.export_urdf:  # issue 15 item 6
        from robid_link.ident.model.urdf_export import export_urdf

        cons = job.result.consistent
        export_urdf(robot, cons.standard, args.export_urdf, dict(zip(cons.names, cons.theta,
                                                                     strict=True)))
        print(f"\n  wrote the identified model as URDF to {args.export_urdf}")
    return 0


# ------------------------------------------------------------------------------- diagnose

def _diagnose_options(p: argparse.ArgumentParser) -> None:
    _shared_inputs(p)
    p.add_argument("--json", metavar="FILE", type=output_path("file", create_parents=True),
                   help="write the diagnosis as JSON")
    p.add_argument("--out", metavar="DIR", type=output_path("dir"),
                   help="write report.html and residual figures per joint")


def _diagnose(args: argparse.Namespace) -> int:
    with _digests_ahead(args):
        load_numerics()
        return _diagnose_loaded(args)


def _diagnose_loaded(args: argparse.Namespace) -> int:
    from robid_link.ident.runner import run_job

    robot, model, data, valid = _inputs(args)
    job = run_job(robot, data, model, analyses=("diagnose",), validate=valid,
                  cutoff_hz=args.cutoff, interval=args.interval, motor_side=args.motor_side,
                  json_files={"diagnose": args.json} if args.json else None,
                  report_dir=args.out, history=args.model or None)
    dg = job.diagnosis
    assert dg is not None  # "diagnose" was asked for
    print(dg.summary())
    if args.out:
        print(f"  wrote {len(job.report_files['diagnose'])} figures to {args.out}; report: "
              f"{job.report_html}")
    if dg.suggestions and args.model:
        s = dg.suggestions[0]
        print(f"  next: robid model add {args.model} {s.label()}")
    return 0


# ------------------------------------------------------------------------ history, model add

def _history_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("model_file", help="model file whose history (.history.jsonl) to show")
    p.add_argument("--out", metavar="PNG", type=figure_path(),
                   help="plot per-joint RMSE per model version")


def _history(args: argparse.Namespace) -> int:
    from robid_link.ident.diagnosis.history import read_history
    from robid_link.ident.report.figures import history_figure

    records = read_history(args.model_file)
    print(f"{args.model_file}: {len(records)} run(s)")
    for k, r in enumerate(records, 1):
        rmse = " ".join(f"{x:8.4g}" for x in r.get("rmse") or [])
        extra = f"  {r['verdict']}" if r.get("verdict") else ""
        print(f" {k:>3} {r.get('time', '')[:19]} {r.get('kind', ''):<9} "
              f"[{', '.join(r.get('effects') or [])}]\n      RMSE {rmse}{extra}")
    if args.out:
        print(f"wrote {history_figure(records, args.out)}")
    return 0


def _model_add_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("model_file", type=output_path("file"),
                   help="model file (YAML with effects:) to edit or create")
    p.add_argument("effect", help="EFFECT or EFFECT@J")


def _model_add(args: argparse.Namespace) -> int:
    from robid_link.ident.diagnosis.history import latest_hypers
    from robid_link.ident.model.effects import (
        DEFAULT_MODEL,
        REGISTRY,
        EffectSpec,
        load_model,
        parse_effect,
        save_model,
    )

    path = Path(args.model_file)
    model = load_model(path) if path.exists() else DEFAULT_MODEL
    spec = parse_effect(args.effect, args.effect)
    chosen = latest_hypers(path, spec.name, spec.joint, spec.side)
    allowed = REGISTRY[spec.name].options
    chosen = {k: v for k, v in chosen.items() if k in allowed and k not in spec.opts}
    if chosen:
        spec = EffectSpec(spec.name, spec.joint, tuple(sorted({**spec.opts, **chosen}.items())),
                          spec.side)
        print(f"  with {', '.join(f'{k} = {v:.4g}' for k, v in chosen.items())} "
              "(chosen by the latest diagnosis)")
    model = model.with_added(spec)
    save_model(path, model)
    print(f"{path}: effects [{', '.join(model.labels())}]")
    return 0


# ----------------------------------------------------------------------------- elasticity

def _elasticity_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--robot", required=True, help="MDH YAML or URDF robot description")
    p.add_argument("--lock", action="append", default=[], metavar="NAME",
                   help="URDF joint to lock; repeatable")
    p.add_argument("--data", action="append", required=True, metavar="LOG",
                   help="stepped-sine log (.csv, .npz, .mat or a ROS bag); repeatable")
    p.add_argument("--fs", type=rate_hz(1e6), metavar="HZ",
                   help="sampling rate in Hz of .mat logs")
    _topic_option(p)
    p.add_argument("--joint", type=bounded_int(1, 64), action="append", default=[], metavar="J",
                   help="axis to fit (1-based); repeatable; default every excited axis")
    p.add_argument("--joints", metavar="J1,J2", help="a pair of axes for the coupled fit")
    p.add_argument("--schedule", metavar="TRAJ_YAML",
                   help="the trajectory header with the step schedule; default: detect the "
                        "steps in the log")
    p.add_argument("--motor-side", action="store_true",
                   help="logs on the motor side: results in motor units (no conversion)")
    p.add_argument("--json", metavar="FILE", type=output_path("file", create_parents=True),
                   help="write the result as JSON")
    p.add_argument("--out", metavar="DIR", type=output_path("dir"),
                   help="write report.html and Bode figures")


def _elasticity(args: argparse.Namespace) -> int:
    from robid_link.config import read_yaml_mapping
    from robid_link.ident.data.logs import load_log
    from robid_link.ident.elastic.elasticity import elasticity_figures, identify_elasticity
    from robid_link.ident.model.robot import load_robot
    from robid_link.ident.report.figures import write_json

    pair = axis_pair(args.joints, "--joints") if args.joints is not None else None
    robot = load_robot(args.robot, args.lock)
    axes_of(robot, "--joint", args.joint)
    axes_of(robot, "--joints", pair or ())
    logs = [load_log(p, robot.n, args.fs, joint_names=robot.joint_names, topic=args.topic,
                     effort_current=robot.effort_current) for p in args.data]
    schedule = None
    if args.schedule:
        schedule = read_yaml_mapping(args.schedule, "trajectory header").get("schedule")
        if not isinstance(schedule, list):
            raise RobidError(f"{args.schedule}: schedule: missing (not a stepped-sine header)")
    joints = list(args.joint)
    if not joints and pair is None:  # every excited axis, and the pair excited together
        from robid_link.ident.elastic.frequency import detect_steps, excited_axes

        try:
            steps = schedule if schedule is not None else detect_steps(
                logs[0].t, logs[0].q, logs[0].tau)
        except DataError as err:
            raise DataError(f"{logs[0].path}: {err}") from err
        joints, pairs = excited_axes(steps)
        pair = pairs[0] if pairs else None
    res = identify_elasticity(robot, logs, joints=joints, pair=pair, schedule=schedule,
                              side="motor" if args.motor_side else "joint")
    print(res.summary())
    if args.json:
        write_json(args.json, res.to_dict())
    if args.out:
        paths = elasticity_figures(res, args.out)
        from robid_link.ident.report.html import write_html_report

        page = write_html_report(args.out, elasticity=res, robot=robot)
        print(f"\n  wrote {len(paths)} figure(s) to {args.out}; report: {page}")
    return 0


COMMANDS = (
    Command(name="identify", help="identify the dynamic model from logs",
            options=_identify_options, check=_identify_check, run=_identify),
    Command(name="diagnose", help="find where the model fails and which effect is missing",
            options=_diagnose_options, check=_fs_check, run=_diagnose),
    Command(name="history", help="the error ladder of a model file",
            options=_history_options, run=_history),
    Command(name="model", help="edit a model file", commands=(
        Command(name="add", help="add an effect (creates the file from the default model)",
                options=_model_add_options, run=_model_add),)),
    Command(name="elasticity", help="joint elasticity (two-mass / coupled) from "
            "stepped-sine logs", options=_elasticity_options, check=_fs_check,
            run=_elasticity),
)
