"""ABB RAPID for the drivers that speak it (file_share, abb_rws): the neutral motion program
rendered as a module of timed ``MoveAbsJ`` moves, and parsed back (tests, the fake peers)."""

from __future__ import annotations

import math
import re
from collections.abc import Sequence

import numpy as np

from robid_link.exceptions import ConfigError, DriverError
from robid_link.jobs import MotionProgram, ProgramTrajectory

__all__ = ["RAPID_RATE_HZ", "MAX_AXES", "rapid_units", "render_rapid", "parse_rapid",
           "module_name"]

#: joint targets per second in the module (the controller interpolates between them)
RAPID_RATE_HZ = 25.0
#: six robot axes plus one external axis in ``eax_a``
MAX_AXES = 7

_TARGET = re.compile(r"\[\[([^\]]*)\],\[([^\]]*)\]\]")


def rapid_units(joint_types: Sequence[str]) -> np.ndarray:
    """RAPID joint targets per model unit: degrees per radian, millimetres per metre."""
    return np.array([180 / math.pi if t == "revolute" else 1000.0 for t in joint_types])


def module_name(exp_id: str) -> str:
    """The RAPID module (and file stem) of one experiment: an identifier of ≤ 32 chars."""
    return re.sub(r"[^A-Za-z0-9_]", "_", f"robid_{exp_id}")[:32]


def render_rapid(program: MotionProgram, rate_hz: float = RAPID_RATE_HZ) -> bytes:
    """An ABB RAPID module that replays the program's trajectory as timed MoveAbsJ through
    joint targets (degrees; mm for prismatic axes; a 7th axis goes to eax_a). Logging of q and
    τ is the cell's own test-signal set-up and not part of the module."""
    traj = program.trajectory()
    return _render(traj, program.exp_id, rate_hz)


def _render(traj: ProgramTrajectory, exp_id: str, rate_hz: float) -> bytes:
    n = traj.q.shape[1]
    if n > MAX_AXES:
        raise DriverError(f"experiment {exp_id}: RAPID joint targets hold at most {MAX_AXES} "
                          f"axes, the program has {n}")
    step = max(1, round(traj.rate_hz / rate_hz))
    idx = np.arange(0, traj.t.size, step)
    if idx[-1] != traj.t.size - 1:
        idx = np.append(idx, traj.t.size - 1)
    pts = traj.q[idx] * rapid_units(traj.joint_types)
    dts = np.diff(traj.t[idx])
    rows = []
    for p in pts:
        rob = [f"{x:.4f}" for x in p[:6]] + ["0"] * (6 - min(6, n))
        ext = [f"{p[6]:.4f}" if n == 7 else "9E9"] + ["9E9"] * 5
        rows.append(f"[[{','.join(rob)}],[{','.join(ext)}]]")
    body = ",\n        ".join(rows)
    lines = [
        f"MODULE {module_name(exp_id)}",
        f"    ! robid_link motion program: experiment {exp_id}, robot {traj.robot}",
        f"    ! {traj.kind} trajectory, {traj.t[-1]:.3f} s, {len(idx)} joint targets",
        f"    CONST num n_points := {len(idx)};",
        f"    CONST num dt{{{len(dts)}}} := [{', '.join(f'{d:.4f}' for d in dts)}];",
        f"    CONST jointtarget path{{{len(idx)}}} := [\n        {body}];",
        "",
        "    PROC main()",
        "        MoveAbsJ path{1}, v100, fine, tool0;",
        "        WaitTime 0.5;",
        "        FOR i FROM 2 TO n_points DO",
        "            MoveAbsJ path{i}, v1000 \\T:=dt{i-1}, z1, tool0;",
        "        ENDFOR",
        "        MoveAbsJ path{n_points}, v100, fine, tool0;",
        "    ENDPROC",
        "ENDMODULE",
        "",
    ]
    return "\n".join(lines).encode()


def parse_rapid(text: str, joint_types: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """Joint targets (rad / m) and their move times from a module ``render_rapid`` wrote."""
    n = len(joint_types)
    m = re.search(r"jointtarget path\{(\d+)\} := \[(.*?)\];", text, re.S)
    d = re.search(r"CONST num dt\{(\d+)\} := \[(.*?)\];", text, re.S)
    if m is None or d is None:
        raise ConfigError("RAPID module: no 'path' joint targets or 'dt' times")
    targets = []
    for rob, ext in _TARGET.findall(m.group(2)):
        vals = [float(x) for x in rob.split(",")][: min(6, n)]
        if n == 7:
            vals.append(float(ext.split(",")[0]))
        targets.append(vals)
    if len(targets) != int(m.group(1)):
        raise ConfigError("RAPID module: target count differs from the declared size")
    dts = np.array([float(x) for x in d.group(2).split(",")])
    return np.array(targets) / rapid_units(joint_types), dts
