"""The link daemon: store (locked state dir), driver, control socket, campaign runner and
systemd notifications in one event loop. SIGTERM stops between journaled steps; a restarted
daemon finishes the bookkeeping of every unfinished run (what was given before is taken and
stored) and then leaves it ``interrupted``: no motion until an operator resumes it."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import multiprocessing
import os
import signal
import time
from collections.abc import Awaitable, Callable, Mapping, Sequence
from contextlib import AbstractAsyncContextManager
from typing import Any

from robid_link.config import DaemonConfig, robot_name, with_joint_count
from robid_link.exceptions import (
    ApprovalError,
    ConfigError,
    DriverError,
    RobidError,
    StoreFullError,
    StoreUnavailableError,
)
from robid_link.jobs import WORKER_PRELOAD, RobotInfo, RobotInfoJob
from robid_link.link import campaign as cp
from robid_link.link.checks import ModelWatch, campaign_findings, daemon_findings
from robid_link.link.control import ControlServer
from robid_link.link.driver import Done
from robid_link.link.notify import Notifier, setup_logging
from robid_link.link.registry import make_driver
from robid_link.link.store import AsyncStore, open_store
from robid_link.link.worker import run_in_worker

__all__ = ["Daemon"]

log = logging.getLogger("robid.daemon")

def _kill_hook(spec: str | None) -> Any:
    """``ROBID_FAULT_KILL_AFTER=step[:n]``: SIGKILL this process after the n-th such step."""
    if not spec:
        return lambda step: None
    step, _, count = spec.partition(":")
    left = [int(count or 1)]

    def hook(name: str) -> None:
        if name == step:
            left[0] -= 1
            if left[0] == 0:
                os.kill(os.getpid(), signal.SIGKILL)

    return hook


#: runs waiting in the queue at most: a start (or resume) beyond it is refused in one line
MAX_QUEUED = 64
#: times a run's attempt may be withdrawn for a store failure before the run fails (a store
#: that fails on the same write again and again must not make the robot start over forever)
MAX_OUTAGES = 3


class Daemon:
    """The link daemon; ``async with Daemon(cfg) as d: await d.wait_stopped()``."""

    def __init__(self, cfg: DaemonConfig, env: Mapping[str, str] | None = None) -> None:
        self.cfg = cfg
        env = os.environ if env is None else env
        self.notifier = Notifier(env)
        self._kill = _kill_hook(env.get("ROBID_FAULT_KILL_AFTER"))
        self.ctx = multiprocessing.get_context(cfg.worker_start_method)
        if cfg.worker_start_method == "forkserver":
            # children fork with the numerical stack imported (numba kernels come from cache)
            self.ctx.set_forkserver_preload(["robid_link.link.worker", *WORKER_PRELOAD])
        self.store: AsyncStore | None = None
        self.driver: Any = None
        self.robot: RobotInfo | None = None
        self.robot_name: str | None = None  # the robot's name in the store
        self._queue: asyncio.Queue[str] = asyncio.Queue()
        self._current: str | None = None
        self._run_task: asyncio.Task[None] | None = None
        # held while a run is taken from the queue and started, and while a cancel decides:
        # the store is read with awaits, and a queued run must never start once cancelled
        self._handover = asyncio.Lock()
        self._cancelling: set[str] = set()
        self._run_ended = asyncio.Event()
        self._paused: list[str] = []  # runs waiting for space in the state_dir, in order
        # runs found unfinished at start: their first execution gives nothing to the controller
        self._bookkeeping: set[str] = set()
        # the one line while the store cannot take a run (state_dir full, database unreachable)
        self._full: str | None = None
        self._unreachable = False  # the store's database did not answer: probe it
        # attempts withdrawn while the store could not journal it: (run_id, exp_id, nonce)
        self._withdrawn: list[tuple[str, str, str]] = []
        self._outages: dict[str, int] = {}  # run_id → attempts withdrawn for the store
        self._stop = asyncio.Event()
        self.ready = asyncio.Event()
        self._tasks: list[asyncio.Task[None]] = []
        self._stack: contextlib.AsyncExitStack | None = None
        self.models = ModelWatch()
        self._refused: set[str] = set()  # campaigns whose files were missing at start

    def stop(self) -> None:
        """Ask ``wait_stopped`` to return (the signal handlers of ``run_daemon`` call it)."""
        self._stop.set()

    async def wait_stopped(self) -> None:
        await self._stop.wait()

    async def __aenter__(self) -> Daemon:
        """Open the store, check the robot and the driver, open the driver and the control
        socket, start ``_runner_loop`` (and ``_watchdog_loop``) in a TaskGroup; READY. A
        start-up error is raised here with everything opened so far closed again."""
        cfg = self.cfg
        stack = contextlib.AsyncExitStack()
        try:
            self.driver = make_driver(cfg.driver)
            self._check_config()
            self.robot = await run_in_worker(self.ctx, RobotInfoJob(str(cfg.robot), cfg.lock))
            # campaigns with a channels budget split their experiments by the joint count
            self.cfg = cfg = with_joint_count(cfg, self.robot.n)
            self.robot_name = robot_name(cfg, self.robot.name)
            self.store = open_store(cfg.state_dir, url=cfg.store, robot=self.robot_name,
                                    log_store=cfg.log_store)
            await self.store.open()
            stack.push_async_callback(self._closed_store)
            description = await asyncio.to_thread(cfg.robot.read_bytes)
            await self.store.register_robot(self.robot.name, cfg.robot.name, description,
                                            cfg.lock)
            self.driver.bind_feedforward(cp.feedforward_source(cfg, self.ctx))
            cp.check_capabilities(cfg, self.driver)  # before anything can move
            self.driver.bind_robot(self.robot)
            await stack.enter_async_context(self.driver)
            await stack.enter_async_context(ControlServer(cfg.control_socket, self.handle,
                                                          cfg.socket_mode))
            tg = await stack.enter_async_context(asyncio.TaskGroup())
            await self._withdraw_orphans()
            await self._interrupted_at_start()
            ready_status = await self._status_line()  # READY is the first message systemd gets
            self._tasks = [tg.create_task(self._runner_loop(), name="robid-runner"),
                           tg.create_task(self._space_loop(), name="robid-space"),
                           tg.create_task(self._preflight_all(), name="robid-preflight")]
            if self.notifier.watchdog_s:
                self._tasks.append(tg.create_task(self._watchdog_loop(), name="robid-watchdog"))
        except BaseException:
            for task in self._tasks:
                task.cancel()
            await stack.aclose()
            raise
        self._stack = stack
        self.notifier.send(READY=1, STATUS=ready_status)
        self.ready.set()
        log.info("daemon ready robot=%s joints=%d driver=%s socket=%s store=%s pid=%d",
                 self.robot_name, self.robot.n, cfg.driver["name"], cfg.control_socket,
                 "postgresql" if cfg.store else "sqlite", os.getpid())
        return self

    async def __aexit__(self, *exc: Any) -> None:
        """Cancel the loops (the current step is journaled: an unfinished run gets its
        bookkeeping at the next start, then waits for an operator's resume), then close the
        control socket, the driver and the store. The body's own
        exception goes on unchanged (not wrapped into the TaskGroup's ExceptionGroup)."""
        log.info("stopping: the current step is journaled; an unfinished run waits for an "
                 "operator's resume after the next start")
        self.notifier.send(STOPPING=1, STATUS="stopping")
        for task in self._tasks:
            task.cancel()
        stack, self._stack = self._stack, None
        assert stack is not None
        await stack.aclose()

    def _check_config(self) -> None:
        """What ``robid config check`` checks besides the keys: a path the daemon needs is an
        error (no start); a campaign's missing file a warning (its starts are refused)."""
        cfg = self.cfg
        problems = daemon_findings(cfg, type(self.driver).options)
        if problems:
            more = (f" (and {len(problems) - 1} more: robid config check --config {cfg.path})"
                    if len(problems) > 1 else "")
            raise ConfigError(f"{cfg.path}: {problems[0].line}{more}")
        for name in cfg.campaigns:
            for finding in campaign_findings(cfg, name):
                log.warning("%s: campaign %s: its runs will be refused: %s", cfg.path, name,
                            finding.line)
                self._refused.add(name)
            self.models.seen(cfg, name)

    async def _closed_store(self) -> None:
        assert self.store is not None
        await self.store.close()
        log.info("daemon stopped")

    async def _runner_loop(self) -> None:
        """Runs one after the other. A store that fails between a run's steps pauses the run
        (resumed when it answers again): the loop, and the daemon, stay up."""
        while True:
            run_id = await self._queue.get()
            try:
                await self._run_one(run_id)
                await self._withdraw_orphans()  # a run that ended leaves nothing given
            except (StoreFullError, StoreUnavailableError) as err:
                self._pause(run_id, err)
            except Exception as err:  # noqa: BLE001 - e.g. the failure's own write refused
                log.error("run=%s left as the store has it after an error: %s: %s", run_id,
                          type(err).__name__, err, exc_info=err)
            self.notifier.send(STATUS=await self._status_line())

    async def _run_one(self, run_id: str) -> None:
        assert self.store is not None
        async with self._handover:  # a cancel finds the run queued or started, never between
            if (await self.store.run(run_id))["state"] not in ("queued", "running"):
                return  # cancelled while it waited
            self._current = run_id
            self._run_ended.clear()
            status = await self._status_line()
            self._launch(run_id)
        self.notifier.send(STATUS=status)
        try:
            await self._execute(run_id)
        finally:
            self._current, self._run_task = None, None
            self._run_ended.set()

    def _pause(self, run_id: str, err: StoreFullError | StoreUnavailableError) -> None:
        """The run waits, journaled as it is, until the store takes writes again."""
        if run_id not in self._paused:
            self._paused.append(run_id)
        self._unreachable = self._unreachable or isinstance(err, StoreUnavailableError)
        self._set_full(str(err))

    def _launch(self, run_id: str) -> None:
        """The run's own task (``cancel`` stops it); awaited by ``_execute`` with no await in
        between, so it never runs unwatched. A run found unfinished at start only has its
        bookkeeping done (no motion)."""
        assert self.store is not None and self.robot is not None
        may_give = run_id not in self._bookkeeping
        self._run_task = asyncio.create_task(
            cp.execute_run(self.cfg, self.store, self.driver, self.ctx, run_id, self.robot.n,
                           self._kill, self.models, may_give=may_give,
                           on_withdrawn=lambda e, n: self._withdrawn.append((run_id, e, n))),
            name=f"robid-run-{run_id}")

    async def _interrupted_at_start(self) -> None:
        """Unfinished runs at start: a cancel that was under way is finished; every other run
        gets its bookkeeping (queued, no motion), then waits for an operator's resume."""
        assert self.store is not None
        for run_id in await self.store.unfinished_runs():
            if any(j["step"] == "cancel_requested" for j in await self.store.journal(run_id)):
                log.info("run=%s a cancel was under way: finishing it", run_id)
                await self._finish_cancel(run_id)
                continue
            log.info("run=%s interrupted by a restart: bookkeeping, no motion", run_id)
            self._bookkeeping.add(run_id)
            self._queue.put_nowait(run_id)

    async def _execute(self, run_id: str) -> None:
        """Await the run's task; a cancel finishes it, a store that cannot be written (full,
        unreachable) pauses it (what it gave was withdrawn first)."""
        assert self.store is not None and self._run_task is not None
        try:
            await self._run_task
        except asyncio.CancelledError:
            current = asyncio.current_task()
            if run_id not in self._cancelling or (current and current.cancelling()):
                raise  # the daemon stops: the run resumes at the next start
            await self._finish_cancel(run_id)
        except (StoreFullError, StoreUnavailableError) as err:
            self._pause(run_id, err)
        except Exception as err:  # a bug must fail its run, not the daemon (or resume loop)
            cause = f"{type(err).__name__}: {err}"
            log.error("run=%s internal error: %s", run_id, cause, exc_info=err)
            with contextlib.suppress(StoreFullError, StoreUnavailableError):
                await self._withdraw_out(run_id)  # the stop first, then the failure
                await self.store.set_run(run_id, "failed", error=f"internal error: {cause}")
        finally:
            self._cancelling.discard(run_id)
            if run_id not in self._paused:  # a paused bookkeeping goes on without motion
                self._bookkeeping.discard(run_id)

    async def _finish_cancel(self, run_id: str) -> None:
        """Withdraw what is still out (so no controller runs it later), keep a log that was
        already announced, journal, state ``cancelled``."""
        assert self.store is not None
        await self._withdraw_out(run_id)
        await self.store.set_run(run_id, "cancelled", error="cancelled by the operator")
        log.info("run=%s cancelled", run_id)

    async def _withdraw_out(self, run_id: str) -> None:
        """Take back every program of the run that may still be out (a failed attempt's
        too: its withdraw is done before it is journaled, but a daemon of an older version
        journaled first)."""
        assert self.store is not None
        for row in await self.store.experiments(run_id):
            if row["state"] in ("giving", "given", "taken", "attempt_failed") and row["nonce"]:
                await self._withdraw_row(row)

    async def _withdraw_row(self, row: dict[str, Any]) -> None:
        """Take back an experiment's 'ready'; a log the controller already announced is
        stored first (a captured log is never lost)."""
        assert self.store is not None
        run_id, exp_id, nonce = row["run_id"], row["exp_id"], row["nonce"]
        if row["state"] == "taken" and not row["log_sha"]:
            try:
                async with asyncio.timeout(30):
                    data = await self.driver.fetch_logs(Done(exp_id, nonce, row["done_sha"],
                                                             row["done_size"]))
                    await self.store.put_log(data, run_id=run_id, exp_id=exp_id)
            except (DriverError, OSError, TimeoutError) as err:  # OSError: the store is full
                # a log that cannot be fetched (corrupt, gone) never keeps a program out
                log.warning("run=%s exp=%s announced log not stored: %s", run_id, exp_id, err)
        try:
            async with asyncio.timeout(30):
                await self.driver.withdraw(exp_id, nonce)
        except (DriverError, OSError, TimeoutError) as err:
            log.warning("run=%s exp=%s withdraw failed: %s", run_id, exp_id, err)
            return
        await self.store.step(run_id, exp_id, "withdrawn")

    async def _withdraw_orphans(self) -> None:
        assert self.store is not None
        for row in await self.store.given_without_run():
            log.info("run=%s exp=%s withdrawing a 'ready' its run no longer watches",
                     row["run_id"], row["exp_id"])
            await self._withdraw_row(row)

    async def _preflight_all(self) -> None:
        """One line per campaign a run of which would be refused (``start`` checks again)."""
        assert self.store is not None
        for name in self.cfg.campaigns:
            if name in self._refused:
                continue  # said at start
            try:
                await cp.preflight(self.cfg, self.store, self.ctx, name)
            except (StoreFullError, StoreUnavailableError) as err:
                self._set_full(str(err))
                self._unreachable = self._unreachable or isinstance(err, StoreUnavailableError)
                return
            except RobidError as err:
                log.error("%s: campaign %s: %s (start refused until fixed)", self.cfg.path,
                          name, err)

    def _set_full(self, line: str | None) -> None:
        """One log line when the store stops taking runs (full, unreachable), one when it
        takes them again."""
        if line and not self._full:
            log.error("%s; new runs refused, status still served", line)
        elif not line and self._full:
            log.info("the store takes writes again: resuming %d paused run(s)",
                     len(self._paused))
        self._full = line

    #: how often the free space of the state_dir is looked at
    space_poll_s = 5.0

    async def _space_loop(self) -> None:
        """Check for room (and, after a failure, that the database answers) every few seconds
        (from the start: a daemon started on a full disk serves status and waits); when the
        store is back, journal what was withdrawn meanwhile and re-queue the paused runs. A
        lost robot lock (StoreLockLostError) never comes back: no motion until a restart."""
        assert self.store is not None
        while True:
            try:
                await self.store.require_space()
                if self._unreachable:
                    await self.store.unfinished_runs()  # a read: reconnects, takes the lock
                if self._full:
                    await self._store_back()
                self._unreachable = False
            except (StoreFullError, StoreUnavailableError) as err:
                self._set_full(str(err))
            await asyncio.sleep(self.space_poll_s)

    async def _store_back(self) -> None:
        assert self.store is not None
        line = self._full
        while self._withdrawn:
            run_id, exp_id, nonce = self._withdrawn[0]
            row = await self.store.experiment(run_id, exp_id)
            if row["nonce"] == nonce and row["state"] in ("giving", "given"):
                await self.store.step(run_id, exp_id, "attempt_failed",
                                      error=f"withdrawn: {line}")
                self._outages[run_id] = self._outages.get(run_id, 0) + 1
            self._withdrawn.pop(0)
        await self._withdraw_orphans()
        self._unreachable = False
        self._set_full(None)
        while self._paused:
            run_id = self._paused[0]
            if any(j["step"] == "cancel_requested" for j in await self.store.journal(run_id)):
                await self._finish_cancel(run_id)  # a cancel the outage interrupted
            elif self._outages.get(run_id, 0) > MAX_OUTAGES:
                await self.store.set_run(run_id, "failed", error=(
                    f"the store failed while an attempt was out {self._outages[run_id]} "
                    f"times (each withdrawn); last: {line}"))
            else:
                self._queue.put_nowait(run_id)
            self._paused.pop(0)

    async def _watchdog_loop(self) -> None:
        assert self.notifier.watchdog_s is not None
        while True:  # from the event loop: a blocked loop stops the pings, systemd restarts us
            self.notifier.send(WATCHDOG=1)
            await asyncio.sleep(self.notifier.watchdog_s)

    async def _status_line(self) -> str:
        if self._full:
            return f"{self._full}; {len(self._paused)} run(s) paused"
        try:
            return await self._store_status()
        except Exception as err:  # noqa: BLE001 - the line says what the store answered
            return f"{err}; {len(self._paused)} run(s) paused"

    async def _store_status(self) -> str:
        assert self.store is not None
        held = [r for r in await self.store.runs(100) if r["state"] == "interrupted"]
        waiting = ""
        if held:
            since = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(
                min(r["state_since"] for r in held)))
            waiting = (f"; {len(held)} run(s) interrupted, waiting for an operator since "
                       f"{since} (robid campaign resume RUN)")
        current = self._current
        if current is None:
            return f"idle, {self._queue.qsize()} run(s) queued{waiting}"
        run = await self.store.run(current)
        return (f"run {current} ({run['campaign']}): {run['step'] or run['state']}, "
                f"{run['progress']['stored']}/{run['progress']['total']} logs{waiting}")

    # ----------------------------------------------------------------- control requests
    def _command_table(self) -> dict[str, Callable[[dict[str, Any]], Awaitable[dict[str, Any]]]]:
        """The control socket's commands: name → handler of the request."""
        return {"ping": self._ping, "start": self._start, "status": self._status,
                "cancel": lambda req: self._cancel(str(req.get("run_id"))),
                "resume": self._resume,
                "results": self._results, "list": self._list, "approve": self._approve,
                "params_approve": self._params, "params_rollback": self._params}

    async def handle(self, req: dict[str, Any]) -> dict[str, Any]:
        """Answer one control request (``cmd`` and its arguments) from the command table."""
        assert self.store is not None
        table = self._command_table()
        handler = table.get(req["cmd"])
        if handler is None:
            raise ConfigError(f"unknown command {req['cmd']!r} (known: "
                              f"{', '.join(sorted(table))})")
        return await handler(req)

    async def _ping(self, req: dict[str, Any]) -> dict[str, Any]:
        return {"ok": True, "pid": os.getpid(),
                "robot": {"name": self.robot.name, "joints": self.robot.n}
                if self.robot else None}

    async def _start(self, req: dict[str, Any]) -> dict[str, Any]:
        assert self.store is not None
        if self._full:
            raise (StoreUnavailableError if self._unreachable else StoreFullError)(self._full)
        await self.store.require_space()
        trigger = req.get("trigger", "operator")
        self._check_room()
        name = str(req.get("campaign"))
        if name in self.cfg.campaigns:  # else create_run says so
            try:
                await cp.preflight(self.cfg, self.store, self.ctx, name, str(trigger))
            except ApprovalError as err:  # unattended: only approved programs
                log.warning("start of %s refused: %s", name, err)
                raise
        run_id = await cp.create_run(self.cfg, self.store, name, trigger,
                                     force=req.get("force") is True)
        self._queue.put_nowait(run_id)
        log.info("run=%s queued campaign=%s trigger=%s", run_id, req.get("campaign"), trigger)
        return {"ok": True, "run_id": run_id}

    def _check_room(self) -> None:
        if self._queue.qsize() >= MAX_QUEUED:
            raise ConfigError(f"{self._queue.qsize()} runs are queued already (at most "
                              f"{MAX_QUEUED}); wait for them or cancel some")

    async def _status(self, req: dict[str, Any]) -> dict[str, Any]:
        """The runs and the status line; with the store unreachable, the line only (the
        daemon's own state: what is paused, why)."""
        assert self.store is not None
        try:
            runs = ([await self.store.run(req["run_id"])] if req.get("run_id")
                    else await self.store.runs(int(req.get("limit", 20))))
        except StoreUnavailableError as err:
            self._unreachable = True
            raise StoreUnavailableError(await self._status_line()) from err
        drift = [f.message for f in cp.drift_flags_of(await self.store.results(self.robot_name),
                                                       self.robot_name)] \
            if self.robot_name else []
        return {"ok": True, "runs": runs, "current": self._current,
                "status": await self._status_line(), "drift": drift}

    async def _results(self, req: dict[str, Any]) -> dict[str, Any]:
        assert self.store is not None
        return {"ok": True, "results": await self.store.results(req.get("robot"),
                                                                req.get("run_id"))}

    async def _list(self, req: dict[str, Any]) -> dict[str, Any]:
        return {"ok": True, "campaigns": cp.describe_campaigns(self.cfg)}

    async def _approve(self, req: dict[str, Any]) -> dict[str, Any]:
        assert self.store is not None
        name = str(req.get("campaign"))
        if name not in self.cfg.campaigns:
            raise ConfigError(f"campaign {name!r}: not in {self.cfg.path}")
        programs = await cp.prepare_programs(self.cfg, self.store, self.ctx, name)
        for exp_id, prog in programs:
            await self.store.approve(prog.sha256, name, exp_id, str(req.get("by", "operator")))
        return {"ok": True, "approved": [{"experiment": e, "sha256": p.sha256,
                                          "duration_s": p.duration_s}
                                         for e, p in programs]}

    async def _resume(self, req: dict[str, Any]) -> dict[str, Any]:
        """An operator's go-ahead for a run interrupted by a restart (the CLI's ``campaign
        resume``, the operator's page): it is queued and moves again from where it stopped."""
        assert self.store is not None
        run_id, by = str(req.get("run_id")), str(req.get("by", "operator"))
        async with self._handover:  # (on a full disk it is paused before any motion)
            state = (await self.store.run(run_id))["state"]
            if state != "interrupted":
                raise ConfigError(f"run {run_id} is {state}: only an interrupted run is "
                                  "resumed")
            self._check_room()
            await self.store.note(run_id, None, "resumed", by=by)
            await self.store.set_run(run_id, "queued", step=f"resumed by {by}")
            self._queue.put_nowait(run_id)
        log.info("run=%s resumed by %s", run_id, by)
        return {"ok": True, "run_id": run_id, "state": "queued",
                "message": f"run {run_id} resumed by {by}: queued"}

    async def _cancel(self, run_id: str) -> dict[str, Any]:
        """A queued, paused or interrupted run is dropped; the running one stops at its next
        step, after its 'ready' was withdrawn. The request is journaled first: a daemon that
        dies during the cancel finishes it at its next start."""
        assert self.store is not None
        async with self._handover:
            state = (await self.store.run(run_id))["state"]
            if state not in ("queued", "running", "interrupted"):
                raise ConfigError(f"run {run_id} is {state}: nothing to cancel")
            await self.store.note(run_id, None, "cancel_requested")
            started = run_id == self._current and self._run_task is not None
            if started:
                assert self._run_task is not None
                self._cancelling.add(run_id)
                self._run_task.cancel()
            else:
                if run_id in self._paused:
                    self._paused.remove(run_id)
                await self._finish_cancel(run_id)
        if started:
            async with asyncio.timeout(60):
                await self._run_ended.wait()
        return {"ok": True, "run_id": run_id, "state": (await self.store.run(run_id))["state"],
                "message": f"run {run_id} cancelled; nothing of it is left for the "
                           "controller"}

    async def _params(self, req: dict[str, Any]) -> dict[str, Any]:
        """Approve a parameter set for unattended uploads, or give the controller back the
        set it had before the one in use (byte for byte)."""
        assert self.store is not None
        cmd, robot, ref = req["cmd"], str(req.get("robot")), req.get("set")
        by = str(req.get("by", "operator"))
        if robot != self.robot_name:  # its store rows and its controller are another's
            raise ConfigError(f"robot {robot}: this daemon holds robot {self.robot_name}; "
                              f"{'approve' if cmd == 'params_approve' else 'roll back'} "
                              f"{robot}'s parameter sets with {robot}'s own daemon")
        sets = await self.store.param_sets(robot)
        if not sets:
            raise ConfigError(f"robot {robot}: no parameter set stored yet")
        if cmd == "params_approve":
            row = await self.store.param_set(robot, str(ref)) if ref else sets[-1]
            await self.store.approve_param_set(row["sha256"], by)
            return {"ok": True, "message": f"approved parameter set {row['version']} of "
                    f"{robot} ({row['sha256'][:16]}…) for unattended uploads"}
        if self._current is not None:
            raise ConfigError(f"rollback refused: run {self._current} is in progress; roll "
                              "back when it has ended")
        active = await self.store.active_param_sets(robot)
        if len(active) < 2:
            raise ConfigError(f"robot {robot}: the controller has had no earlier set to roll "
                              "back to")
        await cp.upload_set(self.store, self.driver, robot, active[-2], None, unattended=False,
                            force=True)  # the set the controller ran before: the operator's
        row = next(s for s in sets if s["sha256"] == active[-2])
        return {"ok": True, "message": f"rolled {robot} back to parameter set {row['version']} "
                f"({active[-2][:16]}…), acknowledged by the controller"}


async def run_daemon(cfg: DaemonConfig,
                     services: Sequence[Callable[[Daemon], AbstractAsyncContextManager[Any]]]
                     = ()) -> int:
    """``robid daemon``: serve until SIGTERM or SIGINT; each of ``services`` (the operator's
    web page) is entered with the ready daemon and left before it stops."""
    setup_logging(cfg.log_level)
    loop = asyncio.get_running_loop()
    async with Daemon(cfg) as daemon, contextlib.AsyncExitStack() as extras:
        for service in services:
            await extras.enter_async_context(service(daemon))
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, daemon.stop)
        try:
            await daemon.wait_stopped()
        finally:
            for sig in (signal.SIGTERM, signal.SIGINT):
                loop.remove_signal_handler(sig)
    return 0
