"""``robid demo``: the main job on an embedded default.

Until the daemon exists this runs identification + report on a simulated 6-axis robot whose
truth holds friction the default model knows, and the a-priori model is off by ±20 %.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from robid_link.ident.data import write_log_csv
from robid_link.ident.effects import Model
from robid_link.ident.excitation import random_fourier
from robid_link.ident.identify import identify, load_logs
from robid_link.ident.report import write_json, write_report
from robid_link.ident.robot import load_robot

__all__ = ["run_demo", "DEMO_ROBOT"]

DEMO_ROBOT = Path(__file__).resolve().parent.parent / "examples" / "robots" / "industrial6.yaml"


def run_demo(work: Path, out: Path, json_path: str | None = None) -> int:
    from fakes.plant import Plant, Truth, perturbed_inertials

    robot = load_robot(DEMO_ROBOT)
    print(f"robid demo: simulated {robot.name} ({robot.n} joints), identification and report")
    rate = 500.0
    t = np.arange(0.0, 40.0, 1.0 / rate)
    traj = random_fourier(robot, harmonics=5, base_hz=0.1, seed=7)
    q, qd, qdd = traj.evaluate(t)
    truth = Truth(
        inertials=perturbed_inertials(robot, seed=11, spread=0.2),
        effects=({"name": "viscous", "fv": 3.0}, {"name": "coulomb", "fc": 2.0}),
        noise_tau=0.3,
        q_resolution=2 * np.pi / 2**20,
    )
    log = Plant(robot, truth).run(t, q, qd, qdd, seed=3)
    path = work / "demo_log.csv"
    write_log_csv(path, log["t"], log["q"], log["tau"])
    data = load_logs(robot, [path])
    res = identify(robot, data, Model.parse(["rigid_body", "viscous", "coulomb"]))
    print(res.summary())
    files = write_report(res, out)
    print(f"\nrobid demo: wrote {len(files)} report files to {out}/")
    if json_path:
        write_json(json_path, res.to_dict())
    return 0
