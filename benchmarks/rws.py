"""The RWS link on loopback against the file share, measured in the same run: give→take
hand-off (the controller writes ``robid_done`` → ``take_done`` returns, through the websocket
event and one GET) and log transfer through the file service (a 60 s 6-axis 1 kHz log)."""

from __future__ import annotations

import asyncio
import hashlib
import logging
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from robid_link.drivers.file_share import FileShareDriver, log_name
from robid_link.drivers.rws_api import done_value, log_file, size_value
from robid_link.fakes.controller import default_truth, log_csv, make_peer
from robid_link.ident.model.robot import load_robot
from robid_link.link import registry
from robid_link.link.driver import Done

__all__ = ["bench_rws"]

ROBOT = Path(__file__).resolve().parent.parent / "examples" / "robots" / "industrial6.yaml"
SHA = "0" * 64


def _big_log(seconds: float = 60.0, rate: float = 1000.0) -> bytes:
    rng = np.random.default_rng(0)
    t = np.arange(int(seconds * rate)) / rate
    return log_csv(t, rng.normal(size=(t.size, 6)), 50 * rng.normal(size=(t.size, 6)))


async def _handoffs(driver: Any, peer: Any, n: int) -> list[float]:
    out = []
    async with driver:
        for i in range(n):
            nonce = f"n{i}"
            peer.vars.update(robid_exp="exp", robid_nonce=nonce, robid_done="", robid_size="")
            peer.exec_state = "running"
            waiter = asyncio.create_task(driver.take_done("exp", nonce, timeout_s=10))
            while not any(s["ws"] is not None for s in list(peer._subs.values())):
                await asyncio.sleep(0.001)  # subscribed: the daemon is waiting
            await asyncio.sleep(0.005)
            stamp: list[float] = []

            def answer(nonce: str = nonce, stamp: list[float] = stamp) -> None:
                stamp.append(time.perf_counter())
                peer._set_var("robid_size", size_value(nonce, 0))
                peer._set_var("robid_done", done_value(nonce, SHA))

            threading.Thread(target=peer._in_loop, args=(answer,)).start()
            await waiter
            out.append(time.perf_counter() - stamp[0])
    peer.exec_state = "stopped"
    return out


async def _fetches(driver: Any, done: Done, n: int) -> list[float]:
    out = []
    async with driver:
        for _ in range(n):
            t0 = time.perf_counter()
            await driver.fetch_logs(done)
            out.append(time.perf_counter() - t0)
    return out


def _stats(lat: list[float]) -> dict[str, float]:
    a = np.array(lat) * 1e3
    return {"median_ms": float(np.median(a)), "p99_ms": float(np.percentile(a, 99)),
            "n": float(a.size)}


def bench_rws(n_handoff: int = 200, n_fetch: int = 5) -> dict[str, Any]:
    """Hand-off median/p99 per RWS version and the file share (inotify); log MB/s each."""
    from benchmarks.handoff import bench_handoff

    logging.getLogger("robid").setLevel(logging.ERROR)
    robot = load_robot(ROBOT)
    data = _big_log()
    done = Done("exp", "nf", hashlib.sha256(data).hexdigest(), len(data))
    res: dict[str, Any] = {"log_mb": len(data) / 1e6}
    for version in (1, 2):
        with tempfile.TemporaryDirectory() as tmp:
            peer = make_peer("abb_rws", robot, default_truth(robot), Path(tmp), version=version)
            with peer:
                remote = peer.home / log_file("exp", "nf")[len("$HOME/"):]
                remote.write_bytes(data)
                opts = peer.driver_options()
                lat = asyncio.run(_handoffs(registry.make_driver(opts), peer, n_handoff))
                t = asyncio.run(_fetches(registry.make_driver(opts), done, n_fetch))
            label = f"RWS {version}.0 ({'https' if peer.tls else 'http'})"
            res[label] = {**_stats(lat), "mb_s": len(data) / 1e6 / float(np.median(t))}
    with tempfile.TemporaryDirectory() as tmp:
        share = Path(tmp)
        for d in ("inbox", "outbox", "sem"):
            (share / d).mkdir()
        (share / "outbox" / log_name("exp", "nf")).write_bytes(data)
        fs = FileShareDriver(share=share, canary_interval_s=0)
        t = asyncio.run(_fetches(fs, done, n_fetch))
    h = bench_handoff(n_inotify=n_handoff, n_polling=2, n_loop=1)["inotify"]
    res["file share (inotify)"] = {**h, "mb_s": len(data) / 1e6 / float(np.median(t))}
    return res
