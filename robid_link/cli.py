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

from robid_link.exceptions import ConfigError, RobidError

__all__ = ["main"]




def _shared_inputs(p: argparse.ArgumentParser) -> None:
    p.add_argument("--robot", required=True, help="MDH YAML or URDF robot description")
    p.add_argument("--data", action="append", required=True, metavar="LOG",
                   help="log file (.csv, .npz, .mat); repeat to identify on several")
    p.add_argument("--validate", action="append", metavar="LOG",
                   help="held-out log(s); default: the last 20 %% of each --data file")
    p.add_argument("--lock", action="append", default=[], metavar="NAME",
                   help="URDF joint to lock (e.g. gripper fingers); repeatable")
    p.add_argument("--fs", type=float, help="sampling rate in Hz (needed for .mat logs)")
    p.add_argument("--cutoff", type=float, metavar="HZ",
                   help="zero-phase low-pass cutoff (default 10 Hz, at most 40 %% of Nyquist)")
    p.add_argument("--interval", type=int, default=1, metavar="K",
                   help="keep every K-th sample after anti-alias filtering (default 1)")
    p.add_argument("--motor-side", action="store_true",
                   help="logs are on the motor side; convert through the robot's transmission")
    p.add_argument("--model", help="model file (YAML with effects:); default "
                   "[rigid_body, viscous, coulomb]")
    p.add_argument("--add", action="append", default=[], metavar="EFFECT[@J]",
                   help="add an effect to the model for this run; repeatable")


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="robid", description="Dynamic-model identification of "
                                 "industrial robots.")
    ap.add_argument("--debug", action="store_true", help="show tracebacks")
    sub = ap.add_subparsers(dest="cmd", required=True)

    p = sub.add_parser("identify", help="identify the dynamic model from logs")
    _shared_inputs(p)
    p.add_argument("--method", choices=("ols", "wls", "irls", "consistent"), default="ols",
                   help="consistent: standard parameters kept physically realizable, with the "
                        "CAD inertials as prior (weight chosen by cross-validation)")
    p.add_argument("--export-urdf", metavar="FILE", help="with --method consistent: write the "
                   "robot's URDF with the identified inertials")
    p.add_argument("--weight", default="bisquare",
                   help="IRLS weight: andrews, bisquare, cauchy, fair, huber, logistic, "
                        "talwar, welsch")
    p.add_argument("--json", metavar="FILE", help="write the result as JSON")
    p.add_argument("--out", metavar="DIR", help="write figures, parameter table and YAML")

    p = sub.add_parser("diagnose", help="find where the model fails and which effect is missing")
    _shared_inputs(p)
    p.add_argument("--json", metavar="FILE", help="write the diagnosis as JSON")
    p.add_argument("--out", metavar="DIR", help="write residual figures per joint")

    p = sub.add_parser("history", help="the error ladder of a model file")
    p.add_argument("model_file")
    p.add_argument("--out", metavar="PNG", help="plot per-joint RMSE per model version")

    p = sub.add_parser("show-robot", help="draw the kinematic chain at a pose (PNG)")
    p.add_argument("--robot", required=True)
    p.add_argument("--lock", action="append", default=[], metavar="NAME")
    p.add_argument("--q", type=float, nargs="+", metavar="DEG",
                   help="joint positions in degrees (metres for prismatic); default zeros")
    p.add_argument("--out", required=True, metavar="PNG")

    p = sub.add_parser("model", help="edit a model file")
    msub = p.add_subparsers(dest="model_cmd", required=True)
    pa = msub.add_parser("add", help="add an effect (creates the file from the default model)")
    pa.add_argument("model_file")
    pa.add_argument("effect", help="EFFECT or EFFECT@J")

    p = sub.add_parser("excite", help="design an optimized excitation trajectory")
    p.add_argument("--robot", required=True)
    p.add_argument("--lock", action="append", default=[], metavar="NAME")
    p.add_argument("--out", required=True, metavar="TRAJ", help="trajectory CSV (+ .yaml header)")
    p.add_argument("--duration", type=float, default=20.0, metavar="S",
                   help="length in seconds, whole periods (default 20)")
    p.add_argument("--harmonics", type=int, default=8, metavar="K")
    p.add_argument("--base-hz", type=float, default=0.1, help="Fourier base frequency")
    p.add_argument("--rate", type=float, default=250.0, metavar="HZ",
                   help="controller rate of the trajectory file (default 250)")
    p.add_argument("--model", help="model file whose base set is excited (default model)")
    p.add_argument("--evaluations", type=int, default=2500,
                   help="optimizer budget per restart (3 restarts)")
    p.add_argument("--seed", type=int, default=0)

    p = sub.add_parser("simulate", help="run a trajectory on the simulated robot, write a log")
    p.add_argument("--robot", required=True)
    p.add_argument("--lock", action="append", default=[], metavar="NAME")
    p.add_argument("--truth", required=True, help="truth file (inertials, effects, noise)")
    p.add_argument("--trajectory", required=True, metavar="TRAJ")
    p.add_argument("--out", required=True, metavar="LOG")
    p.add_argument("--seed", type=int, default=0)

    p = sub.add_parser("demo", help="the whole job on a simulated cell: fake controller, "
                       "daemon, campaign, identification, diagnosis, report")
    p.add_argument("--json", metavar="FILE", help="write the run's result as JSON")
    p.add_argument("--out", metavar="DIR", default="demo-out")
    p.add_argument("--driver", default="file_share",
                   help="the controller link to run the demo over (its fake peer plays the "
                   "cell): file_share, abb_rws, canopen_drives, modbus_plc, serial_line")

    _link_parsers(sub)
    return ap


