"""A URScript program's motion on the fake UR controller: the program run on the interpreter
(one target per controller step), the targets through the core's plant (its fault schedule), the
rows the controller then streams (q, q̇, τ) and the register writes on their times."""

from __future__ import annotations

import io
import logging
from dataclasses import dataclass, field

import numpy as np
import yaml

from robid_link.exceptions import RobidError
from robid_link.fakes.controller import ControllerCore
from robid_link.fakes.ur.vm import Machine, Program

__all__ = ["Motion", "simulate", "read_log"]

log = logging.getLogger("robid.fake_controller")


@dataclass
class Motion:
    """One program: compiling (``start`` None), then following ``rows`` (q, qd, τ at ``rate``)."""

    name: str
    fault: str | None = None
    start: float | None = None
    rate: float = 1.0
    rows: np.ndarray = field(default_factory=lambda: np.zeros((1, 18)))
    events: list[tuple[float, int, int]] = field(default_factory=list)  # (τ, register, value)
    fault_at: float = 0.0
    duration: float = 0.0
    next_event: int = 0
    struck: bool = False  # the fault at fault_at has happened


def simulate(core: ControllerCore, program: Program, m: Motion, *, q_start: np.ndarray,
             steptime: float, run: int, fault_at: float) -> None:
    """Run ``program`` on a machine from ``q_start``, the arm's motion on the plant (the
    core's run ``run``, its fault schedule): fills ``m`` (rows, rate, duration, register
    events; its fault strikes at ``fault_at`` of the path)."""
    step = steptime
    qd_max = float(np.min(core.robot.limits.qd_max))
    machine = program.run(Machine(q_start.tolist(), steptime=step,
                                  qd_max=qd_max if np.isfinite(qd_max) else 3.2))
    if not machine.targets:
        machine.targets.append(q_start.tolist())
    q = np.asarray(machine.targets)
    t = np.arange(q.shape[0] + 1) * step
    q = np.vstack([q, q[-1:]])
    # the plant gets the targets on the 8 ms grid (a spline through them is the path):
    # a CSV of every 2 ms step would hold the interpreter lock for seconds while parsed,
    # and this controller's clients would see their stream stall
    stride = max(1, round(0.008 / step))
    keep = np.unique(np.append(np.arange(0, t.size, stride), t.size - 1))
    buf = io.StringIO()
    np.savetxt(buf, np.column_stack([t[keep], q[keep]]), delimiter=",", fmt="%.9g",
               header="t," + ",".join(f"q{j}" for j in range(1, 7)), comments="")
    head = yaml.safe_dump({"rate_hz": 1.0 / (stride * step), "kind": "custom",
                           "robot": core.robot.name,
                           "joint_types": ["revolute"] * 6}).encode()
    res = core.run(m.name, str(run), buf.getvalue().encode(), head)
    m.fault = res.fault
    if res.fault == "never_answer":
        return
    data = res.log
    if res.fault == "fail":  # the core reports failure; the arm moves until it stops
        data = core.simulate(core.trajectory(buf.getvalue().encode(), head),
                                  core.seed + len(core.handled))
    elif res.error is not None:
        raise RobidError(res.error)
    arr = read_log(data)
    qd = np.gradient(arr[:, 1:7], arr[:, 0], axis=0) if arr.shape[0] > 1 else \
        np.zeros((1, 6))
    m.rows = np.column_stack([arr[:, 1:7], qd, arr[:, 7:13]])
    m.rate = float((arr.shape[0] - 1) / max(arr[-1, 0] - arr[0, 0], 1e-9))
    m.duration = float(arr[-1, 0] - arr[0, 0])
    m.events = [(k * step, reg, value) for k, reg, value in machine.registers]
    path = [tau_ for tau_, _, _ in m.events]
    lo, hi = (min(path), max(path)) if len(path) >= 2 else (0.0, m.duration)
    m.fault_at = lo + fault_at * (hi - lo) if m.fault else float("inf")
    for text in machine.messages:
        log.info("program %s: textmsg %s", m.name, text)


def read_log(data: bytes, chunk: int = 20_000) -> np.ndarray:
    """A log CSV (header line first) as an array, parsed in slices: one parse of a long log
    would hold the interpreter lock (and this controller's streams) for seconds."""
    lines = data.split(b"\n")[1:]
    parts = [np.loadtxt(lines[k: k + chunk], delimiter=",", ndmin=2)
             for k in range(0, len(lines), chunk) if any(lines[k: k + chunk])]
    return np.vstack(parts)
