"""`make bench --only consistent`: the physically consistent estimator against OLS on one log.

Both run in-process on the same 60 s, 6-axis, 1 kHz log (median of 3; warm caches first),
each with its held-out figures (``to_dict``), as ``robid identify`` prints them.
"""

from __future__ import annotations

import tempfile
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np

from robid_link.ident.fit.identify import identify, load_logs
from robid_link.ident.model.effects import DEFAULT_MODEL
from robid_link.ident.model.robot import load_robot

__all__ = ["bench_consistent", "report"]


def bench_consistent(robot_path: Path, make_npz: Callable[[Path, int, float], None],
                     seconds: float = 60.0) -> dict[str, float]:
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "consistent.npz"
        make_npz(data, int(seconds * 1000), 1000.0)
        robot = load_robot(robot_path)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            logs = load_logs(robot, [data])
            identify(robot, logs, DEFAULT_MODEL, interval=20)
            identify(robot, logs, DEFAULT_MODEL, interval=20, method="consistent")
            t_ols, t_cons = [], []
            for _ in range(3):  # median of 3: the machine is shared
                t0 = time.perf_counter()
                ols = identify(robot, logs, DEFAULT_MODEL)
                ols.to_dict()
                t_ols.append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                cons = identify(robot, logs, DEFAULT_MODEL, method="consistent")
                cons.to_dict()
                t_cons.append(time.perf_counter() - t0)
    return {"ols_s": float(np.median(t_ols)), "consistent_s": float(np.median(t_cons)),
            "ratio": float(np.median(np.array(t_cons) / np.array(t_ols))),
            "ols_rel": float(ols.validation.relative_error or 0.0),
            "consistent_rel": float(cons.validation.relative_error or 0.0),
            "n_evaluations": float(cons.consistent.n_evaluations)}


def report(r: dict[str, float]) -> None:
    print(f"consistent (log-Cholesky + CAD prior, λ by blocked CV), 6 axes, 60 s at 1 kHz: "
          f"{r['consistent_s']:.2f} s vs OLS {r['ols_s']:.2f} s → {r['ratio']:.1f}× (target ≤ 2×); "
          f"validation {100 * r['consistent_rel']:.2f} % vs OLS {100 * r['ols_rel']:.2f} %; "
          f"{r['n_evaluations']:.0f} objective evaluations")
