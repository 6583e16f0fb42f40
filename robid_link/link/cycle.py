"""One experiment's cycle, journaled step by step: give (program + 'ready') → take ('done',
with a timeout) → fetch → store the raw log → load-check it. A failed attempt is retried a
bounded number of times with a growing, jittered delay and a fresh nonce, so a late answer of
an earlier attempt is recognised as stale. Every state is resumable after a crash."""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import secrets
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

from robid_link.exceptions import CycleError, DataError, DriverError, ProtocolError
from robid_link.jobs import MotionProgram
from robid_link.link.driver import Done, Driver
from robid_link.link.retry import Backoff
from robid_link.link.store import AsyncStore

__all__ = ["CyclePolicy", "run_cycle", "new_nonce"]

log = logging.getLogger("robid.cycle")

#: test hook: ``ROBID_FAULT_KILL_AFTER=step[:n]`` SIGKILLs the daemon right after the n-th
#: journal entry of that step (proves resumption at every point of the cycle)
KillHook = Callable[[str], None]


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
                    kill_hook: KillHook = lambda step: None) -> str:
    """Run (or resume) one experiment; returns the SHA-256 of its stored, checked log."""
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
    if state == "attempt_failed" and nonce:  # killed before the old 'ready' was taken back
        await driver.withdraw(exp_id, nonce)
    if state not in ("giving", "given", "taken"):
        nonce = None  # pending, or a failed attempt: start a new one
    while True:
        try:
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
                done = await driver.take_done(exp_id, nonce, policy.timeout_s)
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
            await store.step(run_id, exp_id, "attempt_failed", error=str(err))
            try:
                await driver.withdraw(exp_id, nonce)
            except (DriverError, OSError) as werr:
                log.warning("run=%s exp=%s withdraw failed: %s", run_id, exp_id, werr)
            log.warning("run=%s exp=%s attempt=%d failed: %s", run_id, exp_id, attempt, err)
            if isinstance(err, ProtocolError):  # the robot may have moved: an operator decides
                await store.step(run_id, exp_id, "failed", error=str(err))
                raise CycleError(f"experiment {exp_id}: {err} (not retried: the controller "
                                 "answered, the motion may have run)") from err
            if attempt > policy.retries:
                await store.step(run_id, exp_id, "failed", error=str(err))
                raise CycleError(f"experiment {exp_id}: {err} (after {attempt} attempt"
                                 f"{'s' if attempt > 1 else ''})") from err
            delay = policy.backoff.delay(attempt)
            await store.note(run_id, exp_id, "retry", attempt=attempt + 1,
                             delay_s=round(delay, 3))
            await asyncio.sleep(delay)
            nonce, state = None, "pending"
