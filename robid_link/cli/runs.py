"""``robid status``, ``results``: runs and their results, from the daemon over its control
socket or, when no daemon answers, from the store — or, with ``--store URL``, from a plant's
store (every robot); the run tables and the progress display that ``campaign start --wait``
and the demo print too."""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any

from robid_link.cli.types import (
    Command,
    bounded_int,
    figure_path,
    output_path,
    positive_float,
    refuse_given,
)
from robid_link.exceptions import DaemonUnreachable, RobidError

__all__ = ["COMMANDS", "wait_for_run", "format_runs", "format_results", "report_lines",
           "store_reader", "store_option", "open_store_option", "request"]


def request(path: str | Path, req: dict[str, Any], timeout_s: float = 30.0) -> dict[str, Any]:
    """One request to the daemon (``link.control.request``), imported when a command talks to
    it: ``robid identify`` and the other commands that never do skip asyncio's import."""
    from robid_link.link.control import request as send

    return send(path, req, timeout_s)


def _unreachable(err: DaemonUnreachable) -> str:
    """What the status line says when no answer came: absent and frozen differ."""
    text = str(err)
    if "no answer within" in text or "closed the connection" in text:
        return f"daemon not answering (running but busy or frozen: {text})"
    if "permission denied" in text:
        return f"daemon unknown ({text})"
    return "daemon not running"


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
        if run["state"] in ("completed", "failed", "cancelled", "interrupted"):
            if tty:
                stream.write("\n")
            if run["state"] == "failed":
                stream.write(f"run {run_id} failed: {run['error']}\n")
            elif run["state"] == "interrupted":
                stream.write(f"run {run_id} interrupted by a daemon restart: it waits for "
                             f"robid campaign resume {run_id}\n")
            return run
        time.sleep(poll_s)


def format_runs(runs: list[dict[str, Any]], robots: bool = False) -> str:
    """The run table; ``robots``: with the robot of each run (a plant's store)."""
    if not runs:
        return "no runs yet"
    who = f"{'robot':<14} " if robots else ""
    lines = [f"{'run_id':<24} {who}{'campaign':<12} {'trigger':<8} {'state':<10} progress"]
    for r in runs:
        p = r["progress"]
        tail = r.get("error") if r["state"] == "failed" else (r.get("step") or "")
        if r["state"] == "interrupted" and r.get("state_since"):
            since = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(r["state_since"]))
            tail = f"since {since}, {tail}"
        who = f"{r.get('robot') or '?':<14} " if robots else ""
        lines.append(f"{r['run_id']:<24} {who}{r['campaign']:<12} {r['trigger']:<8} "
                     f"{r['state']:<10} {p['stored']}/{p['total']} logs  {tail or ''}")
    return "\n".join(lines)


def _elasticity_lines(r: dict[str, Any], previous_k: dict[tuple[str, int], float]) -> list[str]:
    """K, D, f_res per joint of an elasticity result, K against the robot's previous run."""
    lines = []
    for res in r["record"].get("experiments", []):
        for j in res["result"].get("joints", []):
            key = (r["robot"], j["joint"])
            was = previous_k.get(key)
            change = f"  K vs previous {100 * (j['k'] - was) / was:+.1f} %" if was else ""
            previous_k[key] = j["k"]
            lines.append(f"{r['run_id']:<24} {r['robot']:<14} {'elastic':<9} joint "
                         f"{j['joint']}: K {j['k']:.4g}, D {j['d']:.4g}, f_res "
                         f"{j['f_res_hz']:.3g} Hz{change}")
    return lines


def _rmse_line(r: dict[str, Any], previous: dict[str, list[float]]) -> str:
    """Per-joint RMSE of an identification or diagnosis; an identification against the
    robot's previous one (the joint that changed most)."""
    rec = r["record"]
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
    return (f"{r['run_id']:<24} {r['robot']:<14} {r['kind']:<9} RMSE [{rmse}] N·m"
            + (f"  rel {100 * rel:.2f} %" if rel is not None else "") + extra)


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
        if r["kind"] == "elasticity":
            lines += _elasticity_lines(r, previous_k)
        elif "tracking" in rec:  # a verification path: how well the robot followed it
            tr = rec["tracking"]
            lines.append(f"{r['run_id']:<24} {r['robot']:<14} {r['kind']:<9} tool RMS "
                         f"{tr['tool_rms_mm']:.3f} mm, max {tr['tool_max_mm']:.3f} mm, after "
                         f"the stop {tr['residual_mm']:.3f} mm")
        else:
            lines.append(_rmse_line(r, previous))
    return "\n".join(lines)


