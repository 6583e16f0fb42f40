"""sd_notify checked against a fake NOTIFY_SOCKET: READY, STATUS, WATCHDOG at half of
WATCHDOG_USEC only for the right WATCHDOG_PID, STOPPING; the shipped systemd units."""

from __future__ import annotations

import asyncio
import configparser
import os
import re
import shutil
import socket
import subprocess
from pathlib import Path

import pytest

from robid_link.link.daemon import Daemon
from robid_link.link.notify import Notifier

from .conftest import write_config
from .test_daemon import with_daemon

UNITS = Path(__file__).resolve().parents[2] / "robid_link" / "systemd"


class FakeSystemd:
    def __init__(self, path: Path) -> None:
        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.setblocking(False)

    def messages(self) -> list[str]:
        out = []
        while True:
            try:
                out.append(self.sock.recv(4096).decode())
            except BlockingIOError:
                return out

    def close(self) -> None:
        self.sock.close()


@pytest.mark.parametrize("pid_matches", [True, False])
def test_daemon_notifies_systemd(tmp_path: Path, pid_matches: bool) -> None:
    cfg = write_config(tmp_path)
    fake = FakeSystemd(tmp_path / "notify.sock")
    env = {"NOTIFY_SOCKET": str(fake.path), "WATCHDOG_USEC": "200000",
           "WATCHDOG_PID": str(os.getpid() if pid_matches else 1)}

    async def body(d: Daemon) -> None:
        await asyncio.sleep(0.5)

    try:
        with_daemon(cfg, body, env=env)
        msgs = fake.messages()
    finally:
        fake.close()
    assert msgs[0].startswith("READY=1\nSTATUS=idle")
    assert msgs[-1] == "STOPPING=1\nSTATUS=stopping"
    pings = msgs.count("WATCHDOG=1")
    if pid_matches:
        assert 3 <= pings <= 8  # every 0.1 s (half of 0.2 s) for ~0.5 s
    else:
        assert pings == 0


def test_notifier_addresses_and_silence() -> None:
    assert Notifier({"NOTIFY_SOCKET": "@robid/x"}).address == "\0robid/x"
    silent = Notifier({})
    assert not silent.enabled and silent.send(READY=1) is False
    assert Notifier({"WATCHDOG_USEC": "3000000"}).watchdog_s == 1.5
    assert Notifier({"WATCHDOG_USEC": "3000000", "WATCHDOG_PID": "1"}).watchdog_s is None


def test_units_are_what_the_readme_promises() -> None:
    svc = configparser.ConfigParser(interpolation=None, strict=False)
    svc.read(UNITS / "robid-link.service")
    assert svc["Service"]["Type"] == "notify"
    assert svc["Service"]["RuntimeDirectory"] == "robid"
    assert "robid daemon --config" in svc["Service"]["ExecStart"]
    assert int(svc["Service"]["WatchdogSec"]) > 0
    timer = configparser.ConfigParser(interpolation=None, strict=False)
    timer.read(UNITS / "robid-nightly.timer")
    assert timer["Timer"]["Persistent"] == "false"
    night = configparser.ConfigParser(interpolation=None, strict=False)
    night.read(UNITS / "robid-nightly.service")
    assert "--trigger timer" in night["Service"]["ExecStart"]


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="no systemd-analyze here")
@pytest.mark.parametrize("unit", ["robid-link.service", "robid-nightly.service"])
def test_units_are_hardened(unit: str) -> None:
    """systemd's own exposure score of the shipped units stays below 5 (it was 8.7)."""
    out = subprocess.run(["systemd-analyze", "security", "--offline=true", str(UNITS / unit)],
                         capture_output=True, text=True, timeout=60)
    m = re.search(r"Overall exposure level for \S+: ([0-9.]+)", out.stdout + out.stderr)
    if m is None:
        pytest.skip(f"systemd-analyze cannot score units offline here: {out.stderr.strip()}")
    assert float(m.group(1)) < 5.0, out.stdout


def test_network_share_detection_reads_the_process_mounts(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """ProcSubset=pid hides /proc/mounts; the per-process table stays readable."""
    from robid_link.drivers import file_share

    real = Path.read_text

    def read_text(self: Path, *a: object, **kw: object) -> str:
        if str(self) == "/proc/mounts":
            raise PermissionError("hidden by ProcSubset=pid")
        if str(self) == "/proc/self/mounts":
            return f"server:/cell {tmp_path} nfs4 rw 0 0\n"
        return real(self, *a, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(Path, "read_text", read_text)
    assert file_share.network_fs(tmp_path) == "nfs4"
