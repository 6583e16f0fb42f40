"""`make bench --only elasticity`: `robid elasticity` on a 6-axis stepped-sine log (24 steps per
axis at 2 kHz, the simulated elastic industrial6) against one `robid identify` on a rigid-body
log of the same length and rate, both through the CLI in this process (median of 3), both logs
.npz (the ratio compares the analyses, not a CSV parser with an npz reader); and the time the
campaign's simulation takes (the trajectory, its states, the closed-loop plant, the log
written), its compiled loop's cache loaded by a short run first, as the analyses are warmed.
"""

from __future__ import annotations

import contextlib
import io
import tempfile
import time
import warnings
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

__all__ = ["bench_elasticity", "report"]

POSE_DEG = (0.0, 20.0, -90.0, -90.0, -90.0, 0.0)
SINGLES = (1, 4, 5, 6)
PAIR = (2, 3)


def _stepped_sine_log(robot_path: Path, truth_path: Path, out: Path, samples: int | None = None
                      ) -> tuple[int, Path, float, float]:
    """The campaign's log (``samples``: only its first ones, to warm the caches) and the wall
    and CPU seconds its simulation took: the stepped-sine trajectory, its states, the
    closed-loop plant, the log written. The trajectory's file is written after (for its
    header's schedule): a campaign hands the program over as data."""
    from robid_link.fakes.plant import Plant, load_truth
    from robid_link.ident.elastic.frequency import ElasticityOptions, elasticity_trajectory
    from robid_link.ident.excite.excitation import trajectory_states, write_trajectory
    from robid_link.ident.model.robot import load_robot

    robot = load_robot(robot_path)
    truth = load_truth(truth_path, robot)
    opts = ElasticityOptions(joints=SINGLES, pairs=(PAIR,), pose=tuple(np.radians(POSE_DEG)))
    t0, c0 = time.perf_counter(), time.process_time()
    traj = elasticity_trajectory(robot, opts)
    if samples is not None:
        traj = replace(traj, t=traj.t[:samples], q=traj.q[:samples])
    log = Plant(robot, truth).run(*trajectory_states(traj, 2000.0))
    np.savez(out / "log.npz", t=log["t"], q=log["q"], tau=log["tau"])
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    _, header = write_trajectory(out / "traj.csv", traj)
    return int(log["t"].size), Path(header), wall, cpu


def _timed(argv: list[str]) -> float:
    from robid_link.cli import main

    t0 = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if main(argv) != 0:
            raise RuntimeError(f"robid {argv[0]} failed")
    return time.perf_counter() - t0


def bench_elasticity(robot_path: Path, truth_path: Path,
                     make_npz: Callable[[Path, int, float], None]) -> dict[str, float]:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        _stepped_sine_log(robot_path, truth_path, out, samples=400)  # numba's cache, imports
        samples, header, sim_s, sim_cpu_s = _stepped_sine_log(robot_path, truth_path, out)
        make_npz(out / "rigid.npz", samples, 2000.0)
        el = ["elasticity", "--robot", str(robot_path), "--data", str(out / "log.npz"),
              "--schedule", str(header), "--joints", ",".join(map(str, PAIR))]
        for j in SINGLES:
            el += ["--joint", str(j)]
        ident = ["identify", "--robot", str(robot_path), "--data", str(out / "rigid.npz")]
        _timed(ident + ["--interval", "50"])  # warm imports and caches of both, once
        _timed(el)
        t_el, t_id = [], []
        for _ in range(3):  # median of 3: the machine is shared
            t_el.append(_timed(el))
            t_id.append(_timed(ident))
    return {"samples": samples, "simulate_s": sim_s, "simulate_cpu_s": sim_cpu_s,
            "elasticity_s": float(np.median(t_el)),
            "identify_s": float(np.median(t_id)),
            "ratio": float(np.median(np.array(t_el) / np.array(t_id)))}


def report(r: dict[str, float]) -> None:
    print(f"elasticity, 6 axes × 24 steps at 2 kHz ({r['samples']:,} samples; 4 single axes + "
          f"the 2–3 pair): {r['elasticity_s']:.2f} s vs one identify on a rigid-body log of the "
          f"same length {r['identify_s']:.2f} s → {r['ratio']:.2f}× (simulating the log took "
          f"{r['simulate_s']:.1f} s, {r['simulate_cpu_s']:.1f} s of CPU)")
