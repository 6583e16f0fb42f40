"""The README's simulate example runs as written with the truth file shipped for each example
robot (faster excitation options appended; argparse keeps the last value)."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from robid_link.cli import main

ROOT = Path(__file__).resolve().parents[1]
ROBOTS = ROOT / "examples" / "robots"
FAST = {"excite": ["--duration", "6", "--harmonics", "3", "--evaluations", "20"]}


def readme_simulate_commands() -> list[list[str]]:
    """The ``robid …`` lines of the README's first code block under the simulate section."""
    text = (ROOT / "README.md").read_text()
    section = text.split("## Simulated robot and excitation", 1)[1]
    block = re.search(r"```\n(.*?)```", section, re.S)
    assert block, "README: no code block under 'Simulated robot and excitation'"
    lines = block.group(1).replace("\\\n", " ").splitlines()
    return [shlex.split(line)[1:] for line in lines if line.startswith("robid ")]


def test_every_example_robot_ships_a_truth_file() -> None:
    robots = sorted(p for p in ROBOTS.glob("*.yaml") if not p.name.endswith(".truth.yaml"))
    assert robots
    for robot in robots:
        assert (ROBOTS / f"{robot.stem}.truth.yaml").is_file(), robot.name


@pytest.mark.parametrize("robot", ["arm3", "industrial6"])
def test_readme_simulate_example_runs(robot: str, tmp_path: Path, capsys: pytest.CaptureFixture,
                                      monkeypatch: pytest.MonkeyPatch) -> None:
    commands = readme_simulate_commands()
    assert [c[0] for c in commands] == ["excite", "simulate", "identify"]
    monkeypatch.chdir(tmp_path)
    (tmp_path / "examples").symlink_to(ROOT / "examples")
    for argv in commands:
        argv = [a.replace("arm3", robot) for a in argv] + FAST.get(argv[0], [])
        rc = main(argv)
        out = capsys.readouterr()
        assert rc == 0, (argv, out.err)
    assert (tmp_path / "log.csv").is_file()
    assert f"identify — {robot}" in out.out
