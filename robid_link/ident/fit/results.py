"""The identification result: figures, parameters, notes; a terminal summary and JSON.

Like a statsmodels results object it keeps what it was fitted on (the prepared problem and
the design) and computes the held-out figures, predictions and residuals on first use.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from robid_link.ident.data.noise import AT_FLOOR, LagSums, Whiteness, noise_floor
from robid_link.ident.data.preprocess import CHUNK, Prepared, Problem
from robid_link.ident.fit.design import (
    Design,
    block_columns,
    predict_torque,
    random_states,
)
from robid_link.ident.model.dynamics import rigid_torque
from robid_link.ident.model.threads import SLOTS, in_slots

__all__ = ["ErrorStats", "Parameter", "IdentResult", "HeldOut", "evaluate_held_out",
           "StatsAccumulator", "TRACE_SAMPLES", "parameter_unit"]

#: max samples per validation trace kept for plots
TRACE_SAMPLES = 20000


@dataclass
class ErrorStats:
    """Per-joint residual statistics (N·m) plus FloBaRoID's relative error."""

    rmse: np.ndarray
    std: np.ndarray
    var: np.ndarray
    n_samples: int
    relative_error: float | None = None  # mean‖e(t)‖ / mean‖τ(t)‖
    abs_error: float | None = None  # mean‖e(t)‖

    def as_dict(self) -> dict[str, Any]:
        return {
            "rmse": _list(self.rmse),
            "std": _list(self.std),
            "var": _list(self.var),
            "n_samples": self.n_samples,
            "relative_error": _num(self.relative_error),
            "abs_error": _num(self.abs_error),
        }


def row_mask(prep: Prepared, a: int, b: int) -> np.ndarray | None:
    """(b − a, n) bool: which joints' torques count on rows a..b of a prepared log — the
    joints the log holds (a partial log) and, of those, the rows where the joint does not
    stick (``tau_mask``); None when every torque counts."""
    m = None if prep.tau_mask is None else prep.tau_mask[a:b]
    if prep.log.partial:
        held = prep.log.held
        m = np.broadcast_to(held, (b - a, held.size)) if m is None else m & held
    return m


class StatsAccumulator:
    """Streams residuals e and measured τ (m, n) into ErrorStats; with a mask (a partial log,
    sticking rows) each joint's figures come from the rows where its torque counts."""

    def __init__(self, n: int) -> None:
        self.s1 = np.zeros(n)
        self.s2 = np.zeros(n)
        self.counts = np.zeros(n, dtype=np.int64)
        self.count = 0
        self.norm_e = 0.0
        self.norm_tau = 0.0

    def merge(self, other: StatsAccumulator) -> None:
        """Add another accumulator's sums (chunks summed apart, then in order)."""
        self.s1 += other.s1
        self.s2 += other.s2
        self.counts += other.counts
        self.count += other.count
        self.norm_e += other.norm_e
        self.norm_tau += other.norm_tau

    def add(self, e: np.ndarray, tau: np.ndarray, mask: np.ndarray | None = None) -> None:
        """``mask`` (m, n) or (n,): which joints' torques count on each row (None: all);
        a joint a log does not hold has NaN there, never summed."""
        # joints × rows: numpy sums a (rows, 6) array along its rows ten times slower
        e_t, tau_t = np.array(e.T, order="C"), np.array(tau.T, order="C")
        if mask is not None:
            mask_t = np.array(np.broadcast_to(mask, e.shape).T, order="C")
            e_t[~mask_t] = 0.0
            tau_t[~mask_t] = 0.0
        sq = e_t * e_t
        self.s1 += e_t.sum(axis=1)
        self.s2 += sq.sum(axis=1)
        self.counts += e.shape[0] if mask is None else mask_t.sum(axis=1)
        self.count += e.shape[0]
        self.norm_e += float(np.sqrt(sq.sum(axis=0)).sum())
        self.norm_tau += float(np.sqrt((tau_t * tau_t).sum(axis=0)).sum())

    def stats(self) -> ErrorStats | None:
        if self.count == 0:
            return None
        with np.errstate(invalid="ignore", divide="ignore"):  # a joint with no rows: NaN
            mean = self.s1 / self.counts
            ms = self.s2 / self.counts
        var = np.maximum(ms - mean * mean, 0.0)
        rel = self.norm_e / self.norm_tau if self.norm_tau > 0 else None
        return ErrorStats(np.sqrt(ms), np.sqrt(var), var, self.count, rel,
                          self.norm_e / self.count)


