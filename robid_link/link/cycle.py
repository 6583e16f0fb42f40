"""One experiment's cycle, journaled step by step: give (program + 'ready') → take ('done',
with a timeout) → fetch → store the raw log → load-check it. A failed attempt is withdrawn
(its stop/abort first, then the failure stored) and retried a bounded number of times with a
growing, jittered delay and a fresh nonce, so a late answer of an earlier attempt is recognised
as stale. Every state is resumable after a crash; after a restart the cycle first runs without
motion (``may_give=False``): it takes and stores what was given before, and stops with
``MotionWithheld`` where a new give would be needed."""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import secrets
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

from robid_link.exceptions import (
    CycleError,
    DataError,
    DriverError,
    ProtocolError,
    StoreFullError,
    StoreUnavailableError,
)
from robid_link.jobs import MotionProgram
from robid_link.link.driver import Done, Driver
from robid_link.link.retry import Backoff
from robid_link.link.store import AsyncStore

__all__ = ["CyclePolicy", "run_cycle", "new_nonce", "MotionWithheld", "BOOKKEEPING_TAKE_S"]

log = logging.getLogger("robid.cycle")

#: test hook: ``ROBID_FAULT_KILL_AFTER=step[:n]`` SIGKILLs the daemon right after the n-th
#: journal entry of that step (proves resumption at every point of the cycle)
KillHook = Callable[[str], None]
#: told ``(exp_id, nonce)`` of an attempt withdrawn while the store could not journal it
#: (the daemon journals it when the store answers again)
Withdrawn = Callable[[str, str], None]

#: after a restart, the least time an attempt given before it is waited for (its own timeout
#: may have run out while no daemon watched: its answer may be there all the same)
BOOKKEEPING_TAKE_S = 3.0


class MotionWithheld(Exception):  # noqa: N818 - control flow, not an error
    """The cycle would give a program (a new attempt) while motion is not allowed: after a
    restart, until an operator resumes the run."""

    def __init__(self, exp_id: str) -> None:
        super().__init__(f"experiment {exp_id}: motion withheld until an operator resumes")
        self.exp_id = exp_id


@dataclass(frozen=True)
class CyclePolicy:
    timeout_s: float
    retries: int = 2
    backoff_s: float = 2.0
    backoff_cap_s: float = 60.0

    @property
    def backoff(self) -> Backoff:
        return Backoff(self.backoff_s, max(self.backoff_s, self.backoff_cap_s))


def new_nonce() -> str:
    return secrets.token_hex(4)


