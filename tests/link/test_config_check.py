"""Issue 25, the daemon's side: ``robid config check`` and the daemon's start check the same
things — every path the config names and each campaign's files — one line each naming the key,
the path and the problem; the daemon refuses to start on an error and warns about a campaign
whose runs will be refused; a model file edited under a running daemon is reloaded at the next
run with a line in the log; a timer start with nothing approved exits 6 (nothing to do)."""

from __future__ import annotations

import asyncio
import logging
import os
import re
from pathlib import Path
from typing import Any

import pytest
import yaml

from robid_link.cli import main
from robid_link.cli.campaign import EXIT_NOTHING_TO_DO
from robid_link.config import load_daemon_config
from robid_link.exceptions import ConfigError
from robid_link.link.checks import ModelWatch, campaign_findings, daemon_findings
from robid_link.link.daemon import Daemon

from .conftest import QUICK, wait_run, write_config

ONE = {"experiments": [QUICK["experiments"][0]], "identify": False, "timeout_s": 4,
       "backoff_s": 0.05, "retries": 2}


def config_check(cfg: Path, capsys: pytest.CaptureFixture[str]) -> tuple[int, list[str], str]:
    rc = main(["config", "check", "--config", str(cfg)])
    out = capsys.readouterr()
    return rc, out.out.strip().splitlines(), out.err.strip()


def _edit(cfg: Path, **over: Any) -> Path:
    doc = yaml.safe_load(cfg.read_text())
    doc.update(over)
    cfg.write_text(yaml.safe_dump(doc))
    return cfg


# ----------------------------------------------------------------------------- config check

def test_a_sound_config_checks_every_path_ok(tmp_path, capsys):
    rc, lines, err = config_check(write_config(tmp_path, {"one": ONE}), capsys)
    assert rc == 0, (lines, err)
    assert lines == ["robot: ok", "state_dir: ok", "control_socket: ok", "one: ok"]


@pytest.mark.parametrize(("key", "make", "problem"), [
    ("robot", lambda t: t / "none.yaml", "robot description not found"),
    ("robot", lambda t: _fifo(t / "robot.yaml"), "robot description is a FIFO, not a regular "
                                                  "file"),
    ("robot", lambda t: _folder(t / "robot.yaml"), "robot description is a folder"),
    ("state_dir", lambda t: _file(t / "state"), "is not a folder"),
    ("state_dir", lambda t: Path("/proc/robid/state"), "cannot be created: cannot write in "
                                                       "/proc"),
    ("log_store", lambda t: _file(t / "logs"), "is not a folder"),
    ("log_store", lambda t: _file(t / "logs") / "a", "cannot be created: "),
    ("control_socket", lambda t: _file(t / "ctl.sock"), "exists and is not a socket"),
    ("control_socket", lambda t: t / ("x" * 120) / "ctl.sock", "a Unix socket path"),
    ("control_socket", lambda t: _file(t / "run") / "ctl.sock", "its folder"),
])
def test_every_path_the_daemon_needs_is_checked(tmp_path, capsys, key, make, problem):
    bad = make(tmp_path)
    if str(bad).startswith("/proc") and not Path("/proc").is_dir():
        pytest.skip("no /proc")
    cfg = write_config(tmp_path, {"one": ONE}, **{key: str(bad)})
    rc, lines, err = config_check(cfg, capsys)
    assert rc == 1 and err == ""
    line = next(ln for ln in lines if ln.startswith(f"{key}: "))
    assert line.startswith(f"{key}: {bad}: ") and problem in line, line


def test_driver_paths_are_checked(tmp_path, capsys):
    cfg = write_config(tmp_path, {"one": ONE})
    doc = yaml.safe_load(cfg.read_text())
    doc["driver"]["share"] = str(tmp_path / "no-share")
    cfg.write_text(yaml.safe_dump(doc))
    rc, lines, _ = config_check(cfg, capsys)
    assert rc == 1
    assert f"driver.share: {tmp_path / 'no-share'}: folder not found" in lines


