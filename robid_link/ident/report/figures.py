"""Report files: measured vs predicted torque per joint, parameter tables, robot drawings."""

from __future__ import annotations

import csv
import io
import logging
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from robid_link.atomic import atomic_write, write_json
from robid_link.ident.fit.results import IdentResult
from robid_link.ident.model.robot import Robot

__all__ = ["pyplot", "write_report", "draw_robot", "write_json", "residual_figures",
           "history_figure", "trend_figure", "tracking_figure"]


def pyplot() -> Any:
    """matplotlib's pyplot on the Agg backend (files only), its font-cache chatter quieted."""
    import matplotlib

    # a fresh install builds matplotlib's font cache at the first figure and tells of every
    # mathtext font it lacks (a screenful of "findfont: ... not found"): nothing a user acts on
    logging.getLogger("matplotlib.font_manager").setLevel(logging.ERROR)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _write_text(path: Path, text: str) -> None:
    atomic_write(path, text.encode())


def _save_figure(fig: Any, path: Path, dpi: int) -> None:
    """Render to memory first: a reader never sees half an image."""
    buf = io.BytesIO()
    fig.savefig(buf, dpi=dpi, format=path.suffix.lstrip(".").lower() or "png")
    atomic_write(path, buf.getvalue())


def write_report(res: IdentResult, out_dir: str | Path) -> list[Path]:
    """Per-joint torque figures, parameters.csv, parameters.yaml, summary.txt."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = [out / "summary.txt", out / "parameters.csv", out / "parameters.yaml"]
    _write_text(written[0], res.summary() + "\n")
    table = io.StringIO(newline="")
    w = csv.writer(table)
    w.writerow(["name", "value", "std", "rel_std_pct", "nominal", "unit", "side", "expression"])
    for p in res.parameters:
        w.writerow([p.name, f"{p.value:.10g}", f"{p.std:.6g}", f"{p.rel_std_pct:.4g}",
                    "" if p.nominal is None else f"{p.nominal:.10g}", p.unit or "", p.side,
                    p.expression])
    doc = {
        "robot": res.robot,
        "effects": res.effects,
        "hyper_parameters": res.hypers,
        "joints": res.joints,
        "base_parameters": {p.name: {"value": p.value, "std": p.std, "unit": p.unit,
                                     "side": p.side, "expression": p.expression}
                            for p in res.parameters},
    }
    _write_text(written[1], table.getvalue())
    _write_text(written[2], yaml.safe_dump(doc, sort_keys=False, allow_unicode=True))
    written += _torque_figures(res, out)
    return written


def _torque_figures(res: IdentResult, out: Path) -> list[Path]:
    if not res.traces:
        return []
    plt = pyplot()
    paths = []
    for j, jt in enumerate(res.joints):
        if all(np.isnan(tr["tau"][:, j]).all() for tr in res.traces):
            continue  # partial logs: no held-out log holds this joint's torque
        fig, (ax1, ax2) = plt.subplots(2, 1, sharex=True, figsize=(10, 5.5),
                                       gridspec_kw={"height_ratios": [2, 1]})
        for tr in res.traces:
            if np.isnan(tr["tau"][:, j]).all():  # a partial log without this joint's torque
                continue
            t = tr["t"] - tr["t"][0]
            ax1.plot(t, tr["tau"][:, j], lw=0.8, color="0.3", label="measured")
            ax1.plot(t, tr["pred"][:, j], lw=0.9, color="tab:blue", label="model")
            ax2.plot(t, tr["tau"][:, j] - tr["pred"][:, j], lw=0.6, color="tab:red")
        rmse = res.rmse[j]
        ax1.set_title(f"joint {jt['joint']} ({jt['name']}): validation, RMSE {rmse:.3g} N·m")
        ax1.set_ylabel("torque [N·m]")
        handles, labels = ax1.get_legend_handles_labels()
        ax1.legend(handles[:2], labels[:2], loc="upper right")
        ax2.axhline(0.0, color="0.6", lw=0.5)
        ax2.set_ylabel("residual [N·m]")
        ax2.set_xlabel("time [s]")
        fig.tight_layout()
        path = out / f"torque_joint{jt['joint']}.png"
        _save_figure(fig, path, 110)
        plt.close(fig)
        paths.append(path)
    return paths


def draw_robot(robot: Robot, q: np.ndarray, path: str | Path) -> Path:
    """The kinematic chain at pose q: joint origins, links, and each joint's axis."""
    import pinocchio as pin

    plt = pyplot()
    data = robot.model.createData()
    pin.forwardKinematics(robot.model, data, robot.pin_q(np.asarray(q, dtype=float)))
    pts = [np.zeros(3)]
    axes = []
    for j in range(robot.n):
        m = data.oMi[j + 1]
        pts.append(np.array(m.translation))
        axes.append(np.array(m.rotation) @ robot.axes[j])
    pts_a = np.array(pts)
    span = float(np.ptp(pts_a, axis=0).max()) or 1.0
    fig = plt.figure(figsize=(7, 7))
    ax = fig.add_subplot(projection="3d")
    parents = [-1, *robot.parents]
    for k in range(1, len(pts)):
        a = pts_a[parents[k] + 1] if parents[k] >= 0 else pts_a[0]
        b = pts_a[k]
        ax.plot(*zip(a, b, strict=True), color="tab:gray", lw=3)
    for j in range(robot.n):
        o, u = pts_a[j + 1], axes[j] * 0.12 * span
        color = "tab:red" if robot.joint_types[j] == "revolute" else "tab:green"
        ax.quiver(*o, *u, color=color, arrow_length_ratio=0.25)
    ax.scatter(*pts_a.T, color="k", s=12)
    c = pts_a.mean(axis=0)
    for setter, k in ((ax.set_xlim, 0), (ax.set_ylim, 1), (ax.set_zlim, 2)):
        setter(c[k] - 0.6 * span, c[k] + 0.6 * span)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")
    ax.set_title(f"{robot.name} at q = [{_pose_text(robot, q)}] (arrows: joint axes)")
    _place_labels(fig, ax, _joint_labels(robot, pts_a[1:], span))
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    _save_figure(fig, p, 100)
    plt.close(fig)
    return p


