"""The Universal Robots link under load: a program of ``seconds`` streamed over RTDE at 500 Hz
by the fake UR controller in its own process while identification runs back to back in other
processes (the worker's load on the same cores). Packages the controller numbered as sent are
compared with what the driver received and recorded; inter-arrival p99 and maximum. The fake
shares the cores with the load, so the driver waits up to 5 s (not 1 s) before it calls the
stream stopped; holes are packages the fake's own host was too late to send (none below 5 s)."""

from __future__ import annotations

import asyncio
import json
import re
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from robid_link.ident.excite import excitation as ex
from robid_link.ident.excite import program as pg
from robid_link.ident.model.robot import load_robot
from robid_link.jobs import RobotInfo
from robid_link.link import registry

__all__ = ["bench_rtde", "report"]

ROOT = Path(__file__).resolve().parent.parent
ROBOT = ROOT / "examples" / "robots" / "industrial6.yaml"
TRUTH = ("rate_hz: 500\nnoise: {tau: 0.2, q_resolution: 6.0e-6}\n"
         "effects: [{name: viscous, fv: 2.0}, {name: coulomb, fc: 1.5}]\n")


def _program(seconds: float) -> Any:
    """A slow six-joint sway from rest to rest: 0.1 Hz, up to 0.3 rad under a sin² envelope
    over the whole program (smooth in every derivative: coarse knots, a small script)."""
    robot = load_robot(ROBOT)
    t = np.arange(0.0, seconds, 0.02)
    ramp = np.sin(np.pi * t / t[-1]) ** 2
    q = 0.3 * np.sin(2 * np.pi * 0.1 * t)[:, None] * ramp[:, None] * \
        np.array([1.0, -0.5, 0.5, 1.0, -1.0, 1.0]) + np.array([0, -0.5, 0.5, 0, 0.5, 0])
    return robot, pg.make_program(robot, ex.Trajectory(t, q, 50.0, "custom", robot.name),
                                  "rtde_bench")


def _identify_loop(data: Path, stop: threading.Event, runs: list[float]) -> None:
    """``robid identify`` on ``data`` in another process, again and again, until ``stop``."""
    while not stop.is_set():
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "robid_link.cli", "identify", "--robot",
                        str(ROBOT), "--data", str(data)], capture_output=True, check=False)
        runs.append(time.perf_counter() - t0)


async def _stream(options: dict[str, Any], robot: Any, program: Any, seconds: float
                  ) -> dict[str, float]:
    # the fake controller shares these two cores with the load (a real one does not): a stall
    # of its own process must not read as a stopped stream; the gaps are reported instead
    driver: Any = registry.make_driver({**options, "start_timeout_s": 600.0,
                                        "stream_timeout_s": 5.0})
    driver.bind_robot(RobotInfo.of(robot))
    async with driver:
        await driver.put_program(program)
        await driver.give_ready("rtde_bench", "b1")
        done = await driver.take_done("rtde_bench", "b1", timeout_s=seconds + 900)
        data = await driver.fetch_logs(done)
        await driver.acknowledge(done)
    return {**driver.last_stats, "log_mb": len(data) / 1e6}


def bench_rtde(seconds: float = 600.0) -> dict[str, Any]:
    from benchmarks.run import _make_npz

    robot, program = _program(seconds)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        # made before the stream: its numba kernels hold this process's interpreter lock
        _make_npz(work / "load.npz", 60_000, 1000.0)
        (work / "cell").mkdir()
        (work / "truth.yaml").write_text(TRUTH)
        ready, log = work / "ready.json", work / "controller.log"
        stop = threading.Event()
        runs: list[float] = []
        with open(log, "wb") as out:
            peer = subprocess.Popen(
                [sys.executable, "-m", "robid_link.cli", "fake-controller", "--driver", "ur_rtde",
                 "--workdir", str(work / "cell"), "--robot", str(ROBOT), "--truth",
                 str(work / "truth.yaml"), "--ready-file", str(ready)],
                stdout=out, stderr=subprocess.STDOUT)
            load = threading.Thread(target=_identify_loop,
                                    args=(work / "load.npz", stop, runs),
                                    name="bench-identify")
            try:
                end = time.monotonic() + 60
                while not ready.exists():
                    if peer.poll() is not None or time.monotonic() > end:
                        raise RuntimeError(f"fake UR controller did not start: {log.read_text()}")
                    time.sleep(0.05)
                load.start()
                stats = asyncio.run(_stream(json.loads(ready.read_text()), robot, program,
                                            seconds))
            finally:
                stop.set()
                if load.is_alive():
                    load.join()
                peer.terminate()
                peer.wait(30)
        m = re.findall(r"RTDE client closed: (\d+) packages sent, (\d+) skipped", log.read_text())
    if not m:
        raise RuntimeError("the fake controller did not report what it sent")
    sent, skipped = (int(x) for x in m[-1])
    return {**stats, "seconds": seconds, "sent": sent, "skipped_by_controller": skipped,
            "lost": sent - int(stats["packages"]), "identify_runs": len(runs)}


def report(r: dict[str, Any]) -> None:
    print(f"RTDE 500 Hz, {r['seconds']:.0f} s program, {r['identify_runs']} identifications "
          f"alongside: {r['lost']} of {r['sent']} packages lost (goal 0), "
          f"{r['path_missed']:.0f} holes on the path, {r['skipped_by_controller']} skipped by "
          f"the fake controller's host; inter-arrival p99 {r['p99_inter_arrival_ms']:.2f} ms, "
          f"max {r['max_inter_arrival_ms']:.1f} ms (period 2 ms); {r['rows']:.0f} rows, "
          f"{r['log_mb']:.1f} MB log")
