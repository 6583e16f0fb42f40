"""The store's interface: every operation the daemon, the campaigns, the cycle and the
operator commands use, async and backend-neutral (a cell's SQLite, a plant's PostgreSQL).

What a store keeps, and the guarantees every backend gives:

- **runs** (``run_id``, ``campaign``, ``trigger``, ``state`` in ``RUN_STATES``,
  ``state_since`` (when the run entered its state: set by ``create_run`` and by every
  ``set_run`` that changes the state, kept by one that does not), ``created``, ``started``,
  ``finished``, ``spec`` (a dict), ``error``, ``step``), each with its
  **experiments** in order (``run_id``, ``exp_id``, ``position``, ``kind``, ``state``,
  ``attempt``, ``nonce``, ``program_sha``, ``done_sha``, ``done_size``, ``log_sha``,
  ``error``, ``updated``) and a **journal** of steps (``seq``, ``time``, ``run_id``,
  ``exp_id``, ``step``, ``detail`` (a dict)). A step changes an experiment's row and
  journals it in one transaction: a daemon killed at any moment resumes from the journal.
- **raw logs and programs**: content-addressed files on the cell's disk (``dir``), written and
  made durable before the row that names them, so every log is stored exactly once.
- **results** (``id``, ``run_id``, ``robot``, ``kind``, ``time``, ``record`` (a dict)),
  **approvals** of programs by hash, **parameter sets** (``sha256``, ``robot``, ``version``,
  ``run_id``, ``created``, ``body`` (bytes), ``approved``, ``approved_by``) and their
  **uploads** (``seq``, ``robot``, ``sha256``, ``time``, ``run_id``, ``state``, ``error``).
- A store opened for a robot is that robot's view of a shared database: its runs, logs,
  programs and approvals; every row it writes names the robot. The **robots** directory holds
  each robot's type, description and the daemon that holds it.
- One daemon per state dir and robot (``StoreLockedError``); a full disk is ``StoreFullError``
  (the run waits; nothing stored is lost); an unknown run or experiment is ``ConfigError``.

Rows cross the interface as plain dicts (JSON-able but for ``body``), never a backend's row
type. No operation blocks the event loop: a backend does its I/O on its own thread (SQLite) or
with an async driver.
"""

from __future__ import annotations

import abc
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Self

from robid_link.exceptions import ConfigError
from robid_link.jobs import MotionProgram

__all__ = ["AsyncStore", "RUN_STATES", "STEP_FIELDS", "log_file", "log_url", "is_url",
           "pick_param_set", "acknowledged_sets"]

#: ``interrupted``: a daemon restarted under the run; it finished the run's bookkeeping (logs
#: announced before the restart stored, what needs no motion done) and waits for an operator's
#: ``resume`` before any further motion (``state_since`` says since when)
RUN_STATES = ("queued", "running", "interrupted", "completed", "failed", "cancelled")
#: the columns of an experiment a step may set
STEP_FIELDS = frozenset({"attempt", "nonce", "program_sha", "done_sha", "done_size", "log_sha",
                         "error"})


def log_file(folder: Path, sha: str) -> Path:
    """Where the raw log of SHA-256 ``sha`` lives under a store's ``folder``."""
    return folder / "logs" / sha[:2] / f"{sha}.csv"


def is_url(location: str) -> bool:
    """An fsspec URL (``s3://…``, ``file://…``) rather than a folder."""
    return "://" in location


def log_url(location: str, sha: str) -> str:
    """Where the raw log ``sha`` is, given its row's ``location`` (a folder or a URL)."""
    if is_url(location):
        return f"{location.rstrip('/')}/logs/{sha[:2]}/{sha}.csv"
    return str(log_file(Path(location), sha))


def pick_param_set(sets: Sequence[dict[str, Any]], robot: str, ref: str) -> dict[str, Any]:
    """The one set of ``sets`` whose version is ``ref`` or whose sha256 starts with it."""
    hits = [s for s in sets if str(s["version"]) == ref or s["sha256"].startswith(ref)]
    if len(hits) != 1:
        raise ConfigError(f"robot {robot}: {'no' if not hits else 'more than one'} "
                          f"parameter set matches {ref!r}")
    return hits[0]


