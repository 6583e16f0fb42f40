"""``robid demo``: the whole job on a simulated cell (the job itself: ``robid_link.demo``)."""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from robid_link.cli.types import Command, known_peer, output_path

__all__ = ["COMMANDS"]


def _demo_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", metavar="FILE", type=output_path("file", create_parents=True),
                   help="write the run's result as JSON")
    p.add_argument("--out", metavar="DIR", default="demo-out", type=output_path("dir"),
                   help="report folder (default demo-out)")
    p.add_argument("--quick", action="store_true",
                   help="a shorter excitation (20 s, a lighter optimisation): the same story in "
                   "about a third of the time")
    p.add_argument("--driver", default="file_share",
                   help="the controller link to run the demo over (its fake peer plays the "
                   "cell): file_share, abb_rws, canopen_drives, modbus_plc, serial_line, ur_rtde")


def _demo(args: argparse.Namespace) -> int:
    from robid_link.demo import run_demo

    with tempfile.TemporaryDirectory(prefix="robid-demo-") as tmp:
        return run_demo(Path(tmp), Path(args.out), args.json, driver=args.driver,
                        quick=args.quick)


COMMANDS = (
    Command(name="demo", help="the whole job on a simulated cell: fake controller, daemon, "
            "campaign, identification, diagnosis, report", options=_demo_options,
            check=known_peer, run=_demo),
)
