"""Issue 14, items 2, 10 and 11 (loaders and CLI input): every ordinary mistake is one line
naming the file (or option), no traceback, no hang, and no wrong success."""

from __future__ import annotations

import io
import logging
import math
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

from robid_link.cli import _parser, main
from robid_link.config import load_daemon_config
from robid_link.exceptions import RobidError
from robid_link.fakes.plant import load_truth
from robid_link.ident.data.logs import load_log
from robid_link.ident.diagnosis.history import history_path, read_history
from robid_link.ident.excite.excitation import read_trajectory
from robid_link.ident.model.effects import load_model, parse_effect
from robid_link.ident.model.robot import load_robot

from .conftest import ROBOTS, mdh_to_urdf

ARM3 = str(ROBOTS / "arm3.yaml")


def one_line(exc: pytest.ExceptionInfo[RobidError], name: str | Path) -> str:
    msg = str(exc.value)
    assert "\n" not in msg, msg
    assert str(name) in msg, msg
    return msg


def run_cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    rc = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    errors = [line for line in err if not line.startswith("robid: warning:")]
    assert rc == 2, err
    assert len(errors) == 1 and errors[0].startswith("robid: error: "), err
    return errors[0]


# ----------------------------------------------------------------------------- item 2: limits

JOINT = ('<joint name="j1" type="{kind}"><parent link="base"/><child link="l1"/>'
         '<axis xyz="0 0 1"/>{limit}</joint>')
LINK = ('<link name="l1"><inertial><mass value="{mass}"/><inertia ixx="{ixx}" ixy="0" ixz="0" '
        'iyy="0.01" iyz="0" izz="0.01"/></inertial></link>')


def urdf(tmp_path: Path, *, kind: str = "revolute", mass: str = "1.0", ixx: str = "0.01",
         limit: str = '<limit lower="-1" upper="1" effort="10" velocity="2"/>') -> Path:
    p = tmp_path / "r.urdf"
    p.write_text(f'<robot name="r"><link name="base"/>{LINK.format(mass=mass, ixx=ixx)}'
                 f'{JOINT.format(kind=kind, limit=limit)}</robot>')
    return p


@pytest.mark.parametrize(("limit", "problem"), [
    ('<limit lower="0" upper="0" effort="10" velocity="2"/>', "lower limit 0 is not below"),
    ('<limit lower="1" upper="-1" effort="10" velocity="2"/>', "lower limit 1 is not below"),
    ('<limit effort="10" velocity="2"/>', "<limit> without lower"),
    ("", "a revolute joint needs a <limit> element"),
])
def test_urdf_inconsistent_or_missing_limits_are_refused(tmp_path, limit, problem):
    p = urdf(tmp_path, limit=limit)
    with pytest.raises(RobidError, match="joint 'j1': .*" + problem) as exc:
        load_robot(p)
    one_line(exc, p)


def test_urdf_unlimited_joint_needs_a_logged_override(tmp_path, caplog):
    p = urdf(tmp_path, limit='<limit lower="0" upper="0" effort="10" velocity="2"/>')
    with caplog.at_level(logging.WARNING):
        robot = load_robot(p, allow_unlimited=True)
    assert math.isinf(robot.limits.q_max[0])
    assert "accepted as unlimited" in caplog.text and "j1" in caplog.text


def test_mdh_missing_limits_refused_unless_allowed(tmp_path, caplog):
    p = tmp_path / "r.yaml"
    p.write_text("joints: [{alpha: 0, a: 0, theta: 0, d: 0.1}]\n")
    with pytest.raises(RobidError, match=r"joints\[0\]\.limits\.q: position limits missing") as e:
        load_robot(p)
    one_line(e, p)
    p.write_text("allow_unlimited: true\njoints: [{alpha: 0, a: 0, theta: 0, d: 0.1}]\n")
    with caplog.at_level(logging.WARNING):
        assert load_robot(p).n == 1
    assert "unlimited" in caplog.text


def test_continuous_joint_is_bounded_to_one_turn(tmp_path):
    robot = load_robot(urdf(tmp_path, kind="continuous", limit=""))
    assert robot.unbounded == (True,)
    assert robot.limits.q_min[0] == -math.pi and robot.limits.q_max[0] == math.pi


@pytest.mark.parametrize("effort", ["0", "-5"])
def test_zero_or_negative_torque_limit_refused(tmp_path, effort):
    p = urdf(tmp_path, limit=f'<limit lower="-1" upper="1" effort="{effort}" velocity="2"/>')
    with pytest.raises(RobidError, match="effort limit .* must be positive") as exc:
        load_robot(p)
    one_line(exc, p)
    q = tmp_path / "r.yaml"
    q.write_text(f"joints: [{{alpha: 0, a: 0, theta: 0, d: 0.1, limits: {{q: [-9, 9], "
                 f"tau: {effort}}}}}]\n")
    with pytest.raises(RobidError, match=r"limits\.tau: must be positive") as exc:
        load_robot(q)
    one_line(exc, q)


