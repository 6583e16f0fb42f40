"""The report document: one JSON-able dict of everything report.html shows, built from the
worker's public results (IdentResult, Diagnosis, ElasticityResult, tracking, history)."""

from __future__ import annotations

import math
import shlex
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from robid_link import __version__
from robid_link.ident.fit.results import IdentResult
from robid_link.ident.model.robot import Robot
from robid_link.ident.report.pack import pack
from robid_link.ident.report.series import joint_units, signals

if TYPE_CHECKING:  # the report imports neither scipy.stats nor the elasticity fits
    from robid_link.ident.diagnosis.diagnose import Diagnosis
    from robid_link.ident.elastic.elasticity import ElasticityResult

__all__ = ["report_document", "ladder_section", "tracking_section", "bode_section",
           "parameter_rows", "FORMAT"]

FORMAT = "robid-report/1"
#: suggestions drawn with their evidence figures (all of them are in the table)
EVIDENCE_MAX = 5
#: points per evidence scatter (a scatter may take every k-th row: order does not matter)
EVIDENCE_POINTS = 6000

#: what a parameter name's prefix stands for (the leading term of a base parameter)
_MEANING = {"m": "mass of link {j}", "mx": "first moment m·cx of link {j}",
            "my": "first moment m·cy of link {j}", "mz": "first moment m·cz of link {j}",
            "xx": "inertia Ixx of link {j} about its frame", "yy": "inertia Iyy of link {j}",
            "zz": "inertia Izz of link {j}", "xy": "product of inertia Ixy of link {j}",
            "xz": "product of inertia Ixz of link {j}", "yz": "product of inertia Iyz of link {j}",
            "ia": "rotor inertia through the gear, joint {j}", "fv": "viscous friction, joint {j}",
            "fc": "Coulomb friction, joint {j}", "off": "torque offset, joint {j}",
            "fcp": "Coulomb friction moving +, joint {j}",
            "fcn": "Coulomb friction moving −, joint {j}",
            "fst": "Stribeck breakaway above Coulomb, joint {j}",
            "fp": "pre-sliding friction level, joint {j}",
            "rps": "ripple, sine amplitude, joint {j}",
            "rpc": "ripple, cosine amplitude, joint {j}",
            "dfc": "Coulomb friction drift, joint {j}", "dfv": "viscous friction drift, joint {j}",
            "mu": "load-dependent friction coefficient, joint {j}",
            "fpc": "power-law friction, Coulomb part, joint {j}",
            "fpv": "power-law friction, velocity part, joint {j}",
            "fpb": "power-law friction, offset, joint {j}",
            "spr": "spring (Fourier term), joint {j}"}
#: prefixes whose value cannot be negative for a body that exists (when not a combination)
_NON_NEGATIVE = {"m": "a negative mass", "xx": "a negative moment of inertia",
                 "yy": "a negative moment of inertia", "zz": "a negative moment of inertia",
                 "ia": "a negative rotor inertia", "fv": "negative viscous friction (it would "
                 "feed energy in)", "fc": "negative Coulomb friction (it would push, not brake)"}


def _finite(x: Any) -> float | None:
    return float(x) if x is not None and math.isfinite(float(x)) else None


def _prefix(name: str) -> tuple[str, str]:
    prefix, _, joint = name.rpartition("_")
    prefix = "spr" if prefix.startswith("spr") else prefix
    return prefix, joint.lstrip("mj")


