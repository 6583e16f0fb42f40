"""give → take hand-off latency of the file-share driver over a local folder: the time from the
controller's atomic rename of its 'done' to the daemon's ``take_done`` returning, for the
inotify observer, the polling fallback, and a 1-second polling loop like the original tool's."""

from __future__ import annotations

import asyncio
import os
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from robid_link.atomic import fsync_dir
from robid_link.drivers.file_share import FileShareDriver, done_text

__all__ = ["bench_handoff"]

SHA = "0" * 64


def _write_done(sem: Path, name: str, stamp: list[float]) -> None:
    """The controller's side: temp file, fsync, then the rename that makes it visible."""
    tmp = sem / f".{name}.tmp"
    with open(tmp, "wb") as fh:
        fh.write(done_text(SHA, 0))
        fh.flush()
        os.fsync(fh.fileno())
    stamp.append(time.perf_counter())
    os.replace(tmp, sem / name)
    fsync_dir(sem)


async def _driver_latencies(share: Path, observer: str, n: int) -> list[float]:
    driver = FileShareDriver(share=share, observer=observer, poll_interval_s=0.1,
                             canary_interval_s=0)
    out = []
    rng = np.random.default_rng(0)
    async with driver:
        for i in range(n):
            nonce = f"n{i}"
            waiter = asyncio.create_task(driver.take_done("exp", nonce, timeout_s=10))
            # the answer comes at a random phase of the polling observer's cycle
            await asyncio.sleep(0.005 + (rng.uniform(0, 0.1) if observer == "polling" else 0))
            stamp: list[float] = []
            writer = threading.Thread(target=_write_done,
                                      args=(share / "sem", f"exp.{nonce}.done", stamp))
            writer.start()
            await waiter
            t1 = time.perf_counter()
            await asyncio.to_thread(writer.join)
            out.append(t1 - stamp[0])
    return out


async def _one_second_loop(share: Path, n: int) -> list[float]:
    """The original semTake: look for the file once a second."""
    out = []
    for i in range(n):
        path = share / "sem" / f"old.n{i}.done"
        stamp: list[float] = []
        delay = (i * 0.37) % 1.0  # the answer arrives at any phase of the loop
        timer = threading.Timer(delay, _write_done, args=(share / "sem", path.name, stamp))
        timer.start()
        while not path.exists():
            await asyncio.sleep(1.0)
        out.append(time.perf_counter() - stamp[0])
        timer.join()
    return out


def bench_handoff(n_inotify: int = 300, n_polling: int = 40, n_loop: int = 8
                  ) -> dict[str, dict[str, float]]:
    import logging

    logging.getLogger("robid").setLevel(logging.ERROR)
    res = {}
    with tempfile.TemporaryDirectory(dir=os.environ.get("ROBID_BENCH_DIR")) as tmp:
        shares = []
        for k in range(3):  # a fresh share per method: no answers left from another
            shares.append(Path(tmp) / f"share{k}")
            for d in ("inbox", "outbox", "sem"):
                (shares[-1] / d).mkdir(parents=True)
        for name, coro in (("inotify", _driver_latencies(shares[0], "inotify", n_inotify)),
                           ("polling 0.1 s", _driver_latencies(shares[1], "polling", n_polling)),
                           ("1 s loop (original)", _one_second_loop(shares[2], n_loop))):
            lat = np.array(asyncio.run(coro)) * 1e3
            res[name] = {"median_ms": float(np.median(lat)),
                         "p99_ms": float(np.percentile(lat, 99)), "n": float(lat.size)}
    return res
