"""The link's sub-commands of ``robid``: fake-controller, campaign, status, results (``daemon``
starts in cli.py, with the web page when the config asks for it).
Operator commands talk to the daemon over its control socket; ``status`` and ``results`` read
the store directly when no daemon answers."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from robid_link.config import load_daemon_config
from robid_link.exceptions import DaemonUnreachable, RobidError
from robid_link.link.control import PREFLIGHT_TIMEOUT_S, request

__all__ = ["dispatch", "wait_for_run", "format_runs", "format_results", "report_lines"]


def dispatch(args: argparse.Namespace) -> int:
    if args.cmd == "fake-controller":
        return _fake_controller(args)
    cfg = load_daemon_config(args.config)
    if args.cmd == "config":
        return _config_check(cfg)
    if args.cmd == "campaign":
        if args.campaign_cmd == "start":
            run_id = request(cfg.control_socket, {"cmd": "start", "campaign": args.name,
                                                  "trigger": args.trigger},
                             timeout_s=PREFLIGHT_TIMEOUT_S)["run_id"]
            print(run_id)
            if not args.wait:
                if args.json:
                    from robid_link.ident.report.figures import write_json

                    write_json(args.json, {"run_id": run_id, "state": "queued"})
                return 0
            run = wait_for_run(cfg.control_socket, run_id)
            results = request(cfg.control_socket, {"cmd": "results", "run_id": run_id})
            if args.json:
                from robid_link.ident.report.figures import write_json

                write_json(args.json, {"run": run, "results": results["results"]})
            print(format_results(results["results"]))
            for line in report_lines(cfg.state_dir, [run_id]):
                print(line)
            return 0 if run["state"] == "completed" else 1
        if args.campaign_cmd == "cancel":
            ans = request(cfg.control_socket, {"cmd": "cancel", "run_id": args.run_id},
                          timeout_s=120.0)
            print(ans["message"])
            return 0
        if args.campaign_cmd == "list":
            try:
                campaigns = request(cfg.control_socket, {"cmd": "list"})["campaigns"]
            except DaemonUnreachable as err:  # the list is the config's: no daemon needed
                print(f"robid: {err}; reading {cfg.path}", file=sys.stderr)
                from robid_link.link.campaign import describe_campaigns

                campaigns = describe_campaigns(cfg)
            for c in campaigns:
                exps = ", ".join(f"{e['id']} ({e['kind']})" for e in c["experiments"])
                print(f"{c['name']}: {exps}; identify {c['identify']}, "
                      f"diagnose {c['diagnose']}")
            return 0
        ans = request(cfg.control_socket, {"cmd": "approve", "campaign": args.name},
                      timeout_s=600.0)
        for a in ans["approved"]:
            print(f"approved {a['experiment']}: {a['sha256'][:16]}… "
                  f"({a['duration_s']:.1f} s of motion, limits checked)")
        return 0
    if args.cmd == "status":
        try:
            ans = request(cfg.control_socket, {"cmd": "status"})
        except DaemonUnreachable as err:
            print(f"robid: {err}; reading the store", file=sys.stderr)
            from robid_link.link.campaign import drift_flags
            from robid_link.link.store import Store

            with Store(cfg.state_dir, readonly=True) as store:
                ans = {"runs": store.runs(), "status": _unreachable(err),
                       "drift": [f.message for f in drift_flags(store, _robot_name(cfg))]}
        if args.json:
            from robid_link.ident.report.figures import write_json

            write_json(args.json, {"runs": ans["runs"], "status": ans["status"],
                                   "drift": ans.get("drift", [])})
        print(f"daemon: {ans['status']}")
        print(format_runs(ans["runs"]))
        for line in report_lines(cfg.state_dir, [r["run_id"] for r in ans["runs"]
                                                 if r["state"] == "completed"]):
            print(line)
        for line in ans.get("drift", []):
            print(f"drift: {line}")
        return 0
    if args.cmd == "params":
        return _params(args, cfg)
    if args.cmd == "results":
        robot = None if args.compare else args.robot
        try:
            res = request(cfg.control_socket, {"cmd": "results", "robot": robot})["results"]
        except DaemonUnreachable:
            from robid_link.link.store import Store

            with Store(cfg.state_dir, readonly=True) as store:
                res = store.results(robot)
        if args.trend or args.compare:
            return _drift(args, res)
        print(format_results(res))
        for line in report_lines(cfg.state_dir, [r["run_id"] for r in reversed(res)]):
            print(line)
        return 0
    raise AssertionError(args.cmd)


def report_lines(state_dir: Path, run_ids: list[str], most: int = 5) -> list[str]:
    """``report RUN: PATH`` of the first ``most`` of these runs that have a report.html."""
    out = []
    for run_id in dict.fromkeys(run_ids):
        page = state_dir / "reports" / run_id / "report.html"
        if page.is_file():
            out.append(f"report {run_id}: {page}")
        if len(out) == most:
            break
    return out


def _unreachable(err: DaemonUnreachable) -> str:
    """What the status line says when no answer came: absent and frozen differ."""
    text = str(err)
    if "no answer within" in text or "closed the connection" in text:
        return f"daemon not answering (running but busy or frozen: {text})"
    if "permission denied" in text:
        return f"daemon unknown ({text})"
    return "daemon not running"


def _config_check(cfg: Any) -> int:
    """``robid config check``: one line per campaign, exit 1 when any would be refused."""
    from robid_link.link.campaign import check_config
    from robid_link.link.registry import make_driver

    driver = make_driver(cfg.driver)
    bad = 0
    for name, reason in check_config(cfg, driver).items():
        print(f"{name}: {'ok' if reason is None else reason}")
        bad += reason is not None
    return 1 if bad else 0


def _progress(run: dict[str, Any]) -> str:
    p = run["progress"]
    width = 20
    filled = int(width * p["stored"] / max(p["total"], 1))
    step = f": {run['step']}" if run.get("step") else ""
    return (f"[{'#' * filled}{'.' * (width - filled)}] {p['stored']}/{p['total']} logs  "
            f"{run['state']}{step}")


def wait_for_run(socket_path: Path, run_id: str, poll_s: float = 0.5,
                 stream: Any = None) -> dict[str, Any]:
    """Show the run's progress until it ends; return the final run record."""
    stream = stream or sys.stdout
    tty = stream.isatty()
    last = ""
    while True:
        run = request(socket_path, {"cmd": "status", "run_id": run_id})["runs"][0]
        line = _progress(run)
        if line != last:
            stream.write(("\r\033[K" if tty else "") + line + ("" if tty else "\n"))
            stream.flush()
            last = line
        if run["state"] in ("completed", "failed", "cancelled"):
            if tty:
                stream.write("\n")
            if run["state"] == "failed":
                stream.write(f"run {run_id} failed: {run['error']}\n")
            return run
        time.sleep(poll_s)