@pytest.mark.parametrize("value", [5, [1], {"a": 1}, True])
def test_a_driver_option_of_the_wrong_type_is_one_line(tmp_path, capsys, value):
    """It was a TypeError from deep in the driver; both commands refuse it before any work."""
    cfg = write_config(tmp_path, {"one": ONE})
    doc = yaml.safe_load(cfg.read_text())
    doc["driver"]["share"] = value
    cfg.write_text(yaml.safe_dump(doc))
    for argv in (["config", "check", "--config", str(cfg)], ["daemon", "--config", str(cfg)]):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("robid: error: "), err
        assert "driver.share: expected a folder path, got " in err[0]


def test_campaign_files_are_checked(tmp_path, capsys):
    (tmp_path / "traj.csv").write_text("t,q1,q2,q3\n0,0,0,0\n0.01,0,0,0\n")  # no .yaml header
    fifo = _fifo(tmp_path / "fifo.yaml")
    cfg = write_config(tmp_path, {
        "one": ONE, "nomodel": {**ONE, "model": str(tmp_path / "none.yaml")},
        "fifomodel": {**ONE, "model": str(fifo)},
        "custom": {"experiments": [{"kind": "custom", "id": "path", "trajectory": "traj.csv"}],
                   "identify": False},
        "nocustom": {"experiments": [{"kind": "custom", "trajectory": "gone.csv"}]}})
    rc, lines, _ = config_check(cfg, capsys)
    assert rc == 1
    got = dict(ln.split(": ", 1) for ln in lines)
    assert got["one"] == "ok"
    assert got["nomodel"] == f"campaigns.nomodel.model: {tmp_path / 'none.yaml'}: model file " \
                             "not found"
    assert got["fifomodel"].endswith("model file is a FIFO, not a regular file")
    assert got["custom"] == (f"campaigns.custom.experiments.path.trajectory: "
                             f"{tmp_path / 'traj.yaml'}: trajectory header not found")
    assert got["nocustom"].startswith("campaigns.nocustom.experiments.custom.trajectory: "
                                      f"{tmp_path / 'gone.csv'}: trajectory file not found")


def _fifo(p: Path) -> Path:
    os.mkfifo(p)
    return p


def _folder(p: Path) -> Path:
    p.mkdir()
    return p


def _file(p: Path) -> Path:
    p.write_text("x")
    return p


# ----------------------------------------------------------------------------- daemon start

def _start_daemon(cfg: Path) -> Any:
    async def go() -> Any:
        async with asyncio.timeout(120), Daemon(load_daemon_config(cfg), env={}):
            return "started"

    return asyncio.run(go())


@pytest.mark.parametrize("key", ["robot", "state_dir", "control_socket"])
def test_the_daemon_refuses_to_start_on_a_path_error(tmp_path, key):
    bad = {"robot": lambda: tmp_path / "none.yaml", "state_dir": lambda: _file(tmp_path / "state"),
           "control_socket": lambda: _file(tmp_path / "ctl.sock")}[key]()
    cfg = write_config(tmp_path, {"one": ONE}, **{key: str(bad)})
    with pytest.raises(ConfigError) as err:
        _start_daemon(cfg)
    assert str(err.value).startswith(f"{cfg.resolve()}: {key}: {bad}: ")
    assert "\n" not in str(err.value)
    assert not (tmp_path / "state" / "robid.sqlite").exists()  # refused before the store


def test_the_same_findings_for_config_check_and_daemon(tmp_path):
    """One function each for the whole daemon and a campaign: both callers use them."""
    cfg = load_daemon_config(write_config(tmp_path, {"one": {**ONE, "model": "gone.yaml"}},
                                          robot=str(tmp_path / "none.yaml")))
    assert [f.key for f in daemon_findings(cfg)] == ["robot"]
    assert [f.key for f in campaign_findings(cfg, "one")] == ["campaigns.one.model"]


