"""Modbus PLC and serial line against the file share, in one run on loopback: the give→take
hand-off (the controller's answer → ``take_done`` returning) and the transfer rate of a 60 s
6-axis 1 kHz log (``fetch_logs``, checksum included). A pty ignores the baud rate: the serial
figures at 115200 and 921600 baud are paced by the fake controller (10 bits per byte). At
921600 baud the whole log travels compressed (zlog1, the driver's default) and is timed end to
end; the plain GET chunks (``compress: false``, an older controller) and 115200 baud are timed
over a slice of the log and extrapolated; "unpaced" is the pty's own speed."""

from __future__ import annotations

import asyncio
import hashlib
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from robid_link.fakes.controller import default_truth, log_csv, make_peer
from robid_link.ident.excite import excitation as ex
from robid_link.ident.excite import program as pg
from robid_link.ident.model.robot import load_robot
from robid_link.jobs import RobotInfo
from robid_link.link import registry
from robid_link.link.driver import Done, Driver

__all__ = ["bench_handoffs", "bench_transfer", "sixty_second_log"]

ROOT = Path(__file__).resolve().parent.parent
ARM3 = ROOT / "examples" / "robots" / "arm3.yaml"


def sixty_second_log() -> bytes:
    """A 6-axis log, 60 s at 1 kHz, in the project's CSV format (what a real cell records)."""
    rng = np.random.default_rng(0)
    t = np.arange(60_000) / 1000.0
    q = np.sin(np.outer(t, [0.3, 0.5, 0.7, 1.1, 1.3, 1.7])) + 1e-6 * rng.normal(size=(60_000, 6))
    tau = 40 * np.cos(np.outer(t, [0.3, 0.5, 0.7, 1.1, 1.3, 1.7])) + rng.normal(size=(60_000, 6))
    return log_csv(t, q, tau)


def _cell(name: str, work: Path, **opts: Any) -> tuple[Any, Driver]:
    robot = load_robot(ARM3)
    peer = make_peer(name, robot, default_truth(robot, rate_hz=100.0), work, **opts)
    peer.start()
    driver = registry.make_driver(peer.driver_options())
    driver.bind_robot(RobotInfo.of(robot))
    return peer, driver


async def _handoffs(peer: Any, driver: Driver, n: int) -> list[float]:
    robot = load_robot(ARM3)
    t = np.arange(0.0, 0.05, 0.01)
    prog = pg.make_program(robot, ex.Trajectory(t, np.zeros((len(t), 3)), 100.0, "custom",
                                                robot.name), "bench")
    out = []
    async with driver:
        await driver.put_program(prog)
        for i in range(n + 3):  # the first three warm up
            nonce = f"{0x1000 + i:08x}"
            await driver.give_ready("bench", nonce)
            done = await driver.take_done("bench", nonce, timeout_s=30)
            t1 = time.perf_counter()
            await driver.acknowledge(done)
            if i >= 3:
                out.append(t1 - peer.answer_times[nonce])
    return out


