"""Driver tests: the leak check (threads, asyncio tasks) is the autouse fixture of
``tests/conftest.py``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from robid_link.ident.excite import excitation as ex
from robid_link.ident.excite import program as pg
from robid_link.ident.model.robot import Robot, load_robot
from robid_link.jobs import MotionProgram

ARM3 = Path(__file__).resolve().parents[2] / "examples" / "robots" / "arm3.yaml"


def bump_program(robot: Robot, seconds: float, peak_rad: float) -> MotionProgram:
    """A sin² bump of ``seconds`` at 100 Hz from rest to rest, ``peak_rad`` on joint 1 (−1×,
    0.5× on joints 2 and 3, the pattern repeated on further joints): the program the driver
    tests hand to their peers."""
    t = np.arange(0.0, seconds, 0.01)
    weights = np.resize(np.array([1.0, -1.0, 0.5]), robot.n)
    q = peak_rad * np.sin(np.pi * t / seconds)[:, None] ** 2 * weights
    return pg.make_program(robot, ex.Trajectory(t, q, 100.0, "custom", robot.name), "exp1")


@pytest.fixture(scope="module")
def robot() -> Robot:
    return load_robot(ARM3)


@pytest.fixture(scope="module")
def program(robot: Robot) -> MotionProgram:
    """The contract suite's program (0.6 s, 3 joints, 5 cm peaks)."""
    return bump_program(robot, 0.6, 0.05)