def parameter_rows(doc: Mapping[str, Any]) -> list[dict[str, Any]]:
    """The parameter table: value, σ, %σ, CAD value, change, unit, side, meaning, check."""
    rows = []
    for p in doc["parameters"]:
        prefix, joint = _prefix(p["name"])
        value, std, cad = p["value"], p["std"], p.get("nominal")
        change = None if cad is None else value - cad
        lone = p["expression"].strip() == p["name"]
        if prefix in _NON_NEGATIVE and lone and value < -2.0 * std:
            check, ok = f"{_NON_NEGATIVE[prefix]}: not physical", False
        elif std > abs(value) and std > 0:
            check, ok = "σ larger than the value: not identified from these logs", None
        elif prefix in _NON_NEGATIVE and lone:
            check, ok = "sign physical", True
        else:  # a first moment or product of inertia may have either sign
            check, ok = "any sign" if lone else "combination: no sign to check", None
        rows.append({
            "name": p["name"], "value": value, "std": std, "rel_std_pct": p.get("rel_std_pct"),
            "nominal": cad, "change": change,
            "change_sigmas": None if change is None or std <= 0 else abs(change) / std,
            "unit": p.get("unit") or "", "side": p.get("side", "joint"),
            "meaning": _MEANING.get(prefix, "").format(j=joint),
            "expression": p["expression"], "check": check, "check_ok": ok,
            "identified": not std > abs(value)})
    return rows


def _consistency(doc: Mapping[str, Any]) -> str:
    cons = doc.get("consistent")
    if cons:
        eig = cons.get("min_eig_pseudo_inertia") or []
        state = "physically consistent" if cons.get("physically_consistent") else \
            "NOT physically consistent"
        return (f"standard parameters {state}: smallest eigenvalue of each link's "
                f"pseudo-inertia {', '.join(f'{x:.3g}' for x in eig)} (positive: a body that "
                "can exist)")
    return ("base parameters (OLS/WLS/IRLS): signs are checked where a parameter is not a "
            "combination; a full physical-consistency check needs --method consistent")


def _verdict(res: Mapping[str, Any] | None, dg: Mapping[str, Any] | None) -> dict[str, str]:
    if dg is not None:
        code = dg["verdict"]
        if code == "missing_effect":
            top = dg["suggestions"][0]
            text = (f"missing effect: {top['label']} cuts the held-out error by "
                    f"{100 * top['gain']:.0f} %")
            if len(dg["suggestions"]) > 1:
                text += f" ({len(dg['suggestions']) - 1} more suggestion(s) below)"
        elif code == "doubtful":
            text = "doubtful: " + "; ".join(dg.get("doubts") or [])
        else:
            text = "adequate: no catalog effect cuts the held-out error significantly"
        return {"code": code, "text": text}
    if res is None:
        return {"code": "none", "text": "no identification in this report"}
    at = [str(k + 1) for k, ok in enumerate(res.get("at_noise_floor") or []) if ok]
    text = (f"not diagnosed; joint(s) {', '.join(at)} at the noise floor (residual white)" if at
            else "not diagnosed: run robid diagnose to learn which effect is missing")
    return {"code": "not_diagnosed", "text": text}


def _errors(doc: Mapping[str, Any]) -> dict[str, Any]:
    keys = ("rmse", "noise_floor", "rmse_fit", "rmse_nominal")
    return {"per_joint": [{"joint": jt["joint"], "name": jt["name"],
                           **{k: _finite((doc.get(k) or [None] * len(doc["joints"]))[i])
                              for k in keys},
                           "unit": joint_units(jt["type"])["tau"]}
                          for i, jt in enumerate(doc["joints"])],
            "relative_error": _finite(doc.get("relative_error")),
            "relative_error_nominal": _finite(doc.get("relative_error_nominal")),
            "validation_source": doc.get("validation_source"),
            "errors_on": doc.get("errors_on", {})}


def _robot_drawing(robot: Robot, q: np.ndarray, where: str) -> dict[str, Any]:
    """Joint origins and axes (world frame, metres) at pose q, for the drawing."""
    import pinocchio as pin

    data = robot.model.createData()
    pin.forwardKinematics(robot.model, data, robot.pin_q(np.asarray(q, dtype=float)))
    points = [[0.0, 0.0, 0.0]]
    axes = []
    for j in range(robot.n):
        m = data.oMi[j + 1]
        points.append([float(x) for x in m.translation])
        axes.append([float(x) for x in np.asarray(m.rotation) @ robot.axes[j]])
    return {"points": points, "axes": axes, "parents": [p + 1 for p in robot.parents],
            "q": [float(x) for x in q], "where": where,
            "gravity": [float(x) for x in robot.gravity]}