# --------------------------------------------------------------------------------- status

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


def _robot_name(cfg: Any) -> str:
    """The robot's name as the store records it (``config.robot_name``)."""
    from robid_link.config import robot_name
    from robid_link.ident.model.robot import description_name

    return robot_name(cfg, description_name(cfg.robot, cfg.lock))


def store_reader(cfg: Any) -> Any:
    """The store of a daemon config, opened read-only while no daemon answers: its SQLite
    file, or its robot's view of the plant's store."""
    from robid_link.link.store import open_reader

    return open_reader(cfg, _robot_name(cfg))


def open_store_option(text: str, *, readonly: bool = True) -> Any:
    """``--store URL``: a plant's PostgreSQL store (or a state dir's SQLite), read-only
    unless ``readonly`` is False (a writer of results that is no daemon)."""
    from robid_link.link.store import Store

    url, folder = store_location(text)
    return Store(folder, url=url, readonly=readonly, exclusive=False)


def store_location(text: str) -> tuple[str | None, Path | None]:
    """``--store``'s (URL, state dir): one of them, checked; an error names ``--store``."""
    from robid_link.config import check_store_url
    from robid_link.link.store.postgres import is_store_url
    from robid_link.link.store.sqlite import DB_NAME

    if is_store_url(text):
        return check_store_url(text, "--store"), None
    expect = "expected postgresql://USER@HOST:PORT/DB or a daemon's state dir"
    if not text.strip() or "://" in text:
        raise RobidError(f"--store {text!r}: {expect}")
    folder = Path(text).expanduser()
    if not folder.is_dir():
        what = "no such folder" if not os.path.lexists(folder) else "not a folder"
        raise RobidError(f"--store {folder}: {what} ({expect})")
    if not (folder / DB_NAME).is_file():
        raise RobidError(f"--store {folder}: holds no store (no {DB_NAME}: not a daemon's "
                         "state dir, or no daemon ran there yet)")
    return None, folder


def store_option(p: argparse.ArgumentParser, *, required: bool = False) -> None:
    p.add_argument("--store", metavar="URL", required=required,
                   help="a plant's store: postgresql://USER@HOST:PORT/DB (the password from "
                   "PGPASSWORD or a PGPASSFILE), or a state dir")


def _config_or_store(p: argparse.ArgumentParser) -> None:
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--config", metavar="C", help="daemon config (YAML)")
    g.add_argument("--store", metavar="URL",
                   help="a plant's store instead: postgresql://USER@HOST:PORT/DB (the password "
                   "from PGPASSWORD or a PGPASSFILE), or a state dir; every robot's runs")


def _status_options(p: argparse.ArgumentParser) -> None:
    _config_or_store(p)
    p.add_argument("--limit", type=bounded_int(1, 100_000),
                   help="newest runs shown (default: 20 from a daemon, 50 from a store)")
    p.add_argument("--json", metavar="FILE", type=output_path("file", create_parents=True),
                   help="write the runs as JSON")


def _plant_status(args: argparse.Namespace) -> dict[str, Any]:
    """Every robot's runs and drift flags, from a plant's store."""
    from robid_link.link.campaign import drift_flags

    with open_store_option(args.store) as store:
        runs = store.runs(args.limit or 50)
        drift = [f"{r['robot']}: {f.message}" for r in store.robots()
                 for f in drift_flags(store, r["robot"])]
        return {"runs": runs, "status": f"plant store {store.where.removeprefix('store ')}: "
                f"{len(store.robots())} robot(s)", "drift": drift}


