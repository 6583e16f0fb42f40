"""The ``robid`` command: parse, call, print. Errors are one line, never a traceback."""

from __future__ import annotations

import argparse
import sys
import tempfile
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from robid_link import __version__
from robid_link.cli_types import (
    OneLineParser,
    bounded_int,
    finite_float,
    output_path,
    positive_float,
)
from robid_link.exceptions import ConfigError, RobidError

__all__ = ["main"]

_ROBOT_HELP = "robot description: MDH YAML (.yaml) or URDF (.urdf)"
_LOCK_HELP = "URDF joint to lock (e.g. gripper fingers); repeatable"
_UNLIMITED_HELP = ("accept revolute/prismatic joints without consistent position limits "
                   "(logged as a warning); otherwise such a robot file is refused")
_SEED_HELP = "random seed (default 0)"
#: most samples a generated trajectory or simulated log may have (≈ 3 h at 1 kHz)
MAX_SAMPLES = 10_000_000


def _robot_options(p: argparse.ArgumentParser, *, lock_help: str = _LOCK_HELP) -> None:
    p.add_argument("--robot", required=True, help=_ROBOT_HELP)
    p.add_argument("--lock", action="append", default=[], metavar="NAME", help=lock_help)
    p.add_argument("--allow-unlimited", action="store_true", help=_UNLIMITED_HELP)


def _shared_inputs(p: argparse.ArgumentParser) -> None:
    _robot_options(p, lock_help="URDF joint to lock (e.g. gripper fingers); repeatable")
    p.add_argument("--data", action="append", required=True, metavar="LOG",
                   help="log file (.csv, .npz, .mat); repeat to identify on several")
    p.add_argument("--validate", action="append", metavar="LOG",
                   help="held-out log(s); default: the last 20 %% of each --data file")
    p.add_argument("--fs", type=positive_float(1e6), metavar="HZ",
                   help="sampling rate in Hz (needed for .mat logs)")
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


