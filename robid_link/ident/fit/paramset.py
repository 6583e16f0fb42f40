"""The parameter set a controller gets: what one identification found (base parameters with
their expressions, friction and the other effects of the model, elasticity when measured),
as one canonical, content-hashed document — and how a controller turns it into feedforward.

The controller side needs physical link inertials, not base parameters: the set carries the
a-priori (CAD) inertials projected onto the identified base parameters, θ = θ₀ + K⁺(β − K·θ₀),
the standard parameters nearest to CAD that reproduce every identified torque exactly.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from robid_link.exceptions import ModelError
from robid_link.ident.model.robot import Robot
from robid_link.jobs import PARAMETER_SET_FORMAT as FORMAT
from robid_link.jobs import ParameterSet, canonical_bytes, set_sha256

__all__ = ["FORMAT", "make_parameter_set", "canonical_bytes", "set_sha256", "Feedforward",
           "feedforward", "setpoint_states", "setpoint_torque", "diff_sets",
           "physical_problem"]

#: joint-side friction a controller's feedforward applies (other effects: reported only)
_FRICTION = {"fv": "viscous", "fc": "coulomb", "off": "offset"}


def make_parameter_set(robot: Robot, identify_doc: Mapping[str, Any], *, run_id: str,
                       elasticity: Mapping[str, Any] | None = None,
                       periods: Mapping[int, float] | None = None) -> dict[str, Any]:
    """The parameter set of one identification (``IdentResult.to_dict()``), with the
    projected standard inertials when the robot has a-priori ones. ``periods``: the ripple
    period (rad) per joint (from 1) of the model's ``ripple`` effects, when it has some."""
    params = identify_doc.get("parameters") or []
    if not params:
        raise ModelError(f"run {run_id}: the identification has no parameters to hand over")
    base = [{k: p.get(k) for k in ("name", "value", "std", "expression", "unit", "side")}
            for p in params]
    if not all(isinstance(p["value"], int | float) and math.isfinite(p["value"])
               for p in base):
        raise ModelError(f"run {run_id}: a parameter is not a finite number; refusing to "
                         "build a parameter set from it")
    effects = list(identify_doc.get("effects") or [])
    doc: dict[str, Any] = {
        "format": FORMAT, "robot": robot.name, "joints": list(robot.joint_names),
        "run_id": run_id, "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "effects": effects, "base_parameters": base,
        "friction": _friction(robot, base, "joint"),
        # friction identified on the motors (motor-side logs, ``viscous@m6``): motor units,
        # never mixed into the joints' lists a controller feeds forward
        "friction_motor": _friction(robot, base, "motor"),
        "standard_inertials": (theta := _projected(robot, effects, base)),
        # inverse dynamics (feedforward) is linear in θ and needs no physical body; a
        # controller that simulates or checks the model wants one: say which it is
        "physically_consistent": None if theta is None else physical_problem(
            np.asarray(theta)) is None,
        "ripple": _ripple(base, identify_doc, periods or {}),
        "elasticity": [dict(e) for e in (elasticity or {}).get("joints", [])],
        "relative_error": identify_doc.get("relative_error"),
    }
    # what makes the set unfit for a controller: the fit's doubts (physically impossible,
    # worse than CAD) and standard inertials of no body; the link uploads an unfit set only
    # when the operator forces it
    unfit = [str(d) for d in identify_doc.get("doubts") or []]
    why = None if theta is None else physical_problem(np.asarray(theta))
    if why is not None:
        from robid_link.ident.fit.physics import REMEDY

        unfit.append(f"the standard inertials describe no body that can exist ({why}); {REMEDY}")
    doc["unfit"] = unfit
    doc["uploadable"] = not unfit
    doc["sha256"] = set_sha256(doc)
    return doc