def _link_parsers(sub: Any) -> None:
    p = sub.add_parser("daemon", help="run the link daemon in the foreground (systemd unit)")
    p.add_argument("--config", required=True, metavar="C")

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
    p.add_argument("--ready-file", metavar="F", help="write the daemon's driver: mapping "
                   "for this peer as JSON to F once it serves (ports chosen at start)")
    p.add_argument("--robot", required=True)
    p.add_argument("--lock", action="append", default=[], metavar="NAME")
    p.add_argument("--truth", help="truth file (default: nominal inertials, viscous and "
                   "Coulomb friction, torque noise)")
    p.add_argument("--fault", help="never_answer, die, truncated_log, corrupt_log, "
                   "answer_twice, stale_semaphore, nan_log, fail, or one of the peer's own")
    p.add_argument("--fault-count", type=int, default=1, metavar="N",
                   help="how many programs the fault hits (default 1)")
    p.add_argument("--seed", type=int, default=0)

    p = sub.add_parser("campaign", help="start, list or approve test campaigns")
    csub = p.add_subparsers(dest="campaign_cmd", required=True)
    pc = csub.add_parser("start", help="queue a run of a campaign (prints its run_id)")
    pc.add_argument("name")
    pc.add_argument("--config", required=True, metavar="C")
    pc.add_argument("--trigger", choices=("operator", "timer"), default="operator",
                    help="timer: unattended, runs only approved programs")
    pc.add_argument("--wait", action="store_true", help="show progress until the run ends")
    pc.add_argument("--json", metavar="FILE", help="with --wait: write the run and results")
    pc = csub.add_parser("list", help="the campaigns of the config")
    pc.add_argument("--config", required=True, metavar="C")
    pc = csub.add_parser("approve", help="generate, check and approve a campaign's programs "
                         "for unattended runs")
    pc.add_argument("name")
    pc.add_argument("--config", required=True, metavar="C")

    p = sub.add_parser("status", help="runs, their state and progress")
    p.add_argument("--config", required=True, metavar="C")
    p.add_argument("--json", metavar="FILE")

    p = sub.add_parser("params", help="the parameter sets each robot's controller gets: "
                       "show, diff, approve (for unattended uploads), rollback")
    p.add_argument("params_cmd", choices=("show", "diff", "approve", "rollback"))
    p.add_argument("sets", nargs="*", metavar="SET",
                   help="a set's version number or sha256 prefix (show: one; diff: two, "
                   "default the set in use and the newest; approve: one, default the newest)")
    p.add_argument("--config", required=True, metavar="C")
    p.add_argument("--robot", required=True, metavar="NAME")
    p.add_argument("--json", metavar="FILE", help="show: write the set(s) as JSON")

    p = sub.add_parser("results", help="identification results across runs and robots")
    p.add_argument("--config", required=True, metavar="C")
    p.add_argument("--robot", metavar="NAME", help="only this robot's results")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--trend", action="store_true",
                   help="with --robot: each parameter over the stored runs, drift flagged")
    g.add_argument("--compare", nargs=2, metavar=("ROBOT_A", "ROBOT_B"),
                   help="the latest identification of two robots of one type side by side")
    p.add_argument("--sigma", type=float, default=5.0,
                   help="drift flag: change in combined standard errors (default 5)")
    p.add_argument("--min-change", type=float, default=0.10, metavar="FRACTION",
                   help="drift flag: change of the baseline, at the lower end of its 95 %% "
                   "interval (default 0.10)")
    p.add_argument("--json", metavar="FILE", help="write the trend as JSON")
    p.add_argument("--out", metavar="PNG", help="plot the trend of the flagged (or all "
                   "physically readable) parameters")


