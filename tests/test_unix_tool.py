"""Issue 25: the CLI as a well-behaved Unix tool. Each case a new user tripped over ends in one
line naming the thing and the problem (exit 2), a bug in one ``internal error`` line (exit 70),
and nothing is silently ignored."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from robid_link.cli import EXIT_INTERNAL, main
from robid_link.cli.analyse import IRLS_WEIGHTS
from robid_link.cli.types import Command
from robid_link.exceptions import RobidError

from .conftest import ROBOTS

ARM3 = str(ROBOTS / "arm3.yaml")


def one_error(argv: list[str], capsys: pytest.CaptureFixture[str], *names: str) -> str:
    """Run ``robid argv``: exit 2, one stderr line ``robid: error: …`` naming each of names."""
    rc = main(argv)
    err = [line for line in capsys.readouterr().err.strip().splitlines()
           if not line.startswith("robid: warning:")]
    assert rc == 2, err
    assert len(err) == 1 and err[0].startswith("robid: error: "), err
    for name in names:
        assert name in err[0], err[0]
    return err[0]


# ----------------------------------------------------------------------------- tracebacks

def test_show_robot_unknown_image_format_is_refused_before_the_drawing(tmp_path, capsys):
    out = tmp_path / "chain.xyz"
    line = one_error(["show-robot", "--robot", ARM3, "--out", str(out)], capsys, str(out),
                     "unknown image format .xyz")
    assert ".png" in line and not out.exists()


@pytest.mark.parametrize("folder", ["/proc", "/sys"])
def test_identify_out_into_a_folder_that_cannot_be_written(tmp_path, capsys, folder):
    """Refused at parse time, before the identification: even as root, where os.access says
    yes, the probe file cannot be made."""
    if not Path(folder).is_dir():
        pytest.skip(f"no {folder}")
    target = f"{folder}/robid-out"
    one_error(["identify", "--robot", ARM3, "--data", str(tmp_path / "none.csv"), "--out",
               target], capsys, target, f"cannot write in folder {folder}")


def test_an_output_file_that_is_a_device_or_fifo_is_refused(tmp_path, capsys):
    """An atomic write renames over its target: /dev/null would be replaced by a file."""
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    for target, kind in ((os.devnull, "a character device"), (str(fifo), "a FIFO")):
        one_error(["identify", "--robot", ARM3, "--data", "x.csv", "--json", target], capsys,
                  target, kind)


def _only_command(monkeypatch: pytest.MonkeyPatch, run: object) -> None:
    """``robid history M`` runs ``run`` instead (the parser and error path stay real)."""
    import robid_link.cli as cli

    group = argparse.Namespace(COMMANDS=(Command(
        name="history", help="", options=lambda p: p.add_argument("model_file"), run=run),))
    monkeypatch.setattr(cli, "GROUPS", (group,))


def test_an_unforeseen_os_error_is_one_line_naming_the_file(monkeypatch, tmp_path, capsys):
    def fail(args: argparse.Namespace) -> int:
        raise PermissionError(13, "Permission denied", str(tmp_path / "h.jsonl"))

    _only_command(monkeypatch, fail)
    one_error(["history", "m.yaml"], capsys, f"{tmp_path / 'h.jsonl'}: Permission denied")


def test_a_bug_is_one_internal_error_line_and_debug_shows_the_traceback(monkeypatch, capsys):
    def bug(args: argparse.Namespace) -> int:
        raise TypeError("unsupported operand")

    _only_command(monkeypatch, bug)
    assert main(["history", "m.yaml"]) == EXIT_INTERNAL
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("robid: internal error: TypeError: "), err
    assert "test_unix_tool.py:" in err[0] and "--debug" in err[0]
    with pytest.raises(TypeError):
        main(["--debug", "history", "m.yaml"])


_PRINTS_A_LOT = """
import argparse, sys
import robid_link.cli as cli
from robid_link.cli.types import Command

def run(args):
    for i in range(200_000):
        print("run", i)
    return 0