def _ripple(base: list[dict[str, Any]], doc: Mapping[str, Any], periods: Mapping[int, float]
            ) -> list[dict[str, float]]:
    """Position-periodic torque (cogging) per joint: s·sin(2πq/P) + c·cos(2πq/P)."""
    values = {p["name"]: float(p["value"]) for p in base}
    hypers = doc.get("hyper_parameters") or {}
    out = []
    for name, s in values.items():
        if not name.startswith("rps_"):
            continue
        j = int(name.split("_", 1)[1])
        period = periods.get(j, (hypers.get(f"ripple@{j}") or {}).get("period"))
        if period is None or f"rpc_{j}" not in values:
            continue
        out.append({"joint": j, "period": float(period), "sin": s, "cos": values[f"rpc_{j}"]})
    return out


def _friction(robot: Robot, base: list[dict[str, Any]], side: str) -> dict[str, list[float]]:
    """Friction per joint (``side`` "joint") or per motor ("motor") for the feedforward; a
    negative viscous or Coulomb coefficient (an estimate that is noise, or another effect's
    stand-in) would push the joint: zero it."""
    values: dict[str, float] = {}
    for p in base:
        prefix, _, tail = str(p["name"]).rpartition("_")
        sided = tail[:1] in ("j", "m") and tail[1:].isdigit()
        where = ("motor" if tail[0] == "m" else "joint") if sided else (p.get("side") or "joint")
        if where == side:
            values[f"{prefix}_{tail[1:] if sided else tail}"] = float(p["value"])
    out = {kind: [values.get(f"{prefix}_{j}", 0.0) for j in range(1, robot.n + 1)]
           for prefix, kind in _FRICTION.items()}
    for kind in ("viscous", "coulomb"):
        out[kind] = [max(v, 0.0) for v in out[kind]]
    return out


def _projected(robot: Robot, effects: list[str], base: list[dict[str, Any]]
               ) -> list[float] | None:
    """θ = θ₀ + K⁺(β − K·θ₀) over the rigid-body columns; None without a-priori inertials."""
    if robot.nominal is None:
        return None
    from robid_link.ident.fit.design import base_set_for
    from robid_link.ident.model.robot import standard_parameter_names

    values = {p["name"]: float(p["value"]) for p in base}
    standard = standard_parameter_names(robot.n)
    if all(n in values for n in standard):  # a consistent fit: the standard parameters
        return [values[n] for n in standard]
    from robid_link.ident.model.effects import Model

    model = Model.parse([e for e in effects if e == "rigid_body"] or ["rigid_body"])
    bs, _ = base_set_for(robot, model.blocks(robot))
    names = list(bs.base_names)
    if not all(n in values for n in names):
        return None  # a model without rigid_body: keep CAD
    beta = np.array([values[n] for n in names])
    k_mat = bs.combination[:, : 10 * robot.n]
    theta0 = np.asarray(robot.nominal, dtype=float)
    theta = theta0 + np.linalg.pinv(k_mat) @ (beta - k_mat @ theta0)
    return [float(x) for x in theta]