# ----------------------------------------------------------------------------- item 10: files

def bomb(levels: int = 9) -> str:
    text = 'a0: &a0 ["x","x","x","x","x","x","x","x","x"]\n'
    for i in range(1, levels):
        refs = ",".join([f"*a{i - 1}"] * 9)
        text += f"a{i}: &a{i} [{refs}]\n"
    return text


@pytest.mark.parametrize("kind", ["robot", "model", "truth", "config", "trajectory"])
def test_yaml_alias_bomb_is_refused_fast(tmp_path, arm3, kind):
    p = tmp_path / ("traj.yaml" if kind == "trajectory" else f"{kind}.yaml")
    p.write_text(bomb())
    (tmp_path / "traj.csv").write_text("t,q1,q2,q3\n0,0,0,0\n0.004,0,0,0\n")
    load = {"robot": lambda: load_robot(p), "model": lambda: load_model(p),
            "truth": lambda: load_truth(p, arm3), "config": lambda: load_daemon_config(p),
            "trajectory": lambda: read_trajectory(tmp_path / "traj.csv")}[kind]
    start = time.monotonic()
    with pytest.raises(RobidError, match="refused YAML") as exc:
        load()
    assert time.monotonic() - start < 5
    one_line(exc, p)


def test_yaml_document_size_is_bounded(tmp_path):
    p = tmp_path / "model.yaml"
    p.write_text("effects: [rigid_body]\n" + "#" * (5 << 20))
    with pytest.raises(RobidError, match="bytes allowed") as exc:
        load_model(p)
    one_line(exc, p)


