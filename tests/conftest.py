"""Shared fixtures: robots, simulated logs with known truth, the real KUKA data."""

from __future__ import annotations

import os

# BLAS on one thread, as the CLI runs it (robid_link/cli/__init__.py) and the benches: set before
# numpy loads. Two OpenBLAS threads spinning on small matrices cost the excitation test six
# times its CPU, more with the two workers of `make test` on two cores.
if not any(k in os.environ for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS",
                                     "MKL_NUM_THREADS")):
    os.environ["OPENBLAS_NUM_THREADS"] = "1"

import asyncio
import logging
import math
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
import pytest

from robid_link.fakes.plant import Plant, Truth, perturbed_inertials
from robid_link.ident.data.logs import write_log_csv
from robid_link.ident.excite.excitation import random_fourier
from robid_link.ident.fit.design import base_set_for
from robid_link.ident.model.effects import Model
from robid_link.ident.model.robot import Robot, load_robot

ROOT = Path(__file__).resolve().parent.parent
ROBOTS = ROOT / "examples" / "robots"
KUKA = ROOT.parent / "shared" / "data" / "kuka_lwr4"


# ----------------------------------------------------------------------------- test kinds

#: every test is a unit test (one part, in-process fakes) unless its file is listed here:
#: contract tests run one interface against every implementation (each driver with its peer,
#: the golden transcripts); end-to-end tests run the daemon, a peer in another process, a
#: browser or a real server. `pytest -m unit` is the quick loop; `make test` runs them all.
TEST_KINDS = {
    "contract": ("drivers/test_contract.py", "drivers/test_golden_*.py"),
    "e2e": ("link/test_end_to_end*.py", "drivers/test_*_end_to_end.py",
            "link/test_harden_process.py", "link/test_verify_campaign.py",
            "link/test_daemon_properties.py", "browser/test_*.py", "test_examples.py"),
}


def kind_of(path: Path) -> str:
    """The kind of a test file (``unit``, ``contract`` or ``e2e``) by ``TEST_KINDS``."""
    rel = path.resolve().relative_to(ROOT / "tests")
    kinds = [k for k, globs in TEST_KINDS.items() if any(rel.match(g) for g in globs)]
    assert len(kinds) <= 1, f"{rel}: listed as {kinds}"
    return kinds[0] if kinds else "unit"


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        item.add_marker(getattr(pytest.mark, kind_of(item.path)))
    if hasattr(config, "workerinput"):  # an xdist worker: the controller takes this order
        items[:] = longest_first(items)


# ----------------------------------------------------------------------------- -n 2 (xdist)

#: files whose tests share module-level state, so one worker runs them all (the fuzz tally of
#: test_fuzz_cli.py counts the inputs of test_fuzz.py too)
SAME_WORKER = {"tests/test_fuzz.py": "tests/test_fuzz_cli.py"}


#: files that run several processes each (a daemon per cell): sent out first with the
#: end-to-end files
SLOW_FILES = ("drivers/test_hostile.py",)


