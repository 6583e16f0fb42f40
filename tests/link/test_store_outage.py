"""The store failing under a running link (review of the PostgreSQL store): a write that fails
mid-attempt withdraws the attempt before anything else; an unreachable database pauses the run
(never fails it), the daemon stays up and answers, and the run goes on when the store is back;
a robot lock lost with the connection is latched (no further motion). Real PostgreSQL:
tests/servers.py, reached through a loopback proxy the test can cut."""

from __future__ import annotations

import asyncio
import contextlib
import os
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from robid_link.exceptions import (
    RobidError,
    StoreLockedError,
    StoreLockLostError,
    StoreUnavailableError,
)
from robid_link.link.daemon import Daemon
from robid_link.link.store import Store, ThreadedStore

from .conftest import write_config
from .test_daemon import ONE, with_daemon
from .test_harden import state_is, until

LINE = "store postgresql://robid@127.0.0.1:5/robid: connection lost (server closed)"


def _ready(tmp: Path) -> list[str]:
    return [n for n in os.listdir(tmp / "share" / "sem") if n.endswith(".ready")]


class _Events:
    """What happened after the store first failed, in order: the driver's withdraw and the
    store calls the daemon made."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        from robid_link.drivers.file_share import FileShareDriver

        self.seen: list[str] = []
        self.failed = False
        withdraw = FileShareDriver.withdraw

        async def tracked(driver: Any, exp_id: str, nonce: str) -> None:
            if self.failed:
                self.seen.append("withdraw")
            await withdraw(driver, exp_id, nonce)

        monkeypatch.setattr(FileShareDriver, "withdraw", tracked)
        for name in ("step", "set_run", "note"):
            real = getattr(ThreadedStore, name)

            def wrap(real: Any = real, name: str = name) -> Any:
                async def call(store: Any, *args: Any, **kw: Any) -> Any:
                    if self.failed:
                        self.seen.append(name)
                    return await real(store, *args, **kw)
                return call

            monkeypatch.setattr(ThreadedStore, name, wrap())


def test_a_store_error_after_the_give_withdraws_before_the_run_fails(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Review: the store raising on the 'given' write left the 'ready' out (nobody watching
    it) and failed the run. The stop goes out first, then the failure (one line)."""
    cfg = write_config(tmp_path, {"one": ONE})
    events = _Events(monkeypatch)
    real = ThreadedStore.step

    async def step(self: Any, run_id: str, exp_id: str, state: str, **kw: Any) -> None:
        if state == "given" and not events.failed:
            events.failed = True
            raise RobidError("the journal refused the step")  # not a store outage: a bug
        await real(self, run_id, exp_id, state, **kw)

    monkeypatch.setattr(ThreadedStore, "step", step)

    async def body(d: Daemon) -> tuple[dict, list[dict]]:
        run_id = (await d.handle({"cmd": "start", "campaign": "one"}))["run_id"]
        await until(lambda: state_is(d, run_id, "failed"), 30)
        await until(lambda: not _ready(tmp_path), 10)
        assert d.store is not None
        # the runner's sweep journals the withdraw once the failed run has ended
        await until(lambda: _withdrawn(d, run_id), 10)
        return await d.store.run(run_id), await d.store.journal(run_id)

    async def _withdrawn(d: Daemon, run_id: str) -> bool:
        assert d.store is not None
        return any(j["step"] == "withdrawn" for j in await d.store.journal(run_id))

    run, journal = with_daemon(cfg, body)  # no controller: a 'ready' left would stay
    assert _ready(tmp_path) == []
    assert events.seen[0] == "withdraw", events.seen  # before the failure is stored
    assert run["error"] == "the journal refused the step"
    assert "withdrawn" in [j["step"] for j in journal if j["exp_id"]]  # the sweep journals it