def _robot_section(robot: Robot | None, joints: Sequence[Mapping[str, Any]], pose: Any,
                   where: str) -> dict[str, Any]:
    out: dict[str, Any] = {"name": robot.name if robot else None, "joints": []}
    for jt in joints:
        row = {**jt, "units": joint_units(jt.get("type", "revolute"))}
        if robot is not None:
            j = int(jt["joint"]) - 1
            lim = robot.limits
            row["limits"] = {k: [_finite(lo), _finite(hi)] for k, lo, hi in (
                ("q", lim.q_min[j], lim.q_max[j]), ("qd", -lim.qd_max[j], lim.qd_max[j]),
                ("tau", -lim.tau_max[j], lim.tau_max[j]))}
        out["joints"].append(row)
    if robot is not None:
        q = np.zeros(robot.n) if pose is None else np.asarray(pose, dtype=float)
        out["drawing"] = _robot_drawing(robot, q, where if pose is not None else "q = 0")
    return out


def _evidence(dg: Diagnosis, suggestions: list[dict[str, Any]]) -> dict[str, Any]:
    """The diagnosis' residual rows (filtered residual with q, q̇, q̈) of the joints the first
    suggestions name: what their R² and repeat figures were computed on."""
    res = dg.residuals
    if not res or "r" not in res:
        return {}
    joints = sorted({s["joint"] for s in suggestions[:EVIDENCE_MAX] if s.get("joint")})
    n = res["r"].shape[0]
    step = max(1, math.ceil(n / EVIDENCE_POINTS))
    out = {}
    for j in joints:
        out[str(j)] = {k: pack(np.asarray(res[k])[::step, j - 1]) for k in ("r", "q", "qd", "qdd")}
    return out


def _diagnosis_section(dg: Diagnosis, model_file: str | Path | None) -> dict[str, Any]:
    doc = dg.to_dict()
    target = shlex.quote(str(model_file)) if model_file else "MODEL.yaml"
    for k, s in enumerate(doc["suggestions"], 1):
        s["rank"] = k
        s["command"] = f"robid model add {target} {s['label']}"
        r2 = {v: s.get(f"r2_{v}") for v in ("q", "qd", "qdd")}
        known = {v: x for v, x in r2.items() if x is not None}
        s["strongest"] = max(known, key=lambda v: known[v]) if known else None
        s["evidence_figures"] = k <= EVIDENCE_MAX and s.get("joint") is not None
    doc["model_file"] = str(model_file) if model_file else None
    doc["evidence"] = _evidence(dg, doc["suggestions"])
    return doc


def ladder_section(records: Sequence[Mapping[str, Any]], data_sha: Sequence[str] = ()
                   ) -> dict[str, Any]:
    """The error ladder: history records in order, one rung per run (an identify and a
    diagnose record of the same model and data are one rung), each model a version labelled
    by what it added or removed; ``data_sha``: this report's logs (rungs on them marked)."""
    rungs: list[dict[str, Any]] = []
    versions: list[tuple[str, ...]] = []
    for rec in records:
        effects = tuple(rec.get("effects") or ())
        shas = tuple(sorted(d.get("sha256") or "" for d in rec.get("data") or []))
        last = rungs[-1] if rungs else None
        if last and last["effects"] == list(effects) and last["_shas"] == shas and \
                last.get("run_id") == rec.get("run_id") and rec.get("kind") not in last["kinds"]:
            last["kinds"].append(rec.get("kind"))
            last["verdict"] = last["verdict"] or rec.get("verdict")
            continue
        if effects not in versions:
            versions.append(effects)
        v = versions.index(effects)
        prev = versions[v - 1] if v else ()
        added = [e for e in effects if e not in prev]
        removed = [e for e in prev if e not in effects]
        label = (f"v{v + 1}: " + " ".join([*(f"+{e}" for e in added),
                                         *(f"−{e}" for e in removed)])) if v else \
            f"v1: {', '.join(effects) or 'no effects'}"
        rungs.append({"_shas": shas, "time": rec.get("time"), "kinds": [rec.get("kind")],
                      "run_id": rec.get("run_id"), "version": v + 1, "label": label,
                      "effects": list(effects), "added": added, "removed": removed,
                      "rmse": [_finite(x) for x in rec.get("rmse") or []],
                      "relative_error": _finite(rec.get("relative_error")),
                      "data": [Path(d.get("path") or "").name for d in rec.get("data") or []],
                      "same_data": bool(data_sha) and set(shas) == set(data_sha),
                      "verdict": rec.get("verdict")})
    for r in rungs:
        del r["_shas"]
    return {"rungs": rungs, "versions": len(versions)}