cli.GROUPS = (argparse.Namespace(COMMANDS=(Command(name="many", help="", run=run),)),)
sys.exit(cli.main(["many"]))
"""


def test_a_closed_pipe_ends_quietly():
    """``robid … | head -1``: no BrokenPipeError traceback, no 'Exception ignored'."""
    with subprocess.Popen([sys.executable, "-c", _PRINTS_A_LOT], stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE) as proc:
        assert proc.stdout is not None and proc.stderr is not None
        assert proc.stdout.readline() == b"run 0\n"
        proc.stdout.close()
        err = proc.stderr.read().decode()
        assert proc.wait(timeout=60) == 141
    assert "Traceback" not in err and "Exception ignored" not in err, err


# ------------------------------------------------------------- contradictory options refused

@pytest.mark.parametrize(("argv", "names"), [
    (["identify", "--robot", ARM3, "--data", "x.csv", "--weight", "huber"],
     ["--weight", "--method irls", "ols"]),
    (["identify", "--robot", ARM3, "--data", "x.csv", "--method", "wls", "--weight", "huber"],
     ["--weight", "wls"]),
    (["identify", "--robot", ARM3, "--data", "x.csv", "--fs", "500"], ["--fs", ".mat"]),
    (["diagnose", "--robot", ARM3, "--data", "x.npz", "--fs", "500"], ["--fs", ".mat"]),
    (["elasticity", "--robot", ARM3, "--data", "x.csv", "--fs", "500"], ["--fs", ".mat"]),
    (["excite", "--robot", ARM3, "--out", "t.csv", "--steps", "6"],
     ["--steps", "--kind fourier"]),
    (["excite", "--robot", ARM3, "--out", "t.csv", "--joint", "2"], ["--joint"]),
    (["excite", "--robot", ARM3, "--out", "t.csv", "--kind", "elasticity", "--harmonics", "3"],
     ["--harmonics", "--kind elasticity"]),
    (["excite", "--robot", ARM3, "--out", "t.csv", "--kind", "elasticity", "--seed", "3"],
     ["--seed"]),
    (["excite", "--robot", ARM3, "--out", "t.csv", "--kind", "elasticity", "--model", "m.yaml"],
     ["--model"]),
    (["results", "--config", "c.yaml", "--sigma", "3"], ["--sigma", "--trend"]),
    (["results", "--config", "c.yaml", "--robot", "r", "--out", "t.png"], ["--out", "--trend"]),
    (["results", "--config", "c.yaml", "--compare", "a", "b", "--robot", "c"],
     ["--robot", "--compare"]),
    (["params", "diff", "--config", "c.yaml", "--robot", "r", "--json", "x.json"],
     ["--json", "params show"]),
    (["params", "approve", "1", "2", "--config", "c.yaml", "--robot", "r"], ["params approve"]),
    (["params", "rollback", "3", "--config", "c.yaml", "--robot", "r"],
     ["params rollback", "'3'"]),
    (["fake-controller", "--share", ".", "--robot", ARM3, "--fault-count", "2"],
     ["--fault-count", "--fault"]),
    (["demo", "--driver", "nope"], ["--driver nope", "file_share"]),
    (["elasticity", "--robot", ARM3, "--data", "x.csv", "--joints", "2,2"], ["--joints 2,2"]),
    (["excite", "--robot", ARM3, "--out", "t.csv", "--kind", "elasticity", "--f-min", "70"],
     ["--f-min 70", "--f-max 60"]),
    (["excite", "--robot", ARM3, "--out", "t.csv", "--kind", "elasticity", "--rate", "100"],
     ["--f-max 60", "--rate 100"]),
])
def test_contradictory_options_are_refused_not_ignored(tmp_path, monkeypatch, capsys, argv,
                                                       names):
    """Before any file is read (none of these exists)."""
    monkeypatch.chdir(tmp_path)
    one_error(argv, capsys, *names)


def test_weight_choices_are_the_estimators(capsys):
    from robid_link.ident.fit.estimate import WEIGHTS

    assert set(IRLS_WEIGHTS) == set(WEIGHTS)


def test_implausible_rates_are_refused_at_parse_time(capsys):
    for argv in (["excite", "--robot", ARM3, "--out", "t.csv", "--rate", "1e-6"],
                 ["identify", "--robot", ARM3, "--data", "x.mat", "--fs", "0.5"]):
        one_error(argv, capsys, "--rate" if "--rate" in argv else "--fs", "[10,")


# ----------------------------------------------------------------------------- show-robot

def test_show_robot_titles_the_pose_in_the_units_given(tmp_path, monkeypatch, capsys):
    from robid_link.ident.report import figures

    titles: list[str] = []
    real = figures._place_labels

    def spy(fig, ax, labels):
        titles.append(ax.get_title())
        real(fig, ax, labels)

    monkeypatch.setattr(figures, "_place_labels", spy)
    assert main(["show-robot", "--robot", ARM3, "--q", "30", "45", "10", "--out",
                 str(tmp_path / "a.png")]) == 0
    assert titles == ["arm3 at q = [30°, 45°, 10°] (arrows: joint axes)"]


def test_show_robot_labels_do_not_overlap(tmp_path, monkeypatch):
    """Joints at one place share a label; labels a few pixels apart move aside."""
    from robid_link.ident.model.robot import load_robot
    from robid_link.ident.report import figures

    boxes: list[list[object]] = []
    real = figures._place_labels

    def spy(fig, ax, labels):
        real(fig, ax, labels)
        renderer = fig.canvas.get_renderer()
        boxes.append([t.get_window_extent(renderer) for t in ax.texts])
        boxes.append([label for _, label in labels])

    monkeypatch.setattr(figures, "_place_labels", spy)
    robot = load_robot(ROBOTS / "industrial6.yaml")
    figures.draw_robot(robot, np.radians([0, -30, 60, 0, 45, 0]), tmp_path / "i.png")
    placed, labels = boxes
    assert any(", " in str(label) for label in labels)  # the wrist's axes 4 and 5 share one
    assert len(placed) == len(labels)
    for i, a in enumerate(placed):
        for b in placed[i + 1:]:
            assert not a.overlaps(b)  # type: ignore[attr-defined]


# ----------------------------------------------------------------------------- robot files

_ARM = ('<link name="{child}"><inertial><mass value="1"/><inertia ixx="0.01" ixy="0" ixz="0" '
        'iyy="0.01" iyz="0" izz="0.01"/></inertial></link>')
_JOINT = ('<joint name="{name}" type="revolute"><parent link="{parent}"/><child link="{child}"/>'
          '<axis xyz="0 0 1"/>{extra}<limit lower="-1" upper="1" effort="10" velocity="2"/>'
          '</joint>')


def _urdf(tmp_path: Path, links: list[str], joints: list[tuple[str, str, str]],
          extra: str = "") -> Path:
    p = tmp_path / "r.urdf"
    body = "".join(_ARM.format(child=c) for c in links)
    body += "".join(_JOINT.format(name=n, parent=a, child=b, extra=extra) for n, a, b in joints)
    p.write_text(f'<robot name="r"><link name="base"/>{body}</robot>')
    return p


@pytest.mark.parametrize(("links", "joints", "names"), [
    (["l1"], [("j1", "base", "l1"), ("j2", "l1", "l1")],
     ["joint 'j2'", "parent and child are both link 'l1'", "loop"]),
    (["l1", "l2"], [("j1", "base", "l1"), ("j2", "l1", "l2"), ("j3", "l2", "l1")],
     ["link 'l1'", "'j1' and 'j3'"]),
    (["l1", "l2"], [("j2", "l1", "l2"), ("j3", "l2", "l1")], ["'j2'", "'j3'", "form a loop"]),
    (["l1", "l2"], [("j1", "base", "l1")], ["'base' and 'l2'", "no parent joint"]),
])
def test_urdf_that_is_not_one_tree_is_refused(tmp_path, capsys, links, joints, names):
    p = _urdf(tmp_path, links, joints)
    one_error(["show-robot", "--robot", str(p), "--out", str(tmp_path / "r.png")], capsys,
              str(p), *names)
    assert not (tmp_path / "r.png").exists()


def test_urdf_parser_output_is_summarised_into_the_one_line(tmp_path, capfd):
    """urdfdom writes several lines to file descriptor 2 itself: none reaches the terminal,
    the error line says what it found and where."""
    p = _urdf(tmp_path, ["l1"], [("j1", "base", "l1")], '<dynamics damping="x"/>')
    assert main(["show-robot", "--robot", str(p), "--out", str(tmp_path / "r.png")]) == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert err == [f"robid: error: {p}: cannot parse URDF: damping value (x) is not a valid "
                   "float; Could not parse joint_dynamics element for joint [j1]"]
    with pytest.raises(RobidError, match="damping value"):
        main(["--debug", "show-robot", "--robot", str(p), "--out", str(tmp_path / "r.png")])


def test_urdf_parser_complaint_about_an_unused_part_is_one_warning(tmp_path, capfd):
    p = _urdf(tmp_path, ["l1"], [("j1", "base", "l1")])
    p.write_text(p.read_text().replace(
        '<link name="l1">', '<link name="l1"><visual><geometry><box size="1 x"/></geometry>'
        '</visual>'))
    assert main(["show-robot", "--robot", str(p), "--out", str(tmp_path / "r.png")]) == 0
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"robid: warning: {p}: the URDF parser "
                                               "skipped: "), err
    assert "visual element for Link [l1]" in err[0]


# ----------------------------------------------------------------------------- truth rates

@pytest.mark.parametrize("rate", [1e-6, 0.5, 9.99, 2e5])
def test_truth_with_an_implausible_sampling_rate_is_refused(tmp_path, arm3, rate):
    from robid_link.fakes.plant import load_truth

    p = tmp_path / "truth.yaml"
    p.write_text(f"rate_hz: {rate}\n")
    with pytest.raises(RobidError) as exc:
        load_truth(p, arm3)
    msg = str(exc.value)
    assert "\n" not in msg and str(p) in msg and "rate_hz" in msg and "[10, 100000] Hz" in msg


def test_trajectory_header_with_an_implausible_rate_is_refused(tmp_path):
    from robid_link.ident.excite.excitation import read_trajectory

    (tmp_path / "t.csv").write_text("t,q1\n0,0\n1000000,0\n")
    (tmp_path / "t.yaml").write_text("rate_hz: 1e-6\nkind: custom\n")
    with pytest.raises(RobidError, match=r"t\.yaml: rate_hz: expected a rate in \[10, 100000\]"):
        read_trajectory(tmp_path / "t.csv")


def test_the_cli_the_config_and_the_worker_agree_on_plausible_rates():
    from robid_link import kinds
    from robid_link.cli.types import MIN_RATE_HZ
    from robid_link.ident.excite import excitation

    assert MIN_RATE_HZ == kinds.MIN_RATE_HZ == excitation.MIN_RATE_HZ


# ----------------------------------------------------------------------------- noise

_WORKER_JOBS = """
import asyncio, multiprocessing, sys
from robid_link.jobs import WORKER_PRELOAD, ProgramJob
from robid_link.link.worker import run_in_worker