def test_a_failure_that_cannot_be_stored_leaves_the_daemon_up(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Review: the store refusing the step and then the run's failure (an error of no known
    kind) crashed the daemon out of its runner loop. It stays up: nothing is left given, the
    next request is answered."""
    cfg = write_config(tmp_path, {"one": ONE})
    broken = {"on": False}
    step, set_run = ThreadedStore.step, ThreadedStore.set_run

    async def bad_step(self: Any, run_id: str, exp_id: str, state: str, **kw: Any) -> None:
        if state == "given":
            broken["on"] = True
        if broken["on"]:
            raise RobidError("the journal refused the step")
        await step(self, run_id, exp_id, state, **kw)

    async def bad_set_run(self: Any, run_id: str, state: str, **kw: Any) -> None:
        if broken["on"] and state == "failed":
            raise RobidError("the journal refused the failure")
        await set_run(self, run_id, state, **kw)

    monkeypatch.setattr(ThreadedStore, "step", bad_step)
    monkeypatch.setattr(ThreadedStore, "set_run", bad_set_run)

    async def body(d: Daemon) -> dict:
        await d.handle({"cmd": "start", "campaign": "one"})
        await until(lambda: broken["on"] and d._current is None, 30)
        return await d.handle({"cmd": "ping"})

    assert with_daemon(cfg, body)["ok"]
    assert _ready(tmp_path) == []


class _Outage:
    """The blocking store's connection under the test's control: while ``down``, every query
    (reads too) raises StoreUnavailableError as a lost PostgreSQL connection does."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, error: type[StoreUnavailableError]
                 = StoreUnavailableError) -> None:
        self.down = False
        real = Store._connection

        def connection(store: Store) -> Any:
            if self.down:
                raise error(LINE)
            return real(store)

        monkeypatch.setattr(Store, "_connection", connection)
        monkeypatch.setattr(Daemon, "space_poll_s", 0.1)