def tracking_section(tracking: Mapping[str, Any], joints: Sequence[Mapping[str, Any]]
                     ) -> dict[str, Any]:
    """Verification runs by phase (``before``/``after``/``check``: a Tracking's ``as_dict``):
    the tool's errors in mm and each joint's in degrees (mm for a prismatic joint)."""
    phases = {}
    for phase in ("before", "after", "check"):
        tr = tracking.get(phase)
        if not tr:
            continue
        scale = [1000.0 if jt.get("type") == "prismatic" else 180.0 / math.pi for jt in joints]
        if len(scale) != len(tr["joint_rms"]):
            scale = [180.0 / math.pi] * len(tr["joint_rms"])
        phases[phase] = {"tool_rms_mm": tr["tool_rms_mm"], "tool_max_mm": tr["tool_max_mm"],
                         "residual_mm": tr["residual_mm"],
                         "joint_rms": [x * s for x, s in zip(tr["joint_rms"], scale,
                                                             strict=True)],
                         "joint_max": [x * s for x, s in zip(tr["joint_max"], scale,
                                                             strict=True)]}
    units = ["mm" if jt.get("type") == "prismatic" else "deg" for jt in joints]
    return {"phases": phases, "joint_units": units, "trace": _tracking_trace(tracking)}


def _tracking_trace(tracking: Mapping[str, Any], points: int = 600) -> dict[str, Any] | None:
    """The phases' tool-error traces on one time grid (each phase's bin peaks interpolated;
    null past a phase's end), or None when no phase has one."""
    traces = {ph: tr["trace"] for ph in ("before", "after", "check")
              if (tr := tracking.get(ph)) and isinstance(tr.get("trace"), Mapping)
              and len(tr["trace"].get("t") or ()) >= 2}
    if not traces:
        return None
    end = max(float(tr["t"][-1]) for tr in traces.values())
    grid = np.linspace(0.0, end, points)
    out: dict[str, Any] = {"t": [round(float(x), 4) for x in grid]}
    for ph, tr in traces.items():
        t, mm = np.asarray(tr["t"], dtype=float), np.asarray(tr["mm"], dtype=float)
        y = np.interp(grid, t, mm, left=np.nan, right=np.nan)
        out[ph] = [None if not math.isfinite(v) else round(float(v), 5) for v in y]
    return out


def bode_section(results: Sequence[ElasticityResult]) -> dict[str, Any]:
    """The Bode figures and the fitted parameters of one or more elasticity results (a run's
    experiments one after the other: their joints, responses and notes in that order)."""
    from robid_link.ident.elastic.elasticity import bode_cells

    out: dict[str, Any] = {"frfs": [], "joints": [], "notes": [], "data_files": []}
    for el in results:
        for frf in el.frfs:
            fine, cells = bode_cells(el, frf)
            names = ([f"H{a}{b}" for a in frf.joints for b in frf.joints]
                     if len(frf.joints) == 2 else [f"joint {frf.joints[0]}"])
            out["frfs"].append({
                "joints": list(frf.joints), "f_hz": [float(x) for x in frf.f_hz],
                "coherence": [float(x) for x in np.clip(frf.coherence, 0.0, 1.0)],
                "f_model": [float(x) for x in fine], "cells": [
                    {"name": name, "mag": np.abs(meas).tolist(),
                     "phase": np.degrees(np.angle(meas)).tolist(),
                     "mag_model": np.abs(line).tolist(),
                     "phase_model": np.degrees(np.angle(line)).tolist()}
                    for name, (meas, line) in zip(names, cells, strict=True)]})
        doc = el.to_dict()
        out["robot"], out["side"] = doc["robot"], doc["side"]
        out["joints"] += doc["joints"]
        out["notes"] += doc["notes"]
        out["data_files"] += doc["data_files"]
        if "coupled" in doc and "coupled" not in out:
            out["coupled"] = doc["coupled"]
    return out


