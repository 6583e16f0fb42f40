"""Checks of robot descriptions before Pinocchio sees them: physical inertias, and a URDF's
structure, masses, inertias and joint limits, each refused in one line naming the link or joint.

Pinocchio's own URDF errors are multi-line C++ text and an unparsable mass silently becomes 0,
so the file is read here first (bounded, no DOCTYPE or entities).
"""

from __future__ import annotations

import math
import os
import re
import sys
import tempfile
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from robid_link.exceptions import RobotError
from robid_link.safeyaml import read_bounded

__all__ = ["inertia_problem", "UrdfJoint", "check_urdf", "MAX_URDF_BYTES", "native_stderr",
           "parser_summary"]

#: a URDF with meshes referenced by path is a few hundred kB
MAX_URDF_BYTES = 32 * 1024 * 1024
_JOINT_TYPES = {"revolute", "continuous", "prismatic", "fixed", "floating", "planar"}
_INERTIA = ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")


def inertia_problem(i_c: np.ndarray, tol: float = 1e-9) -> str | None:
    """Why a 3×3 rotational inertia (about the centre of mass) is not physical, or None.

    Symmetric positive semi-definite and the triangle inequality of its principal moments.
    """
    if not np.all(np.isfinite(i_c)):
        return "inertia must be finite"
    if not np.allclose(i_c, i_c.T, rtol=0, atol=tol * max(1.0, float(np.abs(i_c).max()))):
        return "inertia matrix is not symmetric"
    scale = max(float(np.abs(i_c).max()), 1e-300)
    eig = np.linalg.eigvalsh(i_c)
    if eig.min() < -tol * scale:
        return f"inertia is not positive semi-definite (principal moment {eig.min():.4g})"
    a, b, c = eig
    if a + b < c - tol * scale:
        return (f"principal moments {a:.4g}, {b:.4g}, {c:.4g} break the triangle inequality "
                "(no rigid body has them)")
    return None


@dataclass(frozen=True)
class UrdfJoint:
    """A joint's type and limits as written in the URDF (SI units; inf where absent)."""

    name: str
    kind: str
    lower: float = -math.inf
    upper: float = math.inf
    velocity: float = math.inf
    effort: float = math.inf
    #: why the position limits are unusable (missing, lower ≥ upper), or "" when they are fine
    limit_problem: str = ""


def _float(text: str | None, what: str, p: Path) -> float:
    try:
        v = float(text) if text is not None else math.nan
    except ValueError:
        v = math.nan
    if not math.isfinite(v):
        shown = repr(text) if text is None or len(text) <= 30 else repr(text[:27] + "...")
        raise RobotError(f"{p}: {what}: expected a finite number, got {shown}")
    return v


def _vec3(elem: ET.Element | None, attr: str, what: str, p: Path) -> None:
    text = elem.get(attr) if elem is not None else None
    if text is None:
        return
    parts = text.split()
    if len(parts) != 3:
        raise RobotError(f"{p}: {what}: expected 3 numbers, got {text[:30]!r}")
    for k, v in enumerate(parts):
        _float(v, f"{what}[{k}]", p)


def _name(elem: ET.Element, kind: str, p: Path, seen: set[str]) -> str:
    name = elem.get("name")
    if not name:
        raise RobotError(f"{p}: a <{kind}> without a name")
    if name in seen:
        raise RobotError(f"{p}: {kind} '{name[:60]}' defined twice")
    seen.add(name)
    return name