@dataclass
class Parameter:
    name: str
    value: float
    std: float
    expression: str
    nominal: float | None = None
    unit: str | None = None  # SI, of the leading term (a base parameter's sum shares it)
    side: str = "joint"  # "motor": acts on the motor (motor-side identification)

    @property
    def rel_std_pct(self) -> float:
        return 100.0 * self.std / abs(self.value) if self.value != 0 else math.inf

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.name, "value": self.value, "std": self.std,
                "rel_std_pct": _num(self.rel_std_pct), "expression": self.expression,
                "nominal": self.nominal, "unit": self.unit, "side": self.side}


#: parameter name prefix → unit at a revolute joint (prismatic: N·m → N, rad → m, kg·m² → kg)
_UNITS = {"m": "kg", "mx": "kg·m", "my": "kg·m", "mz": "kg·m", "xx": "kg·m²", "xy": "kg·m²",
          "xz": "kg·m²", "yy": "kg·m²", "yz": "kg·m²", "zz": "kg·m²", "ia": "kg·m²",
          "fv": "N·m·s/rad", "dfv": "N·m·s/rad", "fc": "N·m", "off": "N·m", "fcp": "N·m",
          "fcn": "N·m", "fst": "N·m", "dfc": "N·m", "rps": "N·m", "rpc": "N·m", "fpc": "N·m",
          "fpv": "N·m·(s/rad)^α", "fpb": "N·m", "mu": "1"}
#: effects that act on the motor when the logs are motor-side (the rigid body never does)
_MOTOR_EFFECTS = {"ia", "fv", "dfv", "fc", "off", "fcp", "fcn", "fst", "dfc", "rps", "rpc",
                  "fpc", "fpv", "fpb"}


def parameter_unit(name: str, joint_types: Sequence[str], motor_side: bool
                   ) -> tuple[str | None, str]:
    """(unit, side) of an identified parameter from its name (``fv_2``, ``zz_1``, ``spr1c_3``)."""
    prefix, _, joint = name.rpartition("_")
    prefix = prefix.rstrip("0123456789cs") if prefix.startswith("spr") else prefix
    unit = "N·m" if prefix == "spr" else _UNITS.get(prefix)
    side = "motor" if motor_side and prefix in _MOTOR_EFFECTS else "joint"
    if joint[:1] in ("m", "j") and joint[1:].isdigit():  # a sided effect: fv_m6, fc_j5
        side, joint = ("motor" if joint[0] == "m" else "joint"), joint[1:]
    per_joint = prefix in _MOTOR_EFFECTS or prefix == "spr"  # in the joint's coordinate
    if unit is not None and per_joint and joint.isdigit() and \
            0 < int(joint) <= len(joint_types) and joint_types[int(joint) - 1] == "prismatic":
        unit = unit.replace("N·m", "N").replace("rad", "m").replace("kg·m²", "kg")
    return unit, side


@dataclass
class HeldOut:
    """The model (and the a-priori model) on the held-out rows: statistics and plot traces."""

    validation: ErrorStats | None
    nominal: ErrorStats | None
    traces: list[dict[str, Any]]
    #: the raw residual's autocorrelation on the held-out rows, against white noise
    whiteness: Whiteness | None = None


