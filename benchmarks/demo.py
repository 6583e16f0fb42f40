"""`make bench --only demo`: `robid demo` (simulated cell, daemon, worker, diagnosis, report) on
a warm install — once to warm the imports' bytecode and numba's caches, then timed — against
the one-minute budget of `make demo`; also its CPU seconds (this process's children), which
say what the wall time would be on a machine nobody else uses."""

from __future__ import annotations

import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

__all__ = ["bench_demo", "report"]

BUDGET_S = 60.0


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def bench_demo() -> dict[str, float]:
    with tempfile.TemporaryDirectory() as tmp:
        argv = [sys.executable, "-m", "robid_link.cli", "demo", "--out"]
        subprocess.run([*argv, str(Path(tmp) / "warm")], check=True, capture_output=True,
                       cwd=tmp)
        cpu0, t0 = _children_cpu(), time.perf_counter()
        subprocess.run([*argv, str(Path(tmp) / "timed")], check=True, capture_output=True,
                       cwd=tmp)
        return {"wall_s": time.perf_counter() - t0, "cpu_s": _children_cpu() - cpu0}


def report(r: dict[str, float]) -> None:
    print(f"robid demo, warm: {r['wall_s']:.1f} s wall, {r['cpu_s']:.1f} s CPU (target wall "
          f"≤ {BUDGET_S:.0f} s)" + ("" if r["wall_s"] <= BUDGET_S else "  ✗"))