def longest_first(items: list[pytest.Item]) -> list[pytest.Item]:
    """The files in the order two workers take them: the end-to-end ones (and
    ``SLOW_FILES``) first, then by number of tests, so the last file either worker takes is
    short and both finish close together. Within a file the order stays."""
    def scope(item: pytest.Item) -> str:
        rel = item.path.resolve().relative_to(ROOT).as_posix()
        return SAME_WORKER.get(rel, rel)

    count: dict[str, int] = {}
    first: dict[str, int] = {}
    for i, item in enumerate(items):
        count[scope(item)] = count.get(scope(item), 0) + 1
        first.setdefault(scope(item), i)

    def key(item: pytest.Item) -> tuple[bool, int, int]:
        rel = item.path.resolve().relative_to(ROOT / "tests")
        slow = kind_of(item.path) == "e2e" or any(rel.match(g) for g in SLOW_FILES)
        return not slow, -count[scope(item)], first[scope(item)]

    return sorted(items, key=key)


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """``make test`` runs ``-n 2 --dist loadfile``: each file on one worker (its module-scoped
    fixtures, a browser, a report made once, stay once), the files of ``SAME_WORKER``
    together, in the order of ``longest_first``. Other ``--dist`` modes are xdist's own."""
    if config.getoption("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    config.option.loadscopereorder = False  # the workers' collection is in order already

    class Scheduling(LoadFileScheduling):  # type: ignore[misc]
        def _split_scope(self, nodeid: str) -> str:
            scope = str(super()._split_scope(nodeid))
            return SAME_WORKER.get(scope, scope)

    return Scheduling(config, log)


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    """Lines a test leaves for the end of the run (``record_property("summary", line)``):
    collected where the terminal is (the controller under ``-n 2``)."""
    if report.when == "call":
        _SUMMARY.extend(str(v) for k, v in report.user_properties if k == "summary")


def pytest_terminal_summary(terminalreporter: Any) -> None:
    for text in _SUMMARY:
        terminalreporter.write_line(text)


_SUMMARY: list[str] = []


@pytest.fixture(scope="session")
def arm3() -> Robot:
    return load_robot(ROBOTS / "arm3.yaml")


@pytest.fixture(scope="session")
def industrial6() -> Robot:
    return load_robot(ROBOTS / "industrial6.yaml")


@pytest.fixture(scope="session")
def kuka_dir() -> Path:
    if not (KUKA / "kuka_lwr4.urdf").is_file():
        pytest.skip("real KUKA LWR4+ data not found in ../shared/data/kuka_lwr4")
    return KUKA


@dataclass
class SimLog:
    path: Path
    truth: Truth
    data: dict[str, np.ndarray]

    def true_base(self, robot: Robot, model: Model) -> np.ndarray:
        """β = K·θ_true for the model's structural base set (friction from the truth)."""
        base, names = base_set_for(robot, model.blocks(robot))
        full = np.zeros(len(names))
        full[: 10 * robot.n] = self.truth.inertials
        for eff in self.truth.effects:
            key = {"viscous": ("fv_", "fv"), "coulomb": ("fc_", "fc"), "offset": ("off_", "b")}
            prefix, field = key[eff["name"]]
            for j in range(robot.n):
                if eff.get("joint") in (None, j + 1) and f"{prefix}{j + 1}" in names:
                    full[names.index(f"{prefix}{j + 1}")] = eff[field]
        return base.combination @ full


def simulate(robot: Robot, path: Path, *, duration: float = 30.0, rate: float = 500.0,
             noise: float = 0.5, effects: tuple = ({"name": "viscous", "fv": 2.0},
                                                   {"name": "coulomb", "fc": 1.5}),
             seed: int = 0, derivatives: bool = True, q_resolution: float = 0.0,
             inertials: np.ndarray | None = None) -> SimLog:
    """A CSV log of the inverse-dynamics plant following a random Fourier trajectory."""
    traj = random_fourier(robot, harmonics=5, base_hz=0.1, seed=seed)
    t = np.arange(0.0, duration, 1.0 / rate)
    q, qd, qdd = traj.evaluate(t)
    truth = Truth(perturbed_inertials(robot, seed + 100) if inertials is None else inertials,
                  effects=tuple(effects), noise_tau=noise, q_resolution=q_resolution)
    log = Plant(robot, truth).run(t, q, qd, qdd, seed=seed + 200)
    write_log_csv(path, log["t"], log["q"], log["tau"], log["qd"] if derivatives else None,
                  log["qdd"] if derivatives else None)
    return SimLog(path, truth, log)


# ----------------------------------------------------------------------------- leak check


class _LeakCheckLoop(asyncio.SelectorEventLoop):
    """Records the tasks still pending when ``asyncio.run``'s main coroutine returns: the
    runner would cancel them silently, but a task that outlives its owner is a leak (an
    unjoined ``_xxx_loop``, a forgotten ``create_task``)."""

    def __init__(self) -> None:
        super().__init__()
        self._main_done = False

    def run_until_complete(self, future: Any) -> Any:
        first = not self._main_done
        self._main_done = True
        try:
            return super().run_until_complete(future)
        finally:
            if first:
                _LEAKED_TASKS.extend(
                    f"{t.get_name()} ({getattr(t.get_coro(), '__qualname__', t.get_coro())})"
                    for t in asyncio.all_tasks(self) if not t.done())


class _LeakCheckPolicy(asyncio.DefaultEventLoopPolicy):
    def new_event_loop(self) -> asyncio.AbstractEventLoop:
        return _LeakCheckLoop()


_LEAKED_TASKS: list[str] = []


@pytest.fixture(autouse=True)
def no_leaks() -> Iterator[None]:
    """A test that leaves a thread (observer, fake controller, worker bridge) running, or an
    asyncio task pending when its ``asyncio.run`` returns, fails. The identification's slot
    threads (``robid-slot``) live as long as the process by design (``model.threads``)."""
    before = set(threading.enumerate())
    old_policy = asyncio.get_event_loop_policy()
    asyncio.set_event_loop_policy(_LeakCheckPolicy())
    _LEAKED_TASKS.clear()
    try:
        yield
    finally:
        asyncio.set_event_loop_policy(old_policy)
    tasks = list(_LEAKED_TASKS)
    _LEAKED_TASKS.clear()
    assert not tasks, f"test leaked asyncio tasks: {tasks}"
    end = time.monotonic() + 5.0
    while time.monotonic() < end:
        left = [t for t in set(threading.enumerate()) - before if t.is_alive()
                and not t.name.startswith(("asyncio_", "ThreadPoolExecutor", "robid-slot"))]
        if not left:
            return
        time.sleep(0.05)
    raise AssertionError(f"test leaked threads: {[t.name for t in left]}")


@pytest.fixture(autouse=True)
def robid_logging() -> Iterator[None]:
    """The ``robid`` logger as it was before the test: a test that runs ``setup_logging`` (the
    daemon's or the demo's, in-process) leaves a handler on that test's captured stdout and
    stops propagation, and a later test's log lines would go to a closed file and miss
    ``caplog`` — which test comes later depends on the order (``-n 2`` changes it)."""
    logger = logging.getLogger("robid")
    saved = (list(logger.handlers), logger.level, logger.propagate)
    try:
        yield
    finally:
        for h in set(logger.handlers) - set(saved[0]):
            logger.removeHandler(h)
        logger.handlers[:] = saved[0]
        logger.setLevel(saved[1])
        logger.propagate = saved[2]


def mdh_to_urdf(robot: Robot) -> str:
    """An equivalent URDF of a serial MDH robot (same placements, axes and inertials)."""
    parts = [f'<robot name="{robot.name}_urdf">', '<link name="base"/>']
    parent = "base"
    for j in range(robot.n):
        pl = robot.placements[j]
        xyz = " ".join(f"{v:.17g}" for v in np.array(pl.translation))
        rpy = " ".join(f"{v:.17g}" for v in pin.rpy.matrixToRpy(np.array(pl.rotation)))
        inert = pin.Inertia.FromDynamicParameters(robot.nominal[10 * j: 10 * j + 10])
        c = np.array(inert.lever)
        ic = np.array(inert.inertia)
        kind = "revolute" if robot.joint_types[j] == "revolute" else "prismatic"
        link = f"l{j + 1}"
        parts.append(
            f'<joint name="{robot.joint_names[j]}" type="{kind}"><parent link="{parent}"/>'
            f'<child link="{link}"/><origin xyz="{xyz}" rpy="{rpy}"/><axis xyz="0 0 1"/>'
            f'<limit lower="{-math.pi}" upper="{math.pi}" effort="5000" velocity="3"/></joint>')
        parts.append(
            f'<link name="{link}"><inertial><origin xyz="{c[0]:.17g} {c[1]:.17g} {c[2]:.17g}"/>'
            f'<mass value="{inert.mass:.17g}"/><inertia ixx="{ic[0, 0]:.17g}" '
            f'ixy="{ic[0, 1]:.17g}" ixz="{ic[0, 2]:.17g}" iyy="{ic[1, 1]:.17g}" '
            f'iyz="{ic[1, 2]:.17g}" izz="{ic[2, 2]:.17g}"/></inertial></link>')
        parent = link
    parts.append("</robot>")
    return "\n".join(parts)


# ----------------------------------------------------------------------------- servers


@pytest.fixture(scope="session")
def postgres() -> Iterator[Any]:
    """A real PostgreSQL cluster on loopback for the session (tests/servers.py)."""
    from tests.servers import postgres_server

    with postgres_server() as pg:
        yield pg


@pytest.fixture
def pg_url(postgres: Any) -> str:
    """A fresh, empty database of the session's cluster: its URL (no password in it)."""
    return str(postgres.create_database())


@pytest.fixture(scope="session")
def dask_scheduler() -> Iterator[Any]:
    """A real ``dask scheduler`` with one ``dask worker`` on loopback for the session."""
    from tests.servers import dask_cluster

    with dask_cluster() as cluster:
        yield cluster
