"""Joint elasticity from frequency responses: the results of the two-mass fits per joint and
the coupled fit of a pair (H11, H12, H21, H22 with the coupled inertia Jcop), the job over
logs, summary and figures. The models are in ``models``, the fits in ``fitting``.

Model (motor side measured): Jm·q̈m + D(q̇m − q̇a) + K(qm − qa) = τ,
Ja·q̈a + Jcop·q̈a2 + Ba·q̇a + Kg·qa + D(q̇a − q̇m) + K(qa − qm) = 0 (Ba: the joint's viscous
friction on the arm side; Kg gravity's stiffness at the pose, from the rigid model).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from robid_link.exceptions import DataError, EstimationError, RobidError
from robid_link.ident.data.logs import Log
from robid_link.ident.elastic.fitting import (
    CoupledElasticity,
    JointElasticity,
    arm_swing,
    fit_coupled,
    fit_two_mass,
)
from robid_link.ident.elastic.frequency import (
    Frf,
    frf_from_log,
    frf_from_schedule,
    log_rate,
    log_schedule,
)
from robid_link.ident.elastic.models import (
    arm_coulomb_frf,
    as_logged,
    coupled_frf,
    three_mass_frf,
    two_mass_frf,
)
from robid_link.ident.model.robot import Robot
from robid_link.ident.model.threads import in_free_slots

__all__ = ["two_mass_frf", "three_mass_frf", "coupled_frf", "arm_coulomb_frf", "as_logged",
           "arm_swing", "gravity_stiffness", "JointElasticity", "CoupledElasticity",
           "ElasticityResult", "fit_two_mass", "fit_coupled", "identify_elasticity",
           "elasticity_figures", "bode_cells"]

_T = TypeVar("_T")


@dataclass
class ElasticityResult:
    """What ``robid elasticity`` reports; keeps the FRFs it was fitted on (for the figures)."""

    robot: str
    joints: list[JointElasticity]
    frfs: list[Frf]
    coupled: CoupledElasticity | None = None
    side: str = "joint"
    notes: list[str] = field(default_factory=list)
    data_files: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        doc: dict[str, Any] = {"robot": self.robot, "side": self.side,
                               "joints": [j.as_dict() for j in self.joints],
                               "notes": list(self.notes), "data_files": list(self.data_files)}
        if self.coupled is not None:
            doc["coupled"] = self.coupled.as_dict()
        doc["frfs"] = [_frf_dict(f) for f in self.frfs]
        return doc

    def summary(self) -> str:
        unit = "kg·m²" if self.side == "joint" else "kg·m² (motor side)"
        lines = [f"Elasticity of {self.robot} ({len(self.joints)} joint(s), inertias in {unit}, "
                 "K in N·m/rad, D in N·m·s/rad)",
                 f"  {'joint':>5} {'Jm':>10} {'Ja':>10} {'K':>11} {'D':>9} {'f_res Hz':>9} "
                 f"{'f_anti Hz':>9} {'Ba':>8} {'delay ms':>8} {'fit rms':>8} {'χ²/dof':>7}"]
        for j in self.joints:
            lines.append(f"  {j.joint:>5} {j.jm:>10.4g} {j.ja:>10.4g} {j.k:>11.5g} {j.d:>9.4g} "
                         f"{j.f_res_hz:>9.4g} {j.f_antires_hz:>9.4g} {j.ba:>8.3g} "
                         f"{1e3 * j.delay_s:>8.3g} {j.fit_rms:>8.3g} {j.chi2:>7.3g}")
            lines.append(f"  {'±':>5} {j.std['jm']:>10.2g} {j.std['ja']:>10.2g} "
                         f"{j.std['k']:>11.2g} {j.std['d']:>9.2g} {'':>9} {'':>9} "
                         f"{j.std['ba']:>8.2g} {1e3 * j.std.get('delay_s', 0.0):>8.2g}")
        held = sorted({j.hold_s for j in self.joints if j.hold_s > 0})
        if held:
            lines.append(f"  the logged torque is held over each sample "
                         f"({', '.join(f'{1e3 * h:.3g} ms' for h in held)}; fitted with the "
                         "hold's delay and aliasing), the delay column is on top of it")
        if self.coupled is not None:
            c = self.coupled
            lines.append(f"  coupled {c.joints[0]}–{c.joints[1]}: Jcop {c.jcop:.4g} "
                         f"± {c.std['jcop']:.2g}, fit rms {c.fit_rms:.3g}")
        lines += [f"  [{i}] {n}" for i, n in enumerate(self.notes, 1)]
        return "\n".join(lines)


# ----------------------------------------------------------------------------- job


def identify_elasticity(robot: Robot, logs: Sequence[Log], *, joints: Sequence[int] = (),
                        pair: tuple[int, int] | None = None,
                        schedule: Sequence[dict[str, Any]] | None = None,
                        tau_model: Sequence[np.ndarray] | None = None,
                        side: str = "joint", inertials: np.ndarray | None = None
                        ) -> ElasticityResult:
    """Elasticity of ``joints`` (1-based, each its own two-mass fit) and/or a coupled ``pair``
    from stepped-sine logs. ``schedule``: the steps from the trajectory header (else detected
    in each log); ``tau_model``: per log, the identified rigid-body + friction torque;
    ``inertials``: standard parameters for the arm's gravity stiffness at the logs' pose
    (default the robot's nominal ones)."""
    if not logs:
        raise EstimationError("elasticity: no logs")
    for j in (*joints, *(pair or ())):
        if not 1 <= j <= robot.n:
            raise EstimationError(f"elasticity: joint {j} not in 1..{robot.n}")
    notes: list[str] = []
    frfs: list[Frf] = []
    fitted: list[JointElasticity] = []
    coupled = None
    targets: list[tuple[int, ...]] = [(j,) for j in joints] + ([tuple(pair)] if pair else [])
    found = None if schedule is not None else [
        _named(log.path, log_schedule, log.t, log.q, log.tau) for log in logs]
    log_rates = [log_rate(log.t) for log in logs]
    gravity_known = threading.Event()
    kg: list[np.ndarray] = []

    def gravity() -> None:
        try:
            kg.append(_gravity_stiffness_of_logs(robot, logs, side, inertials, notes))
        finally:
            gravity_known.set()

    def analyse(target: tuple[int, ...]) -> tuple[Frf, list[JointElasticity],
                                                  CoupledElasticity | None, list[str]] | None:
        """The target's FRF, then its fit once the gravity stiffness is known."""
        frf = _merged_frf(logs, target, schedule, tau_model, found, log_rates)
        gravity_known.wait()
        if not kg:
            return None  # the gravity stiffness failed: its error is raised first
        own: list[str] = []
        cols = [j - 1 for j in target]
        if len(target) == 1:
            return frf, [fit_two_mass(frf, own, float(kg[0][cols[0], cols[0]]))], None, own
        pj, cp = fit_coupled(frf, own, kg[0][np.ix_(cols, cols)])
        return frf, pj, cp, own

    # the pair's job, the longest, right after the gravity stiffness its fit waits for
    order = sorted(range(len(targets)), key=lambda k: -len(targets[k]))
    done = _in_free_slots([gravity] + [partial(analyse, targets[k]) for k in order])
    by_target = [done[0]] + [done[1 + p] for p in np.argsort(order)]
    for got in by_target:  # an error: the first in the order they ran in before
        if isinstance(got, RobidError):
            raise got
    for frf, pj, cp, own in by_target[1:]:
        frfs.append(frf)
        fitted += pj
        coupled = cp if cp is not None else coupled
        notes += own
    if schedule is None:
        notes.append("steps detected from the log alone (no schedule given)")
    return ElasticityResult(robot.name, fitted, frfs, coupled, side, notes,
                            [log.path for log in logs])


def gravity_stiffness(robot: Robot, q: np.ndarray, inertials: np.ndarray) -> np.ndarray:
    """∂g/∂q (n×n, symmetrized) at the pose q: the stiffness gravity adds to the arm side
    (negative where it pulls the arm away), by central differences of Y(q, 0, 0)·π."""
    from robid_link.ident.model.regressor import rigid_regressor

    n = robot.n
    eps = 1e-5
    qs = np.repeat(np.asarray(q, dtype=float)[None], 2 * n, axis=0)
    for j in range(n):
        qs[2 * j, j] += eps
        qs[2 * j + 1, j] -= eps
    zeros = np.zeros_like(qs)
    g = rigid_regressor(robot, qs, zeros, zeros) @ inertials
    kg = ((g[0::2] - g[1::2]) / (2 * eps)).T  # column j: ∂g/∂q_j
    return 0.5 * (kg + kg.T)


def _gravity_stiffness_of_logs(robot: Robot, logs: Sequence[Log], side: str,
                               inertials: np.ndarray | None, notes: list[str]) -> np.ndarray:
    theta = inertials if inertials is not None else robot.nominal
    if theta is None or side != "joint" or not np.any(robot.gravity):
        if theta is None and np.any(robot.gravity):
            notes.append("no inertials for the arm's gravity stiffness: K is the spring plus "
                         "gravity's ∂g/∂q at the pose (give the robot's inertials)")
        return np.zeros((robot.n, robot.n))
    # the joints in rows (a column of q is strided), partitioned in place: 15 ms, not 28, for
    # 822k samples; the same medians
    rows = np.empty((robot.n, sum(log.q.shape[0] for log in logs)))
    start = 0
    for log in logs:
        rows[:, start:start + log.q.shape[0]] = log.q.T
        start += log.q.shape[0]
    pose = np.median(rows, axis=1, overwrite_input=True)
    return gravity_stiffness(robot, pose, np.asarray(theta, dtype=float))


def _named(path: str, analysis: Callable[..., _T], *args: Any) -> _T:
    """The frequency analysis works on arrays: its data errors get the log's name here."""
    try:
        return analysis(*args)
    except DataError as err:
        raise DataError(f"{path}: {err}") from err


def _in_free_slots(jobs: Sequence[Callable[[], Any]]) -> list[Any]:
    """Each job's result or its error, the jobs shared by the two slots as they come free (the
    gravity stiffness, each target's FRF and fit: the sine sums and the third mass's fits
    release the GIL, and each job runs whole in one slot, so no result depends on the
    threads)."""
    out: list[Any] = [None] * len(jobs)

    def one(k: int, slot: int) -> None:
        try:
            out[k] = jobs[k]()
        except RobidError as err:
            out[k] = err

    in_free_slots(range(len(jobs)), one)
    return out


def _merged_frf(logs: Sequence[Log], target: tuple[int, ...],
                schedule: Sequence[dict[str, Any]] | None,
                tau_model: Sequence[np.ndarray] | None,
                found: Sequence[Sequence[dict[str, Any]]] | None,
                log_rates: Sequence[float]) -> Frf:
    parts = []
    for i, log in enumerate(logs):
        tm = tau_model[i] if tau_model is not None else None
        try:
            if schedule is not None:
                parts.append(_named(log.path, frf_from_schedule, log.t, log.q, log.tau,
                                    schedule, target, tm, log_rates[i]))
            else:
                parts.append(_named(log.path, frf_from_log, log.t, log.q, log.tau, target, tm,
                                    found[i] if found else None, log_rates[i]))
        except RobidError as err:  # one log without this joint's steps is fine if another has
            if len(logs) == 1:
                raise
            last = err
    if not parts:
        raise last
    if len(parts) == 1:
        return parts[0]
    order = np.argsort(np.concatenate([p.f_hz for p in parts]))
    f, g, coh, snr = (np.concatenate([getattr(p, a) for p in parts])[order]
                      for a in ("f_hz", "g", "coherence", "snr"))

    def joined(name: str) -> np.ndarray | None:
        got = [getattr(p, name) for p in parts]
        return None if any(x is None for x in got) else np.concatenate(got)[order]

    rates = {p.rate_hz for p in parts}
    return Frf(target, f, g, coh, snr, source=parts[0].source, tau_amp=joined("tau_amp"),
               drift=joined("drift"), g_var=joined("g_var"), qm_harmonics=joined("qm_harmonics"),
               rate_hz=rates.pop() if len(rates) == 1 else None)


def _frf_dict(frf: Frf) -> dict[str, Any]:
    """The measured points for a report's Bode plot (the pair's g as 2×2 lists per point)."""
    doc: dict[str, Any] = {"joints": list(frf.joints), "source": frf.source,
                           "f_hz": frf.f_hz.tolist(), "g_re": frf.g.real.tolist(),
                           "g_im": frf.g.imag.tolist(), "coherence": frf.coherence.tolist(),
                           "rate_hz": frf.rate_hz}
    if frf.g_var is not None:
        doc["g_std"] = np.sqrt(frf.g_var).tolist()
    return doc


# ----------------------------------------------------------------------------- figures


def bode_cells(res: ElasticityResult, frf: Frf
               ) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
    """(model frequencies, [(measured, model)] per cell): motor acceleration over torque of one
    fitted FRF, measured at its points and of the fit (as the log shows it: its hold and delay)
    on 400 log-spaced frequencies; one cell for a joint, H11, H12, H21, H22 (row major) for a
    pair."""
    by_joint = {j.joint: j for j in res.joints}
    fine = np.geomspace(frf.f_hz[0], frf.f_hz[-1], 400)
    s2 = -(2 * np.pi * fine) ** 2
    if len(frf.joints) == 1:
        return fine, [(frf.accel, s2 * by_joint[frf.joints[0]].model_frf(fine, logged=True))]
    a, b = (by_joint[j] for j in frf.joints)
    assert res.coupled is not None
    model = s2[:, None, None] * as_logged(
        fine, coupled_frf(fine, (a.jm, b.jm), (a.ja, b.ja), res.coupled.jcop, (a.k, b.k),
                          (a.d, b.d), (a.ba, b.ba), np.array(res.coupled.kg)),
        (a.jm, b.jm), delay_s=(a.delay_s, b.delay_s), hold_s=a.hold_s)
    return fine, [(frf.accel[:, r, c], model[:, r, c]) for r in range(2) for c in range(2)]


def elasticity_figures(res: ElasticityResult, out_dir: str | Path) -> list[Path]:
    """Bode magnitude and phase of q̈m/τ per fitted FRF: measured circles shaded by coherence,
    the model as a line, parameters and resonances under the plot; the 2×2 grid for a pair."""
    from matplotlib.ticker import NullFormatter

    from robid_link.ident.report.figures import pyplot

    plt = pyplot()

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    by_joint = {j.joint: j for j in res.joints}
    paths = []
    for frf in res.frfs:
        fine, pairs = bode_cells(res, frf)
        cells = dict(zip([(0, 0)] if len(pairs) == 1 else [(0, 0), (0, 1), (1, 0), (1, 1)],
                         pairs, strict=True))
        text = _param_text([by_joint[j] for j in frf.joints])
        if len(frf.joints) == 2:
            assert res.coupled is not None
            text += f"\nJcop {res.coupled.jcop:.4g}"
        nr, nc = (1, 1) if len(cells) == 1 else (2, 2)
        fig = plt.figure(figsize=(6.5 * nc, 5.5 * nr))
        grid = fig.add_gridspec(2 * nr, nc, height_ratios=[2, 1] * nr, hspace=0.6)
        for (r, c), (meas, line) in cells.items():
            am = fig.add_subplot(grid[2 * r, c])
            ap = fig.add_subplot(grid[2 * r + 1, c], sharex=am)
            shade = np.clip(frf.coherence, 0, 1)
            am.loglog(fine, np.abs(line), "-", color="C0", label="model")
            am.scatter(frf.f_hz, np.abs(meas), c=shade, cmap="Greys", vmin=0, vmax=1,
                       edgecolors="C3", label="measured")
            ap.semilogx(fine, np.degrees(np.angle(line)), "-", color="C0")
            ap.scatter(frf.f_hz, np.degrees(np.angle(meas)), c=shade, cmap="Greys", vmin=0,
                       vmax=1, edgecolors="C3")
            name = (f"H{frf.joints[r]}{frf.joints[c]}" if len(frf.joints) == 2
                    else f"joint {frf.joints[0]}")
            am.set_title(f"{name}: motor acceleration / motor torque")
            am.set_ylabel("|q̈m/τ|")
            ap.set_ylabel("phase (deg)")
            ap.set_xlabel("frequency (Hz)")
            for ax in (am, ap):  # log axes: label the decades only
                ax.xaxis.set_minor_formatter(NullFormatter())
            am.legend(fontsize=8)
        fig.text(0.02, 0.005, text, fontsize=8, family="monospace", va="bottom")
        fig.subplots_adjust(bottom=0.2 if nr == 1 else 0.12)
        path = out / f"elasticity_{'_'.join(map(str, frf.joints))}.png"
        fig.savefig(path, dpi=90)
        plt.close(fig)
        paths.append(path)
    return paths


def _param_text(params: Sequence[JointElasticity]) -> str:
    return "\n".join(f"joint {p.joint}: Jm {p.jm:.4g}  Ja {p.ja:.4g}  K {p.k:.5g}  D {p.d:.4g}  "
                     f"Ba {p.ba:.3g}  delay {1e3 * p.delay_s:.3g} ms  "
                     f"f_res {p.f_res_hz:.4g} Hz  f_antires {p.f_antires_hz:.4g} Hz"
                     for p in params)
