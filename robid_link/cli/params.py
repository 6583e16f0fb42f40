"""``robid params show``, ``diff``, ``approve``, ``rollback``: the parameter sets each robot's
controller gets. Show and diff read the store; approve and rollback go through the daemon (it
owns the store and, for a rollback, the controller link)."""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from robid_link.cli.types import Command, config_option, output_path, refuse_given
from robid_link.exceptions import RobidError

if TYPE_CHECKING:
    from robid_link.config import DaemonConfig

__all__ = ["COMMANDS"]


def _options(p: argparse.ArgumentParser) -> None:
    p.add_argument("params_cmd", choices=tuple(_ACTIONS),
                   help="show the sets, diff two, approve one for unattended uploads, or "
                   "roll the controller back to the set before the one in use")
    p.add_argument("sets", nargs="*", metavar="SET",
                   help="a set's version number or sha256 prefix (show: one; diff: two, "
                   "default the set in use and the newest; approve: one, default the newest)")
    config_option(p)
    p.add_argument("--robot", required=True, metavar="NAME", help="the robot's name")
    p.add_argument("--json", metavar="FILE", type=output_path("file", create_parents=True),
                   help="show: write the set(s) as JSON")


def _check(args: argparse.Namespace) -> None:
    if args.params_cmd == "diff" and len(args.sets) not in (0, 2):
        raise RobidError("params diff: give two sets, or none (the set in use and the newest)")
    if args.params_cmd == "approve" and len(args.sets) > 1:
        raise RobidError(f"params approve: give one set, or none (the newest), not "
                         f"{len(args.sets)}")
    if args.params_cmd == "rollback" and args.sets:
        raise RobidError(f"params rollback: takes no set (it goes back to the set before the "
                         f"one in use), got {args.sets[0]!r}")
    if args.params_cmd != "show":
        refuse_given(args, ["--json"], "applies to params show only")


def _via_daemon(args: argparse.Namespace, cfg: DaemonConfig) -> int:
    from robid_link.link.control import request

    req = {"cmd": f"params_{args.params_cmd}", "robot": args.robot,
           "set": args.sets[0] if args.sets else None}
    ans = request(cfg.control_socket, req, timeout_s=600.0)
    print(ans["message"])
    return 0


def _stored(args: argparse.Namespace, cfg: DaemonConfig
            ) -> tuple[list[dict[str, Any]], list[str], list[dict[str, Any]]]:
    """(every stored set of the robot, the sha256 of the sets in use, the sets named)."""
    from robid_link.cli.runs import store_reader

    with store_reader(cfg) as store:
        sets = store.param_sets(args.robot)
        active = store.active_param_sets(args.robot)
        picked = [store.param_set(args.robot, ref) for ref in args.sets]
    if not sets:
        raise RobidError(f"robot {args.robot}: no parameter set stored yet")
    return sets, active, picked


def _diff(args: argparse.Namespace, cfg: DaemonConfig) -> int:
    from robid_link.ident.fit.paramset import diff_sets

    sets, active, picked = _stored(args, cfg)
    if not picked:
        in_use = next((s for s in sets if active and s["sha256"] == active[-1]), sets[0])
        picked = [in_use, sets[-1]]
    a, b = (json.loads(p["body"]) for p in picked)
    print(f"robot {args.robot}: set {picked[0]['version']} → set {picked[1]['version']}")
    print("\n".join(diff_sets(a, b)) or "  identical parameters")
    return 0


def _show(args: argparse.Namespace, cfg: DaemonConfig) -> int:
    sets, active, picked = _stored(args, cfg)
    for s in picked or sets:
        mark = " (in use)" if active and s["sha256"] == active[-1] else ""
        ok = f"approved by {s['approved_by']}" if s["approved"] else "not approved"
        print(f"set {s['version']}: {s['sha256'][:16]}… from run {s['run_id']}, {ok}{mark}")
        if picked:
            doc = json.loads(s["body"])
            for p in doc["base_parameters"]:
                print(f"  {p['name']:<12}{p['value']:>14.6g} ± {p['std']:<10.3g} "
                      f"{p['expression']}")
    if args.json:
        from robid_link.atomic import write_json

        write_json(args.json, {"robot": args.robot, "sets": [
            json.loads(s["body"]) for s in (picked or sets)]})
    return 0


_ACTIONS: dict[str, Callable[[argparse.Namespace, DaemonConfig], int]] = {
    "show": _show, "diff": _diff, "approve": _via_daemon, "rollback": _via_daemon}


def _params(args: argparse.Namespace) -> int:
    from robid_link.config import load_daemon_config

    return _ACTIONS[args.params_cmd](args, load_daemon_config(args.config))


COMMANDS = (
    Command(name="params", help="the parameter sets each robot's controller gets: show, diff, "
            "approve (for unattended uploads), rollback", options=_options, check=_check,
            run=_params),
)