def _pose_text(robot: Robot, q: np.ndarray) -> str:
    """The pose as the user gives it: degrees for revolute joints, metres for prismatic."""
    return ", ".join(f"{np.degrees(v):.4g}°" if kind == "revolute" else f"{v:.4g} m"
                     for v, kind in zip(np.asarray(q, dtype=float), robot.joint_types,
                                        strict=True))


def _joint_labels(robot: Robot, origins: np.ndarray, span: float
                  ) -> list[tuple[np.ndarray, str]]:
    """One label per place: joints whose origins coincide (a wrist, a shoulder's two axes)
    share one label instead of printing over each other."""
    groups: list[tuple[np.ndarray, list[str]]] = []
    for j, o in enumerate(origins):
        name = f"{j + 1}:{robot.joint_names[j]}"
        for at, names in groups:
            if np.linalg.norm(at - o) < 0.02 * span:
                names.append(name)
                break
        else:
            groups.append((o, [name]))
    return [(at, ", ".join(names)) for at, names in groups]


#: label offsets tried in turn (points from the joint), nearest first
_LABEL_OFFSETS = ((6, 6), (6, -14), (-6, 6), (-6, -14), (14, 18), (14, -26), (-14, 18),
                  (-14, -26), (26, 0), (-26, 0), (30, 30), (30, -38), (-30, 30), (-30, -38))


def _place_labels(fig: Any, ax: Any, labels: list[tuple[np.ndarray, str]]) -> None:
    """Joint labels in screen space, each at the first offset where it overlaps no label
    placed before (joints a few millimetres apart project onto one spot)."""
    from mpl_toolkits.mplot3d import proj3d

    fig.canvas.draw()  # fixes the projection and gives a renderer
    renderer = fig.canvas.get_renderer()
    proj = ax.get_proj()
    placed: list[Any] = []
    for at, label in labels:
        x2, y2, _ = proj3d.proj_transform(*at, proj)
        for k, (dx, dy) in enumerate(_LABEL_OFFSETS):
            text = ax.annotate(
                label, (x2, y2), xytext=(dx, dy), textcoords="offset points",
                ha="left" if dx > 0 else "right", fontsize=8,
                bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.8},
                arrowprops={"arrowstyle": "-", "lw": 0.5, "color": "0.4"} if k >= 4 else None)
            box = text.get_window_extent(renderer)
            if not any(box.overlaps(other) for other in placed) or k == len(_LABEL_OFFSETS) - 1:
                placed.append(box)
                break
            text.remove()


