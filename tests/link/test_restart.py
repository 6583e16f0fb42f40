"""No motion after a restart without an operator's command (issue 19): a daemon that starts
under an unfinished run does its bookkeeping — the log of the attempt given before is taken and
stored once — and gives nothing more; the run waits 'interrupted' (timer-approved or not), the
status says since when, and 'resume' goes on. A cancel the daemon died in is finished at the
next start, never resumed."""

from __future__ import annotations

import asyncio
import os
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from robid_link.config import load_daemon_config
from robid_link.link.daemon import Daemon
from robid_link.link.store import Store

from .conftest import write_config

TWO = {"experiments": [{"kind": "friction", "speeds": [0.5], "joints": [1], "rate_hz": 100},
                       {"kind": "friction", "id": "second", "speeds": [0.5], "joints": [3],
                        "rate_hz": 100}],
       "identify": False, "timeout_s": 20, "backoff_s": 0.05, "retries": 1}


def life(cfg: Path, body: Callable[[Daemon], Awaitable[Any]]) -> Any:
    """One daemon life in this process."""
    async def go() -> Any:
        async with asyncio.timeout(150), Daemon(load_daemon_config(cfg), env={}) as d:
            return await body(d)

    return asyncio.run(go())


async def until_state(d: Daemon, run_id: str, *states: str) -> dict[str, Any]:
    assert d.store is not None
    async with asyncio.timeout(120):
        while (run := await d.store.run(run_id))["state"] not in states:
            await asyncio.sleep(0.05)
    return run


def _gives(d: Daemon, run_id: str) -> Awaitable[int]:
    async def count() -> int:
        assert d.store is not None
        return sum(j["step"] == "giving" for j in await d.store.journal(run_id))
    return count()


def test_an_approved_timer_run_interrupted_mid_motion_waits_for_the_operator(
        tmp_path: Path, controller: Any) -> None:
    """Issue 19, 6: it resumed motion when the daemon booted. Now the restart takes the log
    of the experiment given before (stored once) and gives nothing; 'resume' goes on."""
    cfg = write_config(tmp_path, {"c": TWO})

    async def first(d: Daemon) -> str:
        await d.handle({"cmd": "approve", "campaign": "c"})
        stop = asyncio.Event()
        d._kill = lambda step: stop.set() if step == "given" else None  # the daemon dies here
        run_id = (await d.handle({"cmd": "start", "campaign": "c", "trigger": "timer"}))[
            "run_id"]
        async with asyncio.timeout(120):
            await stop.wait()
        return str(run_id)

    async def second(d: Daemon) -> tuple[dict[str, Any], int, str, dict[str, Any], int]:
        run = await until_state(d, run_id, "interrupted", "failed", "completed")
        gives = await _gives(d, run_id)
        await asyncio.sleep(1.0)  # nothing moves while the run waits
        status = (await d.handle({"cmd": "status"}))["status"]
        assert await _gives(d, run_id) == gives
        await d.handle({"cmd": "resume", "run_id": run_id, "by": "tester"})
        done = await until_state(d, run_id, "completed", "failed")
        return run, gives, status, done, await _gives(d, run_id)

    with controller() as ctrl:
        run_id = life(cfg, first)
        handled = len(ctrl.handled)
        run, gives, status, done, gives_after = life(cfg, second)
    assert run["state"] == "interrupted" and run["trigger"] == "timer"
    assert "waiting for the operator" in run["step"] and run["state_since"] > 0
    assert [e["state"] for e in run["experiments"]] == ["stored", "pending"]  # bookkeeping
    assert gives == 1 and handled == 1  # one give, one program run, before the resume
    assert "1 run(s) interrupted, waiting for an operator since" in status
    assert done["state"] == "completed" and gives_after == 2 and len(ctrl.handled) == 2
    with Store(tmp_path / "state", readonly=True) as store:
        assert store.log_count() == 2
        assert [j["detail"].get("by") for j in store.journal(run_id)
                if j["step"] == "resumed"] == ["tester"]
    assert not any(n.endswith(".ready") for n in os.listdir(tmp_path / "share" / "sem"))


def test_a_cancel_the_daemon_died_in_is_finished_at_the_next_start(tmp_path: Path) -> None:
    """Issue 19, 1: the daemon crashed during a cancel and, restarted, resumed the cancelled
    run and moved the robot. The cancel is journaled first: the restart finishes it."""
    cfg = write_config(tmp_path, {"c": TWO})
    with Store(tmp_path / "state") as st:
        run_id = st.create_run("c", "operator", {"campaign": "c"},
                               [("friction", "friction"), ("second", "friction")])
        st.set_run(run_id, "running", step="experiment 1/2 friction")
        st.step(run_id, "friction", "giving", attempt=1, nonce="n0", program_sha=None)
        st.step(run_id, "friction", "given")
        st.note(run_id, None, "cancel_requested")  # then the daemon died
    ready = tmp_path / "share" / "sem" / "friction.n0.ready"
    ready.parent.mkdir(parents=True)
    ready.write_text("{}\n")

    async def body(d: Daemon) -> tuple[dict[str, Any], int]:
        run = await until_state(d, run_id, "cancelled", "failed", "completed", "interrupted")
        await asyncio.sleep(0.5)
        return run, await _gives(d, run_id)

    run, gives = life(cfg, body)  # no controller at all: nothing may be given
    assert run["state"] == "cancelled" and gives == 1  # the one from before the crash
    assert not ready.exists()  # taken back
