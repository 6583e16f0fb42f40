"""systemd's side of the daemon: sd_notify over ``NOTIFY_SOCKET`` (READY, STATUS, WATCHDOG,
STOPPING), a few lines instead of a dependency, silent when not run by systemd; and the log's one
line per record, with its syslog priority under journald."""

from __future__ import annotations

import logging
import os
import socket
import sys
import time
from collections.abc import Mapping
from typing import TextIO

__all__ = ["Notifier", "setup_logging"]

log = logging.getLogger("robid.notify")


class Notifier:
    def __init__(self, env: Mapping[str, str] | None = None) -> None:
        env = os.environ if env is None else env
        addr = env.get("NOTIFY_SOCKET", "")
        self.address: str | None = None
        if addr.startswith("@"):
            self.address = "\0" + addr[1:]  # abstract namespace
        elif addr.startswith("/"):
            self.address = addr
        usec, pid = env.get("WATCHDOG_USEC"), env.get("WATCHDOG_PID")
        self.watchdog_s: float | None = None
        if usec and (not pid or pid == str(os.getpid())):
            try:
                self.watchdog_s = int(usec) / 2e6  # ping at half the timeout
            except ValueError:
                log.warning("WATCHDOG_USEC=%r is not a number; no watchdog pings", usec)

    @property
    def enabled(self) -> bool:
        return self.address is not None

    def send(self, **fields: str | int) -> bool:
        """``send(READY=1, STATUS="idle")``; False when not under systemd or on error."""
        if self.address is None:
            return False
        msg = "\n".join(f"{k}={v}" for k, v in fields.items()).encode()
        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as s:
                s.sendto(msg, self.address)
        except OSError as err:
            log.warning("sd_notify to %r failed: %s", self.address, err)
            return False
        return True


_PRIORITY = {logging.DEBUG: 7, logging.INFO: 6, logging.WARNING: 4, logging.ERROR: 3,
             logging.CRITICAL: 2}


class _LineFormatter(logging.Formatter):
    """One line per record, ``key=value`` fields in the message; under journald the line
    starts with its syslog priority (``<6>``) and journald adds the time."""

    def __init__(self, journald: bool) -> None:
        super().__init__()
        self.journald = journald

    def format(self, record: logging.LogRecord) -> str:
        msg = record.getMessage().replace("\n", " | ")
        if self.journald:
            return f"<{_PRIORITY.get(record.levelno, 6)}>{record.name}: {msg}"
        stamp = time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(record.created))
        return f"{stamp} {record.levelname.lower():<7} {record.name}: {msg}"


def setup_logging(level: str = "info", stream: TextIO | None = None) -> None:
    """robid's log lines to ``stream`` (stdout, for journald), replacing earlier handlers."""
    root = logging.getLogger("robid")
    for h in list(root.handlers):
        root.removeHandler(h)
    handler = logging.StreamHandler(stream or sys.stdout)
    handler.setFormatter(_LineFormatter(bool(os.environ.get("JOURNAL_STREAM"))))
    root.addHandler(handler)
    root.setLevel(level.upper())
    root.propagate = False
