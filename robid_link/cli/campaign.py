"""``robid campaign start``, ``list``, ``cancel``, ``resume``, ``approve``: the operator's
requests to the daemon over its control socket (``list`` reads the config when no daemon
answers)."""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING

from robid_link.cli.runs import format_results, report_lines, request, wait_for_run
from robid_link.cli.types import Command, config_option, output_path
from robid_link.exceptions import ApprovalError, DaemonUnreachable

if TYPE_CHECKING:
    from robid_link.config import DaemonConfig

__all__ = ["COMMANDS", "EXIT_NOTHING_TO_DO"]

#: ``campaign start --trigger timer`` with a program nobody approved: no run, nothing moved.
#: 6 is LSB's "program is not configured", which systemd names (status=6/NOTCONFIGURED): the
#: nightly unit shows as failed with that name, never as a success (robid-nightly.service)
EXIT_NOTHING_TO_DO = 6


def _config(args: argparse.Namespace) -> DaemonConfig:
    from robid_link.config import load_daemon_config

    return load_daemon_config(args.config)


def _name_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("name", help="campaign name (from the config's campaigns:)")
    config_option(p)


def _start_options(p: argparse.ArgumentParser) -> None:
    _name_options(p)
    p.add_argument("--trigger", choices=("operator", "timer"), default="operator",
                   help="timer: unattended, runs only approved programs")
    p.add_argument("--wait", action="store_true", help="show progress until the run ends")
    p.add_argument("--force", action="store_true",
                   help="upload the identified parameter set even if the worker marks it "
                        "unfit (validates worse than CAD, physically impossible)")
    p.add_argument("--json", metavar="FILE", type=output_path("file", create_parents=True),
                   help="with --wait: write the run and results")


def _start(args: argparse.Namespace) -> int:
    from robid_link.link.control import PREFLIGHT_TIMEOUT_S

    cfg = _config(args)
    try:
        run_id = request(cfg.control_socket, {"cmd": "start", "campaign": args.name,
                                              "trigger": args.trigger,
                                              **({"force": True} if args.force else {})},
                         timeout_s=PREFLIGHT_TIMEOUT_S)["run_id"]
    except ApprovalError as err:  # unattended, and nothing approved: nothing to do
        if args.trigger != "timer":
            raise
        print(f"robid: nothing to do: {err}", file=sys.stderr)
        return EXIT_NOTHING_TO_DO
    print(run_id)
    if not args.wait:
        if args.json:
            from robid_link.atomic import write_json

            write_json(args.json, {"run_id": run_id, "state": "queued"})
        return 0
    run = wait_for_run(cfg.control_socket, run_id)
    results = request(cfg.control_socket, {"cmd": "results", "run_id": run_id})
    if args.json:
        from robid_link.atomic import write_json

        write_json(args.json, {"run": run, "results": results["results"]})
    print(format_results(results["results"]))
    for line in report_lines(cfg.state_dir, [run_id]):
        print(line)
    return 0 if run["state"] == "completed" else 1


def _list(args: argparse.Namespace) -> int:
    cfg = _config(args)
    try:
        campaigns = request(cfg.control_socket, {"cmd": "list"})["campaigns"]
    except DaemonUnreachable as err:  # the list is the config's: no daemon needed
        print(f"robid: {err}; reading {cfg.path}", file=sys.stderr)
        from robid_link.link.campaign import describe_campaigns

        campaigns = describe_campaigns(cfg)
    for c in campaigns:
        exps = ", ".join(f"{e['id']} ({e['kind']})" for e in c["experiments"])
        print(f"{c['name']}: {exps}; identify {c['identify']}, diagnose {c['diagnose']}")
    return 0


def _cancel_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_id", help="the run's id (robid status)")
    config_option(p)


def _cancel(args: argparse.Namespace) -> int:
    cfg = _config(args)
    ans = request(cfg.control_socket, {"cmd": "cancel", "run_id": args.run_id},
                  timeout_s=120.0)
    print(ans["message"])
    return 0


def _resume(args: argparse.Namespace) -> int:
    cfg = _config(args)
    ans = request(cfg.control_socket, {"cmd": "resume", "run_id": args.run_id})
    print(ans["message"])
    return 0


def _approve(args: argparse.Namespace) -> int:
    cfg = _config(args)
    ans = request(cfg.control_socket, {"cmd": "approve", "campaign": args.name},
                  timeout_s=600.0)
    for a in ans["approved"]:
        print(f"approved {a['experiment']}: {a['sha256'][:16]}… "
              f"({a['duration_s']:.1f} s of motion, limits checked)")
    return 0


COMMANDS = (
    Command(name="campaign", help="start, list, cancel, resume or approve test campaigns",
            commands=(
        Command(name="start", help="queue a run of a campaign (prints its run_id)",
                options=_start_options, run=_start),
        Command(name="list", help="the campaigns of the config", options=config_option,
                run=_list),
        Command(name="cancel", help="drop a queued run, or stop the running one after "
                "withdrawing its program", options=_cancel_options, run=_cancel),
        Command(name="resume", help="let a run interrupted by a daemon restart move again "
                "(no run moves after a restart without it)", options=_cancel_options,
                run=_resume),
        Command(name="approve", help="generate, check and approve a campaign's programs for "
                "unattended runs", options=_name_options, run=_approve),
    )),
)