def _one_line_warnings() -> None:
    def show(message: Warning | str, category: type[Warning], *args: Any, **kw: Any) -> None:
        print(f"robid: warning: {message}", file=sys.stderr)

    warnings.showwarning = show  # type: ignore[assignment]
    warnings.simplefilter("default")


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
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
    from robid_link.link.commands import dispatch

    return dispatch(args)


def _load_model(args: argparse.Namespace):
    from robid_link.ident.effects import DEFAULT_MODEL, load_model, parse_effect, save_model

    if args.model and not Path(args.model).exists():
        save_model(args.model, DEFAULT_MODEL)  # the error ladder starts at the default model
        print(f"created {args.model} with the default model [{', '.join(DEFAULT_MODEL.labels())}]")
    model = load_model(args.model)
    for entry in args.add:
        model = model.with_added(parse_effect(entry, f"--add {entry}"))
    return model


def _inputs(args: argparse.Namespace):
    """The shared inputs of identify and diagnose: robot, model, data and validation logs."""
    from robid_link.ident.identify import load_logs
    from robid_link.ident.robot import load_robot

    robot = load_robot(args.robot, args.lock)
    model = _load_model(args)
    data = load_logs(robot, args.data, args.fs, args.motor_side)
    valid = load_logs(robot, args.validate, args.fs, args.motor_side) if args.validate else None
    return robot, model, data, valid


def _identify(args: argparse.Namespace) -> int:
    from robid_link.ident.identify import identify
    from robid_link.ident.report import write_json, write_report

    robot, model, data, valid = _inputs(args)
    if args.export_urdf and args.method != "consistent":
        raise ConfigError("--export-urdf needs --method consistent (standard parameters)")
    res = identify(robot, data, model, validate=valid, cutoff_hz=args.cutoff,
                   interval=args.interval, method=args.method, weight=args.weight,
                   motor_side=args.motor_side)
    print(res.summary())
    doc = res.to_dict()
    if args.json:
        write_json(args.json, doc)
    if args.out:
        paths = write_report(res, args.out)
        print(f"\n  wrote {len(paths)} files to {args.out}")
    if args.export_urdf:  # issue 15 item 6
        from robid_link.ident.urdf_export import export_urdf

        cons = res.consistent
        export_urdf(robot, cons.standard, args.export_urdf, dict(zip(cons.names, cons.theta,
                                                                     strict=True)))
        print(f"\n  wrote the identified model as URDF to {args.export_urdf}")
    _record(args, "identify", doc)
    return 0


def _record(args: argparse.Namespace, kind: str, doc: dict[str, Any]) -> None:
    if args.model:
        from robid_link.ident.history import append_record, result_record

        append_record(args.model, result_record(kind, doc))


