"""RAPID rendering of the neutral program (drivers that speak RAPID: file_share, abb_rws)."""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np
import pytest

from robid_link.drivers.file_share import FileShareDriver
from robid_link.drivers.rapid import parse_rapid, render_rapid
from robid_link.exceptions import ConfigError, DriverError
from robid_link.ident.excite import excitation as ex
from robid_link.ident.excite import program as pg
from robid_link.ident.model.robot import load_robot
from robid_link.jobs import MotionProgram

ROBOTS = Path(__file__).resolve().parents[2] / "examples" / "robots"


@pytest.mark.parametrize("robot_file", ["arm3.yaml", "industrial6.yaml"])
def test_rapid_module_parses_back_to_the_trajectory(robot_file: str) -> None:
    robot = load_robot(ROBOTS / robot_file)
    t = np.arange(0.0, 4.0, 0.004)
    four = ex.fit_limits(robot, ex.random_fourier(robot, harmonics=3, base_hz=0.25, seed=2))
    traj = ex.Trajectory(t, four.evaluate(t)[0], 250.0, "fourier", robot.name)
    program = pg.make_program(robot, traj, "rb1")
    text = render_rapid(program).decode()
    assert text.startswith("MODULE robid_rb1") and text.rstrip().endswith("ENDMODULE")
    assert "MoveAbsJ path{i}, v1000 \\T:=dt{i-1}, z1, tool0;" in text
    targets, dts = parse_rapid(text, robot.joint_types)
    idx = np.arange(0, t.size, 10)
    idx = np.append(idx, t.size - 1) if idx[-1] != t.size - 1 else idx
    np.testing.assert_allclose(targets, traj.q[idx], atol=1e-4 * np.pi / 180 * 1.01)
    np.testing.assert_allclose(np.cumsum(dts), t[idx][1:] - t[0], atol=1e-3)


def test_file_share_renders_rapid_only_when_asked(tmp_path: Path) -> None:
    robot = load_robot(ROBOTS / "arm3.yaml")
    t = np.arange(0.0, 1.0, 0.01)
    traj = ex.Trajectory(t, np.zeros((t.size, 3)), 100.0, "custom", robot.name)
    program = pg.make_program(robot, traj, "c1")

    async def put(**kw: object) -> set[str]:
        share = tmp_path / f"share{len(kw)}"
        share.mkdir()
        drv = FileShareDriver(share=share, canary_interval_s=0, **kw)  # type: ignore[arg-type]
        drv.bind_robot(robot)
        async with drv:
            await drv.put_program(program)
        return {p.name for p in (share / "inbox").iterdir()}

    assert asyncio.run(put()) == {"c1.traj.csv", "c1.traj.yaml", "c1.mod"}
    assert asyncio.run(put(rapid=False)) == {"c1.traj.csv", "c1.traj.yaml"}


def test_rapid_refuses_more_than_seven_axes(tmp_path: Path) -> None:
    eight = type("R", (), {"n": 8, "name": "octo"})()
    drv = FileShareDriver(share=tmp_path, canary_interval_s=0)
    with pytest.raises(ConfigError, match=r"driver\.rapid: .* at most 7 axes, robot octo has 8"):
        drv.bind_robot(eight)  # type: ignore[arg-type]
    FileShareDriver(share=tmp_path, canary_interval_s=0, rapid=False).bind_robot(eight)  # type: ignore[arg-type]


def test_a_malformed_program_is_a_driver_error() -> None:
    bad = MotionProgram("x1", {"traj.csv": b"t,q1\n0,nan\n", "traj.yaml": b"rate_hz: 10\n"},
                           0.0)
    with pytest.raises(DriverError, match="program x1: .*non-finite"):
        render_rapid(bad)
    with pytest.raises(DriverError, match="program x1: file traj.yaml missing"):
        MotionProgram("x1", {"traj.csv": b"t,q1\n0,0\n"}, 0.0).trajectory()