def format_runs(runs: list[dict[str, Any]]) -> str:
    if not runs:
        return "no runs yet"
    lines = [f"{'run_id':<24} {'campaign':<12} {'trigger':<8} {'state':<10} progress"]
    for r in runs:
        p = r["progress"]
        tail = r.get("error") if r["state"] == "failed" else (r.get("step") or "")
        lines.append(f"{r['run_id']:<24} {r['campaign']:<12} {r['trigger']:<8} "
                     f"{r['state']:<10} {p['stored']}/{p['total']} logs  {tail or ''}")
    return "\n".join(lines)


def format_results(results: list[dict[str, Any]]) -> str:
    """Per-joint validation RMSE of every result, oldest first: runs and robots side by side,
    each identification compared with the robot's previous one."""
    if not results:
        return "no results yet"
    lines = []
    previous: dict[str, list[float]] = {}
    previous_k: dict[tuple[str, int], float] = {}
    for r in results:
        rec = r["record"]
        if r["kind"] == "elasticity":  # K, D, f_res per joint, against the previous run
            for res in rec.get("experiments", []):
                for j in res["result"].get("joints", []):
                    key = (r["robot"], j["joint"])
                    was = previous_k.get(key)
                    change = (f"  K vs previous {100 * (j['k'] - was) / was:+.1f} %"
                              if was else "")
                    previous_k[key] = j["k"]
                    lines.append(f"{r['run_id']:<24} {r['robot']:<14} {'elastic':<9} joint "
                                 f"{j['joint']}: K {j['k']:.4g}, D {j['d']:.4g}, f_res "
                                 f"{j['f_res_hz']:.3g} Hz{change}")
            continue
        if "tracking" in rec:  # a verification path: how well the robot followed it
            tr = rec["tracking"]
            lines.append(f"{r['run_id']:<24} {r['robot']:<14} {r['kind']:<9} tool RMS "
                         f"{tr['tool_rms_mm']:.3f} mm, max {tr['tool_max_mm']:.3f} mm, after "
                         f"the stop {tr['residual_mm']:.3f} mm")
            continue
        rmse = " ".join(f"{x:7.3g}" for x in rec.get("rmse") or [])
        rel = rec.get("relative_error")
        extra = f"  {rec['verdict']}" if rec.get("verdict") else ""
        if rec.get("suggestions"):
            s = rec["suggestions"][0]
            extra += f" → {s['effect']}{'@' + str(s['joint']) if s.get('joint') else ''}"
        if r["kind"] == "identify" and rec.get("rmse"):
            before = previous.get(r["robot"])
            if before is not None and len(before) == len(rec["rmse"]):
                worst = max(range(len(before)), key=lambda j: abs(rec["rmse"][j] - before[j])
                            / max(before[j], 1e-12))
                change = (rec["rmse"][worst] - before[worst]) / max(before[worst], 1e-12)
                extra += f"  vs previous: joint {worst + 1} {100 * change:+.1f} %"
            previous[r["robot"]] = rec["rmse"]
        lines.append(f"{r['run_id']:<24} {r['robot']:<14} {r['kind']:<9} RMSE [{rmse}] N·m"
                     + (f"  rel {100 * rel:.2f} %" if rel is not None else "") + extra)
    return "\n".join(lines)


