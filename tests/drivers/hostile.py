"""One hostile cell in a process of its own (``python -m tests.drivers.hostile SPEC``): a fake
peer playing a misbehaving controller, the link daemon in this process, one short campaign
started over the control socket. It prints one JSON line: how the run ended, when the failure
was stored and when the controller side saw its stop/abort, whether status requests were
answered meanwhile, and the process's peak RSS (VmHWM, reset just before the cell starts:
the memory the hostile controller could make the daemon take).

SPEC (JSON): ``driver``, ``fault``, ``fault_count`` (1), ``peer`` (peer options), ``driver_over``
(daemon driver options), ``experiment`` (a friction sweep by default), ``retries`` (0),
``timeout_s`` (the take's, 20), ``robot`` (an example robot's name, arm3; a UR controller moves
industrial6), ``mute_clients`` (control-socket clients that send and never
read), ``symlink_inbox`` (the share's inbox replaced by a link after the daemon opened).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import re
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import yaml

ROBOTS = Path(__file__).resolve().parents[2] / "examples" / "robots"
ARM3 = ROBOTS / "arm3.yaml"
FRICTION = {"kind": "friction", "speeds": [0.5], "joints": [1], "rate_hz": 100}


def peak_rss_mb() -> float:
    text = Path("/proc/self/status").read_text()
    return int(re.search(r"VmHWM:\s+(\d+)", text).group(1)) / 1024  # type: ignore[union-attr]


class AnonPeak:
    """The largest anonymous RSS (RssAnon: what the process allocated, not the shared
    libraries' file pages, whose resident share depends on the page cache: 120 MB in one
    checkout, 208 MB in a fresh clone for the same cell), sampled every 5 ms in a thread."""

    def __init__(self) -> None:
        self.peak = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    @staticmethod
    def now_mb() -> float:
        text = Path("/proc/self/status").read_text()
        return int(re.search(r"RssAnon:\s+(\d+)", text).group(1)) / 1024  # type: ignore[union-attr]

    def _loop(self) -> None:
        while not self._stop.wait(0.005):
            self.peak = max(self.peak, self.now_mb())

    def __enter__(self) -> AnonPeak:
        self.peak = self.now_mb()
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, self.now_mb())


def reset_peak() -> None:
    """VmHWM back to the current RSS (Linux: 5 into clear_refs)."""
    with contextlib.suppress(OSError):
        Path("/proc/self/clear_refs").write_text("5")


def _stop_times(peer: Any) -> list[float]:
    """When the controller side saw a stop/abort (each peer keeps its own record)."""
    for name in ("stop_times", "stops", "aborts"):
        if hasattr(peer, name):
            return list(getattr(peer, name))
    return list(peer.quick_stops()) if hasattr(peer, "quick_stops") else []


class _Elsewhere:
    """A server a redirect points to: it counts what reaches it (nothing may)."""

    def __init__(self) -> None:
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(8)
        self.sock.settimeout(0.2)
        self.hits = 0
        self.url = f"http://127.0.0.1:{self.sock.getsockname()[1]}/elsewhere"
        self._quit = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while not self._quit.is_set():
            try:
                conn, _ = self.sock.accept()
            except OSError:
                continue
            self.hits += 1
            conn.close()

    def close(self) -> None:
        self._quit.set()
        self._thread.join(2)
        self.sock.close()


async def _ask(path: Path, req: dict[str, Any], timeout_s: float = 10.0,
               within_s: float = 120.0) -> dict[str, Any] | None:
    """One request over the control socket, retried while every slot is busy answering
    clients that do not read (None if it never got through within ``within_s``: the mute
    clients' slots free up after the daemon's write timeout and their queued requests, which
    take longer on a loaded machine)."""
    from robid_link.exceptions import RobidError
    from robid_link.link.control import request

    end = time.monotonic() + within_s
    while time.monotonic() < end:
        try:
            return await asyncio.to_thread(request, path, req, timeout_s)
        except RobidError as err:
            if "try again later" not in str(err):
                raise
        await asyncio.sleep(0.5)
    return None


async def _status(path: Path) -> bool:
    """A status request over the control socket answers."""
    ans = await _ask(path, {"cmd": "status"})
    return bool(ans and ans.get("ok"))


async def _mute(path: Path, n: int) -> list[Any]:
    out = []
    for _ in range(n):
        _, w = await asyncio.open_unix_connection(str(path))
        w.write(b'{"cmd": "status"}\n' * 200)  # requests, their answers never read
        out.append(w)
    return out


async def _cell(spec: dict[str, Any], cfg_path: Path, peer: Any, work: Path) -> dict[str, Any]:
    from robid_link.config import load_daemon_config
    from robid_link.link.control import PREFLIGHT_TIMEOUT_S
    from robid_link.link.daemon import Daemon

    cfg = load_daemon_config(cfg_path)
    out: dict[str, Any] = {"status_during": [], "error_at_start": None}
    try:
        daemon = Daemon(cfg, env={})
        await daemon.__aenter__()
    except Exception as err:  # noqa: BLE001 - a refused start is an outcome here
        out["error_at_start"] = f"{type(err).__name__}: {err}"
        return out
    try:
        if spec.get("symlink_inbox"):
            inbox = Path(peer.driver_options()["share"]) / "inbox"
            for f in inbox.iterdir():
                f.unlink()
            inbox.rmdir()
            inbox.symlink_to(work / "outside", target_is_directory=True)
        mute = await _mute(cfg.control_socket, int(spec.get("mute_clients", 0)))
        ans = await _ask(cfg.control_socket, {"cmd": "start", "campaign": "c"},
                         PREFLIGHT_TIMEOUT_S)
        assert ans is not None, "the start request never got through"
        run_id = ans["run_id"]
        assert daemon.store is not None
        async with asyncio.timeout(float(spec.get("run_timeout_s", 150))):
            while (await daemon.store.run(run_id))["state"] in ("queued", "running"):
                if len(out["status_during"]) < 3:
                    out["status_during"].append(await _status(cfg.control_socket))
                await asyncio.sleep(0.3)
        out["status_after"] = await _status(cfg.control_socket)
        run = await daemon.store.run(run_id)
        journal = await daemon.store.journal(run_id)
        for w in mute:
            w.close()
        out.update(state=run["state"], error=run["error"],
                   failure_stored=min((j["time"] for j in journal
                                       if j["step"] in ("attempt_failed", "failed")),
                                      default=None),
                   given=sum(j["step"] == "given" for j in journal))
    finally:
        await daemon.__aexit__(None, None, None)
    return out


def warm() -> None:
    """Compile (and cache on disk) the numba kernels the cells run, in a process of their own:
    one quiet cell over the RWS and the CANopen fakes (with cold caches, as in a fresh clone,
    the compile's memory was a cell's peak: 285-309 MB against the link's ~220 MB)."""
    for driver in ("abb_rws", "canopen_drives"):
        run({"driver": driver, "fault": None})


def run(spec: dict[str, Any]) -> dict[str, Any]:
    from robid_link.fakes.controller import default_truth, make_peer
    from robid_link.ident.model.robot import load_robot

    robot_path = ROBOTS / f"{spec.get('robot', 'arm3')}.yaml"
    robot = load_robot(robot_path)
    elsewhere = _Elsewhere() if spec.get("fault") == "redirect" else None
    with tempfile.TemporaryDirectory(prefix="robid-hostile-") as tmp:
        work = Path(tmp)
        (work / "cell").mkdir()
        (work / "outside").mkdir()
        peer_opts = dict(spec.get("peer", {}))
        if elsewhere is not None:
            peer_opts["redirect_to"] = elsewhere.url
        reset_peak()
        with AnonPeak() as anon:
            peer = make_peer(spec["driver"], robot, default_truth(robot, rate_hz=200.0),
                             work / "cell", fault=spec.get("fault"),
                             fault_count=int(spec.get("fault_count", 1)), **peer_opts)
            with peer:
                driver = {**peer.driver_options(), **spec.get("driver_over", {})}
                camp = {"experiments": [spec.get("experiment", FRICTION)], "identify": False,
                        "timeout_s": float(spec.get("timeout_s", 20)), "backoff_s": 0.05,
                        "retries": int(spec.get("retries", 0))}
                cfg = {"robot": str(robot_path), "state_dir": str(work / "state"),
                       "control_socket": str(work / "ctl.sock"), "driver": driver,
                       "worker_start_method": "forkserver", "campaigns": {"c": camp}}
                cfg_path = work / "daemon.yaml"
                cfg_path.write_text(yaml.safe_dump(cfg))
                out = asyncio.run(_cell(spec, cfg_path, peer, work))
                out["stops"] = _stop_times(peer)
                out["plc_runs"] = len(getattr(peer, "runs", []))
                out["outside"] = sorted(os.listdir(work / "outside"))
        out["peak_rss_mb"] = peak_rss_mb()
        out["peak_anon_mb"] = anon.peak
    if elsewhere is not None:
        out["elsewhere_hits"] = elsewhere.hits
        elsewhere.close()
    return out


if __name__ == "__main__":
    from robid_link.link.notify import setup_logging

    setup_logging("warning", sys.stderr)
    if sys.argv[1] == "warm":
        warm()
    else:
        print(json.dumps(run(json.loads(sys.argv[1])), default=str))