def _check_link(link: ET.Element, p: Path, seen: set[str]) -> None:
    name = _name(link, "link", p, seen)
    inertial = link.find("inertial")
    if inertial is None:
        return
    where = f"link '{name[:60]}'"
    mass = inertial.find("mass")
    if mass is None:
        raise RobotError(f"{p}: {where}: <inertial> without <mass>")
    m = _float(mass.get("value"), f"{where}: mass", p)
    if m < 0:
        raise RobotError(f"{p}: {where}: mass {m:g} is negative")
    _vec3(inertial.find("origin"), "xyz", f"{where}: inertial origin xyz", p)
    _vec3(inertial.find("origin"), "rpy", f"{where}: inertial origin rpy", p)
    inertia = inertial.find("inertia")
    if inertia is None:
        raise RobotError(f"{p}: {where}: <inertial> without <inertia>")
    v = {k: _float(inertia.get(k), f"{where}: inertia {k}", p) for k in _INERTIA}
    i_c = np.array([[v["ixx"], v["ixy"], v["ixz"]], [v["ixy"], v["iyy"], v["iyz"]],
                    [v["ixz"], v["iyz"], v["izz"]]])
    problem = inertia_problem(i_c)
    if problem:
        raise RobotError(f"{p}: {where}: {problem}")


def _check_joint(joint: ET.Element, p: Path, seen: set[str], links: set[str]) -> UrdfJoint:
    name = _name(joint, "joint", p, seen)
    where = f"joint '{name[:60]}'"
    kind = joint.get("type", "")
    if kind not in _JOINT_TYPES:
        raise RobotError(f"{p}: {where}: unknown type {kind[:30]!r} "
                         f"(expected one of {', '.join(sorted(_JOINT_TYPES))})")
    for end in ("parent", "child"):
        elem = joint.find(end)
        if elem is None or not elem.get("link"):
            raise RobotError(f"{p}: {where}: <{end} link=...> missing")
        if elem.get("link") not in links:
            raise RobotError(f"{p}: {where}: {end} link '{elem.get('link', '')[:60]}' "
                             "is not defined")
    _vec3(joint.find("origin"), "xyz", f"{where}: origin xyz", p)
    _vec3(joint.find("origin"), "rpy", f"{where}: origin rpy", p)
    axis = joint.find("axis")
    if axis is not None and axis.get("xyz") is not None:
        _vec3(axis, "xyz", f"{where}: axis", p)
        if np.linalg.norm([float(x) for x in axis.get("xyz", "").split()]) < 1e-9:
            raise RobotError(f"{p}: {where}: axis has zero length")
    if kind not in ("revolute", "prismatic", "continuous"):
        return UrdfJoint(name, kind)
    limit = joint.find("limit")
    if limit is None:
        if kind == "continuous":
            return UrdfJoint(name, kind)
        raise RobotError(f"{p}: {where}: a {kind} joint needs a <limit> element (lower, upper, "
                         "effort, velocity)")
    caps = {}
    for key in ("effort", "velocity"):
        if limit.get(key) is None:
            raise RobotError(f"{p}: {where}: <limit> without {key}")
        caps[key] = _float(limit.get(key), f"{where}: {key} limit", p)
        if caps[key] <= 0:
            raise RobotError(f"{p}: {where}: {key} limit {caps[key]:g} must be positive")
    if kind == "continuous":
        return UrdfJoint(name, kind, velocity=caps["velocity"], effort=caps["effort"])
    bounds = []
    for key in ("lower", "upper"):
        text = limit.get(key)
        if text is None:
            return UrdfJoint(name, kind, velocity=caps["velocity"], effort=caps["effort"],
                             limit_problem=f"<limit> without {key}")
        bounds.append(_float(text, f"{where}: {key} limit", p))
    lo, hi = bounds
    problem = "" if lo < hi else f"lower limit {lo:g} is not below upper limit {hi:g}"
    return UrdfJoint(name, kind, lo, hi, caps["velocity"], caps["effort"], problem)


def _end_link(joint: ET.Element, end: str) -> str:
    elem = joint.find(end)
    return "" if elem is None else str(elem.get("link", ""))