def _robot_name(cfg: Any) -> str:
    """The robot's name as the store records it (the description's name, else the stem)."""
    from robid_link.ident.model.robot import load_robot

    try:
        return str(load_robot(cfg.robot, cfg.lock).name)
    except RobidError:
        return Path(cfg.robot).stem


def _params(args: argparse.Namespace, cfg: Any) -> int:
    """``robid params``: show and diff read the store; approve and rollback go through the
    daemon (it owns the store and, for a rollback, the controller link)."""
    import json

    from robid_link.ident.fit.paramset import diff_sets
    from robid_link.link.store import Store

    if args.params_cmd in ("approve", "rollback"):
        req = {"cmd": f"params_{args.params_cmd}", "robot": args.robot,
               "set": args.sets[0] if args.sets else None}
        ans = request(cfg.control_socket, req, timeout_s=600.0)
        print(ans["message"])
        return 0
    with Store(cfg.state_dir, readonly=True) as store:
        sets = store.param_sets(args.robot)
        active = store.active_param_sets(args.robot)
        picked = [store.param_set(args.robot, ref) for ref in args.sets]
    if not sets:
        raise RobidError(f"robot {args.robot}: no parameter set stored yet")
    if args.params_cmd == "diff":
        if len(picked) == 1 or len(picked) > 2:
            raise RobidError("params diff: give two sets, or none (the set in use and the "
                             "newest)")
        if not picked:
            in_use = next((s for s in sets if active and s["sha256"] == active[-1]), sets[0])
            picked = [in_use, sets[-1]]
        a, b = (json.loads(p["body"]) for p in picked)
        print(f"robot {args.robot}: set {picked[0]['version']} → set {picked[1]['version']}")
        print("\n".join(diff_sets(a, b)) or "  identical parameters")
        return 0
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
        from robid_link.ident.report.figures import write_json

        write_json(args.json, {"robot": args.robot, "sets": [
            json.loads(s["body"]) for s in (picked or sets)]})
    return 0


def _drift(args: argparse.Namespace, res: list[dict[str, Any]]) -> int:
    from robid_link.ident.diagnosis import drift

    if args.compare:
        print(drift.compare(res, *args.compare))
        return 0
    if not args.robot:
        raise RobidError("--trend: name the robot with --robot NAME")
    tr = drift.trend(res, args.robot, sigma=args.sigma, min_change=args.min_change)
    shown = list(dict.fromkeys(f.parameter for f in tr.flags)) or [
        n for n in tr.values if drift.parameter_kind(n, tr.expressions[n])]
    print(tr.table(shown))
    if args.json:
        from robid_link.ident.report.figures import write_json

        write_json(args.json, tr.as_dict())
    if args.out:
        from robid_link.ident.report.figures import trend_figure

        print(f"wrote {trend_figure(tr, shown, Path(args.out))}")
    return 0


def _fake_controller(args: argparse.Namespace) -> int:
    import json
    import logging
    import signal
    import threading

    from robid_link.atomic import atomic_write
    from robid_link.ident.model.robot import load_robot
    from robid_link.link.daemon import setup_logging
    from robid_link.link.registry import fake_module
    from robid_link.safeyaml import load_yaml

    setup_logging("info")
    options: dict[str, Any] = {}
    for item in args.option:
        key, sep, value = item.partition("=")
        if not sep or not key.isidentifier():
            raise RobidError(f"--option {item!r}: expected KEY=VALUE")
        options[key] = load_yaml(value, f"--option {key}", error=RobidError)
    robot = load_robot(args.robot, args.lock, allow_unlimited=args.allow_unlimited)
    ctrl = fake_module("controller")
    truth = (fake_module("plant").load_truth(args.truth, robot) if args.truth
             else ctrl.default_truth(robot))
    if not Path(args.workdir).is_dir():
        raise RobidError(f"--workdir: {args.workdir}: folder not found")
    try:
        peer = ctrl.make_peer(args.driver, robot, truth, args.workdir, fault=args.fault,
                              fault_count=args.fault_count, seed=args.seed, exit_on_die=True,
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


