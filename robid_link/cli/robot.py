"""``robid show-robot``, ``excite``, ``simulate``: the robot drawn at a pose, the motions that
excite it, and logs of the simulated robot following them. Numerical imports happen in the
handlers: ``robid --help`` and the operator commands start without numpy."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from robid_link.cli.types import (
    Command,
    axes_of,
    axis_pair,
    bounded_int,
    figure_path,
    finite_float,
    output_path,
    positive_float,
    rate_hz,
    refuse_given,
    robot_options,
    seed_option,
)
from robid_link.exceptions import ConfigError, RobidError

__all__ = ["COMMANDS", "MAX_SAMPLES"]

#: most samples a generated trajectory or simulated log may have (≈ 3 h at 1 kHz)
MAX_SAMPLES = 10_000_000


# ----------------------------------------------------------------------------- show-robot

def _show_robot_options(p: argparse.ArgumentParser) -> None:
    robot_options(p)
    p.add_argument("--q", type=finite_float, nargs="+", metavar="DEG",
                   help="joint positions in degrees (metres for prismatic); default zeros")
    p.add_argument("--out", required=True, metavar="PNG",
                   type=figure_path(create_parents=True),
                   help="the drawing (PNG; .svg, .pdf, .jpg by suffix)")


def _show_robot(args: argparse.Namespace) -> int:
    import numpy as np

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


# --------------------------------------------------------------------------------- excite

def _excite_options(p: argparse.ArgumentParser) -> None:
    robot_options(p)
    p.add_argument("--out", required=True, metavar="TRAJ", type=output_path("file"),
                   help="trajectory CSV (+ .yaml header)")
    p.add_argument("--duration", type=positive_float(1e6), metavar="S",
                   help="length in seconds, whole periods (default 20)")
    p.add_argument("--harmonics", type=bounded_int(1, 50), metavar="K",
                   help="Fourier harmonics per joint (default 8)")
    p.add_argument("--base-hz", type=positive_float(100.0), metavar="HZ",
                   help="Fourier base frequency (default 0.1)")
    p.add_argument("--rate", type=rate_hz(), metavar="HZ",
                   help="controller rate of the trajectory file (default 250; 2000 for "
                   "--kind elasticity)")
    p.add_argument("--model", help="model file whose base set is excited (default model)")
    p.add_argument("--evaluations", type=bounded_int(1, 1_000_000), metavar="N",
                   help="optimizer budget per restart (3 restarts; default 2500)")
    seed_option(p, default=None)
    p.add_argument("--kind", choices=("fourier", "elasticity"), default="fourier",
                   help="elasticity: stepped sines per --joint around --pose (schedule in the "
                        "header)")
    p.add_argument("--joint", type=bounded_int(1, 64), action="append", default=[], metavar="J",
                   help="elasticity: axis to excite (1-based); repeatable; default all")
    p.add_argument("--pair", action="append", default=[], metavar="J1,J2",
                   help="elasticity: two axes excited together for the coupled fit; repeatable")
    p.add_argument("--pose", type=finite_float, nargs="+", metavar="DEG",
                   help="elasticity: the pose (degrees per joint)")
    p.add_argument("--f-min", type=positive_float(1000.0), metavar="HZ",
                   help="elasticity: lowest frequency (default 2)")
    p.add_argument("--f-max", type=positive_float(1000.0), metavar="HZ",
                   help="elasticity: highest frequency (default 60)")
    p.add_argument("--steps", type=bounded_int(3, 500), metavar="N",
                   help="elasticity: frequencies per axis (default 24)")


#: the options of one --kind only, with the defaults their help states (the parser's default
#: is None, so that an option of the other kind, which would be ignored, can be refused)
_FOURIER_OPTIONS = {"--duration": 20.0, "--harmonics": 8, "--base-hz": 0.1,
                    "--evaluations": 2500, "--seed": 0, "--model": None}
_ELASTICITY_OPTIONS = {"--joint": None, "--pair": None, "--pose": None, "--f-min": 2.0,
                       "--f-max": 60.0, "--steps": 24}


def _excite_check(args: argparse.Namespace) -> None:
    """An option of the other --kind would be ignored: refused before the robot is read; the
    stepped sines' band must fit below the rate."""
    other = _ELASTICITY_OPTIONS if args.kind == "fourier" else _FOURIER_OPTIONS
    refuse_given(args, list(other), f"not used by --kind {args.kind}")
    if args.kind == "elasticity":
        full = _with_defaults(args)
        rate = args.rate or 2000.0
        if full.f_min >= full.f_max:
            raise ConfigError(f"--f-min {full.f_min:g}: must be below --f-max {full.f_max:g}")
        if full.f_max > 0.2 * rate:
            raise ConfigError(f"--f-max {full.f_max:g}: above 20 % of --rate {rate:g} (raise "
                              "--rate)")