def _parser() -> argparse.ArgumentParser:
    ap = OneLineParser(prog="robid", description="Dynamic-model identification of "
                       "industrial robots.")
    ap.add_argument("--debug", action="store_true", help="show tracebacks")
    ap.add_argument("--version", action="version", version=f"robid {__version__}",
                    help="print the version and exit")
    sub = ap.add_subparsers(dest="cmd", required=True)

    p = sub.add_parser("identify", help="identify the dynamic model from logs")
    _shared_inputs(p)
    p.add_argument("--method", choices=("ols", "wls", "irls", "consistent"), default="ols",
                   help="least squares: ols (default), wls (per-joint weights), irls (robust) "
                   "or consistent (standard parameters kept physically realizable, with the "
                   "CAD inertials as prior, weight chosen by cross-validation)")
    p.add_argument("--export-urdf", metavar="FILE", type=output_path("file"),
                   help="with --method consistent: write the robot's URDF with the "
                   "identified inertials")
    p.add_argument("--weight", default="bisquare",
                   help="IRLS weight: andrews, bisquare, cauchy, fair, huber, logistic, "
                        "talwar, welsch")
    p.add_argument("--json", metavar="FILE", type=output_path("file", create_parents=True),
                   help="write the result as JSON")
    p.add_argument("--out", metavar="DIR", type=output_path("dir"),
                   help="write report.html, figures, parameter table and YAML")

    p = sub.add_parser("diagnose", help="find where the model fails and which effect is missing")
    _shared_inputs(p)
    p.add_argument("--json", metavar="FILE", type=output_path("file", create_parents=True),
                   help="write the diagnosis as JSON")
    p.add_argument("--out", metavar="DIR", type=output_path("dir"),
                   help="write report.html and residual figures per joint")

    p = sub.add_parser("history", help="the error ladder of a model file")
    p.add_argument("model_file", help="model file whose history (.history.jsonl) to show")
    p.add_argument("--out", metavar="PNG", type=output_path("file"),
                   help="plot per-joint RMSE per model version")

    p = sub.add_parser("show-robot", help="draw the kinematic chain at a pose (PNG)")
    _robot_options(p)
    p.add_argument("--q", type=finite_float, nargs="+", metavar="DEG",
                   help="joint positions in degrees (metres for prismatic); default zeros")
    p.add_argument("--out", required=True, metavar="PNG",
                   type=output_path("file", create_parents=True), help="the drawing (PNG)")

    p = sub.add_parser("model", help="edit a model file")
    msub = p.add_subparsers(dest="model_cmd", required=True)
    pa = msub.add_parser("add", help="add an effect (creates the file from the default model)")
    pa.add_argument("model_file", type=output_path("file"),
                    help="model file (YAML with effects:) to edit or create")
    pa.add_argument("effect", help="EFFECT or EFFECT@J")

    p = sub.add_parser("excite", help="design an optimized excitation trajectory")
    _robot_options(p)
    p.add_argument("--out", required=True, metavar="TRAJ", type=output_path("file"),
                   help="trajectory CSV (+ .yaml header)")
    p.add_argument("--duration", type=positive_float(1e6), default=20.0, metavar="S",
                   help="length in seconds, whole periods (default 20)")
    p.add_argument("--harmonics", type=bounded_int(1, 50), default=8, metavar="K",
                   help="Fourier harmonics per joint (default 8)")
    p.add_argument("--base-hz", type=positive_float(100.0), default=0.1, metavar="HZ",
                   help="Fourier base frequency (default 0.1)")
    p.add_argument("--rate", type=positive_float(100_000.0), metavar="HZ",
                   help="controller rate of the trajectory file (default 250; 2000 for "
                   "--kind elasticity)")
    p.add_argument("--model", help="model file whose base set is excited (default model)")
    p.add_argument("--evaluations", type=bounded_int(1, 1_000_000), default=2500, metavar="N",
                   help="optimizer budget per restart (3 restarts; default 2500)")
    p.add_argument("--seed", type=bounded_int(0, 2**32 - 1), default=0, help=_SEED_HELP)
    p.add_argument("--kind", choices=("fourier", "elasticity"), default="fourier",
                   help="elasticity: stepped sines per --joint around --pose (schedule in the "
                        "header)")
    p.add_argument("--joint", type=bounded_int(1, 64), action="append", default=[], metavar="J",
                   help="elasticity: axis to excite (1-based); repeatable; default all")
    p.add_argument("--pair", action="append", default=[], metavar="J1,J2",
                   help="elasticity: two axes excited together for the coupled fit; repeatable")
    p.add_argument("--pose", type=finite_float, nargs="+", metavar="DEG",
                   help="elasticity: the pose (degrees per joint)")
    p.add_argument("--f-min", type=positive_float(1000.0), default=2.0, metavar="HZ",
                   help="elasticity: lowest frequency (default 2)")
    p.add_argument("--f-max", type=positive_float(1000.0), default=60.0, metavar="HZ",
                   help="elasticity: highest frequency (default 60)")
    p.add_argument("--steps", type=bounded_int(2, 500), default=24,
                   help="elasticity: frequencies per axis (default 24)")

    p = sub.add_parser("elasticity", help="joint elasticity (two-mass / coupled) from "
                       "stepped-sine logs")
    p.add_argument("--robot", required=True, help="MDH YAML or URDF robot description")
    p.add_argument("--lock", action="append", default=[], metavar="NAME",
                   help="URDF joint to lock; repeatable")
    p.add_argument("--data", action="append", required=True, metavar="LOG",
                   help="stepped-sine log (.csv, .npz, .mat); repeatable")
    p.add_argument("--fs", type=positive_float(1e6), help="sampling rate in Hz (.mat logs)")
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

    p = sub.add_parser("simulate", help="run a trajectory on the simulated robot, write a log")
    _robot_options(p)
    p.add_argument("--truth", required=True, help="truth file (inertials, effects, noise)")
    p.add_argument("--trajectory", required=True, metavar="TRAJ",
                   help="trajectory CSV (with its .yaml header beside it)")
    p.add_argument("--out", required=True, metavar="LOG", type=output_path("file"),
                   help="the simulated log (CSV)")
    p.add_argument("--seed", type=bounded_int(0, 2**32 - 1), default=0, help=_SEED_HELP)

    p = sub.add_parser("demo", help="the whole job on a simulated cell: fake controller, "
                       "daemon, campaign, identification, diagnosis, report")
    p.add_argument("--json", metavar="FILE", type=output_path("file", create_parents=True),
                   help="write the run's result as JSON")
    p.add_argument("--out", metavar="DIR", default="demo-out", type=output_path("dir"),
                   help="report folder (default demo-out)")
    p.add_argument("--driver", default="file_share",
                   help="the controller link to run the demo over (its fake peer plays the "
                   "cell): file_share, abb_rws, canopen_drives, modbus_plc, serial_line")

    _link_parsers(sub)
    _web_parser(sub)
    return ap