def residual_figures(res: dict[str, np.ndarray], joints: list[dict[str, Any]], out_dir: str | Path
                     ) -> list[Path]:
    """Per joint: residual against time, q, q̇, q̈ and its spectrum; the worst region marked."""
    import scipy.signal as sig

    plt = pyplot()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    r = res["r"]
    for j, jt in enumerate(joints):
        fig, axes = plt.subplots(1, 5, figsize=(17, 3.2))
        rj = r[:, j]
        worst = int(np.argmax(np.convolve(rj**2, np.ones(50) / 50, mode="same")))
        for ax, key, label in zip(axes[:4], ("t", "q", "qd", "qdd"),
                                  ("time [s]", "q [rad]", "q̇ [rad/s]", "q̈ [rad/s²]"),
                                  strict=True):
            x = res[key] if key == "t" else res[key][:, j]
            ax.plot(x, rj, ".", ms=1.0, alpha=0.4, color="tab:blue")
            ax.plot(x[worst], rj[worst], "o", color="tab:red", ms=6, label="worst region")
            ax.set_xlabel(label)
        axes[0].set_ylabel(f"joint {jt['joint']} residual [N·m]")
        axes[0].legend(loc="upper right", fontsize=7)
        fs = float(res["fs"])
        nper = int(min(len(rj) // 4, 4 * fs)) or len(rj)
        f, pxx = sig.welch(rj, fs=fs, nperseg=max(nper, 8))
        axes[4].semilogy(f[1:], pxx[1:])
        axes[4].set_xlabel("frequency [Hz]")
        axes[4].set_ylabel("PSD")
        fig.suptitle(f"joint {jt['joint']} ({jt['name']}): where the model fails")
        fig.tight_layout()
        p = out / f"residual_joint{jt['joint']}.png"
        _save_figure(fig, p, 90)
        plt.close(fig)
        paths.append(p)
    return paths


def history_figure(records: list[dict[str, Any]], path: str | Path) -> Path:
    """The error ladder: per-joint validation RMSE per model version."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8, 4))
    rmse = np.array([r["rmse"] for r in records if r.get("rmse")], dtype=float)
    labels = [", ".join(r.get("effects") or [])[-40:] for r in records if r.get("rmse")]
    for j in range(rmse.shape[1]):
        ax.plot(range(1, len(rmse) + 1), rmse[:, j], "o-", label=f"joint {j + 1}")
    ax.set_xticks(range(1, len(rmse) + 1))
    ax.set_xticklabels([str(k) for k in range(1, len(rmse) + 1)])
    ax.set_xlabel("run (model version)")
    ax.set_ylabel("validation RMSE [N·m]")
    ax.set_yscale("log")
    ax.legend(fontsize=7)
    ax.set_title("error ladder: " + (labels[-1] if labels else ""))
    fig.tight_layout()
    p = Path(path)
    _save_figure(fig, p, 100)
    plt.close(fig)
    return p


def trend_figure(trend: Any, names: list[str], path: str | Path) -> Path:
    """Each named parameter over a robot's runs (value ± 2 std, relative to its baseline),
    flagged runs marked: the drift and wear report."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(9, 4.5))
    x = np.arange(1, len(trend.runs) + 1)
    for name in names:
        vals = trend.values[name]
        ok = [k for k, v in enumerate(vals) if v is not None]
        base = np.mean([vals[k][0] for k in ok[: trend.baseline_runs]]) or 1.0
        v = np.array([vals[k][0] for k in ok]) / base
        e = 2 * np.array([vals[k][1] for k in ok]) / abs(base)
        line = ax.errorbar(x[ok], v, yerr=e, fmt="o-", ms=3, capsize=2, label=name)
        flag = trend.first_flag(name)
        if flag is not None:
            k = next(i for i, r in enumerate(trend.runs) if r["run_id"] == flag.run_id)
            ax.plot(x[k], vals[k][0] / base, "s", ms=10, mfc="none",
                    color=line[0].get_color())
    ax.axhline(1.0, color="0.5", lw=0.8)
    ax.set_xlabel("run (oldest first)")
    ax.set_ylabel("value / baseline (±2 std)")
    ax.set_title(f"{trend.robot}: parameters over {len(trend.runs)} runs "
                 f"({len(trend.flags)} flagged, squares)")
    ax.legend(fontsize=7, ncol=3)
    fig.tight_layout()
    p = Path(path)
    _save_figure(fig, p, 100)
    plt.close(fig)
    return p


def tracking_figure(tracking: dict[str, Any], path: str | Path) -> Path:
    """Before/after the upload: tool error (RMS, max, after the stop) and per-joint RMS."""
    plt = pyplot()
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4))
    b, a = tracking["before"], tracking["after"]
    keys = [("tool_rms_mm", "tool RMS"), ("tool_max_mm", "tool max"),
            ("residual_mm", "after stop")]
    x = np.arange(len(keys))
    ax1.bar(x - 0.2, [b[k] for k, _ in keys], 0.4, label="controller on CAD")
    ax1.bar(x + 0.2, [a[k] for k, _ in keys], 0.4, label="identified set uploaded")
    ax1.set_xticks(x)
    ax1.set_xticklabels([lbl for _, lbl in keys])
    ax1.set_ylabel("tool position error [mm]")
    ax1.legend(fontsize=8)
    j = np.arange(1, len(b["joint_rms"]) + 1)
    ax2.bar(j - 0.2, np.degrees(b["joint_rms"]), 0.4, label="before")
    ax2.bar(j + 0.2, np.degrees(a["joint_rms"]), 0.4, label="after")
    ax2.set_xlabel("joint")
    ax2.set_ylabel("tracking error RMS [deg]")
    ax2.legend(fontsize=8)
    fig.suptitle(f"verification path: tool RMS {b['tool_rms_mm']:.3f} → "
                 f"{a['tool_rms_mm']:.3f} mm")
    fig.tight_layout()
    p = Path(path)
    _save_figure(fig, p, 100)
    plt.close(fig)
    return p