def _npz_bytes(**arrays: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


@pytest.mark.parametrize("content", [b"", b"PK\x03\x04", "half"])
def test_truncated_or_empty_npz(tmp_path, content):
    good = _npz_bytes(t=np.arange(20.0), q=np.zeros((20, 3)), tau=np.zeros((20, 3)))
    p = tmp_path / "log.npz"
    p.write_bytes(good[: len(good) // 2] if content == "half" else content)
    with pytest.raises(RobidError, match="not a readable .npz file") as exc:
        load_log(p, 3)
    one_line(exc, p)


@pytest.mark.parametrize("content", [b"", b"MATLAB 5.0 MAT-file" + b"\0" * 100, "half"])
def test_truncated_or_empty_mat(tmp_path, content):
    import scipy.io

    p = tmp_path / "log.mat"
    scipy.io.savemat(p, {"m": np.zeros((20, 12))})
    good = p.read_bytes()
    p.write_bytes(good[: len(good) // 2] if content == "half" else content)
    with pytest.raises(RobidError) as exc:
        load_log(p, 3, fs=100.0)
    one_line(exc, p)


def test_npz_header_claiming_a_terabyte_is_refused_without_reading(tmp_path):
    header = {"descr": "<f8", "fortran_order": False, "shape": (1 << 37, 1)}
    npy = io.BytesIO()
    np.lib.format.write_array_header_1_0(npy, header)
    p = tmp_path / "log.npz"
    with zipfile.ZipFile(p, "w") as zf:
        zf.writestr("t.npy", npy.getvalue() + b"\0" * 64)
    with pytest.raises(RobidError, match=r"array 't.npy' claims shape") as exc:
        load_log(p, 3)
    one_line(exc, p)


def test_csv_field_over_the_csv_limit(tmp_path):
    p = tmp_path / "log.csv"
    p.write_text("t,q1,tau1\n" + '"' + "1" * 200_000 + '",0,0\n')
    with pytest.raises(RobidError, match="malformed CSV at line 2") as exc:
        load_log(p, 1)
    one_line(exc, p)


@pytest.mark.parametrize(("argv", "option"), [
    (["identify", "--robot", ARM3, "--data", "x.csv", "--cutoff", "nan"], "--cutoff"),
    (["identify", "--robot", ARM3, "--data", "x.csv", "--fs", "inf"], "--fs"),
    (["show-robot", "--robot", ARM3, "--q", "0", "nan", "0", "--out", "x.png"], "--q"),
    (["excite", "--robot", ARM3, "--out", "t.csv", "--rate", "nan"], "--rate"),
    (["excite", "--robot", ARM3, "--out", "t.csv", "--seed", "1" * 40], "--seed"),
    (["excite", "--robot", ARM3, "--out", "t.csv", "--harmonics", "1.5"], "--harmonics"),
    (["identify", "--robot", ARM3, "--data", "x.csv", "--interval", "10" * 20], "--interval"),
])
def test_numeric_options_finite_and_bounded(argv, option, capsys):
    assert option in run_cli(argv, capsys)


def test_huge_integers_in_robot_file(tmp_path):
    p = tmp_path / "r.yaml"
    p.write_text(f"joints: [{{alpha: 0, a: {10 ** 400}, theta: 0, d: 0, limits: {{q: [-9, 9]}}}}]")
    with pytest.raises(RobidError, match=r"joints\[0\]\.a: expected a finite number") as exc:
        load_robot(p)
    one_line(exc, p)


def test_negative_inertias_never_reach_pinocchio(tmp_path, arm3):
    p = tmp_path / "r.yaml"
    p.write_text("joints: [{alpha: 0, a: 0, theta: 0, d: 0, limits: {q: [-9, 9]}, "
                 "inertial: {m: 1, I: [-0.1, 0, 0.1, 0, 0, 0.1]}}]")
    with pytest.raises(RobidError, match="not positive semi-definite") as exc:
        load_robot(p)
    one_line(exc, p)
    t = tmp_path / "truth.yaml"
    rows = [[-1.0] + [0.0] * 9] + [[1.0, 0, 0, 0, 0.1, 0, 0.1, 0, 0, 0.1]] * 2
    t.write_text(f"inertials: {rows}\n")
    with pytest.raises(RobidError, match=r"inertials\[0\] \(link 1\): mass -1 is negative") as e:
        load_truth(t, arm3)
    one_line(e, t)


@pytest.mark.parametrize(("coupling", "problem"), [
    ("[[1, 2.7, 1.0]]", "whole numbers"), ("[[1, a, 1.0]]", "whole numbers"),
    ("[[1, 2]]", "expected \\[joint, motor, factor\\]"), ("5", "expected a list"),
    ("[[1, 9, 1.0]]", "distinct numbers in 1..2"),
])
def test_malformed_couplings(tmp_path, coupling, problem):
    p = tmp_path / "r.yaml"
    p.write_text("joints:\n" + "  - {alpha: 0, a: 0, theta: 0, d: 0, limits: {q: [-9, 9]}}\n" * 2
                 + f"transmission: {{ratios: [10, 10], coupling: {coupling}}}\n")
    with pytest.raises(RobidError, match=problem) as exc:
        load_robot(p)
    one_line(exc, p)


@pytest.mark.parametrize(("effects", "problem"), [
    ("[]", "the list is empty"), ("[offset]", "'rigid_body' missing"),
    ("[rigid_body, {name: spring, joint: 1, order: 1000000}]", "option order"),
    ("[rigid_body, {name: spring, joint: 1, order: 2.5}]", "option order"),
    ("[rigid_body, {name: ripple, joint: 1, period: 0}]", "option period"),
    ("[rigid_body, viscous@]", "after '@' a joint number"),
])
def test_bad_model_files(tmp_path, effects, problem):
    p = tmp_path / "m.yaml"
    p.write_text(f"effects: {effects}\n")
    with pytest.raises(RobidError, match=problem) as exc:
        load_model(p)
    one_line(exc, p)


@pytest.mark.parametrize(("text", "problem"), [
    ("", "the history is empty"), ("[1, 2]\n", "line 1: expected a JSON object"),
    ('{"time": 5, "kind": "identify"}\n', "'time' missing or not text"),
    ('{"time": "t", "kind": "identify", "rmse": ["a"]}\n', "'rmse' must be a list of numbers"),
    ("[" * 100_000 + "\n", "line 1 is not valid JSON"), ("\xff\n", "not a readable UTF-8"),
])
def test_empty_or_malformed_history(tmp_path, text, problem):
    m = tmp_path / "m.yaml"
    history_path(m).write_bytes(text.encode("latin-1"))
    with pytest.raises(RobidError, match=problem) as exc:
        read_history(m)
    one_line(exc, history_path(m))


@pytest.mark.parametrize(("text", "problem"), [
    ("inertials: [[a, b]]", "inertials: expected 3 rows"),
    ("inertials: 5", "inertials: expected 3 rows"),
    ("perturb: [1]", "perturb: expected"),
    ("perturb: {seed: x}", "perturb.seed"),
    ("noise: {tau: .nan}", "noise.tau"),
    ("noise: {tau: [1, x, 2]}", r"noise.tau\[1\]"),
    ("noise: {q_resolution: abc}", "noise.q_resolution"),
    ("rate_hz: .nan", "rate_hz"), ("rate_hz: 1e300", "rate_hz"),
    ("effects: [{name: [1]}]", "unknown plant effect"),
    ("effects: [{name: ripple, joint: 1, amplitude: 1, period: 0}]", "period: expected a positive"),
    ("controller: [1]", "controller: expected a mapping"),
    ("1: 2", "unknown key '1'"),
])
def test_truth_files_with_wrong_types(tmp_path, arm3, text, problem):
    p = tmp_path / "truth.yaml"
    p.write_text(text + "\n")
    with pytest.raises(RobidError, match=problem) as exc:
        load_truth(p, arm3)
    one_line(exc, p)


def test_output_paths_checked_before_the_work(tmp_path, capsys):
    (tmp_path / "afile").write_text("x")
    (tmp_path / "adir").mkdir()
    cases = [
        (["excite", "--robot", ARM3, "--out", str(tmp_path / "no" / "t.csv")], "does not exist"),
        (["identify", "--robot", ARM3, "--data", "x.csv", "--out", str(tmp_path / "afile")],
         "exists and is not a folder"),
        (["identify", "--robot", ARM3, "--data", "x.csv", "--json", str(tmp_path / "adir")],
         "is a folder"),
        (["simulate", "--robot", ARM3, "--truth", "t", "--trajectory", "x",
          "--out", str(tmp_path / "afile" / "log.csv")], "does not exist"),
    ]
    for argv, problem in cases:
        start = time.monotonic()
        assert problem in run_cli(argv, capsys)
        assert time.monotonic() - start < 2  # before any work


def test_non_string_paths_in_configs(tmp_path):
    p = tmp_path / "d.yaml"
    p.write_text("robot: 5\nstate_dir: s\ncontrol_socket: c\ndriver: {name: file_share}\n"
                 "campaigns: {a: {experiments: [rigid_body]}}\n")
    with pytest.raises(RobidError, match="robot: expected a path") as exc:
        load_daemon_config(p)
    one_line(exc, p)


# ----------------------------------------------------------------------------- wrong successes

def test_unparsable_urdf_mass_is_not_zero(tmp_path):
    for mass, problem in (("heavy", "mass: expected a finite number"),
                          ("-2", "mass -2 is negative")):
        p = urdf(tmp_path, mass=mass)
        with pytest.raises(RobidError, match=f"link 'l1': {problem}") as exc:
            load_robot(p)
        one_line(exc, p)


def test_urdf_inertia_must_be_physical(tmp_path):
    p = urdf(tmp_path, ixx="0.5")  # 0.01 + 0.01 < 0.5
    with pytest.raises(RobidError, match="link 'l1': principal moments .* triangle") as exc:
        load_robot(p)
    one_line(exc, p)


def test_urdf_errors_are_one_line_and_doctype_refused(tmp_path):
    p = tmp_path / "r.urdf"
    p.write_text('<?xml version="1.0"?><!DOCTYPE r [<!ENTITY x "y">]><robot name="r"/>')
    with pytest.raises(RobidError, match="DOCTYPE and ENTITY declarations are refused") as exc:
        load_robot(p)
    one_line(exc, p)
    p.write_text('<robot name="r"><link name="a"/><joint name="j" type="revolute">'
                 '<parent link="a"/><child link="zz"/></joint></robot>')
    with pytest.raises(RobidError, match="child link 'zz' is not defined") as exc:
        load_robot(p)
    one_line(exc, p)


def test_add_effect_without_joint_is_refused():
    with pytest.raises(RobidError, match="after '@' a joint number"):
        parse_effect("viscous@", "--add viscous@")


def test_simulate_with_nan_noise_writes_nothing(tmp_path, arm3, capsys):
    truth = tmp_path / "truth.yaml"
    truth.write_text("noise: {tau: .nan}\n")
    out = tmp_path / "log.csv"
    msg = run_cli(["simulate", "--robot", ARM3, "--truth", str(truth), "--trajectory",
                   str(tmp_path / "t.csv"), "--out", str(out)], capsys)
    assert str(truth) in msg and not out.exists()


def test_mdh_urdf_round_trip_still_loads(industrial6, tmp_path):
    p = tmp_path / "i6.urdf"
    p.write_text(mdh_to_urdf(industrial6))
    assert load_robot(p).n == 6


# ----------------------------------------------------------------------------- item 11: CLI

def test_version(capsys):
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == "robid 0.1.0"


def test_every_option_has_help_text():
    import argparse

    missing = []

    def walk(parser: argparse.ArgumentParser, prefix: str) -> None:
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    walk(sub, f"{prefix} {name}")
            elif action.help is None and not isinstance(action, argparse._HelpAction):
                missing.append(f"{prefix} {'/'.join(action.option_strings) or action.dest}")

    walk(_parser(), "robid")
    assert not missing, missing


def test_excite_prints_progress(tmp_path, capsys):
    rc = main(["excite", "--robot", ARM3, "--out", str(tmp_path / "t.csv"), "--evaluations",
               "20", "--duration", "10"])
    out = capsys.readouterr().out
    assert rc == 0
    assert out.count("restart ") >= 3 and "20/20 evaluations" in out