def _web_parser(sub: Any) -> None:
    p = sub.add_parser("web", help="the operator's page, read-only, from a config's state dir "
                       "(no daemon needed)")
    p.add_argument("--config", required=True, help="daemon config (YAML)")
    p.add_argument("--listen", metavar="HOST:PORT",
                   help="address to serve (default web.listen of the config, else "
                        "127.0.0.1:8765; another than loopback needs web.tls_cert, "
                        "web.tls_key and a token)")


def _link_parsers(sub: Any) -> None:
    p = sub.add_parser("daemon", help="run the link daemon in the foreground (systemd unit)")
    p.add_argument("--config", required=True, metavar="C", help="daemon config (YAML)")

    p = sub.add_parser("fake-controller", help="the controller side of a driver's protocol "
                       "over the simulated robot (tests, demos)")
    p.add_argument("--driver", default="file_share",
                   help="the driver whose controller side to play (file_share, abb_rws, "
                   "canopen_drives, modbus_plc, serial_line, or a plug-in's)")
    p.add_argument("--share", "--workdir", dest="workdir", required=True, metavar="DIR",
                   help="the peer's folder: the share (file_share, modbus_plc) or the "
                   "controller's file system")
    p.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                   help="a peer option (YAML value), e.g. --option port=0; repeatable")
    p.add_argument("--ready-file", metavar="F", type=output_path("file"),
                   help="write the daemon's driver: mapping for this peer as JSON to F once it "
                   "serves (ports chosen at start)")
    _robot_options(p)
    p.add_argument("--truth", help="truth file (default: nominal inertials, viscous and "
                   "Coulomb friction, torque noise)")
    p.add_argument("--fault", help="never_answer, die, truncated_log, corrupt_log, "
                   "answer_twice, stale_semaphore, nan_log, fail, or one of the peer's own")
    p.add_argument("--fault-count", type=bounded_int(0, 1_000_000), default=1, metavar="N",
                   help="how many programs the fault hits (default 1)")
    p.add_argument("--seed", type=bounded_int(0, 2**32 - 1), default=0, help=_SEED_HELP)

    p = sub.add_parser("campaign", help="start, list or approve test campaigns")
    csub = p.add_subparsers(dest="campaign_cmd", required=True)
    pc = csub.add_parser("start", help="queue a run of a campaign (prints its run_id)")
    pc.add_argument("name", help="campaign name (from the config's campaigns:)")
    pc.add_argument("--config", required=True, metavar="C", help="daemon config (YAML)")
    pc.add_argument("--trigger", choices=("operator", "timer"), default="operator",
                    help="timer: unattended, runs only approved programs")
    pc.add_argument("--wait", action="store_true", help="show progress until the run ends")
    pc.add_argument("--json", metavar="FILE", type=output_path("file", create_parents=True),
                    help="with --wait: write the run and results")
    pc = csub.add_parser("list", help="the campaigns of the config")
    pc.add_argument("--config", required=True, metavar="C", help="daemon config (YAML)")
    pc = csub.add_parser("cancel", help="drop a queued run, or stop the running one after "
                         "withdrawing its program")
    pc.add_argument("run_id", help="the run's id (robid status)")
    pc.add_argument("--config", required=True, metavar="C", help="daemon config (YAML)")
    pc = csub.add_parser("approve", help="generate, check and approve a campaign's programs "
                         "for unattended runs")
    pc.add_argument("name", help="campaign name (from the config's campaigns:)")
    pc.add_argument("--config", required=True, metavar="C", help="daemon config (YAML)")

    p = sub.add_parser("config", help="check a daemon config without a daemon")
    ksub = p.add_subparsers(dest="config_cmd", required=True)
    pc = ksub.add_parser("check", help="everything each campaign's run will need: one line "
                         "per campaign, ok or the reason")
    pc.add_argument("--config", required=True, metavar="C", help="daemon config (YAML)")

    p = sub.add_parser("status", help="runs, their state and progress")
    p.add_argument("--config", required=True, metavar="C", help="daemon config (YAML)")
    p.add_argument("--json", metavar="FILE", type=output_path("file", create_parents=True),
                   help="write the runs as JSON")

    p = sub.add_parser("params", help="the parameter sets each robot's controller gets: "
                       "show, diff, approve (for unattended uploads), rollback")
    p.add_argument("params_cmd", choices=("show", "diff", "approve", "rollback"),
                   help="show the sets, diff two, approve one for unattended uploads, or "
                   "roll the controller back to the set before the one in use")
    p.add_argument("sets", nargs="*", metavar="SET",
                   help="a set's version number or sha256 prefix (show: one; diff: two, "
                   "default the set in use and the newest; approve: one, default the newest)")
    p.add_argument("--config", required=True, metavar="C", help="daemon config (YAML)")
    p.add_argument("--robot", required=True, metavar="NAME", help="the robot's name")
    p.add_argument("--json", metavar="FILE", type=output_path("file", create_parents=True),
                   help="show: write the set(s) as JSON")

    p = sub.add_parser("results", help="identification results across runs and robots")
    p.add_argument("--config", required=True, metavar="C", help="daemon config (YAML)")
    p.add_argument("--robot", metavar="NAME", help="only this robot's results")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--trend", action="store_true",
                   help="with --robot: each parameter over the stored runs, drift flagged")
    g.add_argument("--compare", nargs=2, metavar=("ROBOT_A", "ROBOT_B"),
                   help="the latest identification of two robots of one type side by side")
    p.add_argument("--sigma", type=positive_float(1e3), default=5.0,
                   help="drift flag: change in combined standard errors (default 5)")
    p.add_argument("--min-change", type=positive_float(10.0), default=0.10, metavar="FRACTION",
                   help="drift flag: change of the baseline, at the lower end of its 95 %% "
                   "interval (default 0.10)")
    p.add_argument("--json", metavar="FILE", type=output_path("file", create_parents=True),
                   help="write the trend as JSON")
    p.add_argument("--out", metavar="PNG", type=output_path("file"),
                   help="plot the trend of the flagged (or all physically readable) parameters")


