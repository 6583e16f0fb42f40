"""The control socket under hostile or broken clients: only a socket is ever replaced, and
connections, line length, nesting, numbers and handler bugs are answered with one line."""

from __future__ import annotations

import asyncio
import json
import logging
import os
import socket
from pathlib import Path
from typing import Any

import pytest

from robid_link.exceptions import ConfigError
from robid_link.link.control import MAX_LINE, ControlServer


async def _handler(req: dict[str, Any]) -> dict[str, Any]:
    if req["cmd"] == "boom":
        raise KeyError("campaign")
    return {"ok": True, "echo": req["cmd"]}


async def _ask(path: Path, line: bytes) -> dict[str, Any]:
    reader, writer = await asyncio.open_unix_connection(str(path), limit=1 << 22)
    writer.write(line)
    await writer.drain()
    answer = await reader.readline()
    writer.close()
    return json.loads(answer)


def test_a_regular_file_at_the_socket_path_is_never_deleted(tmp_path: Path) -> None:
    config = tmp_path / "link.yaml"
    config.write_text("robot: r.yaml\n")

    async def go() -> None:
        async with ControlServer(config, _handler):
            pass

    with pytest.raises(ConfigError, match=r"control_socket: .*link\.yaml: exists and is not "
                                          r"a socket; refusing to replace it"):
        asyncio.run(go())
    assert config.read_text() == "robot: r.yaml\n"
    link = tmp_path / "ctl.sock"
    link.symlink_to(config)
    with pytest.raises(ConfigError, match="exists and is a symbolic link"):
        asyncio.run(ControlServer(link, _handler).__aenter__())
    assert link.is_symlink() and config.exists()


def test_a_dead_daemons_socket_is_replaced(tmp_path: Path) -> None:
    path = tmp_path / "ctl.sock"
    dead = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    dead.bind(str(path))
    dead.close()  # the file stays, nobody listens

    async def go() -> dict[str, Any]:
        async with ControlServer(path, _handler):
            return await _ask(path, b'{"cmd": "ping"}\n')

    assert asyncio.run(go()) == {"ok": True, "echo": "ping"}


def test_hostile_requests_get_one_line_and_the_server_goes_on(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "ctl.sock"
    bad = {
        "huge line": b'{"cmd": "' + b"x" * (2 * MAX_LINE) + b'"}\n',
        "deep nesting": b"[" * 30_000 + b"]" * 30_000 + b"\n",
        "huge number": b'{"cmd": "ping", "n": ' + b"9" * 50_000 + b"}\n",
        "not json": b"\xff\xfe garbage\n",
        "no cmd": b'{"campaign": "nightly"}\n',
        "handler bug": b'{"cmd": "boom"}\n',
    }

    async def go() -> dict[str, dict[str, Any]]:
        async with ControlServer(path, _handler):
            out = {name: await _ask(path, line) for name, line in bad.items()}
            out["after"] = await _ask(path, b'{"cmd": "ping"}\n')
            return out

    with caplog.at_level(logging.DEBUG):
        out = asyncio.run(go())
    assert out.pop("after") == {"ok": True, "echo": "ping"}
    for name, answer in out.items():
        assert answer["ok"] is False and "\n" not in answer["error"], name
    assert "longer than" in out["huge line"]["error"]
    assert "nested deeper" in out["deep nesting"]["error"]
    assert "internal error: KeyError" in out["handler bug"]["error"]
    assert not [r for r in caplog.records if r.exc_info or r.levelno >= logging.ERROR]


def test_idle_connections_are_bounded_and_time_out(tmp_path: Path) -> None:
    path = tmp_path / "ctl.sock"
    fds_before = len(os.listdir("/proc/self/fd"))

    async def go() -> tuple[int, dict[str, Any], dict[str, Any], int]:
        async with ControlServer(path, _handler, max_clients=8, idle_s=0.5) as server:
            idle = [await asyncio.open_unix_connection(str(path)) for _ in range(40)]
            await asyncio.sleep(0.2)
            served = await _ask(path, b'{"cmd": "ping"}\n')  # the longest idle made room
            busy = server.clients
            await asyncio.sleep(1.0)  # the idle ones are dropped by the server
            ok = await _ask(path, b'{"cmd": "ping"}\n')
            for _, w in idle:
                w.close()
            return busy, served, ok, server.clients

    busy, served, ok, left = asyncio.run(go())
    assert busy <= 8 and served == {"ok": True, "echo": "ping"}
    assert ok == {"ok": True, "echo": "ping"} and left <= 1
    assert len(os.listdir("/proc/self/fd")) <= fds_before + 2


def test_clients_that_never_read_cannot_lock_the_operator_out(tmp_path: Path) -> None:
    """Issue 19: 64 clients sending requests and never reading their answers held every slot
    (each answer's write waited for its reader without end); now an answer waits write_s, a
    full server closes the longest-idle client, and the operator is answered."""
    path = tmp_path / "ctl.sock"
    big = {"ok": True, "runs": ["x" * 1000] * 200}  # answers that fill the socket buffers

    async def handler(req: dict[str, Any]) -> dict[str, Any]:
        return big if req["cmd"] == "status" else {"ok": True, "echo": req["cmd"]}

    async def go() -> tuple[list[dict[str, Any]], int]:
        async with ControlServer(path, handler, max_clients=64, write_s=0.5) as server:
            mute = [await asyncio.open_unix_connection(str(path)) for _ in range(64)]
            for _, w in mute:  # requests, never a read
                w.write(b'{"cmd": "status"}\n' * 50)
            await asyncio.sleep(0.2)
            full = await _ask(path, b'{"cmd": "ping"}\n')  # every slot answering: one line
            await asyncio.sleep(0.8)  # past write_s: the mute ones are closed
            left = server.clients
            answers = [full] + [await _ask(path, b'{"cmd": "ping"}\n') for _ in range(3)]
            for _, w in mute:
                w.close()
            return answers, left

    answers, left = asyncio.run(go())
    assert answers[0]["ok"] is False and "try again later" in answers[0]["error"]
    assert answers[1:] == [{"ok": True, "echo": "ping"}] * 3
    assert left == 0
