"""``robid daemon``, ``fake-controller``, ``config check``: the link daemon in the foreground,
the controller side of a driver's protocol over the simulated robot, and a config checked
without a daemon."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from robid_link.cli.types import (
    Command,
    bounded_int,
    config_option,
    known_peer,
    output_path,
    refuse_given,
    robot_options,
    seed_option,
)
from robid_link.exceptions import RobidError

__all__ = ["COMMANDS"]


def _daemon(args: argparse.Namespace) -> int:
    """The daemon, with the operator's page as a service when the config has ``web.listen``
    (the CLI hands it over: the link never imports the web room). The config's keys, driver
    options and paths are checked here first (one error line, before the daemon's logging
    starts); the daemon checks them again."""
    import asyncio

    from robid_link.config import load_daemon_config
    from robid_link.link.checks import daemon_findings
    from robid_link.link.daemon import run_daemon
    from robid_link.link.registry import make_driver

    cfg = load_daemon_config(args.config)
    problems = daemon_findings(cfg, type(make_driver(cfg.driver)).options)
    if problems:
        more = f" (and {len(problems) - 1} more: robid config check)" if problems[1:] else ""
        raise RobidError(f"{cfg.path}: {problems[0].line}{more}")
    services = []
    if cfg.web.listen:
        from robid_link.web.command import daemon_service

        services.append(daemon_service(cfg))
    return asyncio.run(run_daemon(cfg, services))


def _config_check(args: argparse.Namespace) -> int:
    """``robid config check``: what the daemon's start checks, one line per path it needs and
    per campaign (ok, or the key, file and problem); exit 1 when anything is wrong. Keys of
    the wrong type or value are one error line (exit 2), as everywhere."""
    from robid_link.config import load_daemon_config
    from robid_link.link.campaign import check_config
    from robid_link.link.checks import daemon_findings
    from robid_link.link.registry import make_driver

    cfg = load_daemon_config(args.config)
    driver = make_driver(cfg.driver)
    findings = {f.key: f.line for f in daemon_findings(cfg, type(driver).options)}
    local_logs = cfg.log_store is not None and "://" not in cfg.log_store
    paths = ["robot", "state_dir", *(["log_store"] if local_logs else []), "control_socket",
             *(k for k in findings if k.startswith("driver."))]
    for key in paths:
        print(findings.get(key, f"{key}: ok"))
    bad = len(findings)
    for name, reason in check_config(cfg, driver).items():
        print(f"{name}: {'ok' if reason is None else reason}")
        bad += reason is not None
    return 1 if bad else 0


# ------------------------------------------------------------------------ fake-controller

def _fake_controller_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--driver", default="file_share",
                   help="the driver whose controller side to play (file_share, abb_rws, "
                   "canopen_drives, modbus_plc, serial_line, ur_rtde, or a plug-in's)")
    p.add_argument("--share", "--workdir", dest="workdir", required=True, metavar="DIR",
                   help="the peer's folder: the share (file_share, modbus_plc) or the "
                   "controller's file system")
    p.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                   help="a peer option (YAML value), e.g. --option port=0; repeatable")
    p.add_argument("--ready-file", metavar="F", type=output_path("file"),
                   help="write the daemon's driver: mapping for this peer as JSON to F once it "
                   "serves (ports chosen at start)")
    robot_options(p)
    p.add_argument("--truth", help="truth file (default: nominal inertials, viscous and "
                   "Coulomb friction, torque noise)")
    p.add_argument("--fault", help="never_answer, die, truncated_log, corrupt_log, "
                   "answer_twice, stale_semaphore, nan_log, fail, or one of the peer's own")
    p.add_argument("--fault-count", type=bounded_int(0, 1_000_000), metavar="N",
                   help="how many programs the fault hits (default 1)")
    seed_option(p)


def _peer_options(items: list[str]) -> dict[str, Any]:
    """``--option KEY=VALUE`` (repeatable) as keyword arguments, each value read as YAML."""
    from robid_link.safeyaml import load_yaml

    options: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.isidentifier():
            raise RobidError(f"--option {item!r}: expected KEY=VALUE")
        options[key] = load_yaml(value, f"--option {key}", error=RobidError)
    return options


def _fake_controller(args: argparse.Namespace) -> int:
    import json
    import logging
    import signal
    import threading

    from robid_link.atomic import atomic_write
    from robid_link.ident.model.robot import load_robot
    from robid_link.link.notify import setup_logging
    from robid_link.link.registry import fake_module

    setup_logging("info")
    options = _peer_options(args.option)
    robot = load_robot(args.robot, args.lock, allow_unlimited=args.allow_unlimited)
    ctrl = fake_module("controller")
    truth = (fake_module("plant").load_truth(args.truth, robot) if args.truth
             else ctrl.default_truth(robot))
    if not Path(args.workdir).is_dir():
        raise RobidError(f"--workdir: {args.workdir}: folder not found")
    try:
        peer = ctrl.make_peer(args.driver, robot, truth, args.workdir, fault=args.fault,
                              fault_count=1 if args.fault_count is None else args.fault_count,
                              seed=args.seed, exit_on_die=True,
                              **options)
    except TypeError as err:  # an option the peer does not take
        raise RobidError(f"--option: {err}") from err
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with peer:
        driver = peer.driver_options()
        if args.ready_file:
            atomic_write(Path(args.ready_file), json.dumps(driver).encode())
        logging.getLogger("robid.fake_controller").info(
            "serving driver=%s robot=%s fault=%s options=%s", args.driver, robot.name,
            args.fault, json.dumps(driver))
        try:
            peer.wait(stop)
        except KeyboardInterrupt:
            pass
    return 0


def _fake_controller_check(args: argparse.Namespace) -> None:
    known_peer(args)
    if not args.fault:
        refuse_given(args, ["--fault-count"], "needs --fault (which fault to repeat)")


COMMANDS = (
    Command(name="daemon", help="run the link daemon in the foreground (systemd unit)",
            options=config_option, run=_daemon),
    Command(name="fake-controller", help="the controller side of a driver's protocol over the "
            "simulated robot (tests, demos)", options=_fake_controller_options,
            check=_fake_controller_check, run=_fake_controller),
    Command(name="config", help="check a daemon config without a daemon", commands=(
        Command(name="check", help="everything each campaign's run will need: one line per "
                "campaign, ok or the reason", options=config_option, run=_config_check),)),
)
