"""The operator interface: one JSON request per line over a Unix stream socket (mode 0660),
one JSON answer per line. A socket file left by a dead daemon is detected by trying to connect
before it is replaced; nothing but a socket is ever replaced. Connections, line length, JSON
nesting and idle time are bounded: a hostile or broken client gets ``ok: false`` with one line
and never reaches a running campaign."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import socket
import stat
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from robid_link.exceptions import ConfigError, DaemonUnreachable, RobidError

__all__ = ["ControlServer", "request", "PREFLIGHT_TIMEOUT_S"]

log = logging.getLogger("robid.control")

Handler = Callable[[dict[str, Any]], Awaitable[dict[str, Any]]]
#: longest request line, deepest JSON nesting, most clients at once, idle seconds per client
MAX_LINE = 1 << 16
MAX_DEPTH = 16
MAX_CLIENTS = 64
IDLE_S = 120.0
# 'start' answers after the pre-flight, which generates (and optimises) every program of the
# campaign the first time: minutes on a loaded two-core cell PC, not the 30 s of a status
PREFLIGHT_TIMEOUT_S = 900.0


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

    def __init__(self, path: Path, handler: Handler, mode: int = 0o660, *,
                 max_clients: int = MAX_CLIENTS, idle_s: float = IDLE_S) -> None:
        self.path, self._handler, self._mode = Path(path), handler, mode
        self._server: asyncio.Server | None = None
        self._max_clients, self._idle_s = max_clients, idle_s
        self.clients = 0
        self._tasks: set[asyncio.Task[None]] = set()
        self._writers: set[asyncio.StreamWriter] = set()

    def _clear_stale(self) -> None:
        """Remove a dead daemon's socket; refuse anything that is not a socket (a typo in
        ``control_socket`` must never delete the config or a log)."""
        try:
            st = os.lstat(self.path)
        except FileNotFoundError:
            return
        if not stat.S_ISSOCK(st.st_mode):
            kind = "a symbolic link" if stat.S_ISLNK(st.st_mode) else "not a socket"
            raise ConfigError(f"control_socket: {self.path}: exists and is {kind}; refusing "
                              "to replace it")
        if _alive(self.path):
            raise ConfigError(f"control_socket: {self.path}: another daemon answers there")
        log.warning("control_socket=%s stale socket of a dead daemon replaced", self.path)
        self.path.unlink()

    async def __aenter__(self) -> ControlServer:
        self._clear_stale()
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
            # the server does not wait for its client handlers: close their connections (a
            # handler then reads EOF and ends) and await them, so nothing of the operator
            # interface outlives the daemon (cancelling them makes asyncio log an error)
            for writer in list(self._writers):
                writer.close()
            if self._tasks:
                await asyncio.wait(list(self._tasks), timeout=5.0)
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._server.wait_closed(), 2.0)
            self._server = None
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        if task is not None:
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)
        self._writers.add(writer)
        self.clients += 1
        try:
            if self.clients > self._max_clients:
                await _answer(writer, {"ok": False, "error": f"too many connections (at most "
                                       f"{self._max_clients}); try again later"})
                return
            while True:
                try:
                    async with asyncio.timeout(self._idle_s):
                        line = await reader.readline()
                except TimeoutError:
                    return
                except (ValueError, asyncio.LimitOverrunError):  # the line is over the limit
                    await _answer(writer, {"ok": False, "error": f"bad request: longer than "
                                           f"{MAX_LINE} bytes"})
                    return
                if not line:
                    return
                await _answer(writer, await self._serve_line(line))
        except (ConnectionError, asyncio.IncompleteReadError):
            pass
        finally:
            self.clients -= 1
            self._writers.discard(writer)
            writer.close()
            # the server closing under us cancels this wait: the client is done either way
            with contextlib.suppress(Exception, asyncio.CancelledError):
                await writer.wait_closed()

    async def _serve_line(self, line: bytes) -> dict[str, Any]:
        try:
            req = _parse(line)
            return await self._handler(req)
        except RobidError as err:  # its class goes along: the CLI tells 'nothing to do' apart
            return {"ok": False, "error": str(err), "error_class": type(err).__name__}
        except (ValueError, RecursionError) as err:
            return {"ok": False, "error": f"bad request: {str(err).splitlines()[0][:200]}"}
        except Exception as err:  # a bug in a command answers one line; runs go on
            log.warning("control request failed: %s: %s", type(err).__name__, err)
            return {"ok": False, "error": f"internal error: {type(err).__name__}: {err}"}


def _depth(text: str) -> int:
    """Deepest bracket nesting of a JSON text (strings skipped), without parsing it."""
    depth = deepest = 0
    in_str = esc = False
    for ch in text:
        if in_str:
            esc, in_str = (False, in_str) if esc else (ch == "\\", ch != '"')
        elif ch == '"':
            in_str = True
        elif ch in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif ch in "]}":
            depth -= 1
    return deepest


def _parse(line: bytes) -> dict[str, Any]:
    text = line.decode("utf-8", errors="strict")
    if _depth(text) > MAX_DEPTH:
        raise ValueError(f"JSON nested deeper than {MAX_DEPTH}")
    req = json.loads(text)
    if not isinstance(req, dict) or not isinstance(req.get("cmd"), str):
        raise ValueError("expected a JSON object with 'cmd'")
    return req


async def _answer(writer: asyncio.StreamWriter, answer: dict[str, Any]) -> None:
    writer.write(json.dumps(answer, default=str).encode() + b"\n")
    await writer.drain()


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
        raise _error_class(answer.get("error_class"))(
            answer.get("error", "the daemon refused the request"))
    return answer


def _error_class(name: Any) -> type[RobidError]:
    """The daemon's error class by name (one of ``robid_link.exceptions``), else RobidError."""
    from robid_link import exceptions

    cls = getattr(exceptions, str(name), None) if name in exceptions.__all__ else None
    return cls if isinstance(cls, type) and issubclass(cls, RobidError) else RobidError