def test_the_daemon_warns_at_start_about_a_campaign_with_a_missing_file(
        tmp_path, caplog, controller):
    """It starts (the other campaigns are fine), says so at once, and refuses that campaign's
    start in one line naming the key and the file."""
    cfg = write_config(tmp_path, {"one": ONE, "broken": {**ONE, "model": "gone.yaml"},
                                  "custom": {"experiments": [{"kind": "custom", "id": "path",
                                                              "trajectory": "gone.csv"}]}})

    async def body() -> list[str]:
        async with asyncio.timeout(120), Daemon(load_daemon_config(cfg), env={}) as d:
            refused = []
            for name in ("broken", "custom"):
                with pytest.raises(ConfigError) as err:
                    await d.handle({"cmd": "start", "campaign": name})
                refused.append(str(err.value))
            return refused

    with caplog.at_level(logging.WARNING, logger="robid"), controller():
        refused = asyncio.run(body())
    model = f"campaigns.broken.model: {tmp_path / 'gone.yaml'}: model file not found"
    custom = (f"campaigns.custom.experiments.path.trajectory: {tmp_path / 'gone.csv'}: "
              "trajectory file not found")
    warned = [r.getMessage() for r in caplog.records if "will be refused" in r.getMessage()]
    assert warned == [f"{cfg.resolve()}: campaign broken: its runs will be refused: {model}",
                      f"{cfg.resolve()}: campaign custom: its runs will be refused: {custom}"]
    assert refused == [model, custom]


# ----------------------------------------------------------------------------- model reload

def test_model_watch_says_when_a_model_file_changed(tmp_path):
    model = tmp_path / "m.yaml"
    model.write_text("effects: [rigid_body, viscous]\n")
    cfg = load_daemon_config(write_config(tmp_path, {"one": {**ONE, "model": str(model)}}))
    watch = ModelWatch()
    assert watch.seen(cfg, "one") is None  # first read
    assert watch.seen(cfg, "one") is None  # unchanged
    model.write_text("effects: [rigid_body, viscous, coulomb]\n")
    line = watch.seen(cfg, "one", ("rigid_body", "viscous", "coulomb"))
    assert line is not None and line.startswith(f"campaign one: model file {model} changed")
    assert line.endswith("reloaded, this run identifies with it [rigid_body, viscous, coulomb]")
    assert watch.seen(cfg, "one") is None


def test_a_model_file_edited_under_the_daemon_is_reloaded_with_a_line(tmp_path, caplog,
                                                                      controller):
    model = tmp_path / "model.yaml"
    model.write_text("effects: [rigid_body, viscous]\n")
    cfg = write_config(tmp_path, {"one": {**ONE, "model": str(model)}})

    async def body() -> list[dict[str, Any]]:
        async with asyncio.timeout(240), Daemon(load_daemon_config(cfg), env={}) as d:
            runs = []
            for effects in ("[rigid_body, viscous]", "[rigid_body, viscous, coulomb]"):
                model.write_text(f"effects: {effects}\n")
                ans = await d.handle({"cmd": "start", "campaign": "one"})
                runs.append(await wait_run(d, ans["run_id"]))
            return runs

    with caplog.at_level(logging.INFO, logger="robid"), controller():
        first, second = asyncio.run(body())
    assert first["state"] == second["state"] == "completed"
    lines = [r.getMessage() for r in caplog.records if "changed since" in r.getMessage()]
    assert len(lines) == 1 and lines[0].startswith(f"run={second['run_id']} campaign one: "
                                                   f"model file {model} changed")
    assert lines[0].endswith("[rigid_body, viscous, coulomb]")


# ----------------------------------------------------------------------------- the timer

def test_a_timer_start_with_nothing_approved_exits_nothing_to_do(tmp_path, capsys, controller):
    """The nightly unit's run: no program approved, no run queued, exit 6 with one line."""
    cfg = write_config(tmp_path, {"nightly": ONE})
    argv = ["campaign", "start", "nightly", "--trigger", "timer", "--config", str(cfg)]

    async def body() -> tuple[int, list[Any]]:
        async with asyncio.timeout(120), Daemon(load_daemon_config(cfg), env={}) as d:
            rc = await asyncio.to_thread(main, argv)
            return rc, await d.store.runs()  # type: ignore[union-attr]

    with controller():
        rc, runs = asyncio.run(body())
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == EXIT_NOTHING_TO_DO == 6 and runs == []
    assert len(err) == 1 and err[0].startswith("robid: nothing to do: campaign nightly: "
                                               "nothing to do unattended: the program of "
                                               "experiment rigid_body")
    assert "robid campaign approve nightly" in err[0]


