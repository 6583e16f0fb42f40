"""The operator interface: one JSON request per line over a Unix stream socket (mode 0660),
one JSON answer per line. A socket file left by a dead daemon is detected by trying to connect
before it is replaced."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import socket
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from robid_link.exceptions import ConfigError, DaemonUnreachable, RobidError

__all__ = ["ControlServer", "request"]

log = logging.getLogger("robid.control")

Handler = Callable[[dict[str, Any]], Awaitable[dict[str, Any]]]
MAX_LINE = 1 << 20


def _alive(path: Path) -> bool:
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(1.0)
        try:
            s.connect(str(path))
        except OSError:  # refused, gone, or not a socket: nobody answers there
            return False
    return True


class ControlServer:
    """Async context manager serving ``handler`` on ``path``."""

    def __init__(self, path: Path, handler: Handler, mode: int = 0o660) -> None:
        self.path, self._handler, self._mode = Path(path), handler, mode
        self._server: asyncio.Server | None = None

    async def __aenter__(self) -> ControlServer:
        if self.path.exists() or self.path.is_symlink():
            if _alive(self.path):
                raise ConfigError(f"control_socket: {self.path}: another daemon answers there")
            log.warning("control_socket=%s stale socket file replaced", self.path)
            self.path.unlink()
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            old = os.umask(0o777 & ~self._mode & 0o777)
            try:
                self._server = await asyncio.start_unix_server(self._client, str(self.path),
                                                               limit=MAX_LINE)
            finally:
                os.umask(old)
            os.chmod(self.path, self._mode)
        except OSError as err:
            raise ConfigError(f"control_socket: {self.path}: {err.strerror or err}") from err
        return self

    async def __aexit__(self, *exc: object) -> None:
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._server.wait_closed(), 2.0)
            self._server = None
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while line := await reader.readline():
                try:
                    req = json.loads(line)
                    if not isinstance(req, dict) or not isinstance(req.get("cmd"), str):
                        raise ValueError("expected a JSON object with 'cmd'")
                    answer = await self._handler(req)
                except RobidError as err:
                    answer = {"ok": False, "error": str(err)}
                except ValueError as err:
                    answer = {"ok": False, "error": f"bad request: {err}"}
                writer.write(json.dumps(answer, default=str).encode() + b"\n")
                await writer.drain()
        except (ConnectionError, asyncio.IncompleteReadError, asyncio.LimitOverrunError):
            pass
        finally:
            writer.close()
            with contextlib.suppress(Exception):
                await writer.wait_closed()


def request(path: str | Path, req: dict[str, Any], timeout_s: float = 30.0) -> dict[str, Any]:
    """Send one request to the daemon and return its answer (blocking; for the CLI)."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(timeout_s)
        try:
            s.connect(str(path))
        except (FileNotFoundError, ConnectionRefusedError) as err:
            raise DaemonUnreachable(f"control_socket: no daemon answers on {path} "
                                    "(start it with: robid daemon --config C)") from err
        except PermissionError as err:
            raise DaemonUnreachable(f"control_socket: {path}: permission denied (join the "
                                    "socket's group)") from err
        s.sendall(json.dumps(req).encode() + b"\n")
        buf = b""
        try:
            while not buf.endswith(b"\n"):
                chunk = s.recv(65536)
                if not chunk:
                    break
                buf += chunk
        except TimeoutError as err:
            raise DaemonUnreachable(f"control_socket: {path}: no answer within "
                                    f"{timeout_s:g} s") from err
    if not buf:
        raise DaemonUnreachable(f"control_socket: {path}: the daemon closed the connection")
    answer = json.loads(buf)
    if not answer.get("ok", False):
        raise RobidError(answer.get("error", "the daemon refused the request"))
    return answer
