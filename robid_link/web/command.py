"""``robid web`` (the page read-only from a config's state dir) and the daemon's own page."""

from __future__ import annotations

import asyncio
import signal
from collections.abc import Callable
from contextlib import AbstractAsyncContextManager
from typing import Any

from robid_link.config import DaemonConfig, load_daemon_config, robot_name
from robid_link.link.store import open_reader
from robid_link.web.server import DEFAULT_LISTEN, WebServer

__all__ = ["run_web", "daemon_service"]


def run_web(config: str, listen: str | None) -> int:
    """Serve the state dir of ``config`` read-only until SIGINT or SIGTERM."""
    from robid_link.ident.model.robot import description_name

    cfg = load_daemon_config(config)
    robot = robot_name(cfg, description_name(cfg.robot, cfg.lock))
    with open_reader(cfg, robot):  # refuses a state dir without a store now
        pass
    server = WebServer(cfg, listen or cfg.web.listen or DEFAULT_LISTEN, robot)

    async def serve() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        async with server:
            print(f"robid web: {cfg.state_dir} at {server.url} (read-only; Ctrl-C stops)",
                  flush=True)
            await stop.wait()

    asyncio.run(serve())
    return 0


def daemon_service(cfg: DaemonConfig) -> Callable[[Any], AbstractAsyncContextManager[Any]]:
    """The daemon's page (``web.listen``) of its robot as the store names it: the daemon's
    own requests as its actions; the token file is made in the state dir on the first
    start."""
    assert cfg.web.listen is not None

    def start(daemon: Any) -> AbstractAsyncContextManager[Any]:
        return WebServer(cfg, cfg.web.listen or DEFAULT_LISTEN, daemon.robot_name,
                         actions=daemon.handle, create_token=True)

    return start
