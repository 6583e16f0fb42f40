"""sd_notify checked against a fake NOTIFY_SOCKET: READY, STATUS, WATCHDOG at half of
WATCHDOG_USEC only for the right WATCHDOG_PID, STOPPING; the shipped systemd units."""

from __future__ import annotations

import asyncio
import configparser
import os
import socket
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
    svc = configparser.ConfigParser(interpolation=None)
    svc.read(UNITS / "robid-link.service")
    assert svc["Service"]["Type"] == "notify"
    assert svc["Service"]["RuntimeDirectory"] == "robid"
    assert "robid daemon --config" in svc["Service"]["ExecStart"]
    assert int(svc["Service"]["WatchdogSec"]) > 0
    timer = configparser.ConfigParser(interpolation=None)
    timer.read(UNITS / "robid-nightly.timer")
    assert timer["Timer"]["Persistent"] == "false"
    night = configparser.ConfigParser(interpolation=None)
    night.read(UNITS / "robid-nightly.service")
    assert "--trigger timer" in night["Service"]["ExecStart"]