def test_the_nightly_unit_documents_its_nothing_to_do_status():
    import configparser

    from robid_link.cli.campaign import EXIT_NOTHING_TO_DO

    units = Path(__file__).resolve().parents[2] / "robid_link" / "systemd"
    text = (units / "robid-nightly.service").read_text()
    unit = configparser.ConfigParser(interpolation=None, strict=False)
    unit.read_string(text)
    assert unit["Service"]["RestartPreventExitStatus"] == str(EXIT_NOTHING_TO_DO)
    assert "SuccessExitStatus" not in unit["Service"]
    assert f"status={EXIT_NOTHING_TO_DO}/NOTCONFIGURED" in text


def test_a_driver_number_beyond_any_float_is_one_line(tmp_path, capsys):
    """The fuzz found it: 10**400 for a number option was an OverflowError traceback."""
    cfg = write_config(tmp_path, {"one": ONE})
    doc = yaml.safe_load(cfg.read_text())
    doc["driver"]["poll_interval_s"] = 10 ** 400
    cfg.write_text(yaml.safe_dump(doc))
    assert main(["config", "check", "--config", str(cfg)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "driver.poll_interval_s: expected a number >= 0, got 1000" in err[0]


def test_a_folder_the_driver_makes_may_be_missing(tmp_path):
    """CANopen's record_dir is made by the driver: missing is fine if it can be created; a
    share that must be there is not."""
    from dataclasses import replace

    from robid_link.link.options import Folder

    given = {"share": str(tmp_path / "no-share"), "record_dir": str(tmp_path / "rec" / "a")}
    cfg = replace(load_daemon_config(write_config(tmp_path, {"one": ONE})), driver=given)
    opts = {"share": Folder(), "record_dir": Folder(None, created=True)}
    found = daemon_findings(cfg, opts)
    assert [f.line for f in found] == [f"driver.share: {tmp_path / 'no-share'}: folder not found"]
    _file(tmp_path / "rec")
    found = daemon_findings(cfg, opts)
    assert found[-1].line == (f"driver.record_dir: {tmp_path / 'rec' / 'a'}: cannot be created: "
                              f"{tmp_path / 'rec'} is not a folder")


def test_config_check_and_the_start_refuse_an_upload_in_the_same_words(tmp_path, capsys):
    """One capability check: config check's line is the daemon's refusal without the path."""
    cfg = write_config(tmp_path, {"one": ONE, "up": {**ONE, "identify": True, "upload": True}})
    _edit(cfg, driver={"name": "ur_rtde", "host": "127.0.0.1"})
    rc, lines, _ = config_check(cfg, capsys)
    assert rc == 1
    line = next(ln for ln in lines if ln.startswith("up: "))
    assert line.startswith("up: campaigns.up.upload: driver 'ur_rtde' cannot upload parameters "
                           "(capabilities: "), line
    from robid_link.link.campaign import check_capabilities
    from robid_link.link.registry import make_driver

    with pytest.raises(ConfigError) as err:
        check_capabilities(load_daemon_config(cfg), make_driver({"name": "ur_rtde",
                                                                 "host": "127.0.0.1"}))
    assert str(err.value) == f"{cfg}: {line.removeprefix('up: ')}"


def test_a_plug_in_declaring_option_names_only_is_checked_without_its_paths(tmp_path):
    """``options = frozenset({...})`` (the older plug-in form) has no path specs: no crash."""
    cfg = load_daemon_config(write_config(tmp_path, {"one": ONE}))
    assert daemon_findings(cfg, frozenset({"share"})) == []


@pytest.mark.parametrize(("key", "value", "said"), [
    ("retries", 10 ** 400, "retries: expected a non-negative integer up to 1000, got an integer"),
    ("retries", 1001, "retries: expected a non-negative integer up to 1000, got 1001"),
    ("backoff_s", 10 ** 20, "backoff_s: expected a non-negative number up to 1e+09, got 1e+20"),
    ("backoff_s", 1e305, "backoff_s: expected a non-negative number up to 1e+09, got 1e+305"),
])
def test_a_campaign_number_beyond_any_use_is_refused(tmp_path, key, value, said):
    """The fuzz found retries: 10**400 accepted (an int: it would overflow a float later)."""
    cfg = write_config(tmp_path, {"one": {**ONE, key: value}})
    with pytest.raises(ConfigError, match=re.escape(f"campaigns.one.{said}")):
        load_daemon_config(cfg)
