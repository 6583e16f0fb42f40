"""`robid fleet` over a synthetic plant (200 robots × 30 nights of identify results): seconds
per robot with a local Dask cluster of 1 and of 2 worker processes (scaling), the same tasks
run in this process as the baseline; and the store's write latency (one journaled experiment
step: UPDATE + journal INSERT, committed durably) on SQLite (WAL, synchronous=FULL) and on a
real PostgreSQL (fsync on, synchronous_commit on) started here on loopback."""

from __future__ import annotations

import json
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

from robid_link.fleet.analysis import analyse
from robid_link.fleet.engine import DaskEngine, InlineEngine
from robid_link.fleet.synthetic import PlantSpec, fill_store
from robid_link.link.store import Store
from robid_link.link.store import schema as sc

__all__ = ["bench_fleet", "report"]


class _BulkWriter:
    """Collects the plant's results and inserts them in one transaction (filling is not what
    is measured)."""

    def __init__(self) -> None:
        self.rows: list[dict[str, Any]] = []

    def add_result(self, run_id: str, robot: str, kind: str, record: dict[str, Any]) -> None:
        self.rows.append({"run_id": run_id, "robot": robot, "kind": kind, "model_version": "",
                          "time": time.time() + 1e-6 * len(self.rows),
                          "record": json.dumps(record)})


def _plant(folder: Path, robots: int, nights: int) -> dict[str, Any]:
    writer = _BulkWriter()
    planted = fill_store(writer, PlantSpec(robots=robots, nights=nights, wear_every=10))
    with Store(folder) as store, store.conn.begin():  # type: ignore[union-attr]
        store.conn.execute(sc.results.insert(), writer.rows)  # type: ignore[union-attr]
    return planted


def _timed_analysis(folder: Path, engine: Any) -> tuple[float, dict[str, Any]]:
    with Store(folder, readonly=True) as store:
        analyse(store, engine)  # warm: imports on the workers, the store's pages
        t0 = time.perf_counter()
        out = analyse(store, engine)
        return time.perf_counter() - t0, out


def _write_latency(store: Store, n: int) -> dict[str, float]:
    run = store.create_run("bench", "operator", {}, [("a", "rigid_body")])
    times = []
    for k in range(n):
        t0 = time.perf_counter()
        store.step(run, "a", "given", attempt=k, nonce=f"n{k}")
        times.append(time.perf_counter() - t0)
    times.sort()
    return {"median_ms": 1e3 * statistics.median(times),
            "p99_ms": 1e3 * times[min(len(times) - 1, int(0.99 * len(times)))], "n": n}


def bench_fleet(robots: int = 200, nights: int = 30, writes: int = 300) -> dict[str, Any]:
    out: dict[str, Any] = {"robots": robots, "nights": nights}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "plant"
        planted = _plant(folder, robots, nights)
        seconds, base = _timed_analysis(folder, InlineEngine())
        out["inline_s"] = seconds
        for workers in (1, 2):
            engine = DaskEngine(None, workers)
            try:
                t0 = time.perf_counter()
                seconds, rep = _timed_analysis(folder, engine)
                out[f"dask{workers}_s"] = seconds
                out[f"dask{workers}_with_start_s"] = time.perf_counter() - t0
            finally:
                engine.close()
            assert rep["flags"] == base["flags"] and rep["outliers"] == base["outliers"]
        out["flagged"] = len({f["robot"] for f in base["flags"]})
        out["wearing"] = len(planted["wearing"])
        with Store(Path(tmp) / "cell", robot="bench") as store:
            out["sqlite"] = _write_latency(store, writes)
    out["postgresql"] = _pg_latency(writes)
    return out


def _pg_latency(writes: int) -> dict[str, float] | str:
    try:
        import pytest  # the server helper skips through pytest when PostgreSQL is missing

        from tests.servers import postgres_server
    except ImportError as err:
        return f"not measured ({err})"
    try:
        with postgres_server() as pg, tempfile.TemporaryDirectory() as tmp:
            with Store(tmp, url=pg.create_database(), robot="bench") as store:
                return _write_latency(store, writes)
    except (pytest.skip.Exception, pytest.fail.Exception) as err:
        return f"not measured ({err})"


def report(r: dict[str, Any]) -> None:
    n = r["robots"]
    base = r["inline_s"]
    print(f"fleet report, {n} robots × {r['nights']} nights: in this process "
          f"{1e3 * base / n:.1f} ms/robot ({base:.1f} s); local Dask cluster, 1 worker "
          f"{1e3 * r['dask1_s'] / n:.1f} ms/robot, 2 workers {1e3 * r['dask2_s'] / n:.1f} "
          f"ms/robot ({r['dask1_s'] / r['dask2_s']:.2f}× from the second worker; with the "
          f"cluster's start {r['dask1_with_start_s']:.1f} s / {r['dask2_with_start_s']:.1f} s); "
          f"{r['flagged']} of {r['wearing']} wearing robots flagged")
    for name in ("sqlite", "postgresql"):
        v = r[name]
        if isinstance(v, str):
            print(f"store write latency, {name}: {v}")
        else:
            print(f"store write latency, {name:<10} (one journaled step, durable): median "
                  f"{v['median_ms']:.2f} ms, p99 {v['p99_ms']:.2f} ms over {v['n']}")


if __name__ == "__main__":
    report(bench_fleet())