def _status(args: argparse.Namespace) -> int:
    from robid_link.config import load_daemon_config

    if args.store is not None:
        ans = _plant_status(args)
    else:
        cfg = load_daemon_config(args.config)
        try:
            ask = {"cmd": "status", **({"limit": args.limit} if args.limit else {})}
            ans = request(cfg.control_socket, ask)
        except DaemonUnreachable as err:
            print(f"robid: {err}; reading the store", file=sys.stderr)
            from robid_link.link.campaign import drift_flags

            with store_reader(cfg) as store:
                ans = {"runs": store.runs(args.limit or 50), "status": _unreachable(err),
                       "drift": [f.message for f in drift_flags(store, _robot_name(cfg))]}
    if args.json:
        from robid_link.atomic import write_json

        write_json(args.json, {"runs": ans["runs"], "status": ans["status"],
                               "drift": ans.get("drift", [])})
    print(f"{'daemon' if args.store is None else 'store'}: {ans['status']}")
    print(format_runs(ans["runs"], robots=args.store is not None))
    if args.store is None:
        for line in report_lines(cfg.state_dir, [r["run_id"] for r in ans["runs"]
                                                 if r["state"] == "completed"]):
            print(line)
    for line in ans.get("drift", []):
        print(f"drift: {line}")
    return 0


# -------------------------------------------------------------------------------- results

def _results_options(p: argparse.ArgumentParser) -> None:
    _config_or_store(p)
    p.add_argument("--robot", metavar="NAME", help="only this robot's results")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--trend", action="store_true",
                   help="with --robot: each parameter over the stored runs, drift flagged")
    g.add_argument("--compare", nargs=2, metavar=("ROBOT_A", "ROBOT_B"),
                   help="the latest identification of two robots of one type side by side")
    p.add_argument("--sigma", type=positive_float(1e3),
                   help="drift flag: change in combined standard errors (default 5)")
    p.add_argument("--min-change", type=positive_float(10.0), metavar="FRACTION",
                   help="drift flag: change of the baseline, at the lower end of its 95 %% "
                   "interval (default 0.10)")
    p.add_argument("--json", metavar="FILE", type=output_path("file", create_parents=True),
                   help="write the trend as JSON")
    p.add_argument("--out", metavar="PNG", type=figure_path(),
                   help="plot the trend of the flagged (or all physically readable) parameters")


def _results_check(args: argparse.Namespace) -> None:
    if args.trend and not args.robot:
        raise RobidError("--trend: name the robot with --robot NAME")
    if args.compare:
        refuse_given(args, ["--robot"], "not used with --compare (it names its two robots)")
    if not args.trend:
        refuse_given(args, ["--sigma", "--min-change", "--json", "--out"],
                     "applies to --trend only")


def _results(args: argparse.Namespace) -> int:
    from robid_link.config import load_daemon_config

    robot = None if args.compare else args.robot
    if args.store is not None:
        with open_store_option(args.store) as store:
            res = store.results(robot)
    else:
        cfg = load_daemon_config(args.config)
        try:
            res = request(cfg.control_socket, {"cmd": "results", "robot": robot})["results"]
        except DaemonUnreachable:
            with store_reader(cfg) as store:
                res = store.results(robot)
    if args.trend or args.compare:
        return _drift(args, res)
    print(format_results(res))
    if args.store is None:  # reports live on the cell's disk
        for line in report_lines(cfg.state_dir, [r["run_id"] for r in reversed(res)]):
            print(line)
    return 0


def _drift(args: argparse.Namespace, res: list[dict[str, Any]]) -> int:
    from robid_link.ident.diagnosis import drift

    if args.compare:
        print(drift.compare(res, *args.compare))
        return 0
    tr = drift.trend(res, args.robot, sigma=5.0 if args.sigma is None else args.sigma,
                     min_change=0.10 if args.min_change is None else args.min_change)
    shown = list(dict.fromkeys(f.parameter for f in tr.flags)) or [
        n for n in tr.values if drift.parameter_kind(n, tr.expressions[n])]
    print(tr.table(shown))
    if args.json:
        from robid_link.atomic import write_json

        write_json(args.json, tr.as_dict())
    if args.out:
        from robid_link.ident.report.figures import trend_figure

        print(f"wrote {trend_figure(tr, shown, Path(args.out))}")
    return 0


COMMANDS = (
    Command(name="status", help="runs, their state and progress",
            options=_status_options, run=_status),
    Command(name="results", help="identification results across runs and robots",
            options=_results_options, check=_results_check, run=_results),
)