def bench_handoffs(n: int = 60) -> dict[str, dict[str, float]]:
    """Median and p99 of the hand-off per driver, the file share's inotify path alongside."""
    from benchmarks.handoff import _driver_latencies

    res: dict[str, list[float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        share = Path(tmp) / "share"
        share.mkdir()
        res["file_share (inotify)"] = asyncio.run(_driver_latencies(share, "inotify", n))
        for name in ("modbus_plc", "serial_line"):
            work = Path(tmp) / name
            work.mkdir()
            peer, driver = _cell(name, work)
            try:
                res[name] = asyncio.run(_handoffs(peer, driver, n))
            finally:
                peer.stop()
    return {k: {"median_ms": 1e3 * float(np.median(v)),
                "p99_ms": 1e3 * float(np.percentile(v, 99)), "n": len(v)}
            for k, v in res.items()}


async def _fetch(driver: Driver, done: Done) -> float:
    async with driver:
        t0 = time.perf_counter()
        await driver.fetch_logs(done)
        return time.perf_counter() - t0


def _share_rate(name: str, work: Path, data: bytes) -> float:
    from robid_link.drivers.file_share import done_text, log_name

    sha = hashlib.sha256(data).hexdigest()
    peer, driver = _cell(name, work)
    try:
        key, nkey = ("1", "0000abcd") if name == "modbus_plc" else ("exp", "0000abcd")
        (work / "outbox" / log_name(key, nkey)).write_bytes(data)
        (work / "sem" / f"{key}.{nkey}.done").write_bytes(done_text(sha, len(data)))
        if name == "modbus_plc":  # the experiment must have its number on the share
            (work / "inbox" / "experiments.json").write_text('{"exp": 1}')
        wall = asyncio.run(_fetch(driver, Done("exp", "0000abcd", sha, len(data))))
    finally:
        peer.stop()
    return len(data) / wall / 1e6


def _serial_rate(work: Path, data: bytes, pace_baud: int, compress: bool = True) -> float:
    peer, driver = _cell("serial_line", work, pace_baud=pace_baud,
                         baudrate=pace_baud or 921600)
    if not compress:
        driver = registry.make_driver({**peer.driver_options(), "compress": False})
    try:
        peer.offer_log("exp", "0000abcd", data)
        sha = hashlib.sha256(data).hexdigest()
        wall = asyncio.run(_fetch(driver, Done("exp", "0000abcd", sha, len(data))))
    finally:
        peer.stop()
    return len(data) / wall / 1e6


def bench_transfer(plain_slice: int = 768_000, slice_115200: int = 768_000
                   ) -> dict[str, dict[str, float]]:
    """MB/s of ``fetch_logs`` per link; the serial line at 921600 baud over the whole log
    (compressed), in plain chunks and at 115200 baud over a slice of it."""
    data = sixty_second_log()
    out: dict[str, dict[str, float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for k, (label, size, fn) in enumerate((
                ("file_share", len(data), lambda w, d: _share_rate("file_share", w, d)),
                ("modbus_plc (share)", len(data), lambda w, d: _share_rate("modbus_plc", w, d)),
                ("serial_line unpaced pty", len(data), lambda w, d: _serial_rate(w, d, 0)),
                ("serial_line 921600 baud", len(data),
                 lambda w, d: _serial_rate(w, d, 921600)),
                ("serial_line 921600 baud plain", plain_slice,
                 lambda w, d: _serial_rate(w, d, 921600, compress=False)),
                ("serial_line 115200 baud", slice_115200,
                 lambda w, d: _serial_rate(w, d, 115200)))):
            work = Path(tmp) / f"c{k}"
            work.mkdir()
            rate = fn(work, data[:size])
            out[label] = {"mb_s": rate, "measured_bytes": size,
                          "full_log_s": len(data) / 1e6 / rate, "log_bytes": len(data)}
    return out


def report(only: str | None = None) -> dict[str, dict[str, dict[str, float]]]:
    """Print the section of ``make bench`` (``--only modbus|serial`` narrows it); returns
    the hand-offs and the transfers."""
    import logging

    logging.getLogger("robid").setLevel(logging.ERROR)  # the bench's own leftovers, not news
    h = bench_handoffs()
    base = h["file_share (inotify)"]["median_ms"]
    for name, v in h.items():
        if only and only not in name and "file_share" not in name:
            continue
        print(f"give→take hand-off, {name:<22}: median {v['median_ms']:7.2f} ms, p99 "
              f"{v['p99_ms']:7.2f} ms over {v['n']:.0f} ({v['median_ms'] / base:.1f}× the "
              "file share's median)")
    t = bench_transfer()
    ref = t["file_share"]["mb_s"]
    for name, v in t.items():
        if only and only not in name and "file_share" not in name:
            continue
        baud = int(name.split()[1]) if "baud" in name else 0
        part = v["measured_bytes"] < v["log_bytes"]
        how = ("" if not baud else
               "; paced, " + (f"measured on {v['measured_bytes'] / 1e3:.0f} kB and "
                              "extrapolated" if part else "the whole log timed") +
               f"; {v['mb_s'] * 1e6 / (baud / 10):.2f}× the line's {baud / 1e4:.1f} kB/s")
        print(f"log transfer, 60 s 6-axis 1 kHz log ({v['log_bytes'] / 1e6:.1f} MB), "
              f"{name:<24}: {v['mb_s']:8.3f} MB/s, {v['full_log_s']:8.1f} s for the log "
              f"({v['mb_s'] / ref:.2g}× the file share{how})")
    return {"handoff": h, "transfer": t}


def record(fig: Any, r: dict[str, dict[str, dict[str, float]]]) -> None:
    """The section's figures into ``benchmarks.figures.Figures``."""
    h, t = r["handoff"], r["transfer"]
    base = h["file_share (inotify)"]["median_ms"]
    if "modbus_plc" in h:
        v = h["modbus_plc"]
        fig.add("handoff_modbus_ms", v["median_ms"], "ms", label="give→take hand-off, Modbus "
                "PLC, median", baseline=("file share (inotify)", base, "ms"), target="≤ 5 ms",
                ok=v["median_ms"] <= 5, p99_ms=v["p99_ms"])
    if "serial_line" in h:
        v = h["serial_line"]
        fig.add("handoff_serial_ms", v["median_ms"], "ms", label="give→take hand-off, serial "
                "line, median", baseline=("file share (inotify)", base, "ms"), p99_ms=v["p99_ms"])
    for name, v in t.items():
        raw_s = v["log_bytes"] * 10 / 921600
        if name == "serial_line 921600 baud":
            fig.add("serial_921600_log_s", v["full_log_s"], "s", label="serial line at 921,600 "
                    "baud: a 60 s 6-axis log on the wire, compressed (zlog1)",
                    baseline=("the log's bytes at the line's rate", raw_s, "s"),
                    target="≥ 3× less than the baseline", ok=v["full_log_s"] * 3 <= raw_s,
                    times_less=raw_s / v["full_log_s"])
        elif name == "serial_line 921600 baud plain":
            fig.add("serial_921600_plain_log_s", v["full_log_s"], "s", label="serial line at "
                    "921,600 baud: the same log in plain GET chunks (an older controller)",
                    baseline=("the log's bytes at the line's rate", raw_s, "s"))
