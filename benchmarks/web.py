"""`make bench --only web`: ``GET /api/runs`` of the operator's page with 1,000 runs stored
(budget 50 ms; median of 30 requests over HTTP on loopback, the default page of the newest
200 runs and all 1,000), against a bare ``GET /api/params`` of the same server."""

from __future__ import annotations

import asyncio
import statistics
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

import yaml

__all__ = ["bench_web", "report"]

RUNS = 1000
BUDGET_MS = 50.0


def _store(tmp: Path) -> Path:
    from robid_link.link.store import Store

    doc = {"robot": str(Path(__file__).resolve().parent.parent / "examples" / "robots" /
                        "arm3.yaml"),
           "state_dir": str(tmp / "state"), "control_socket": str(tmp / "ctl.sock"),
           "driver": {"name": "file_share", "share": str(tmp)},
           "campaigns": {"nightly": {"experiments": ["rigid_body"]}}}
    (tmp / "daemon.yaml").write_text(yaml.safe_dump(doc))
    with Store(tmp / "state") as store:
        for k in range(RUNS):
            run_id = store.create_run("nightly", "timer", {}, [("rigid_body", "rigid_body"),
                                                               ("friction", "friction")])
            store.set_run(run_id, "completed" if k < RUNS - 2 else "running", step="identifying")
            store.add_result(run_id, "arm3", "identify", {"rmse": [0.5, 0.4, 0.3],
                                                         "parameters": []})
    return tmp / "daemon.yaml"


def _median_ms(url: str, n: int = 30) -> float:
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        with urllib.request.urlopen(url, timeout=30) as r:
            r.read()
        times.append(1000.0 * (time.perf_counter() - t0))
    return statistics.median(times)


def bench_web() -> dict[str, float]:
    from robid_link.config import load_daemon_config
    from robid_link.web.server import WebServer

    with tempfile.TemporaryDirectory() as tmp:
        cfg = load_daemon_config(_store(Path(tmp)))
        server = WebServer(cfg, "127.0.0.1:0", "arm3")
        loop = asyncio.new_event_loop()
        ready, stop = threading.Event(), asyncio.Event()

        async def main() -> None:
            async with server:
                ready.set()
                await stop.wait()

        thread = threading.Thread(target=loop.run_until_complete, args=(main(),))
        thread.start()
        ready.wait(30)
        try:
            _median_ms(server.url + "api/runs", 3)  # warm
            out = {"runs_ms": _median_ms(server.url + "api/runs"),
                   "all_ms": _median_ms(server.url + f"api/runs?limit={RUNS}"),
                   "base_ms": _median_ms(server.url + "api/params")}
        finally:
            loop.call_soon_threadsafe(stop.set)
            thread.join(30)
            loop.close()
    return out


def report(r: dict[str, float]) -> None:
    print(f"web page, GET /api/runs with {RUNS:,} runs stored: {r['runs_ms']:.1f} ms median "
          f"(newest 200; budget {BUDGET_MS:.0f} ms, {r['runs_ms'] / BUDGET_MS:.2f}× of it), "
          f"all {RUNS:,}: {r['all_ms']:.1f} ms; a bare GET /api/params {r['base_ms']:.1f} ms")