def _one_line_warnings() -> None:
    def show(message: Warning | str, category: type[Warning], *args: Any, **kw: Any) -> None:
        print(f"robid: warning: {message}", file=sys.stderr)

    warnings.showwarning = show  # type: ignore[assignment]
    warnings.simplefilter("default")


def main(argv: Sequence[str] | None = None) -> int:
    try:
        args = _parser().parse_args(argv)
    except SystemExit as exc:  # a usage error (already printed in one line), --help, --version
        return exc.code if isinstance(exc.code, int) else 2
    _one_line_warnings()
    try:
        return int(_dispatch(args) or 0)
    except RobidError as err:
        if args.debug:
            raise
        print(f"robid: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("robid: interrupted", file=sys.stderr)
        return 130


def _dispatch(args: argparse.Namespace) -> int:
    if args.cmd == "identify":
        return _identify(args)
    if args.cmd == "show-robot":
        return _show_robot(args)
    if args.cmd == "model":
        return _model_add(args)
    if args.cmd == "demo":
        return _demo(args)
    if args.cmd == "diagnose":
        return _diagnose(args)
    if args.cmd == "history":
        return _history(args)
    if args.cmd == "excite":
        return _excite(args)
    if args.cmd == "simulate":
        return _simulate(args)
    if args.cmd == "elasticity":
        return _elasticity(args)
    if args.cmd in ("web", "daemon"):  # the page: robid web, and the daemon's own
        from robid_link.web.command import daemon_service, run_web

        if args.cmd == "web":
            return run_web(args.config, args.listen)
        import asyncio

        from robid_link.config import load_daemon_config
        from robid_link.link.daemon import run_daemon

        cfg = load_daemon_config(args.config)
        return asyncio.run(run_daemon(cfg, [daemon_service(cfg)] if cfg.web.listen else []))
    from robid_link.link.commands import dispatch

    return dispatch(args)


def _load_model(args: argparse.Namespace):
    from robid_link.ident.model.effects import DEFAULT_MODEL, load_model, parse_effect, save_model

    if args.model and not Path(args.model).exists():
        save_model(args.model, DEFAULT_MODEL)  # the error ladder starts at the default model
        print(f"created {args.model} with the default model [{', '.join(DEFAULT_MODEL.labels())}]")
    model = load_model(args.model)
    for entry in args.add:
        model = model.with_added(parse_effect(entry, f"--add {entry}"))
    return model


def _inputs(args: argparse.Namespace):
    """The shared inputs of identify and diagnose: robot, model, data and validation logs."""
    from robid_link.ident.fit.identify import load_logs
    from robid_link.ident.model.robot import load_robot

    robot = load_robot(args.robot, args.lock, allow_unlimited=args.allow_unlimited)
    model = _load_model(args)
    data = load_logs(robot, args.data, args.fs, args.motor_side)
    valid = load_logs(robot, args.validate, args.fs, args.motor_side) if args.validate else None
    return robot, model, data, valid


def _identify(args: argparse.Namespace) -> int:
    from robid_link.ident.runner import run_job

    robot, model, data, valid = _inputs(args)
    if args.export_urdf and args.method != "consistent":
        raise ConfigError("--export-urdf needs --method consistent (standard parameters)")
    job = run_job(robot, data, model, validate=valid, cutoff_hz=args.cutoff,
                  interval=args.interval, method=args.method, weight=args.weight,
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


def _diagnose(args: argparse.Namespace) -> int:
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


def _show_robot(args: argparse.Namespace) -> int:
    from robid_link.ident.model.robot import load_robot
    from robid_link.ident.report.figures import draw_robot

    robot = load_robot(args.robot, args.lock, allow_unlimited=args.allow_unlimited)
    q = np.zeros(robot.n)
    if args.q is not None:
        if len(args.q) != robot.n:
            raise RobidError(f"--q: {len(args.q)} values given, the robot has {robot.n} joints")
        scale = np.array([np.pi / 180 if t == "revolute" else 1.0 for t in robot.joint_types])
        q = np.array(args.q) * scale
    path = draw_robot(robot, q, args.out)
    for jt in robot.mapping():
        print(f"  {jt['joint']:>2}  {jt['name']}  ({jt['type']})")
    print(f"wrote {path}")
    return 0


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


def _excite(args: argparse.Namespace) -> int:
    from robid_link.ident.excite import excitation as ex
    from robid_link.ident.model.effects import load_model
    from robid_link.ident.model.robot import load_robot

    robot = load_robot(args.robot, args.lock, allow_unlimited=args.allow_unlimited)
    if args.kind == "elasticity":
        return _excite_elasticity(args, robot)
    args.rate = args.rate or 250.0
    periods = max(1, round(args.duration * args.base_hz))
    samples = periods / args.base_hz * args.rate
    if samples > MAX_SAMPLES:
        raise RobidError(f"--duration {args.duration:g} s at --rate {args.rate:g} Hz (whole "
                         f"periods of 1/--base-hz) makes {samples:.3g} samples, more than "
                         f"{MAX_SAMPLES}")
    yaml_out = Path(args.out).with_suffix(".yaml")
    if yaml_out.is_dir() or yaml_out == Path(args.out):
        raise RobidError(f"{args.out}: the header {yaml_out} would not be a file beside it")
    model = load_model(args.model)
    print(f"optimizing the excitation of {robot.name}: 3 restarts × {args.evaluations} "
          "evaluations", flush=True)
    traj, cond = ex.optimize_fourier(robot, harmonics=args.harmonics, base_hz=args.base_hz,
                                     model=model, seed=args.seed,
                                     evaluations=args.evaluations,
                                     progress=lambda line: print(f"  {line}", flush=True))
    rand = [ex.excitation_condition(robot, ex.random_fourier(
        robot, harmonics=args.harmonics, base_hz=args.base_hz, seed=1000 + s), model)
        for s in range(20)]
    t = np.arange(0.0, periods / args.base_hz, 1.0 / args.rate)
    q, qd, qdd = traj.evaluate(t)
    ex.check_limits(robot, q, qd, qdd, ex.nominal_torque(robot, q, qd, qdd), args.out)
    header = ex.fourier_header(traj, cond)
    header["random_median_condition_number"] = float(np.median(rand))
    csv_path, yaml_path = ex.write_trajectory(args.out, ex.Trajectory(
        t, q, args.rate, "fourier", robot.name, header))
    print(f"excitation for {robot.name}: {periods} period(s) of {1 / args.base_hz:.4g} s, "
          f"{args.harmonics} harmonics, {args.rate:g} Hz")
    print(f"  condition number {cond:.3g} (median of 20 random trajectories of the same "
          f"structure: {np.median(rand):.3g}, {np.median(rand) / cond:.2f}× better)")
    print(f"wrote {csv_path} and {yaml_path}")
    return 0


def _excite_elasticity(args: argparse.Namespace, robot: Any) -> int:
    from robid_link.ident.elastic.frequency import ElasticityOptions, elasticity_trajectory
    from robid_link.ident.excite.excitation import write_trajectory

    pose = tuple(np.radians(args.pose)) if args.pose else None
    opts = ElasticityOptions(joints=tuple(args.joint), pairs=tuple(map(_pair, args.pair)),
                             pose=pose, f_min_hz=args.f_min,
                             f_max_hz=args.f_max, steps=args.steps, rate_hz=args.rate or 2000.0)
    traj = elasticity_trajectory(robot, opts)
    csv_path, yaml_path = write_trajectory(args.out, traj)
    print(f"stepped sines for {robot.name}: {len(traj.header['schedule'])} steps, "
          f"{args.f_min:g}–{args.f_max:g} Hz, {traj.t[-1]:.4g} s at {traj.rate_hz:g} Hz")
    print(f"wrote {csv_path} and {yaml_path}")
    return 0


def _pair(text: str, option: str = "--pair") -> tuple[int, int]:
    try:
        a, b = (int(x) for x in text.split(","))
    except ValueError as err:
        raise RobidError(f"{option} {text}: expected two axes J1,J2") from err
    return (a, b)


def _elasticity(args: argparse.Namespace) -> int:
    from robid_link.config import read_yaml_mapping
    from robid_link.ident.data.logs import load_log
    from robid_link.ident.elastic.elasticity import elasticity_figures, identify_elasticity
    from robid_link.ident.model.robot import load_robot
    from robid_link.ident.report.figures import write_json

    robot = load_robot(args.robot, args.lock)
    logs = [load_log(p, robot.n, args.fs) for p in args.data]
    pair = _pair(args.joints, "--joints") if args.joints else None
    schedule = None
    if args.schedule:
        schedule = read_yaml_mapping(args.schedule, "trajectory header").get("schedule")
        if not isinstance(schedule, list):
            raise RobidError(f"{args.schedule}: schedule: missing (not a stepped-sine header)")
    joints = list(args.joint)
    if not joints and pair is None:  # every excited axis, and the pair excited together
        from robid_link.ident.elastic.frequency import detect_steps, excited_axes

        steps = schedule if schedule is not None else detect_steps(
            logs[0].t, logs[0].q, logs[0].tau)
        joints, pairs = excited_axes(steps)
        pair = pairs[0] if pairs else None
    res = identify_elasticity(robot, logs, joints=joints, pair=pair, schedule=schedule,
                              side="motor" if args.motor_side else "joint")
    print(res.summary())
    if args.json:
        write_json(args.json, res.to_dict())
    if args.out:
        from robid_link.ident.report.html import write_html_report

        paths = elasticity_figures(res, args.out)
        page = write_html_report(args.out, elasticity=res, robot=robot)
        print(f"\n  wrote {len(paths)} figure(s) to {args.out}; report: {page}")
    return 0


def _simulate(args: argparse.Namespace) -> int:
    from robid_link.ident.data.logs import write_log_csv
    from robid_link.ident.excite.excitation import read_trajectory, trajectory_states
    from robid_link.ident.model.robot import load_robot
    from robid_link.link.registry import fake_module

    plant = fake_module("plant")
    robot = load_robot(args.robot, args.lock, allow_unlimited=args.allow_unlimited)
    truth = plant.load_truth(args.truth, robot)
    traj = read_trajectory(args.trajectory)
    if traj.q.shape[1] != robot.n:
        raise RobidError(f"{args.trajectory}: {traj.q.shape[1]} joints, the robot has {robot.n}")
    samples = (traj.t[-1] - traj.t[0]) * truth.rate_hz
    if samples > MAX_SAMPLES:
        raise RobidError(f"{args.trajectory}: {traj.t[-1] - traj.t[0]:.4g} s at the truth's "
                         f"{truth.rate_hz:g} Hz makes {samples:.3g} samples, more than "
                         f"{MAX_SAMPLES}")
    t, q, qd, qdd = trajectory_states(traj, truth.rate_hz)
    log = plant.Plant(robot, truth).run(t, q, qd, qdd, seed=args.seed)
    write_log_csv(args.out, log["t"], log["q"], log["tau"])
    print(f"simulated {t[-1] - t[0]:.4g} s of {robot.name} at {truth.rate_hz:g} Hz "
          f"({truth.mode}, {len(truth.effects)} effect(s)); wrote {args.out}")
    return 0


def _demo(args: argparse.Namespace) -> int:
    from robid_link.demo import run_demo

    with tempfile.TemporaryDirectory(prefix="robid-demo-") as tmp:
        return run_demo(Path(tmp), Path(args.out), args.json, driver=args.driver)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
