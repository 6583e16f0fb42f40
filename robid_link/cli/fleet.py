"""``robid fleet``: a plant's robots from its store — trends per model version, drift and wear
flags with their evidence, outliers of each robot type — and ``robid fleet reidentify``: many
robots' stored logs identified with another model, stored as a new model version. Tasks run
on Dask: a LocalCluster, or the scheduler named by ``--scheduler``."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from robid_link.cli.runs import store_option
from robid_link.cli.types import Command, bounded_int, output_path, positive_float
from robid_link.exceptions import RobidError

__all__ = ["COMMANDS"]


def _engine_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scheduler", metavar="tcp://HOST:PORT",
                   help="a Dask scheduler to run the tasks on (default: a local cluster)")
    p.add_argument("--workers", type=bounded_int(1, 256), metavar="N",
                   help="worker processes of the local cluster (default: one per core)")


def _engine_check(args: argparse.Namespace) -> None:
    if args.scheduler and args.workers:
        raise RobidError("--workers: the named scheduler has its own workers; give --workers "
                         "only without --scheduler")
    if args.scheduler and not args.scheduler.startswith(("tcp://", "tls://", "inproc://",
                                                         "ucx://", "ws://", "wss://")):
        raise RobidError(f"--scheduler {args.scheduler}: expected an address like "
                         "tcp://HOST:8786")


def _open_store(text: str, *, write: bool = False) -> Any:
    from robid_link.cli.runs import open_store_option

    return open_store_option(text, readonly=not write)


# ----------------------------------------------------------------------------- report

def _report_options(p: argparse.ArgumentParser) -> None:
    store_option(p)
    _engine_options(p)
    p.add_argument("--json", metavar="FILE", type=output_path("file", create_parents=True),
                   help="write the fleet report as JSON")
    p.add_argument("--out", metavar="DIR", type=output_path("dir"),
                   help="write fleet.json, fleet.txt and a trend figure per flagged robot")
    p.add_argument("--sigma", type=positive_float(1e3), default=5.0,
                   help="drift flag: change in combined standard errors (default 5)")
    p.add_argument("--min-change", type=positive_float(10.0), default=0.10, metavar="FRACTION",
                   help="drift flag: change of the baseline at the lower end of its 95 %% "
                   "interval (default 0.10)")
    p.add_argument("--outlier-z", type=positive_float(1e3), default=3.5, metavar="Z",
                   help="outlier: distance from the type's median in robust standard "
                   "deviations, 1.4826·MAD (default 3.5)")


def _report_check(args: argparse.Namespace) -> None:
    if args.store is None:
        raise RobidError("--store: name the plant's store (postgresql://USER@HOST:PORT/DB or "
                         "a state dir)")
    _engine_check(args)


def _report(args: argparse.Namespace) -> int:
    from robid_link.fleet.analysis import analyse, summary
    from robid_link.fleet.engine import make_engine

    with _open_store(args.store) as store, make_engine(args.scheduler, args.workers) as engine:
        report = analyse(store, engine, sigma=args.sigma, min_change=args.min_change,
                         z_limit=args.outlier_z)
        report["engine"] = engine.describe()
    text = summary(report)
    print(text)
    ran = report["engine"]
    on = ran.get("scheduler") or "this process"
    print(f"{ran['tasks']} tasks on {on} ({ran.get('workers', 1)} worker(s)"
          + (", local cluster)" if ran.get("local_cluster") else ")"))
    if args.json:
        _write_json(Path(args.json), report)
    if args.out:
        _write_out(Path(args.out), report, text)
    return 0


def _write_json(path: Path, doc: dict[str, Any]) -> None:
    from robid_link.atomic import atomic_write

    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, json.dumps(doc, indent=1, allow_nan=False).encode())


def _write_out(folder: Path, report: dict[str, Any], text: str) -> None:
    """fleet.json, fleet.txt and, per robot and model version with flags, its trend figure
    of the flagged parameters."""
    from robid_link.atomic import atomic_write
    from robid_link.fleet.figures import flagged_trend_figures

    folder.mkdir(parents=True, exist_ok=True)
    _write_json(folder / "fleet.json", report)
    atomic_write(folder / "fleet.txt", (text + "\n").encode())
    figures = flagged_trend_figures(report, folder)
    print(f"wrote {folder / 'fleet.json'}, {folder / 'fleet.txt'} and {len(figures)} "
          "trend figure(s)")


# ----------------------------------------------------------------------------- reidentify

def _reidentify_options(p: argparse.ArgumentParser) -> None:
    store_option(p, required=True)
    p.add_argument("--model", required=True, metavar="MODEL.yaml",
                   help="the model to identify with (a model file: effects:)")
    p.add_argument("--robot", default="*", metavar="GLOB",
                   help="robots whose runs are re-identified (default: all)")
    p.add_argument("--since", metavar="DATE", help="only runs created on or after DATE "
                   "(2025-03-01 or 2025-03-01T18:00)")
    p.add_argument("--version", metavar="NAME", help="the model version the results are "
                   "stored as (default: the model file's stem and hash)")
    _engine_options(p)
    p.add_argument("--json", metavar="FILE", type=output_path("file", create_parents=True),
                   help="write the summary per robot as JSON")


def _reidentify(args: argparse.Namespace) -> int:
    from robid_link.fleet.engine import make_engine
    from robid_link.fleet.reidentify import (
        default_version,
        parse_since,
        plan_jobs,
        reidentify,
    )
    from robid_link.jobs import ModelCheckJob
    from robid_link.link.worker import run_here

    since = parse_since(args.since) if args.since else None
    model = Path(args.model)
    run_here(ModelCheckJob(str(model), ()))  # the model file, checked before any task starts
    if args.version is not None and not args.version.strip():
        raise RobidError("--version: expected a name")
    with _open_store(args.store, write=True) as store:
        jobs = plan_jobs(store, model, args.robot, since)
        version = args.version or default_version(model, jobs[0]["model_text"])
        print(f"re-identifying {len(jobs)} run(s) of "
              f"{len({j['robot'] for j in jobs})} robot(s) as model version {version}")
        with make_engine(args.scheduler, args.workers) as engine:
            done = reidentify(engine, jobs, store.add_result, version)
            done["engine"] = engine.describe()
    for robot, r in done["robots"].items():
        rel = (f", mean relative error {100 * r['relative_error']:.2f} %"
               if r["relative_error"] is not None else "")
        print(f"{robot}: {r['identified']} run(s) stored as {version}{rel}"
              + (f", {len(r['failed'])} failed" if r["failed"] else ""))
    print(f"see them beside the campaigns' own: robid fleet --store {args.store}")
    if args.json:
        _write_json(Path(args.json), done)
    return 0


COMMANDS = (
    Command(name="fleet", help="a plant's robots: trends, drift, outliers (Dask)",
            options=_report_options, check=_report_check, run=_report,
            commands=(
                Command(name="reidentify", help="re-identify stored logs of many robots "
                        "with another model, stored as a new model version",
                        options=_reidentify_options, check=_engine_check,
                        run=_reidentify),
            )),
)