async def run_cycle(store: AsyncStore, driver: Driver, run_id: str, exp_id: str,
                    program: MotionProgram, policy: CyclePolicy,
                    check_log: Callable[[str], Awaitable[Any]],
                    kill_hook: KillHook = lambda step: None, *, may_give: bool = True,
                    on_withdrawn: Withdrawn = lambda exp_id, nonce: None) -> str:
    """Run (or resume) one experiment; returns the SHA-256 of its stored, checked log. With
    ``may_give`` false nothing is given: an attempt given before is taken (within what is left
    of its timeout) and stored, and ``MotionWithheld`` is raised where a give would follow.
    Anything else failing while a program is out (the store unreachable or full, a bug)
    withdraws it before the error goes on (``on_withdrawn`` is told when the store could not
    journal that)."""
    if program.exp_id != exp_id:  # a cached program shared by two experiments (same content)
        program = dataclasses.replace(program, exp_id=exp_id)
    row = await store.experiment(run_id, exp_id)
    if row["log_sha"]:
        if row["nonce"] and row["done_sha"]:  # stopped before the share was tidied
            try:
                await driver.acknowledge(Done(exp_id, row["nonce"], row["done_sha"],
                                              row["done_size"]))
            except (DriverError, OSError) as err:
                log.warning("run=%s exp=%s acknowledge failed: %s", run_id, exp_id, err)
        return str(row["log_sha"])
    attempt, nonce, state = int(row["attempt"]), row["nonce"], row["state"]
    if state == "failed":  # the verdict was journaled before the stop: it stands
        reason = row.get("error") or "it failed"
        raise CycleError(f"experiment {exp_id}: {reason} (failed before the restart; a restart "
                         "adds no attempt)")
    if state == "attempt_failed" and nonce:  # killed before the old 'ready' was taken back
        await driver.withdraw(exp_id, nonce)
    if state == "attempt_failed" and attempt > policy.retries:
        # stopped between the last allowed attempt's failure and its verdict: a restart buys
        # no further attempt
        reason = row.get("error") or "its last attempt failed"
        await store.step(run_id, exp_id, "failed", error=reason)
        raise CycleError(f"experiment {exp_id}: {reason} (after {attempt} attempt"
                         f"{'s' if attempt > 1 else ''}; a restart adds none)")
    if state not in ("giving", "given", "taken"):
        nonce = None  # pending, or a failed attempt: start a new one
    take_s = policy.timeout_s
    if not may_give and state == "giving":
        # a give under way when the daemon stopped: whatever of it went out is taken back, and
        # the attempt does not count (no daemon saw it given)
        await driver.withdraw(exp_id, nonce)
        await store.step(run_id, exp_id, "pending", attempt=attempt - 1, nonce=None)
        raise MotionWithheld(exp_id)
    if not may_give and state == "given":  # taken within what is left of its timeout
        take_s = max(BOOKKEEPING_TAKE_S, policy.timeout_s - (time.time() - row["updated"]))
    while True:
        answered = False  # the controller announced this attempt's end: nothing to stop
        try:
            if nonce is None and not may_give:
                raise MotionWithheld(exp_id)
            if nonce is None:
                # room for the log before the robot moves (StoreFullError pauses the run)
                await store.require_space(20 * len(program.files.get("traj.csv", b"")),
                                          f"experiment {exp_id}")
                attempt += 1
                nonce = new_nonce()
                await store.step(run_id, exp_id, "giving", attempt=attempt, nonce=nonce,
                                 program_sha=program.sha256)
                kill_hook("giving")
                state = "giving"
            if state == "giving":
                await driver.put_program(program)
                await driver.give_ready(exp_id, nonce)
                await store.step(run_id, exp_id, "given")
                log.info("run=%s exp=%s step=given nonce=%s attempt=%d", run_id, exp_id, nonce,
                         attempt)
                kill_hook("given")
                state = "given"
            if state == "given":
                done = await driver.take_done(exp_id, nonce, take_s)
                answered = True
                await store.step(run_id, exp_id, "taken", done_sha=done.sha256,
                                 done_size=done.size)
                log.info("run=%s exp=%s step=taken sha256=%s", run_id, exp_id, done.sha256[:12])
                kill_hook("taken")
                state = "taken"
            row = await store.experiment(run_id, exp_id)
            done = Done(exp_id, nonce, row["done_sha"], row["done_size"])
            data = await driver.fetch_logs(done)
            # raw bytes are safe (and journaled) before anything can reject them
            sha = await store.put_log(data, run_id=run_id, exp_id=exp_id)
            kill_hook("raw_stored")
            try:
                await check_log(str(store.log_path(sha)))
            except DataError as err:
                raise DataError(f"log of experiment {exp_id} (kept as {sha[:12]}): "
                                f"{str(err).split(': ', 1)[-1]}") from err
            await store.step(run_id, exp_id, "stored", log_sha=sha, error=None)
            log.info("run=%s exp=%s step=stored log=%s bytes=%d", run_id, exp_id, sha[:12],
                     len(data))
            kill_hook("stored")
            try:
                await driver.acknowledge(done)
            except (DriverError, OSError) as err:  # cosmetic: the log is already safe
                log.warning("run=%s exp=%s acknowledge failed: %s", run_id, exp_id, err)
            return sha
        except (DriverError, DataError) as err:
            # the stop/abort goes out before the failure is stored: nothing the controller
            # could still run waits on a journal write
            await _withdraw(driver, run_id, exp_id, nonce)
            # the verdict is decided before it is journaled, in one step: a stop between an
            # 'attempt_failed' and a 'failed' would let a restart give an attempt that the
            # verdict had refused (after a ProtocolError the motion may already have run)
            protocol = isinstance(err, ProtocolError)
            final = protocol or attempt > policy.retries
            try:
                await store.step(run_id, exp_id, "failed" if final else "attempt_failed",
                                 error=str(err))
            except (StoreFullError, StoreUnavailableError):
                on_withdrawn(exp_id, nonce)
                raise
            log.warning("run=%s exp=%s attempt=%d failed: %s", run_id, exp_id, attempt, err)
            if protocol:  # the robot may have moved: an operator decides
                raise CycleError(f"experiment {exp_id}: {err} (not retried: the controller "
                                 "answered, the motion may have run)") from err
            if final:
                raise CycleError(f"experiment {exp_id}: {err} (after {attempt} attempt"
                                 f"{'s' if attempt > 1 else ''})") from err
            if not may_give:
                raise MotionWithheld(exp_id) from err
            delay = policy.backoff.delay(attempt)
            await store.note(run_id, exp_id, "retry", attempt=attempt + 1,
                             delay_s=round(delay, 3))
            await asyncio.sleep(delay)
            nonce, state, take_s = None, "pending", policy.timeout_s
        except Exception as err:
            # the store (or a bug) failed while a program may be out: the robot is stopped
            # before the error goes on (the run waits, or fails, with nothing running)
            if nonce and state in ("giving", "given") and not answered:
                log.warning("run=%s exp=%s withdrawing attempt %d: %s", run_id, exp_id,
                            attempt, str(err).splitlines()[0] if str(err) else
                            type(err).__name__)
                await _withdraw(driver, run_id, exp_id, nonce)
                if isinstance(err, (StoreFullError, StoreUnavailableError)):
                    on_withdrawn(exp_id, nonce)
            raise


async def _withdraw(driver: Driver, run_id: str, exp_id: str, nonce: str) -> None:
    try:
        await driver.withdraw(exp_id, nonce)
    except DriverError as err:
        log.warning("run=%s exp=%s withdraw failed: %s", run_id, exp_id, err)