def _check_tree(p: Path, edges: list[tuple[str, str, str]], links: set[str]) -> None:
    """The links and joints form one tree: no joint on a single link, one parent joint per
    link, one root, no loop. urdfdom reports these on stderr or not at all (a joint whose
    parent is its own child is dropped silently)."""
    parent_of: dict[str, tuple[str, str]] = {}  # child link → (joint, parent link)
    for joint, parent, child in edges:
        where = f"joint '{joint[:60]}'"
        if parent == child:
            raise RobotError(f"{p}: {where}: parent and child are both link '{child[:60]}' "
                             "(a loop; a joint connects two different links)")
        if child in parent_of:
            raise RobotError(f"{p}: link '{child[:60]}' is the child of joints "
                             f"'{parent_of[child][0][:60]}' and '{joint[:60]}' (a URDF is a "
                             "tree: one parent joint per link)")
        parent_of[child] = (joint, parent)
    roots = sorted(links - set(parent_of))
    for link in sorted(parent_of):  # a loop: following the parents never reaches a root
        path, at = [], link
        while at in parent_of and at not in path:
            path.append(at)
            at = parent_of[at][1]
        if at in path:
            cycle = path[path.index(at):]
            names = " → ".join(f"'{parent_of[x][0][:40]}'" for x in reversed(cycle))
            raise RobotError(f"{p}: joints {names} form a loop (link '{at[:60]}' is its own "
                             "ancestor)")
    if len(roots) > 1:
        raise RobotError(f"{p}: links '{roots[0][:60]}' and '{roots[1][:60]}' both have no "
                         "parent joint: a URDF is one tree (attach one of them with a joint "
                         "or remove it)")


def check_urdf(path: str | Path) -> tuple[str, dict[str, UrdfJoint]]:
    """Read and check a URDF; returns its text and its joints by name."""
    p = Path(path)
    data = read_bounded(p, MAX_URDF_BYTES, RobotError)
    if re.search(rb"<!\s*(DOCTYPE|ENTITY)", data, re.IGNORECASE):
        raise RobotError(f"{p}: DOCTYPE and ENTITY declarations are refused in a URDF")
    try:
        root = ET.fromstring(data)
    except ET.ParseError as err:
        line, col = err.position
        msg = str(err).split(":")[0]
        raise RobotError(f"{p}: invalid XML at line {line}, column {col + 1}: {msg}") from None
    if root.tag != "robot":
        raise RobotError(f"{p}: the root element is <{root.tag[:30]}>, expected <robot>")
    links: set[str] = set()
    for link in root.findall("link"):
        _check_link(link, p, links)
    if not links:
        raise RobotError(f"{p}: the URDF has no <link>")
    seen: set[str] = set()
    elems = root.findall("joint")
    joints = {j.name: j for j in (_check_joint(e, p, seen, links) for e in elems)}
    _check_tree(p, [(str(e.get("name")), _end_link(e, "parent"), _end_link(e, "child"))
                    for e in elems], links)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as err:
        raise RobotError(f"{p}: not a UTF-8 text file") from err
    return text, joints


#: urdfdom's lines that only say that an earlier line failed
_GENERIC = ("joint xml is not initialized correctly", "link xml is not initialized correctly",
            "The XML stream does not contain a valid URDF model")


@contextmanager
def native_stderr() -> Iterator[list[str]]:
    """What C++ code (urdfdom, Pinocchio) writes to file descriptor 2 during the block, as
    lines in the yielded list instead of on the terminal. It writes to the descriptor, not
    to ``sys.stderr``, so the descriptor itself is pointed at a temporary file."""
    lines: list[str] = []
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with tempfile.TemporaryFile() as tmp:
            os.dup2(tmp.fileno(), 2)
            try:
                yield lines
            finally:
                os.dup2(saved, 2)
                tmp.seek(0)
                text = tmp.read(64 * 1024).decode("utf-8", "replace")
                lines.extend(line.strip() for line in text.splitlines() if line.strip())
    finally:
        os.close(saved)


def parser_summary(lines: list[str]) -> str:
    """urdfdom's messages in one line: the first two that say something (``Error:`` prefixes,
    its source locations and the generic follow-ups dropped)."""
    said = []
    for line in lines:
        text = re.sub(r"^(Error|Warning|Info|Debug):\s*", "", line).strip()
        if text and not text.startswith("at line ") and text not in _GENERIC:
            said.append(text)
    return " ".join("; ".join(dict.fromkeys(said[:2])).split())[:300]
