"""The operator interface: one JSON request per line over a Unix stream socket (mode 0660),
one JSON answer per line. A socket file left by a dead daemon is detected by trying to connect
before it is replaced; nothing but a socket is ever replaced. Connections, line length, JSON
nesting, idle time and the time an answer may wait for its reader are bounded: a hostile or
broken client gets ``ok: false`` with one line (or is closed) and never reaches a running
campaign; when every connection is taken, the one idle the longest makes room for the newcomer,
so clients that connect and never read cannot lock the operator out."""

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
#: longest request line, deepest JSON nesting, most clients at once, idle seconds per client,
#: seconds an answer may wait for a client that does not read it
MAX_LINE = 1 << 16
MAX_DEPTH = 16
MAX_CLIENTS = 64
IDLE_S = 120.0
WRITE_S = 10.0
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
                 max_clients: int = MAX_CLIENTS, idle_s: float = IDLE_S,
                 write_s: float = WRITE_S) -> None:
        self.path, self._handler, self._mode = Path(path), handler, mode
        self._server: asyncio.Server | None = None
        self._max_clients, self._idle_s, self._write_s = max_clients, idle_s, write_s
        self.clients = 0
        self.evicted = 0  # idle clients closed to make room for a newcomer
        self._tasks: set[asyncio.Task[None]] = set()
        # every open connection → since when it waits for a request (None: being answered)
        self._writers: dict[asyncio.StreamWriter, float | None] = {}

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
        loop = asyncio.get_running_loop()
        self._writers[writer] = loop.time()
        self.clients += 1
        try:
            if self.clients > self._max_clients and not self._evict_idle(writer):
                await self._answer(writer, {"ok": False, "error": f"too many connections (at "
                                            f"most {self._max_clients}); try again later"})
                return
            while True:
                self._writers[writer] = loop.time()
                try:
                    async with asyncio.timeout(self._idle_s):
                        line = await reader.readline()
                except TimeoutError:
                    return
                except (ValueError, asyncio.LimitOverrunError):  # the line is over the limit
                    await self._answer(writer, {"ok": False, "error": f"bad request: longer "
                                                f"than {MAX_LINE} bytes"})
                    return
                if not line:
                    return
                self._writers[writer] = None
                await self._answer(writer, await self._serve_line(line))
        except (ConnectionError, asyncio.IncompleteReadError, TimeoutError):
            pass  # gone, or it did not read its answer within write_s: closed
        finally:
            self.clients -= 1
            self._writers.pop(writer, None)
            writer.close()
            # the server closing under us cancels this wait: the client is done either way
            with contextlib.suppress(Exception, asyncio.CancelledError):
                await writer.wait_closed()

    def _evict_idle(self, newcomer: asyncio.StreamWriter) -> bool:
        """Close the connection that has waited the longest for a request (never one being
        answered) to make room for ``newcomer``; False when every other one is busy."""
        idle = [(since, w) for w, since in self._writers.items()
                if since is not None and w is not newcomer and not w.is_closing()]
        if not idle:
            return False
        _, oldest = min(idle, key=lambda item: item[0])
        oldest.close()  # its handler reads EOF and ends
        self.evicted += 1
        if self.evicted in (1, 100) or self.evicted % 10_000 == 0:
            log.warning("control socket full (%d connections): %d idle client(s) closed to make "
                        "room", self._max_clients, self.evicted)
        return True

    async def _answer(self, writer: asyncio.StreamWriter, answer: dict[str, Any]) -> None:
        """One answer line; a client that does not take it within ``write_s`` is closed
        (TimeoutError), so its slot never stays taken."""
        writer.write(json.dumps(answer, default=str).encode() + b"\n")
        async with asyncio.timeout(self._write_s):
            await writer.drain()

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
        with contextlib.suppress(BrokenPipeError, ConnectionResetError):
            # a full socket answers and closes before reading: its answer is read below
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
        except ConnectionResetError:
            pass  # what arrived is the answer; nothing is "closed the connection"
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
