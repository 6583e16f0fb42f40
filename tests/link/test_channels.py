"""The ``channels`` campaign option (a controller's signal budget): checked at load, each
identification experiment split into torque groups once the robot's joint count is known, the
program's header telling the controller which torques to log, the fake controller honouring it."""

from __future__ import annotations

import io
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from robid_link.config import load_daemon_config, with_joint_count
from robid_link.exceptions import ConfigError, RobidError
from robid_link.fakes.controller import ControllerCore, default_truth
from robid_link.ident.entry import program
from robid_link.ident.model.robot import load_robot
from robid_link.jobs import ProgramJob, check_name
from robid_link.link.campaign import plan

from .conftest import ROOT, write_config

SIX = ROOT / "examples" / "robots" / "industrial6.yaml"
EXPS = [{"kind": "rigid_body", "duration_s": 4, "harmonics": 3, "evaluations": 20,
         "rate_hz": 50},
        {"kind": "friction", "speeds": [0.3], "joints": [1], "rate_hz": 50},
        {"kind": "verify"}]


def _config(tmp: Path, **camp: object) -> Path:
    return write_config(tmp, {"budget": {"experiments": EXPS, **camp}}, robot=str(SIX))


@pytest.mark.parametrize(("channels", "groups"), [
    (3, ["j1-3", "j4-6"]), (4, ["j1-4", "j5-6"]), (1, [f"j{j}" for j in range(1, 7)])])
def test_experiments_split_into_torque_groups(tmp_path: Path, channels: int,
                                              groups: list[str]) -> None:
    cfg = load_daemon_config(_config(tmp_path, channels=channels))
    camp = cfg.campaigns["budget"]
    assert camp.channels == channels
    assert [e for e, _, _ in plan(camp)] == ["rigid_body", "friction", "verify"]  # n unknown
    camp = with_joint_count(cfg, 6).campaigns["budget"]
    steps = plan(camp)
    ids = [e for e, _, _ in steps]
    # the friction sweep of joint 1 runs only where joint 1's torque is logged
    assert ids == [f"rigid_body-{g}" for g in groups] + [f"friction-{groups[0]}", "verify"]
    assert all(check_name(e, "id") for e in ids)
    torques = [d.torques for _, d, _ in steps if d.kind == "rigid_body"]
    assert sorted(j for g in torques for j in g) == [1, 2, 3, 4, 5, 6]  # every joint once
    assert all(len(g) <= channels for g in torques)
    assert next(d for _, d, _ in steps if d.kind == "verify").torques is None


def test_a_budget_that_holds_every_joint_splits_nothing(tmp_path: Path) -> None:
    cfg = with_joint_count(load_daemon_config(_config(tmp_path, channels=6)), 6)
    assert [e for e, _, _ in plan(cfg.campaigns["budget"])] == ["rigid_body", "friction",
                                                                "verify"]


@pytest.mark.parametrize(("camp", "message"), [
    ({"channels": 0}, "campaigns.budget.channels: expected a positive integer, got 0"),
    ({"channels": 2.5}, "campaigns.budget.channels: expected a positive integer, got 2.5"),
    ({"channels": 65}, "campaigns.budget.channels: expected the torque channels one log may "
                       "hold, 1..64, got 65"),
    ({"channels": 3, "diagnose": True}, "campaigns.budget.channels: the diagnosis needs every "
                                        "joint's torque in each log"),
])
def test_bad_channels_are_refused_at_load(tmp_path: Path, camp: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=r"daemon.yaml: " + re.escape(message)):
        load_daemon_config(_config(tmp_path, **camp))


def test_split_ids_that_would_collide_are_refused(tmp_path: Path) -> None:
    exps = [EXPS[0], {**EXPS[0], "id": "rigid_body-j1-3"}]
    p = write_config(tmp_path, {"budget": {"experiments": exps, "channels": 3}}, robot=str(SIX))
    with pytest.raises(ConfigError, match=r"experiments\[0\].id: 'rigid_body' split by channels "
                                          r"would collide with experiment 'rigid_body-j1-3'"):
        load_daemon_config(p)
    long_id = "x" * 60
    p = write_config(tmp_path, {"budget": {"experiments": [{**EXPS[0], "id": long_id}],
                                           "channels": 3}}, robot=str(SIX))
    with pytest.raises(ConfigError, match=r"experiments\[0\].id: split by channels as"):
        load_daemon_config(p)


def test_program_header_names_the_torques_and_the_controller_logs_only_them() -> None:
    opts = {**EXPS[0]}
    opts.pop("kind")
    prog = program(ProgramJob(str(SIX), (), "rigid_body-j4-6", "rigid_body", opts, str(ROOT),
                              None, (4, 5, 6)))
    head = yaml.safe_load(prog.files["traj.yaml"])
    assert head["log_torques"] == [4, 5, 6] and prog.meta["log_torques"] == [4, 5, 6]
    main = program(ProgramJob(str(SIX), (), "rigid_body-j1-3", "rigid_body", opts, str(ROOT),
                              None, (1, 2, 3)))
    assert main.files["traj.csv"] == prog.files["traj.csv"]  # every group: the same motion
    assert main.sha256 != prog.sha256  # … but a program (an approval) of its own
    robot = load_robot(SIX)
    core = ControllerCore(robot, default_truth(robot, rate_hz=100.0))
    res = core.run("rigid_body-j4-6", "n1", prog.files["traj.csv"], prog.files["traj.yaml"])
    assert res.error is None
    header = res.log.decode().splitlines()[0].split(",")
    assert header == ["t", *(f"q{j}" for j in range(1, 7)), "tau4", "tau5", "tau6"]
    arr = np.loadtxt(io.BytesIO(res.log), delimiter=",", skiprows=1)
    assert arr.shape[1] == 10 and np.isfinite(arr).all()


def test_bad_torque_lists_are_refused() -> None:
    opts = {**EXPS[0]}
    opts.pop("kind")
    with pytest.raises(RobidError, match=r"experiment e: log_torques \[7\]: expected distinct "
                                         r"joint numbers 1..6"):
        program(ProgramJob(str(SIX), (), "e", "rigid_body", opts, str(ROOT), None, (7,)))
    robot = load_robot(SIX)
    core = ControllerCore(robot, default_truth(robot, rate_hz=100.0))
    prog = program(ProgramJob(str(SIX), (), "e", "rigid_body", opts, str(ROOT), None, None))
    bad = prog.files["traj.yaml"] + b"log_torques: [3, 1]\n"
    res = core.run("e", "n1", prog.files["traj.csv"], bad)
    assert res.error is not None and "log_torques: expected ascending joint numbers" in res.error


def test_campaign_list_without_a_daemon_splits_too(tmp_path: Path) -> None:
    from robid_link.link.campaign import describe_campaigns

    cfg = load_daemon_config(_config(tmp_path, channels=3))
    (camp,) = describe_campaigns(cfg)
    assert [e["id"] for e in camp["experiments"]] == ["rigid_body-j1-3", "rigid_body-j4-6",
                                                      "friction-j1-3", "verify"]