async def main():
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(["robid_link.link.worker", *WORKER_PRELOAD])
    for k in range(2):  # numba's parallel kernels make a named semaphore in each worker
        job = ProgramJob(sys.argv[1], (), f"e{k}", "rigid_body", {
            "duration_s": 10.0, "harmonics": 3, "base_hz": 0.1, "rate_hz": 100.0,
            "evaluations": 10, "restarts": 1, "seed": k}, sys.argv[2], None)
        print((await run_in_worker(ctx, job)).sha256[:12], flush=True)

if __name__ == "__main__":
    asyncio.run(main())
"""


def test_worker_processes_leave_no_leaked_semaphore_at_exit(tmp_path):
    """The daemon and the demo printed multiprocessing's 'leaked semaphore' warnings at exit:
    a worker that had answered was terminated before its own exit unregistered numba's lock."""
    script = tmp_path / "jobs.py"
    script.write_text(_WORKER_JOBS)
    out = subprocess.run([sys.executable, str(script), ARM3, str(tmp_path)],
                         capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert len(out.stdout.split()) == 2
    assert "leaked semaphore" not in out.stderr and "resource_tracker" not in out.stderr, \
        out.stderr


@pytest.mark.parametrize(("options", "names"), [
    ({"rate_hz": 1e-6}, ["experiments[0].rate_hz", "[10, 10000]"]),
    ({"rate_hz": 5}, ["experiments[0].rate_hz"]),
    ({"rate_hz": 100}, ["experiments[0].f_max_hz", "rate_hz 100"]),
    ({"f_min_hz": 80}, ["experiments[0].f_min_hz", "f_max_hz 60"]),
])
def test_campaign_rates_are_plausible(tmp_path, options, names):
    """A campaign's experiment rate, and a stepped sine's band below a fifth of it."""
    import yaml

    from robid_link.config import load_daemon_config

    p = tmp_path / "d.yaml"
    p.write_text(yaml.safe_dump({
        "robot": ARM3, "state_dir": "s", "control_socket": "c.sock",
        "driver": {"name": "file_share", "share": "share"},
        "campaigns": {"a": {"experiments": [{"kind": "elasticity", **options}]}}}))
    with pytest.raises(RobidError) as err:
        load_daemon_config(p)
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith(f"{p}: campaigns.a.")
    for name in names:
        assert name in msg, msg


# ------------------------------------------------------- messages that did not name their object

def test_elasticity_analysis_errors_name_the_log(tmp_path, arm3, capsys):
    """The stepped-sine analysis works on arrays: a log without steps is named."""
    from .conftest import simulate

    log = simulate(arm3, tmp_path / "plain.csv", duration=4.0, rate=200.0).path
    one_error(["elasticity", "--robot", ARM3, "--data", str(log)], capsys, str(log),
              "no sinusoidal steps")
    one_error(["elasticity", "--robot", ARM3, "--data", str(log), "--joint", "1"], capsys,
              str(log))


def test_a_damaged_parameter_set_is_named_by_its_hash():
    from robid_link.jobs import PARAMETER_SET_FORMAT, ParameterSet

    with pytest.raises(RobidError, match=r"^parameter set 0123456789ab: damaged \(sha256 "
                                         r"mismatch\)"):
        ParameterSet.from_doc({"format": PARAMETER_SET_FORMAT, "sha256": "0123456789abcdef"})


def test_an_experiment_beyond_the_robot_names_the_experiment(arm3):
    from robid_link.ident.excite.experiments import experiment_trajectory

    with pytest.raises(RobidError, match=r"^experiment sweep: joints: 7 is not a joint of arm3"):
        experiment_trajectory(arm3, "friction", {"joints": [7]}, None, "experiment sweep")


def test_consistent_without_inertials_names_the_robot_file(tmp_path, capsys):
    robot = tmp_path / "bare.yaml"  # two joints, no inertial: entries
    robot.write_text("joints:\n" + "  - {alpha: 0, a: 0.3, theta: 0, d: 0, limits: "
                     "{q: [-3, 3]}}\n" * 2)
    t = np.arange(600) / 100.0
    q = np.column_stack([np.sin(t), np.cos(0.7 * t)])
    np.savetxt(tmp_path / "two.csv", np.column_stack([t, q, q]), delimiter=",",
               header="t,q1,q2,tau1,tau2", comments="", fmt="%.6f")
    one_error(["identify", "--robot", str(robot), "--data", str(tmp_path / "two.csv"),
               "--method", "consistent"], capsys, str(robot), "no", "inertials")
