"""The built wheel installs only under ``robid_link`` (no top-level ``drivers``/``fakes``) and
ships what ``robid demo`` and the systemd route need: examples, units, fakes, drivers, the
report's template and scripts."""

from __future__ import annotations

import sys
import zipfile

NEEDED = ("robid_link/examples/robots/industrial6.yaml", "robid_link/examples/link/daemon.yaml",
          "robid_link/systemd/robid-link.service", "robid_link/fakes/plant.py",
          "robid_link/fakes/controller.py", "robid_link/drivers/file_share.py",
          "robid_link/drivers/rapid.py", "robid_link/cli/__init__.py",
          "robid_link/cli/__main__.py", "robid_link/py.typed",
          "robid_link/ident/report/templates/report.html.j2",
          "robid_link/ident/report/static/uPlot.iife.min.js",
          "robid_link/ident/report/static/report.js",
          "robid_link/ident/report/static/LICENSE.uPlot",
          "robid_link/web/templates/runs.html.j2", "robid_link/web/server.py",
          "robid_link/fakes/canopen/cia402_drive.eds", "robid_link/fakes/rws/peer.py",
          "robid_link/drivers/canopen/drives.py", "robid_link/link/store/sql.py",
          "robid_link/fleet/analysis.py")


def main(path: str) -> int:
    names = zipfile.ZipFile(path).namelist()
    tops = {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")}
    missing = [n for n in NEEDED if n not in names]
    if tops != {"robid_link"} or missing:
        print(f"{path}: top-level packages {sorted(tops)}; missing {missing}")
        return 1
    print(f"{path}: {len(names)} files, all under robid_link/")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