def _with_defaults(args: argparse.Namespace) -> argparse.Namespace:
    """The options of ``--kind`` with their stated defaults where not given."""
    own = _FOURIER_OPTIONS if args.kind == "fourier" else _ELASTICITY_OPTIONS
    filled = {flag.lstrip("-").replace("-", "_"): default for flag, default in own.items()}
    return argparse.Namespace(**{**vars(args), **{k: v for k, v in filled.items()
                                                  if getattr(args, k) is None}})


def _excite(args: argparse.Namespace) -> int:
    import numpy as np

    from robid_link.ident.excite import excitation as ex
    from robid_link.ident.model.effects import load_model
    from robid_link.ident.model.robot import load_robot

    args = _with_defaults(args)
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
    import numpy as np

    from robid_link.ident.elastic.frequency import ElasticityOptions, elasticity_trajectory
    from robid_link.ident.excite.excitation import write_trajectory

    pairs = [axis_pair(p) for p in args.pair]
    axes_of(robot, "--joint", args.joint)
    axes_of(robot, "--pair", [j for p in pairs for j in p])
    if args.pose and len(args.pose) != robot.n:
        raise RobidError(f"--pose: {len(args.pose)} values given, the robot has {robot.n} "
                         "joints")
    pose = tuple(np.radians(args.pose)) if args.pose else None
    opts = ElasticityOptions(joints=tuple(args.joint), pairs=tuple(pairs),
                             pose=pose, f_min_hz=args.f_min,
                             f_max_hz=args.f_max, steps=args.steps, rate_hz=args.rate or 2000.0)
    traj = elasticity_trajectory(robot, opts)
    csv_path, yaml_path = write_trajectory(args.out, traj)
    print(f"stepped sines for {robot.name}: {len(traj.header['schedule'])} steps, "
          f"{args.f_min:g}–{args.f_max:g} Hz, {traj.t[-1]:.4g} s at {traj.rate_hz:g} Hz")
    print(f"wrote {csv_path} and {yaml_path}")
    return 0


# ------------------------------------------------------------------------------- simulate

def _simulate_options(p: argparse.ArgumentParser) -> None:
    robot_options(p)
    p.add_argument("--truth", required=True, help="truth file (inertials, effects, noise)")
    p.add_argument("--trajectory", required=True, metavar="TRAJ",
                   help="trajectory CSV (with its .yaml header beside it)")
    p.add_argument("--out", required=True, metavar="LOG", type=output_path("file"),
                   help="the simulated log (CSV)")
    seed_option(p)


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


COMMANDS = (
    Command(name="show-robot", help="draw the kinematic chain at a pose (PNG)",
            options=_show_robot_options, run=_show_robot),
    Command(name="excite", help="design an optimized excitation trajectory",
            options=_excite_options, check=_excite_check, run=_excite),
    Command(name="simulate", help="run a trajectory on the simulated robot, write a log",
            options=_simulate_options, run=_simulate),
)