def acknowledged_sets(uploads: Sequence[dict[str, Any]]) -> list[str]:
    """The sets a controller acknowledged, oldest first, without repeats in a row: the last
    is in use, the one before it is what a rollback restores."""
    out: list[str] = []
    for sha in (u["sha256"] for u in uploads if u["state"] == "acknowledged"):
        if not out or out[-1] != sha:
            out.append(sha)
    return out


class AsyncStore(abc.ABC):
    """A store as the daemon uses it: ``async with Backend(...) as store`` (or ``open`` and
    ``close``); every operation awaited. ``dir`` is the cell's own folder (raw logs, programs,
    reports), ``reserve_bytes`` the free space kept in reserve (no new motion below it)."""

    dir: Path
    reserve_bytes: int

    async def __aenter__(self) -> Self:
        await self.open()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # ----------------------------------------------------------------- life cycle
    @abc.abstractmethod
    async def open(self) -> None:
        """Take the store for this daemon (StoreLockedError if another daemon holds it) and
        create or migrate its schema."""

    @abc.abstractmethod
    async def close(self) -> None:
        """Finish every operation already asked for, then release the store; safe twice."""

    # ----------------------------------------------------------------- space
    @abc.abstractmethod
    async def free_bytes(self) -> int:
        """Free bytes where the raw logs are written."""

    @abc.abstractmethod
    async def require_space(self, need_bytes: int = 0, what: str = "a new run") -> None:
        """StoreFullError (before any motion) unless ``need_bytes`` fit above the reserve."""

    # ----------------------------------------------------------------- robots
    @abc.abstractmethod
    async def register_robot(self, robot_type: str, description_name: str, description: bytes,
                             lock: tuple[str, ...] = ()) -> None:
        """What the store's robot is: its type (the description's name) and description (what
        a fleet re-identification loads)."""

    # ----------------------------------------------------------------- runs
    @abc.abstractmethod
    async def create_run(self, campaign: str, trigger: str, spec: dict[str, Any],
                         experiments: list[tuple[str, str]]) -> str:
        """A new queued run with its experiments (``(exp_id, kind)`` in order); its id."""

    @abc.abstractmethod
    async def set_run(self, run_id: str, state: str, *, error: str | None = None,
                      step: str | None = None) -> None:
        """A run's state (one of ``RUN_STATES``), error and current step, journaled."""

    @abc.abstractmethod
    async def run(self, run_id: str) -> dict[str, Any]:
        """One run with its ``experiments`` and ``progress`` (``stored``, ``total``)."""

    @abc.abstractmethod
    async def runs(self, limit: int = 50) -> list[dict[str, Any]]:
        """The newest runs first, as ``run`` gives them."""

    @abc.abstractmethod
    async def unfinished_runs(self) -> list[str]:
        """Queued and running runs, oldest first: what a starting daemon finds interrupted
        (it finishes their bookkeeping; none moves again before an operator resumes it)."""

    @abc.abstractmethod
    async def given_without_run(self) -> list[dict[str, Any]]:
        """Experiments whose 'ready' may still be out although their run no longer runs."""

    # ----------------------------------------------------------------- experiments, journal
    @abc.abstractmethod
    async def experiments(self, run_id: str) -> list[dict[str, Any]]:
        """A run's experiments in order."""

    @abc.abstractmethod
    async def experiment(self, run_id: str, exp_id: str) -> dict[str, Any]:
        """One experiment's row."""

    @abc.abstractmethod
    async def step(self, run_id: str, exp_id: str, state: str, **fields: Any) -> None:
        """An experiment's new state and ``fields`` (of ``STEP_FIELDS``), journaled, in one
        transaction."""

    @abc.abstractmethod
    async def note(self, run_id: str, exp_id: str | None, step: str, **detail: Any) -> None:
        """A journal line that changes no state (a retry, a raw log stored, a drift flag)."""

    @abc.abstractmethod
    async def journal(self, run_id: str | None = None) -> list[dict[str, Any]]:
        """The journal (of one run, or all) in order."""

    # ----------------------------------------------------------------- raw logs
    @abc.abstractmethod
    def log_path(self, sha: str) -> Path:
        """Where the raw log of ``sha`` is (no I/O): under ``dir``, or the ``log_store``
        folder that holds the logs instead."""

    @abc.abstractmethod
    async def put_log(self, data: bytes, *, run_id: str | None = None,
                      exp_id: str | None = None) -> str:
        """Store a raw log under its SHA-256, durable before its row; idempotent. With
        ``run_id``, the journal line 'raw_stored' (``log_sha``, ``size``) of that run and
        experiment is written in the same transaction: no log is ever stored unjournaled."""

    @abc.abstractmethod
    async def check_log(self, sha: str) -> Path:
        """The stored log's path after hashing it again (RobidError if missing or damaged)."""

    @abc.abstractmethod
    async def log_count(self) -> int:
        """How many raw logs are stored."""

    # ----------------------------------------------------------------- programs, approvals
    @abc.abstractmethod
    async def program_for(self, key: str) -> str | None:
        """The hash of the program generated for ``key``, if it is still stored."""

    @abc.abstractmethod
    async def put_program(self, key: str, program: MotionProgram) -> str:
        """Keep a generated program (files durable first) under ``key``; its hash."""

    @abc.abstractmethod
    async def load_program(self, sha: str) -> MotionProgram:
        """A stored program, checked against its hash."""

    @abc.abstractmethod
    async def approve(self, sha: str, campaign: str, exp_id: str, by: str) -> None:
        """An operator approved the program of hash ``sha`` for unattended runs."""

    @abc.abstractmethod
    async def approved(self, sha: str) -> bool:
        """Whether the program of hash ``sha`` is approved."""

    # ----------------------------------------------------------------- results
    @abc.abstractmethod
    async def add_result(self, run_id: str, robot: str, kind: str,
                         record: dict[str, Any], *, model_version: str = "") -> None:
        """A run's result of ``kind`` (replacing an earlier one of the same run, kind and
        model version: ``''`` is the run's own model, another a fleet re-identification)."""

    @abc.abstractmethod
    async def results(self, robot: str | None = None, run_id: str | None = None,
                      model_version: str | None = "") -> list[dict[str, Any]]:
        """Results (of a robot, of a run; of the runs' own model, of a model version, or all
        with None) in the order they were stored."""

    # ----------------------------------------------------------------- parameter sets
    @abc.abstractmethod
    async def add_param_set(self, doc: dict[str, Any], body: bytes) -> int:
        """Keep a parameter set (its exact bytes); its version for the robot."""

    @abc.abstractmethod
    async def param_sets(self, robot: str) -> list[dict[str, Any]]:
        """A robot's parameter sets by version."""

    async def param_set(self, robot: str, ref: str) -> dict[str, Any]:
        """A set by version number or (a prefix of) its sha256."""
        return pick_param_set(await self.param_sets(robot), robot, ref)

    @abc.abstractmethod
    async def approve_param_set(self, sha: str, by: str) -> None:
        """An operator approved a parameter set for unattended uploads."""

    @abc.abstractmethod
    async def record_upload(self, robot: str, sha: str, run_id: str | None, state: str,
                            error: str | None = None) -> None:
        """An upload attempt: ``sent``, then ``acknowledged`` or ``failed``."""

    @abc.abstractmethod
    async def uploads(self, robot: str) -> list[dict[str, Any]]:
        """A robot's upload attempts in order."""

    async def active_param_sets(self, robot: str) -> list[str]:
        """The sets the controller acknowledged, oldest first (``acknowledged_sets``)."""
        return acknowledged_sets(await self.uploads(robot))