def test_an_unreachable_store_pauses_the_run_and_it_goes_on_when_back(
        tmp_path: Path, controller: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """Review: a PostgreSQL outage mid-run crashed the daemon (the runner loop's store read
    raised out of its TaskGroup). Now: the attempt is withdrawn first, the run waits (not
    failed), start is refused and status answered in one line, ping answered; when the store
    answers again the withdrawn attempt is journaled and the run completes."""
    cfg = write_config(tmp_path, {"one": ONE})
    events = _Events(monkeypatch)
    outage = _Outage(monkeypatch)
    real = ThreadedStore.step

    async def step(self: Any, run_id: str, exp_id: str, state: str, **kw: Any) -> None:
        if state == "given" and not events.failed:
            outage.down = True
            try:
                await real(self, run_id, exp_id, state, **kw)
            finally:
                events.failed = True
        await real(self, run_id, exp_id, state, **kw)

    monkeypatch.setattr(ThreadedStore, "step", step)

    async def body(d: Daemon) -> tuple[Any, ...]:
        run_id = (await d.handle({"cmd": "start", "campaign": "one"}))["run_id"]
        await until(lambda: run_id in d._paused, 30)
        ping = await d.handle({"cmd": "ping"})
        with pytest.raises(StoreUnavailableError) as start:
            await d.handle({"cmd": "start", "campaign": "one"})
        with pytest.raises(StoreUnavailableError) as status:
            await d.handle({"cmd": "status"})
        await asyncio.sleep(0.5)  # the probes fail meanwhile: the daemon stays up
        outage.down = False
        await until(lambda: state_is(d, run_id, "completed"), 60)
        assert d.store is not None
        return ping, str(start.value), str(status.value), await d.store.run(run_id)

    with controller():
        ping, start, status, run = with_daemon(cfg, body)
    assert ping["ok"]
    assert events.seen[:1] == ["withdraw"], events.seen  # the robot stopped before all else
    assert start == LINE and "\n" not in start
    assert status == f"{LINE}; 1 run(s) paused"
    exp = run["experiments"][0]
    assert exp["state"] == "stored" and exp["attempt"] == 2  # the withdrawn one, then a new one


def test_a_store_failing_on_every_give_fails_the_run_after_a_few(
        tmp_path: Path, controller: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """A store that fails on the same write each time must not make the robot start over
    forever: past MAX_OUTAGES withdrawn attempts the run fails in one line."""
    from robid_link.link import daemon as dm

    monkeypatch.setattr(dm, "MAX_OUTAGES", 1)
    cfg = write_config(tmp_path, {"one": ONE})
    outage = _Outage(monkeypatch)
    real = ThreadedStore.step

    async def step(self: Any, run_id: str, exp_id: str, state: str, **kw: Any) -> None:
        if state == "given":
            outage.down = True
        await real(self, run_id, exp_id, state, **kw)

    monkeypatch.setattr(ThreadedStore, "step", step)

    async def body(d: Daemon) -> dict:
        assert d.store is not None
        run_id = (await d.handle({"cmd": "start", "campaign": "one"}))["run_id"]
        async with asyncio.timeout(60):
            while True:
                await asyncio.sleep(0.05)
                if run_id in d._paused:
                    outage.down = False  # back, until the next give
                with contextlib.suppress(StoreUnavailableError):
                    run = await d.store.run(run_id)
                    if run["state"] == "failed":
                        return run

    with controller():
        run = with_daemon(cfg, body)
    assert run["error"].startswith("the store failed while an attempt was out 2 times "
                                   f"(each withdrawn); last: {LINE}")
    assert [e["attempt"] for e in run["experiments"]] == [2]
    assert _ready(tmp_path) == []


def test_a_lost_robot_lock_stops_all_motion(tmp_path: Path, controller: Any,
                                            monkeypatch: pytest.MonkeyPatch) -> None:
    """The lock could not be taken again after a reconnect: the run waits and never moves
    again in this daemon, a start is refused naming the lost lock."""
    cfg = write_config(tmp_path, {"one": ONE})
    outage = _Outage(monkeypatch, StoreLockLostError)
    real = ThreadedStore.step

    async def step(self: Any, run_id: str, exp_id: str, state: str, **kw: Any) -> None:
        if state == "given":
            outage.down = True
        await real(self, run_id, exp_id, state, **kw)

    monkeypatch.setattr(ThreadedStore, "step", step)

    async def body(d: Daemon) -> tuple[str, list[str]]:
        run_id = (await d.handle({"cmd": "start", "campaign": "one"}))["run_id"]
        await until(lambda: run_id in d._paused, 30)
        await asyncio.sleep(0.5)
        with pytest.raises(StoreUnavailableError) as start:
            await d.handle({"cmd": "start", "campaign": "one"})
        return str(start.value), list(d._paused)

    with controller() as ctrl:
        line, paused = with_daemon(cfg, body)
    assert line == LINE and len(paused) == 1
    assert len(ctrl.handled) <= 1  # the one attempt given before the lock was lost


# ----------------------------------------------------------------- real PostgreSQL
class _Proxy:
    """A loopback TCP proxy to the PostgreSQL server; ``cut()`` drops every connection and
    refuses new ones (closed right after accept) until ``restore()``."""

    def __init__(self, port: int) -> None:
        self.target = port
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.up, self.closed = True, False
        self.socks: list[socket.socket] = []
        self.stranded: list[socket.socket] = []
        self.lock = threading.Lock()
        self.thread = threading.Thread(target=self._accept, daemon=True)
        self.thread.start()

    def _accept(self) -> None:
        self.listener.settimeout(0.05)
        while not self.closed:
            try:
                client, _ = self.listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            client.settimeout(None)
            if not self.up:
                client.close()
                continue
            server = socket.create_connection(("127.0.0.1", self.target))
            with self.lock:
                self.socks += [client, server]
            for a, b in ((client, server), (server, client)):
                threading.Thread(target=self._pipe, args=(a, b), daemon=True).start()

    def _pipe(self, a: socket.socket, b: socket.socket) -> None:
        with contextlib.suppress(OSError):
            while data := a.recv(65536):
                b.sendall(data)
        if b in self.stranded:
            return  # the server is never told: its session lives on
        with contextlib.suppress(OSError):
            b.shutdown(socket.SHUT_RDWR)

    def strand(self) -> None:
        """The network drops between the client and the server: the client's side is closed,
        the server's is left open and silent, so the server keeps the session (and its locks)
        until its keepalive gives up."""
        self.up = False
        with self.lock:
            for client, server in zip(self.socks[::2], self.socks[1::2], strict=True):
                self.stranded.append(server)
                with contextlib.suppress(OSError):
                    client.shutdown(socket.SHUT_RDWR)
                client.close()
            self.socks.clear()

    def cut(self) -> None:
        self.up = False
        with self.lock:
            for s in self.socks:
                with contextlib.suppress(OSError):
                    s.shutdown(socket.SHUT_RDWR)
                s.close()
            self.socks.clear()

    def restore(self) -> None:
        self.up = True

    def close(self) -> None:
        self.closed = True
        self.thread.join(5)
        self.cut()
        for s in self.stranded:
            s.close()
        self.listener.close()


@pytest.fixture
def proxy(postgres: Any) -> Iterator[_Proxy]:
    p = _Proxy(postgres.port)
    yield p
    p.close()


def _sessions_ended(postgres: Any, db: str, timeout_s: float = 20.0) -> None:
    """Wait for the server to end the sessions of ``db`` whose connections were cut (each held
    its robot's lock until then; under load the server takes a moment to notice)."""
    import psycopg

    from tests.servers import PG_PASSWORD, PG_USER

    end = time.monotonic() + timeout_s
    with psycopg.connect(host="127.0.0.1", port=postgres.port, user=PG_USER,
                         password=PG_PASSWORD, dbname="postgres", autocommit=True) as c:
        while c.execute("SELECT count(*) FROM pg_stat_activity WHERE datname = %s",
                        (db,)).fetchone() != (0,):
            assert time.monotonic() < end, f"the server kept the cut sessions of {db}"
            time.sleep(0.05)


def test_a_postgres_outage_is_one_line_and_the_store_comes_back(
        tmp_path: Path, postgres: Any, proxy: _Proxy, monkeypatch: pytest.MonkeyPatch) -> None:
    """Review: the server going away raised SQLAlchemy's OperationalError out of the store
    (a traceback, the daemon died). Now StoreUnavailableError, one line naming the store's URL
    (no password), on writes and reads alike; the next call after the server is back
    reconnects and takes the robot's lock again."""
    from tests.servers import PG_PASSWORD

    monkeypatch.setenv("PGPASSWORD", PG_PASSWORD)  # the pgpass file names the server's port
    url = postgres.create_database().replace(f":{postgres.port}/", f":{proxy.port}/")
    with Store(tmp_path / "a", url=url, robot="r1") as a:
        run = a.create_run("c", "operator", {}, [("e", "rigid_body")])
        proxy.cut()
        lines = []
        for call in (lambda: a.step(run, "e", "giving", attempt=1, nonce="n1"),
                     lambda: a.run(run)):
            with pytest.raises(StoreUnavailableError) as err:
                call()
            lines.append(str(err.value))
        _sessions_ended(postgres, url.rsplit("/", 1)[1])
        proxy.restore()
        a.step(run, "e", "giving", attempt=1, nonce="n1")
        assert a.experiment(run, "e")["state"] == "giving"
        with pytest.raises(StoreLockedError):  # the robot is held again by the same store
            Store(tmp_path / "b", url=url, robot="r1")
    where = f"store postgresql://robid@127.0.0.1:{proxy.port}/"
    for line in lines:
        assert line.startswith(where) and "\n" not in line, line
        assert "connection lost" in line or "cannot reconnect" in line, line
        assert PG_PASSWORD not in line


def test_a_re_lock_ends_the_daemons_own_stale_session(
        tmp_path: Path, postgres: Any, proxy: _Proxy, monkeypatch: pytest.MonkeyPatch) -> None:
    """Review: the network between a cell and its database drops and comes back before the
    server's keepalive has ended the cut session. The re-lock found the robot held — by the
    daemon's own stale session — latched 'lock lost' and asked for the daemon to be stopped.
    Now the store ends its own previous session and takes the robot again (another daemon's
    session is never ended: the test below)."""
    import psycopg

    from tests.servers import PG_PASSWORD, PG_USER

    monkeypatch.setenv("PGPASSWORD", PG_PASSWORD)
    url = postgres.create_database().replace(f":{postgres.port}/", f":{proxy.port}/")
    with Store(tmp_path / "a", url=url, robot="r1") as a:
        run = a.create_run("c", "operator", {}, [("e", "rigid_body")])
        old = a.backend.session_pid  # type: ignore[attr-defined]
        assert old is not None
        proxy.strand()
        with pytest.raises(StoreUnavailableError, match="connection lost"):
            a.step(run, "e", "giving", attempt=1, nonce="n1")
        with psycopg.connect(host="127.0.0.1", port=postgres.port, user=PG_USER,
                             password=PG_PASSWORD, dbname="postgres", autocommit=True) as c:
            alive = "SELECT count(*) FROM pg_stat_activity WHERE pid = %s"
            assert c.execute(alive, (old,)).fetchone() == (1,)  # the server kept it
            proxy.restore()
            a.step(run, "e", "giving", attempt=1, nonce="n1")
            assert a.experiment(run, "e")["state"] == "giving"
            assert a.backend.session_pid not in (None, old)  # type: ignore[attr-defined]
            assert c.execute(alive, (old,)).fetchone() == (0,)
        with pytest.raises(StoreLockedError):  # and the robot is held by the new session
            Store(tmp_path / "b", url=url, robot="r1")


def test_a_lock_lost_with_the_connection_is_latched(tmp_path: Path, pg_url: str) -> None:
    """Review: the robot's session ended on the server, a twin daemon took the robot, and the
    first store went on writing without the lock. Now its re-lock failing latches 'lock lost':
    every call after is one line, and nothing more is written through that store."""
    import psycopg

    from tests.servers import PG_PASSWORD, PG_USER

    a = Store(tmp_path / "a", url=pg_url, robot="r1")
    run = a.create_run("c", "operator", {}, [("e", "rigid_body")])
    assert a.conn is not None
    pid = a.conn.connection.dbapi_connection.info.backend_pid  # type: ignore[union-attr]
    port = int(pg_url.rsplit(":", 1)[1].split("/")[0])
    with psycopg.connect(host="127.0.0.1", port=port, user=PG_USER, password=PG_PASSWORD,
                         dbname="postgres", autocommit=True) as c:
        c.execute("SELECT pg_terminate_backend(%s)", (pid,))
    with pytest.raises(StoreUnavailableError, match="connection lost"):
        a.step(run, "e", "giving", attempt=1, nonce="n1")
    b = Store(tmp_path / "b", url=pg_url, robot="r1")  # the twin takes the robot meanwhile
    try:
        for _ in range(2):
            with pytest.raises(StoreLockLostError) as err:
                a.step(run, "e", "given")
            assert "lock on robot r1 lost" in str(err.value) and "\n" not in str(err.value)
        with pytest.raises(StoreLockLostError):
            a.run(run)
        assert b.experiment(run, "e")["state"] == "pending"  # nothing written by the first
    finally:
        a.close()
        b.close()


def test_a_daemon_on_postgres_rides_out_an_outage(
        tmp_path: Path, postgres: Any, proxy: _Proxy, controller: Any,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The review's case end to end: a daemon whose store is a real PostgreSQL that goes away
    as the attempt is given. The daemon stays up and answers, the attempt is withdrawn, and
    the run completes once the server is reachable again."""
    from tests.servers import PG_PASSWORD

    monkeypatch.setenv("PGPASSWORD", PG_PASSWORD)
    monkeypatch.setattr(Daemon, "space_poll_s", 0.2)
    url = postgres.create_database().replace(f":{postgres.port}/", f":{proxy.port}/")
    cfg = write_config(tmp_path, {"one": ONE}, store=url, robot_name="cell-1")
    events = _Events(monkeypatch)
    real = ThreadedStore.step

    async def step(self: Any, run_id: str, exp_id: str, state: str, **kw: Any) -> None:
        if state == "given" and not events.failed:
            proxy.cut()
            try:
                await real(self, run_id, exp_id, state, **kw)
            finally:
                events.failed = True
        await real(self, run_id, exp_id, state, **kw)

    monkeypatch.setattr(ThreadedStore, "step", step)

    async def body(d: Daemon) -> tuple[Any, ...]:
        run_id = (await d.handle({"cmd": "start", "campaign": "one"}))["run_id"]
        await until(lambda: run_id in d._paused, 30)
        ping = await d.handle({"cmd": "ping"})
        with pytest.raises(StoreUnavailableError) as status:
            await d.handle({"cmd": "status"})
        proxy.restore()
        await until(lambda: state_is(d, run_id, "completed"), 60)
        assert d.store is not None
        return ping, str(status.value), await d.store.run(run_id)

    with controller():
        ping, status, run = with_daemon(cfg, body)
    assert ping["ok"] and events.seen[:1] == ["withdraw"], events.seen
    assert status.startswith(f"store postgresql://robid@127.0.0.1:{proxy.port}/")
    assert "1 run(s) paused" in status and PG_PASSWORD not in status
    assert run["experiments"][0]["attempt"] == 2 and run["state"] == "completed"