def _diagnose(args: argparse.Namespace) -> int:
    from robid_link.ident.diagnose import diagnose
    from robid_link.ident.report import residual_figures, write_json

    robot, model, data, valid = _inputs(args)
    dg = diagnose(robot, data, model, validate=valid, cutoff_hz=args.cutoff,
                  interval=args.interval, motor_side=args.motor_side)
    print(dg.summary())
    doc = dg.to_dict()
    doc["data_files"] = dg.result.to_dict()["data_files"]
    if args.json:
        write_json(args.json, doc)
    if args.out:
        paths = residual_figures(dg.residuals, dg.result.joints, args.out)
        print(f"  wrote {len(paths)} figures to {args.out}")
    if dg.suggestions and args.model:
        s = dg.suggestions[0]
        print(f"  next: robid model add {args.model} {s.label()}")
    _record(args, "diagnose", doc)
    return 0


def _history(args: argparse.Namespace) -> int:
    from robid_link.ident.history import read_history
    from robid_link.ident.report import history_figure

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
    from robid_link.ident.report import draw_robot
    from robid_link.ident.robot import load_robot

    robot = load_robot(args.robot, args.lock)
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
    from robid_link.ident.effects import (
        DEFAULT_MODEL,
        REGISTRY,
        EffectSpec,
        load_model,
        parse_effect,
        save_model,
    )
    from robid_link.ident.history import latest_hypers

    path = Path(args.model_file)
    model = load_model(path) if path.exists() else DEFAULT_MODEL
    spec = parse_effect(args.effect, args.effect)
    chosen = latest_hypers(path, spec.name, spec.joint)
    allowed = REGISTRY[spec.name].options
    chosen = {k: v for k, v in chosen.items() if k in allowed and k not in spec.opts}
    if chosen:
        spec = EffectSpec(spec.name, spec.joint, tuple(sorted({**spec.opts, **chosen}.items())))
        print(f"  with {', '.join(f'{k} = {v:.4g}' for k, v in chosen.items())} "
              "(chosen by the latest diagnosis)")
    model = model.with_added(spec)
    save_model(path, model)
    print(f"{path}: effects [{', '.join(model.labels())}]")
    return 0


def _excite(args: argparse.Namespace) -> int:
    from robid_link.ident import excitation as ex
    from robid_link.ident.effects import load_model
    from robid_link.ident.robot import load_robot

    robot = load_robot(args.robot, args.lock)
    model = load_model(args.model)
    if args.harmonics < 1 or args.base_hz <= 0 or args.rate <= 0 or args.duration <= 0:
        raise RobidError("--harmonics, --base-hz, --rate and --duration must be positive")
    traj, cond = ex.optimize_fourier(robot, harmonics=args.harmonics, base_hz=args.base_hz,
                                     model=model, seed=args.seed,
                                     evaluations=args.evaluations)
    rand = [ex.excitation_condition(robot, ex.random_fourier(
        robot, harmonics=args.harmonics, base_hz=args.base_hz, seed=1000 + s), model)
        for s in range(20)]
    periods = max(1, round(args.duration * args.base_hz))
    t = np.arange(0.0, periods / args.base_hz, 1.0 / args.rate)
    q, qd, qdd = traj.evaluate(t)
    ex.check_limits(robot, q, qd, qdd, ex._nominal_torque(robot, q, qd, qdd), args.out)
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


def _simulate(args: argparse.Namespace) -> int:
    from robid_link.ident.data import write_log_csv
    from robid_link.ident.excitation import read_trajectory, trajectory_states
    from robid_link.ident.robot import load_robot
    from robid_link.link.registry import fake_module

    plant = fake_module("plant")
    robot = load_robot(args.robot, args.lock)
    truth = plant.load_truth(args.truth, robot)
    traj = read_trajectory(args.trajectory)
    if traj.q.shape[1] != robot.n:
        raise RobidError(f"{args.trajectory}: {traj.q.shape[1]} joints, the robot has {robot.n}")
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