def evaluate_held_out(problem: Problem, design: Design, theta: np.ndarray) -> HeldOut:
    """One pass over the validation pieces: columns from the filtered states at the full
    rate against the measured (unfiltered) torques. Chunks go to ``in_slots``; each chunk's
    sums are kept and added in order (the same figures whatever the threads did)."""
    robot = problem.robot
    if not problem.valid:
        return HeldOut(None, None, [])
    tasks = [(pc, a, min(a + CHUNK, pc.hi)) for pc in problem.valid
             for a in range(pc.lo, pc.hi, CHUNK)]
    # traces thinned as they stream: every step-th row of each file's validation rows
    total: dict[str, int] = {}
    for pc in problem.valid:
        total[pc.prep.log.path] = total.get(pc.prep.log.path, 0) + len(pc)
    firsts, seen = [], dict.fromkeys(total, 0)
    for pc, a, b in tasks:
        firsts.append(seen[pc.prep.log.path])
        seen[pc.prep.log.path] += b - a
    out: list[tuple[StatsAccumulator, StatsAccumulator | None, dict[str, np.ndarray],
                    LagSums] | None]
    out = [None] * len(tasks)
    bufs: list[np.ndarray | None] = [None] * SLOTS
    theta_nom = _nominal_theta(problem, design) if robot.nominal is not None else None

    def work(k: int, slot: int) -> None:
        pc, a, b = tasks[k]
        if bufs[slot] is None:
            bufs[slot] = np.empty((CHUNK, design.nnz))
        st = pc.prep.states(a, b)
        c = design.compact(st, bufs[slot])
        pred = design.predict(c, theta)
        tau = pc.prep.tau[a:b]
        known = pc.prep.tau_known
        if known is not None:  # known torques: subtracted from τ, added back to both
            tau, pred = tau + known[a:b], pred + known[a:b]
        m = row_mask(pc.prep, a, b)
        acc = StatsAccumulator(robot.n)
        acc.add(tau - pred, tau, m)
        lag = LagSums(robot.n)
        lag.add(tau - pred, m)
        nom = None
        if robot.nominal is not None:
            pred_nom = (design.predict(c, theta_nom) if theta_nom is not None
                        else rigid_torque(robot, st.q, st.qd, st.qdd, robot.nominal))
            if known is not None:
                pred_nom = pred_nom + known[a:b]
            nom = StatsAccumulator(robot.n)
            nom.add(tau - pred_nom, tau, m)
        step = max(1, total[pc.prep.log.path] // TRACE_SAMPLES)
        keep = (-firsts[k]) % step
        out[k] = (acc, nom, {"t": pc.prep.log.t[a + keep:b:step], "tau": tau[keep::step],
                             "pred": pred[keep::step]}, lag)

    in_slots(range(len(tasks)), work)
    acc = StatsAccumulator(robot.n)
    lags = LagSums(robot.n)
    nom = StatsAccumulator(robot.n) if robot.nominal is not None else None
    parts: dict[str, dict[str, list[np.ndarray]]] = {}
    for (pc, _, _), done in zip(tasks, out, strict=True):
        assert done is not None
        acc.merge(done[0])
        if nom is not None and done[1] is not None:
            nom.merge(done[1])
        lags.merge(done[3])
        tr = parts.setdefault(pc.prep.log.path, {"t": [], "tau": [], "pred": []})
        for key in ("t", "tau", "pred"):
            tr[key].append(done[2][key])
    traces = [{"file": path, **{key: np.concatenate(v) for key, v in tr.items()}}
              for path, tr in parts.items()]
    return HeldOut(acc.stats(), None if nom is None else nom.stats(), traces, lags.result())


def _nominal_theta(problem: Problem, design: Design) -> np.ndarray | None:
    """The values of ``design``'s columns that give the a-priori rigid-body torque (the
    robot's nominal inertials, every effect at zero), least squares on random states —
    exact up to rounding: a base column stands for the standard columns it absorbs. The
    held-out pass then predicts the a-priori model from the columns it has already made
    (an inverse dynamics per row cost as much as the columns). None without a rigid body's
    block or when the columns do not carry that torque."""
    robot = problem.robot
    if robot.nominal is None or not design.blocks or \
            design.blocks[0].effect.name != "rigid_body":
        return None
    st = random_states(robot, np.random.default_rng(11), 64, problem.transmission)
    w = block_columns(robot, design.blocks, st)  # (N, n, P): the rigid body's 10 n first
    target = (w[:, :, : 10 * robot.n] @ robot.nominal).reshape(-1)
    cols = w[:, :, design.cols].reshape(-1, design.p)
    theta, *_ = np.linalg.lstsq(cols, target, rcond=None)
    scale = max(float(np.linalg.norm(target)), 1e-300)
    if float(np.linalg.norm(cols @ theta - target)) > 1e-9 * scale:
        return None
    return np.asarray(theta)


@dataclass
class IdentResult:
    """What ``identify`` returns; ``summary()`` for people, ``to_dict()`` for JSON.

    It keeps the prepared problem and the design it was fitted on: the held-out figures
    (``validation``, ``nominal``, ``rmse``, ``traces``) are computed on first use, and
    ``predict``/``residuals`` evaluate the fitted model on any prepared log of the problem.
    """

    robot: str
    joints: list[dict[str, Any]]
    effects: list[str]
    method: str
    parameters: list[Parameter]
    n_samples: int
    condition_number: float
    fit: ErrorStats
    cutoff_hz: float
    fs_hz: float
    interval: int
    rank: int
    n_standard: int
    least_excited: list[str]
    hypers: dict[str, dict[str, float]]
    #: path, sha256, role ("data" or "validate") and, for a bag, its source (a dict)
    data_files: list[dict[str, Any]]
    validation_source: str
    notes: list[str] = field(default_factory=list)
    theta: np.ndarray | None = field(default=None, repr=False)
    cov: np.ndarray | None = field(default=None, repr=False)
    problem: Problem | None = field(default=None, repr=False, compare=False)
    design: Design | None = field(default=None, repr=False, compare=False)

    @cached_property
    def held_out(self) -> HeldOut:
        if self.problem is None or self.design is None or self.theta is None:
            return HeldOut(None, None, [])
        return evaluate_held_out(self.problem, self.design, self.theta)

    @cached_property
    def noise_floor(self) -> np.ndarray | None:
        """Per joint, the raw torque's measurement noise (N·m; ``noise.noise_floor``: from its
        third differences, which no smooth torque inflates): the validation RMSE, taken on raw
        torque, cannot fall below it; the fit RMSE, on filtered torque, holds almost none of
        it. Read on every row the problem keeps (training and held out): one sensor."""
        if self.problem is None:
            return None
        return noise_floor([*self.problem.train, *self.problem.valid])

    @property
    def doubts(self) -> list[str]:
        """What makes this fit unfit to hand a controller (``physics.fit_doubts``): physically
        impossible base parameters, held-out errors above the CAD model's; each with the
        remedy."""
        from robid_link.ident.fit.physics import fit_doubts

        return fit_doubts(self)

    @property
    def whiteness(self) -> Whiteness | None:
        """The held-out raw residual's autocorrelation against white noise (None: no rows)."""
        return self.held_out.whiteness

    @property
    def at_noise_floor(self) -> list[bool] | None:
        """Per joint: the validation error at the noise estimate (≤ AT_FLOOR×) **and** its
        residual white — what is left is measurement noise. None without held-out rows."""
        val, floor, white = self.validation, self.noise_floor, self.whiteness
        if val is None or floor is None or white is None:
            return None
        return [bool(val.rmse[j] <= AT_FLOOR * floor[j] and white.white[j])
                for j in range(len(self.joints))]

    @property
    def validation(self) -> ErrorStats | None:
        """Errors on the held-out rows against the measured torques (None: none held out)."""
        return self.held_out.validation

    @property
    def nominal(self) -> ErrorStats | None:
        """The a-priori (CAD) model's errors on the same rows, where inertials were given."""
        return self.held_out.nominal

    @property
    def traces(self) -> list[dict[str, Any]]:
        """Measured and predicted torque per validation file, thinned for plots."""
        return self.held_out.traces

    def _fitted(self) -> tuple[Problem, Design, np.ndarray]:
        if self.problem is None or self.design is None or self.theta is None:
            raise ValueError("this result keeps no fitted problem (made without identify)")
        return self.problem, self.design, self.theta

    def predict(self, prep: Prepared | None = None) -> np.ndarray:
        """The fitted model's torque (N, n) on every sample of a prepared log (default: the
        first data file), from its filtered states."""
        pb, design, theta = self._fitted()
        prep = pb.preps[0] if prep is None else prep
        pred = predict_torque(design, prep, theta)
        return pred if prep.tau_known is None else pred + prep.tau_known

    def residuals(self, prep: Prepared | None = None) -> np.ndarray:
        """Measured minus predicted torque (N, n) on every sample of a prepared log."""
        pb, _, _ = self._fitted()
        prep = pb.preps[0] if prep is None else prep
        return prep.tau_measured - self.predict(prep)
    consistent: Any = field(default=None, repr=False)  # ConsistentFit of method "consistent"

    @property
    def rmse(self) -> np.ndarray:
        """Validation RMSE per joint (N·m) against the measured torques."""
        return (self.validation or self.fit).rmse

    def to_dict(self) -> dict[str, Any]:
        val = self.validation
        return {
            "robot": self.robot,
            "joints": self.joints,
            "effects": self.effects,
            "method": self.method,
            "n_samples": self.n_samples,
            "condition_number": _num(self.condition_number),
            "rank": self.rank,
            "rmse": _list(self.rmse),
            "rmse_fit": _list(self.fit.rmse),
            "noise_floor": None if self.noise_floor is None else _list(self.noise_floor),
            "at_noise_floor": self.at_noise_floor,
            "residual_whiteness": None if self.whiteness is None else [
                self.whiteness.joint(j) for j in range(len(self.joints))],
            "errors_on": {"rmse": "raw torque, held-out rows", "rmse_fit": "low-pass filtered "
                          "torque, training rows", "noise_floor": "robust scale of the raw "
                          "torque's third differences (white noise)"},
            "rmse_nominal": None if self.nominal is None else _list(self.nominal.rmse),
            "relative_error": None if val is None else _num(val.relative_error),
            "relative_error_nominal": None if self.nominal is None
            else _num(self.nominal.relative_error),
            "validation": None if val is None else val.as_dict(),
            "validation_source": self.validation_source,
            "fit": self.fit.as_dict(),
            "nominal": None if self.nominal is None else self.nominal.as_dict(),
            "parameters": [p.as_dict() for p in self.parameters],
            "hyper_parameters": self.hypers,
            "least_excited": self.least_excited,
            "preprocessing": {"cutoff_hz": self.cutoff_hz, "fs_hz": self.fs_hz,
                              "interval": self.interval},
            "data_files": self.data_files,
            "notes": self.notes,
            "doubts": self.doubts,
            "consistent": None if self.consistent is None else self.consistent.as_dict(),
        }

    def summary(self) -> str:
        """Compact terminal summary: per-joint errors, parameters with std %, notes."""
        lines = [f"robid identify — {self.robot}: {len(self.joints)} joints, model "
                 f"[{', '.join(self.effects)}], {self.method.upper()}",
                 f"  {self.n_samples} training samples at {self.fs_hz / self.interval:.4g} Hz "
                 f"(cutoff {self.cutoff_hz:.3g} Hz); {self.rank} base parameters of "
                 f"{self.n_standard}; condition number {self.condition_number:.3g}",
                 f"  validation: {self.validation_source}", ""]
        floor = self.noise_floor
        head = f"  {'joint':<16}{'RMSE val':>10}{'noise':>10}{'STD val':>10}{'RMSE fit':>10}"
        if self.nominal is not None:
            head += f"{'RMSE CAD':>10}"
        lines.append(head + "   [N·m]")
        val = self.validation
        for j, jt in enumerate(self.joints):
            row = f"  {jt['joint']:>2} {jt['name'][:12]:<13}"
            row += f"{_f(val.rmse[j]) if val else '—':>10}"
            row += f"{_f(floor[j]) if floor is not None else '—':>10}"
            row += f"{_f(val.std[j]) if val else '—':>10}"
            row += f"{_f(self.fit.rmse[j]):>10}"
            if self.nominal is not None:
                row += f"{_f(self.nominal.rmse[j]):>10}"
            lines.append(row)
        if val is not None and val.relative_error is not None:
            rel = f"  relative error {100 * val.relative_error:.2f} % (mean ‖e‖ {val.abs_error:.3g}"
            rel += " N·m)"
            if self.nominal is not None and self.nominal.relative_error is not None:
                rel += f"; CAD model {100 * self.nominal.relative_error:.2f} %"
            lines.append(rel)
        lines.append("  RMSE val: raw torque on held-out rows; noise: its measurement noise (from "
                     "the raw torque's third differences), which no model explains; RMSE fit: "
                     "filtered torque on training rows")
        lines += self._floor_lines()
        lines += ["", f"  {'parameter':<12}{'value':>12}{'std':>11}{'std %':>8}  stands for"]
        for p in self.parameters:
            pct = p.rel_std_pct
            pct_s = f"{pct:7.1f}" if pct < 1e4 else "   >1e4"
            expr = p.expression if len(p.expression) <= 60 else p.expression[:57] + "..."
            lines.append(f"  {p.name:<12}{p.value:>12.5g}{p.std:>11.3g}{pct_s:>8}  {expr}")
        if self.notes:
            lines.append("")
            lines += [f"  [{i}] {n}" for i, n in enumerate(self.notes, 1)]
        doubts = self.doubts
        if doubts:
            lines.append("")
            lines += [f"  doubt: {d}" for d in doubts]
        return "\n".join(lines)


    def _floor_lines(self) -> list[str]:
        """Which joints sit at the noise floor (at the estimate and white), and which have a
        residual that is not white (more than measurement noise, whatever its size)."""
        at, white = self.at_noise_floor, self.whiteness
        if at is None or white is None:
            return []
        names = [str(jt["joint"]) for jt in self.joints]
        on = [names[j] for j, ok in enumerate(at) if ok]
        out = []
        if on:
            out.append(f"  joint(s) {', '.join(on)}: validation error at the noise floor, residual "
                       "white (what is left is measurement noise)")
        coloured = [j for j in range(len(names)) if not white.white[j]]
        if coloured:
            worst = max(coloured, key=lambda j: float(np.abs(white.acf[:, j]).max()))
            out.append(f"  joint(s) {', '.join(names[j] for j in coloured)}: residual not white "
                       f"(joint {names[worst]}: {white.sentence(worst).split('(', 1)[1]}: more "
                       "than measurement noise")
        return out


def _f(x: float) -> str:
    return f"{x:.4g}" if math.isfinite(x) else "—"  # no rows hold the joint's torque


def _num(x: float | None) -> float | None:
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _list(a: np.ndarray) -> list[float | None]:
    """Numbers for JSON; a joint without figures (no held-out rows hold its torque): None."""
    return [float(v) if math.isfinite(v) else None for v in np.asarray(a, dtype=float)]