def physical_problem(theta: np.ndarray) -> str | None:
    """Why standard parameters (10 per link: m, m·c, inertia about the joint frame) describe
    no rigid body, or None: positive mass, inertia about the centre of mass physical."""
    from robid_link.ident.model.robot_check import inertia_problem

    for j in range(len(theta) // 10):
        m, h = theta[10 * j], theta[10 * j + 1: 10 * j + 4]
        xx, xy, yy, xz, yz, zz = theta[10 * j + 4: 10 * j + 10]
        if not m > 0:
            return f"link {j + 1}: mass {m:.4g} is not positive"
        i_o = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
        c = h / m
        i_c = i_o - m * (np.dot(c, c) * np.eye(3) - np.outer(c, c))
        why = inertia_problem(i_c)
        if why is not None:
            return f"link {j + 1}: {why}"
    return None


@dataclass(frozen=True)
class Feedforward:
    """What a controller computes from a parameter set: standard parameters θ for its inverse
    dynamics (τ = Y(q, q̇, q̈)·θ, linear in θ) plus joint friction per joint."""

    sha256: str
    inertials: np.ndarray | None
    viscous: np.ndarray
    coulomb: np.ndarray
    offset: np.ndarray
    ripple: tuple[tuple[int, float, float, float], ...] = ()  # (joint index, P, sin, cos)

    def friction(self, qd: np.ndarray) -> np.ndarray:
        moving = np.abs(qd) > 1e-6
        return self.viscous * qd + self.coulomb * np.sign(qd) * moving + self.offset

    def extra(self, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
        """Friction plus the position-periodic terms: what is added to inverse dynamics."""
        tau = self.friction(qd)
        for j, period, s, c in self.ripple:
            ph = 2 * np.pi * q[j] / period
            tau[j] += s * np.sin(ph) + c * np.cos(ph)
        return tau


def feedforward(doc: Mapping[str, Any], n_joints: int) -> Feedforward:
    """A parameter set checked for what a controller needs; ModelError names the problem (the
    checks are the door's, ``jobs.ParameterSet``: a driver makes them without numpy)."""
    pset = ParameterSet.from_doc(doc)
    pset.check(n_joints)
    fr = doc.get("friction") or {}
    arrays = {k: np.asarray(fr.get(k, [0.0] * n_joints), dtype=float)
              for k in ("viscous", "coulomb", "offset")}
    inert = doc.get("standard_inertials")
    theta = None if inert is None else np.asarray(inert, dtype=float)
    ripple = tuple((int(r["joint"]) - 1, float(r["period"]), float(r["sin"]), float(r["cos"]))
                   for r in doc.get("ripple") or [])
    return Feedforward(pset.sha256, theta, **arrays, ripple=ripple)


def setpoint_states(q: np.ndarray, period: float) -> tuple[np.ndarray, np.ndarray]:
    """Velocity and acceleration of a setpoint series (N, n) by central differences (one-sided
    velocity and zero acceleration at the ends, where a program is at rest)."""
    if len(q) < 3:
        return np.zeros_like(q), np.zeros_like(q)
    qd = np.gradient(q, period, axis=0)
    qdd = np.zeros_like(q)
    qdd[1:-1] = (q[2:] - 2 * q[1:-1] + q[:-2]) / period**2
    return qd, qdd


def setpoint_torque(robot: Robot, ff: Feedforward, q: np.ndarray, period: float) -> np.ndarray:
    """Model torque (N, n) in N·m along setpoints ``q`` streamed every ``period`` s: rigid-body
    inverse dynamics with the set's standard inertials, τ = Y(q, q̇, q̈)·θ, plus its joint
    friction (what a driver that is the motion master feeds forward)."""
    from robid_link.ident.model.regressor import reference_regressor

    qd, qdd = setpoint_states(q, period)
    tau = np.zeros_like(q)
    if ff.inertials is not None and len(q):
        tau += reference_regressor(robot, q, qd, qdd) @ ff.inertials
    return tau + ff.friction(qd)


def diff_sets(a: Mapping[str, Any], b: Mapping[str, Any]) -> list[str]:
    """Lines naming each base parameter that differs between two sets (by name)."""
    pa = {p["name"]: p for p in a.get("base_parameters", [])}
    pb = {p["name"]: p for p in b.get("base_parameters", [])}
    out = []
    for name in dict.fromkeys([*pa, *pb]):
        if name not in pa or name not in pb:
            out.append(f"  {name:<12} only in {'the second' if name in pb else 'the first'}")
            continue
        va, vb = float(pa[name]["value"]), float(pb[name]["value"])
        if va != vb:
            sd = math.hypot(float(pa[name].get("std") or 0), float(pb[name].get("std") or 0))
            rel = f"{100 * (vb - va) / abs(va):+.1f} %" if va else "new"
            out.append(f"  {name:<12} {va:>12.5g} → {vb:<12.5g} {rel:>9}"
                       + (f"  ({abs(vb - va) / sd:.1f} σ)" if sd > 0 else ""))
    return out
