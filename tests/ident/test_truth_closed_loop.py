"""Case 8 of issue 21: on closed-loop logs the diagnosis suggests only effects the plant has.

A closed loop's friction at a turn is finer than the filter resolves: a joint sticks for a few
milliseconds, or its velocity kinks where Coulomb friction switches, or it slows to a halt and
goes on (a motion's rest point). The logs here come from an independent plant
(``tests/sims/closedloop.py``: its own bodies, a PD or a PI servo at 1 kHz on quantized
encoders, Coulomb friction that sticks, torque noise) and from the demo's own cell; clean, they
must give no suggestion, and with an effect hidden the diagnosis still finds it.
"""

from __future__ import annotations

import math
import os
import warnings
from pathlib import Path

import numpy as np
import pytest

from robid_link.ident.diagnosis.diagnose import diagnose
from robid_link.ident.fit.identify import load_logs
from robid_link.ident.model.effects import DEFAULT_MODEL, EffectSpec
from robid_link.ident.model.robot import load_robot

from ..conftest import ROBOTS
from ..sims.cases import quiet
from ..sims.closedloop import Cell, case, run, write_log


def _diagnose(robot, path: Path, model=DEFAULT_MODEL):
    with warnings.catch_warnings():
        quiet()
        return diagnose(robot, load_logs(robot, [path]), model)


def _clean_log(robot, seed: int, path: Path, duration_s: float = 40.0) -> Path:
    cell, motion = case(robot, seed)
    t, q, tau, _ = run(robot, cell, motion, duration_s)
    return write_log(path, t, q, tau)


@pytest.mark.parametrize("seed", [2, 3])  # at rest every 10 s; the PD, then the PI servo
def test_clean_closed_loop_suggests_nothing(arm3, tmp_path, seed):
    dg = _diagnose(arm3, _clean_log(arm3, seed, tmp_path / "c.csv", 30.0))
    assert dg.suggestions == [], dg.summary()


@pytest.mark.slow
@pytest.mark.skipif(not os.environ.get("ROBID_VALIDATE"), reason="make validate")
def test_clean_closed_loops_at_most_one_false_suggestion_in_twenty(tmp_path):
    """Ten seeds on each robot: both servos, both motions, two noise levels."""
    false = []
    for robot_name in ("arm3", "industrial6"):
        robot = load_robot(ROBOTS / f"{robot_name}.yaml")
        for seed in range(10):
            dg = _diagnose(robot, _clean_log(robot, seed, tmp_path / f"c{seed}.csv"))
            labels = [s.label() for s in dg.suggestions]
            print(f"{robot_name} seed {seed}: {dg.verdict} {labels}")
            false += [f"{robot_name} seed {seed}: {labels}"] if labels else []
    print(f"false suggestions: {len(false)} of 20 clean closed-loop logs")
    assert len(false) <= 1, false


def test_a_ripple_in_the_closed_loop_is_still_found(arm3, tmp_path):
    cell, motion = case(arm3, 2)
    cell = Cell(**{**cell.__dict__, "extra": lambda q, v: np.array(
        [0.6 * math.sin(2 * math.pi * q[0] / 0.1), 0.0, 0.0])})
    t, q, tau, _ = run(arm3, cell, motion, 30.0)
    dg = _diagnose(arm3, write_log(tmp_path / "r.csv", t, q, tau))
    assert [s.label() for s in dg.suggestions] == ["ripple@1"], dg.summary()


def test_the_demo_cell_suggests_only_its_hidden_effect(tmp_path):
    """``robid demo --quick``'s excitation on the demo's cell: ripple@1 and nothing else; with
    it added, nothing."""
    from robid_link.demo import DEMO_ROBOT, HIDDEN, QUICK_RIGID, demo_truth
    from robid_link.fakes.controller import ControllerCore
    from robid_link.ident.excite.experiments import experiment_trajectory
    from robid_link.ident.excite.program import make_program

    robot = load_robot(DEMO_ROBOT)
    opts = {k: v for k, v in QUICK_RIGID.items() if k != "kind"}
    traj = experiment_trajectory(robot, "rigid_body", opts, tmp_path)
    prog = make_program(robot, traj, "rigid_body", {"kind": "rigid_body"})
    core = ControllerCore(robot, demo_truth(robot), seed=3)
    path = tmp_path / "demo.csv"
    path.write_bytes(core.simulate(core.trajectory(prog.files["traj.csv"],
                                                   prog.files["traj.yaml"]), seed=3))
    dg = _diagnose(robot, path)
    hidden = f"{HIDDEN['name']}@{HIDDEN['joint']}"
    assert [s.label() for s in dg.suggestions] == [hidden], dg.summary()
    top = dg.suggestions[0]
    model = DEFAULT_MODEL.with_added(EffectSpec(top.effect, top.joint,
                                                tuple(sorted(top.hypers.items()))))
    after = _diagnose(robot, path, model)
    assert after.suggestions == [], after.summary()
