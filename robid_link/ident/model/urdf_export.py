"""Export identified standard inertial parameters as a URDF that Pinocchio (and ROS) load.

A URDF robot keeps its file with every moving link's ``<inertial>`` replaced; an MDH robot
gets a URDF written from its placements (``mdh_to_urdf``).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pinocchio as pin

from robid_link.atomic import atomic_write
from robid_link.exceptions import RobotError
from robid_link.ident.model.robot import Robot

__all__ = ["inertial_fields", "mdh_to_urdf", "urdf_with_inertials", "export_urdf"]


def inertial_fields(theta10: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Standard parameters about the joint frame → (mass, COM, 3×3 inertia about the COM)."""
    inert = pin.Inertia.FromDynamicParameters(np.asarray(theta10, dtype=float))
    return float(inert.mass), np.array(inert.lever), np.array(inert.inertia)


def _fmt(v: float) -> str:
    return f"{float(v):.17g}"


def _inertial_xml(theta10: np.ndarray) -> ET.Element:
    mass, com, ic = inertial_fields(theta10)
    el = ET.Element("inertial")
    ET.SubElement(el, "origin", xyz=" ".join(_fmt(v) for v in com), rpy="0 0 0")
    ET.SubElement(el, "mass", value=_fmt(mass))
    ET.SubElement(el, "inertia", ixx=_fmt(ic[0, 0]), ixy=_fmt(ic[0, 1]), ixz=_fmt(ic[0, 2]),
                  iyy=_fmt(ic[1, 1]), iyz=_fmt(ic[1, 2]), izz=_fmt(ic[2, 2]))
    return el


def mdh_to_urdf(robot: Robot, standard: np.ndarray | None = None) -> str:
    """A URDF of a serial MDH robot: same placements, axes and limits; inertials from
    ``standard`` (10 n, about the joint frames) or the robot's nominal ones."""
    theta = robot.nominal if standard is None else np.asarray(standard, dtype=float)
    if theta is None:
        raise RobotError(f"{robot.source}: no inertial parameters to write")
    root = ET.Element("robot", name=f"{robot.name}_urdf")
    ET.SubElement(root, "link", name="base")
    parent = "base"
    for j in range(robot.n):
        if robot.parents[j] != j - 1:
            raise RobotError(f"{robot.source}: only serial MDH robots can be written as URDF")
        pl = robot.placements[j]
        kind = "revolute" if robot.joint_types[j] == "revolute" else "prismatic"
        link = f"link_{j + 1}"
        jt = ET.SubElement(root, "joint", name=robot.joint_names[j], type=kind)
        ET.SubElement(jt, "parent", link=parent)
        ET.SubElement(jt, "child", link=link)
        ET.SubElement(jt, "origin", xyz=" ".join(_fmt(v) for v in np.array(pl.translation)),
                      rpy=" ".join(_fmt(v) for v in pin.rpy.matrixToRpy(np.array(pl.rotation))))
        ET.SubElement(jt, "axis", xyz=" ".join(_fmt(v) for v in robot.axes[j]))
        lim = robot.limits
        lo, hi = float(lim.q_min[j]), float(lim.q_max[j])
        ET.SubElement(jt, "limit", lower=_fmt(lo if math.isfinite(lo) else -math.pi),
                      upper=_fmt(hi if math.isfinite(hi) else math.pi),
                      effort=_fmt(lim.tau_max[j] if math.isfinite(lim.tau_max[j]) else 1e4),
                      velocity=_fmt(lim.qd_max[j] if math.isfinite(lim.qd_max[j]) else 10.0))
        ln = ET.SubElement(root, "link", name=link)
        ln.append(_inertial_xml(theta[10 * j: 10 * j + 10]))
        parent = link
    ET.indent(root)
    return ET.tostring(root, encoding="unicode") + "\n"


def urdf_with_inertials(robot: Robot, standard: np.ndarray) -> str:
    """The robot's own URDF with each moving link's ``<inertial>`` replaced by ``standard``.

    Pinocchio merges links hanging on fixed joints into their moving parent; the identified
    body stands for all of them, so their own inertials are removed.
    """
    src = Path(robot.source)
    try:
        tree = ET.parse(src)
    except (OSError, ET.ParseError) as err:
        raise RobotError(f"{src}: cannot read the URDF to export: {err}") from err
    root = tree.getroot()
    joints = {j.get("name"): j for j in root.findall("joint")}
    links = {ln.get("name"): ln for ln in root.findall("link")}
    children: dict[str, list[ET.Element]] = {}
    for jt in joints.values():
        parent = jt.find("parent")
        if parent is not None:
            children.setdefault(str(parent.get("link")), []).append(jt)
    for j, name in enumerate(robot.joint_names):
        moving = joints.get(name)
        if moving is None or moving.get("type") == "fixed":
            raise RobotError(f"{src}: joint '{name}' not found as a moving joint (locked "
                             "joints cannot be exported)")
        child = moving.find("child")
        link = links[str(None if child is None else child.get("link"))]
        _set_inertial(link, _inertial_xml(standard[10 * j: 10 * j + 10]))
        stack = list(children.get(str(link.get("name")), []))
        while stack:  # links welded to this body by fixed joints
            fixed = stack.pop()
            if fixed.get("type") != "fixed":
                continue
            sub = fixed.find("child")
            welded = links[str(None if sub is None else sub.get("link"))]
            _set_inertial(welded, None)
            stack += children.get(str(welded.get("name")), [])
    return ET.tostring(root, encoding="unicode") + "\n"


def _with_dynamics(text: str, robot: Robot, friction: dict[str, float]) -> str:
    root = ET.fromstring(text)
    joints = {j.get("name"): j for j in root.findall("joint")}
    for j, name in enumerate(robot.joint_names):
        fv, fc = friction.get(f"fv_{j + 1}"), friction.get(f"fc_{j + 1}")
        if fv is None and fc is None:
            continue
        jt = joints[name]
        dyn = jt.find("dynamics")
        if dyn is None:
            dyn = ET.SubElement(jt, "dynamics")
        dyn.set("damping", _fmt(fv or 0.0))
        dyn.set("friction", _fmt(fc or 0.0))
    return ET.tostring(root, encoding="unicode") + "\n"


def _set_inertial(link: ET.Element, new: ET.Element | None) -> None:
    old = link.find("inertial")
    pos = list(link).index(old) if old is not None else 0
    if old is not None:
        link.remove(old)
    if new is not None:
        link.insert(pos, new)


def export_urdf(robot: Robot, standard: np.ndarray, path: str | Path,
                friction: dict[str, float] | None = None) -> Path:
    """Write the identified model as URDF (atomic); MDH robots get a generated URDF.

    ``friction`` (parameter name → value) sets each joint's ``<dynamics damping friction>``
    from ``fv_J``/``fc_J`` where given (the other effects have no URDF field).
    """
    standard = np.asarray(standard, dtype=float)
    if standard.size != 10 * robot.n:
        raise RobotError(f"expected {10 * robot.n} standard parameters, got {standard.size}")
    is_urdf = Path(robot.source).suffix.lower() == ".urdf"
    text = urdf_with_inertials(robot, standard) if is_urdf else mdh_to_urdf(robot, standard)
    if friction:
        text = _with_dynamics(text, robot, friction)
    out = Path(path)
    atomic_write(out, text.encode())
    return out