def report_document(*, result: IdentResult | None = None, diagnosis: Diagnosis | None = None,
                    elasticity: ElasticityResult | None = None,
                    tracking: Mapping[str, Any] | None = None,
                    history: Sequence[Mapping[str, Any]] | None = None,
                    robot: Robot | None = None, model_file: str | Path | None = None,
                    run: Mapping[str, Any] | None = None, title: str | None = None
                    ) -> dict[str, Any]:
    """Everything report.html shows, as one JSON-able document (arrays packed)."""
    if result is None and diagnosis is not None:
        result = diagnosis.result
    if robot is None and result is not None and result.problem is not None:
        robot = result.problem.robot
    if result is None and elasticity is None and tracking is None and not history:
        raise ValueError("report: nothing to show (no result, elasticity, tracking or history)")
    res_doc = result.to_dict() if result is not None else None
    dg_doc = _diagnosis_section(diagnosis, model_file) if diagnosis is not None else None
    joints = (res_doc["joints"] if res_doc else robot.mapping() if robot else
              [{"joint": j.joint, "name": f"joint {j.joint}", "type": "revolute"}
               for j in elasticity.joints] if elasticity else [])
    files, series, stats = signals(result) if result is not None else ([], [], None)
    pose, where = None, ""
    if result is not None and result.problem is not None:
        log = result.problem.preps[0].log
        pose, where = log.q[0], f"the first sample of {Path(log.path).name}"
    name = (res_doc or {}).get("robot") or (robot.name if robot else None) or \
        (elasticity.robot if elasticity else "robot")
    doc: dict[str, Any] = {
        "format": FORMAT, "title": title or f"robid report — {name}",
        "generated": time.strftime("%Y-%m-%d %H:%M:%S %z"), "version": __version__,
        "run": dict(run) if run else None,
        "robot": {**_robot_section(robot, joints, pose, where), "name": name},
        "model": {"effects": (res_doc or {}).get("effects"),
                  "file": str(model_file) if model_file else None,
                  "hyper_parameters": (res_doc or {}).get("hyper_parameters")},
        "method": (res_doc or {}).get("method"),
        "verdict": _verdict(res_doc, dg_doc),
        "files": files, "series": series, "residual_stats": stats,
        "noise_floor": (res_doc or {}).get("noise_floor"),
        "diagnosis": dg_doc, "notes": (res_doc or {}).get("notes", []),
        "ladder": None, "bode": None, "tracking": None, "parameters": None, "errors": None,
        "preprocessing": None}
    if res_doc is not None:
        doc["errors"] = _errors(res_doc)
        doc["parameters"] = {"rows": parameter_rows(res_doc), "consistency":
                             _consistency(res_doc), "condition_number":
                             res_doc.get("condition_number"), "rank": res_doc.get("rank"),
                             "least_excited": res_doc.get("least_excited")}
        doc["preprocessing"] = res_doc.get("preprocessing")
    if history:
        doc["ladder"] = ladder_section(history, [f.get("sha256") or "" for f in files])
    if elasticity is not None:
        doc["bode"] = bode_section([elasticity])
    if tracking:
        doc["tracking"] = tracking_section(tracking, joints)
    return doc
