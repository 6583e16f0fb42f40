"""Excitation trajectories: optimized finite Fourier series (Swevers et al.), sweeps, stepped
sines; the trajectory file (CSV + YAML header) and the limit check every program passes.

q_j(t) = q0_j + Σ_l a_jl/(l ω) sin(l ω t) − b_jl/(l ω) cos(l ω t), with analytic derivatives.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from robid_link.exceptions import ConfigError
from robid_link.ident.model.effects import DEFAULT_MODEL, Model, States
from robid_link.ident.model.robot import Robot
from robid_link.kinds import MAX_RATE_HZ, MIN_RATE_HZ
from robid_link.safeopen import file_problem
from robid_link.yamlio import read_yaml_mapping

__all__ = [
    "FourierTrajectory",
    "Trajectory",
    "random_fourier",
    "optimize_fourier",
    "nominal_torque",
    "excitation_condition",
    "nominal_torque",
    "constant_velocity_sweeps",
    "stepped_sine",
    "check_limits",
    "write_trajectory",
    "read_trajectory",
    "trajectory_states",
]

#: fraction of each limit a scaled trajectory may use
LIMIT_MARGIN = 0.9


@dataclass(frozen=True)
class FourierTrajectory:
    base_hz: float
    q0: np.ndarray  # (n,)
    a: np.ndarray  # (n, L)
    b: np.ndarray  # (n, L)

    @property
    def period_s(self) -> float:
        return 1.0 / self.base_hz

    def evaluate(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """q, q̇, q̈ (len(t), n)."""
        w = 2.0 * math.pi * self.base_hz
        harm = np.arange(1, self.a.shape[1] + 1)
        ph = np.outer(t, harm * w)  # (N, L)
        s, c = np.sin(ph), np.cos(ph)
        lw = harm * w
        q = self.q0 + s @ (self.a / lw).T - c @ (self.b / lw).T
        qd = c @ self.a.T + s @ self.b.T
        qdd = -s @ (self.a * lw).T + c @ (self.b * lw).T
        return q, qd, qdd

    def scaled(self, k: float) -> FourierTrajectory:
        return FourierTrajectory(self.base_hz, self.q0, self.a * k, self.b * k)

    def at_rest(self) -> FourierTrajectory:
        """Coefficients projected so that q̇(0) = q̈(0) = 0 (and so at the end of each period):
        Σ_l a_l = 0 and Σ_l l·b_l = 0, by adjusting the first harmonic."""
        a, b = self.a.copy(), self.b.copy()
        harm = np.arange(1, a.shape[1] + 1)
        a[:, 0] = -a[:, 1:].sum(axis=1)
        b[:, 0] = -(b[:, 1:] * harm[1:]).sum(axis=1)
        return FourierTrajectory(self.base_hz, self.q0, a, b)

    def start(self) -> np.ndarray:
        return self.evaluate(np.zeros(1))[0][0]


@dataclass
class Trajectory:
    """A sampled joint trajectory with its header (the trajectory file of DESIGN.md)."""

    t: np.ndarray
    q: np.ndarray
    rate_hz: float
    kind: str
    robot: str
    header: dict[str, Any] = field(default_factory=dict)

    def derivatives(self) -> tuple[np.ndarray, np.ndarray]:
        h = 1.0 / self.rate_hz
        qd = np.gradient(self.q, h, axis=0)
        return qd, np.gradient(qd, h, axis=0)


# ----------------------------------------------------------------------------- limits


def _q_bounds(robot: Robot) -> tuple[np.ndarray, np.ndarray]:
    lim = robot.limits
    return (np.where(np.isfinite(lim.q_min), lim.q_min, -math.pi),
            np.where(np.isfinite(lim.q_max), lim.q_max, math.pi))


def check_limits(robot: Robot, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray,
                 tau: np.ndarray | None = None, where: str = "trajectory") -> None:
    """Raise ConfigError naming the first joint and quantity outside the robot's limits."""
    lim = robot.limits
    deg = np.array([180 / math.pi if t == "revolute" else 1.0 for t in robot.joint_types])
    checks = [("q", q, lim.q_min, lim.q_max, "deg"),
              ("qd", np.abs(qd), None, lim.qd_max, "deg/s"),
              ("qdd", np.abs(qdd), None, lim.qdd_max, "deg/s²")]
    for name, x, lo, hi, unit in checks:
        over = x > hi * (1 + 1e-9)
        under = x < lo * (1 + 1e-9) - 1e-12 if lo is not None else np.zeros_like(over)
        bad = over | under
        if bad.any():
            k, j = np.argwhere(bad)[0]
            bound = hi[j] if over[k, j] or lo is None else lo[j]  # no lo: only over
            raise ConfigError(f"{where}: {name}{j + 1} = {x[k, j] * deg[j]:.4g} {unit} at sample "
                              f"{k + 1} exceeds the limit {bound * deg[j]:.4g} {unit}")
    if tau is not None:
        over = np.abs(tau) > lim.tau_max * (1 + 1e-9)
        if over.any():
            k, j = np.argwhere(over)[0]
            raise ConfigError(f"{where}: the a-priori model needs tau{j + 1} = {tau[k, j]:.4g} N·m "
                              f"at sample {k + 1}, above the limit {lim.tau_max[j]:.4g} N·m")


def nominal_torque(robot: Robot, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray
                   ) -> np.ndarray | None:
    """The a-priori model's torque along a motion, where there are inertials and limits."""
    if robot.nominal is None or not np.isfinite(robot.limits.tau_max).any():
        return None
    from robid_link.ident.model.regressor import rigid_regressor

    return rigid_regressor(robot, q, qd, qdd) @ robot.nominal


def fit_limits(robot: Robot, traj: FourierTrajectory, margin: float = LIMIT_MARGIN,
               n_check: int = 1000, torque: bool = True) -> FourierTrajectory:
    """Largest uniform scaling of the harmonics that keeps q, q̇, q̈ (and the a-priori torque)
    inside the limits."""
    t = np.linspace(0.0, traj.period_s, n_check)
    q, qd, qdd = traj.evaluate(t)
    lim = robot.limits
    lo, hi = _q_bounds(robot)
    dev_hi = (q - traj.q0).max(axis=0)
    dev_lo = (traj.q0 - q).max(axis=0)
    ratios = [np.where(dev_hi > 1e-12, (hi - traj.q0) / np.maximum(dev_hi, 1e-12), np.inf),
              np.where(dev_lo > 1e-12, (traj.q0 - lo) / np.maximum(dev_lo, 1e-12), np.inf)]
    for x, cap in ((qd, lim.qd_max), (qdd, lim.qdd_max)):
        peak = np.abs(x).max(axis=0)
        ratios.append(np.where(np.isfinite(cap), cap / np.maximum(peak, 1e-12), np.inf))
    k = margin * float(np.min(np.concatenate(ratios)))
    out = traj.scaled(k)
    # torque limits are not linear in the scale (gravity stays): shrink until they hold
    for _ in range(20 if torque else 0):
        qs, qds, qdds = out.evaluate(t)
        tau = nominal_torque(robot, qs, qds, qdds)
        if tau is None or np.all(np.abs(tau) <= margin * lim.tau_max):
            break
        out = out.scaled(0.9)
    return out


# ----------------------------------------------------------------------------- design


def excitation_condition(robot: Robot, traj: FourierTrajectory, model: Model = DEFAULT_MODEL,
                         n_samples: int = 200) -> float:
    """Condition number of the column-scaled base regressor over one period."""
    from robid_link.ident.fit.design import make_design

    design = _design_cache(robot, model, make_design)
    t = np.linspace(0.0, traj.period_s, n_samples, endpoint=False)
    q, qd, qdd = traj.evaluate(t)
    w = design.expand(design.compact(States(q, qd, qdd, t))).reshape(-1, design.p)
    norms = np.linalg.norm(w, axis=0)
    if np.any(norms < 1e-12):
        return float("inf")
    sv = np.linalg.svd(w / norms, compute_uv=False)
    return float(sv[0] / max(sv[-1], 1e-300))


_DESIGNS: dict[tuple[int, tuple[str, ...]], Any] = {}


def _design_cache(robot: Robot, model: Model, make: Any) -> Any:
    key = (id(robot), tuple(model.labels()))
    if key not in _DESIGNS:
        _DESIGNS[key] = make(robot, model.blocks(robot))[0]
    return _DESIGNS[key]


def random_fourier(robot: Robot, *, harmonics: int = 5, base_hz: float = 0.1,
                   seed: int = 0, margin: float = LIMIT_MARGIN, at_rest: bool = True
                   ) -> FourierTrajectory:
    """A Fourier trajectory with random coefficients, scaled into the robot's limits."""
    rng = np.random.default_rng(seed)
    lo, hi = _q_bounds(robot)
    q0 = 0.5 * (lo + hi)
    traj = FourierTrajectory(base_hz, q0, rng.normal(size=(robot.n, harmonics)),
                             rng.normal(size=(robot.n, harmonics)))
    return fit_limits(robot, traj.at_rest() if at_rest else traj, margin)


def optimize_fourier(robot: Robot, *, harmonics: int = 8, base_hz: float = 0.1,
                     model: Model = DEFAULT_MODEL, seed: int = 0, evaluations: int = 2500,
                     restarts: int = 3, progress: Callable[[str], None] | None = None
                     ) -> tuple[FourierTrajectory, float]:
    """Minimise the condition number of the column-scaled base regressor (Swevers), within
    the limits, starting and ending at rest. Returns the trajectory and its condition number.

    A (1+1) evolution strategy with the 1/5 success rule, best of ``restarts`` runs: the
    limit scaling makes the objective non-smooth, where gradient methods stall. Torque
    limits of the a-priori model are enforced once on the result (they shrink the
    amplitude, gravity stays). ``progress`` gets a line per block of evaluations and restart.
    """
    best: tuple[FourierTrajectory, float] | None = None
    for r in range(restarts):
        def report(k: int, cond: float, r: int = r) -> None:
            if progress is not None:
                progress(f"restart {r + 1}/{restarts}: {k}/{evaluations} evaluations, "
                         f"condition number {cond:.4g}")

        cand = _evolve(robot, harmonics, base_hz, model, seed * 1000 + r, evaluations, report)
        if best is None or cand[1] < best[1]:
            best = cand
    assert best is not None
    return best


def _evolve(robot: Robot, harmonics: int, base_hz: float, model: Model, seed: int,
            evaluations: int, report: Callable[[int, float], None] | None = None
            ) -> tuple[FourierTrajectory, float]:
    n, L = robot.n, harmonics
    lo, hi = _q_bounds(robot)
    rng = np.random.default_rng(seed)

    def unpack(x: np.ndarray) -> FourierTrajectory:
        a = x[: n * L].reshape(n, L)
        b = x[n * L: 2 * n * L].reshape(n, L)
        q0 = lo + (hi - lo) * (0.5 + 0.3 * np.tanh(x[2 * n * L:]))
        traj = FourierTrajectory(base_hz, q0, a, b).at_rest()
        return fit_limits(robot, traj, n_check=300, torque=False)  # fast: no torque check

    def cost(x: np.ndarray) -> float:
        c = excitation_condition(robot, unpack(x), model, n_samples=120)
        return math.log(c) if math.isfinite(c) else 1e3

    x = np.concatenate((rng.normal(size=2 * n * L), np.zeros(n)))
    fx = cost(x)
    sigma = 0.3
    block = max(1, evaluations // 5)
    for k in range(evaluations):
        if report is not None and k and k % block == 0:
            report(k, math.exp(fx))
        y = x + sigma * rng.normal(size=x.size)
        fy = cost(y)
        if fy < fx:
            x, fx = y, fy
            sigma *= 1.5
        else:
            sigma *= 1.5 ** (-0.25)
        sigma = min(max(sigma, 1e-3), 2.0)
    traj = fit_limits(robot, unpack(x).scaled(1.0 / LIMIT_MARGIN))
    cond = excitation_condition(robot, traj, model)
    if report is not None:
        report(evaluations, cond)
    return traj, cond


def constant_velocity_sweeps(robot: Robot, joint: int, speeds: Sequence[float],
                             rate_hz: float, accel_fraction: float = 0.5) -> np.ndarray:
    """Friction-curve experiment for one joint (0-based): back and forth across its range at
    each speed (rad/s), the other joints at mid-range. Ramps are sine-shaped in acceleration
    (no acceleration steps, so no torque content above the identification filter), peak
    acceleration ``accel_fraction`` of the limit. (N, n) q."""
    lo, hi = _q_bounds(robot)
    span_lo = lo[joint] + 0.1 * (hi[joint] - lo[joint])
    span_hi = hi[joint] - 0.1 * (hi[joint] - lo[joint])
    acc = accel_fraction * robot.limits.qdd_max[joint]
    acc = acc if np.isfinite(acc) else 2.0
    rows = []
    pos = span_lo
    h = 1.0 / rate_hz
    for v in speeds:
        for target in (span_hi, span_lo):
            dist = abs(target - pos)
            direction = math.copysign(1.0, target - pos)
            v_peak = v
            t_acc = math.pi * v_peak / (2.0 * acc)  # peak of a sine-shaped acceleration
            if v_peak * t_acc > dist:  # no cruise phase: lower the peak speed
                v_peak = math.sqrt(2.0 * acc * dist / math.pi)
                t_acc = math.pi * v_peak / (2.0 * acc)
            t_flat = max(0.0, (dist - v_peak * t_acc) / max(v_peak, 1e-12))
            t_total = 2 * t_acc + t_flat
            tt = np.arange(0.0, t_total + 0.5 * h, h)

            def ramp(x: np.ndarray, v_peak: float = v_peak, t_acc: float = t_acc) -> np.ndarray:
                x = np.clip(x, 0.0, t_acc)
                return 0.5 * v_peak * (x - t_acc / math.pi * np.sin(math.pi * x / t_acc))

            s = np.where(tt < t_acc, ramp(tt),
                         np.where(tt < t_acc + t_flat,
                                  ramp(np.array(t_acc)) + v_peak * (tt - t_acc),
                                  dist - ramp(np.maximum(t_total - tt, 0.0))))
            rows.append(pos + direction * s)
            pos = target
            rows.append(np.full(int(0.5 * rate_hz), pos))  # settle
    path = np.concatenate(rows)
    q = np.tile(0.5 * (lo + hi), (path.size, 1))
    q[:, joint] = path
    return q


def stepped_sine(robot: Robot, joint: int, pose: np.ndarray, freqs_hz: Sequence[float],
                 amplitude: float, rate_hz: float, cycles: int = 10) -> np.ndarray:
    """Small sine bursts around a pose at each frequency (elasticity tests). (N, n) q."""
    segments = []
    for f in freqs_hz:
        tt = np.arange(0.0, cycles / f, 1.0 / rate_hz)
        env = np.sin(math.pi * tt / tt[-1]) ** 2  # smooth start and end
        seg = np.tile(pose, (tt.size, 1))
        seg[:, joint] += amplitude * env * np.sin(2 * math.pi * f * tt)
        segments.append(seg)
    return np.concatenate(segments)


# ----------------------------------------------------------------------------- files


def write_trajectory(path: str | Path, traj: Trajectory) -> tuple[Path, Path]:
    """CSV ``t,q1..qn`` at the controller's rate plus a YAML header beside it."""
    p = Path(path)
    n = traj.q.shape[1]
    from robid_link.ident.data.logs import write_numeric_csv

    write_numeric_csv(p, ["t"] + [f"q{j}" for j in range(1, n + 1)],
                      np.column_stack((traj.t, traj.q)))
    meta = {"robot": traj.robot, "rate_hz": traj.rate_hz, "kind": traj.kind,
            "samples": int(traj.t.size), **traj.header}
    y = p.with_suffix(".yaml")
    y.write_text(yaml.safe_dump(meta, sort_keys=False))
    return p, y


def read_trajectory(path: str | Path) -> Trajectory:
    """A trajectory file (CSV ``t,q1..qn`` + YAML header), checked: one-line errors."""
    from robid_link.ident.data.logs import read_numeric_csv

    p = Path(path)
    y = p.with_suffix(".yaml")
    problem = file_problem(p)
    if problem:
        raise ConfigError(f"{p}: trajectory file {problem}")
    problem = file_problem(y)
    if problem:
        raise ConfigError(f"{p}: header file {y.name} {problem}")
    meta = read_yaml_mapping(y, "trajectory header")
    for key in ("rate_hz", "kind"):
        if key not in meta:
            raise ConfigError(f"{y}: missing key {key!r}")
    if meta["kind"] not in ("fourier", "sweep", "stepped_sine", "custom"):
        raise ConfigError(f"{y}: kind: expected fourier, sweep, stepped_sine or custom")
    rate = meta["rate_hz"]
    if not _finite_number(rate) or not MIN_RATE_HZ <= rate <= MAX_RATE_HZ:
        raise ConfigError(f"{y}: rate_hz: expected a rate in [{MIN_RATE_HZ:g}, "
                          f"{MAX_RATE_HZ:g}] Hz, got {repr(rate)[:30]}")
    rate = float(rate)
    header, arr = read_numeric_csv(p, ConfigError, "a header t,q1..qn", max_bytes=1 << 30)
    n = len(header) - 1
    if n < 1 or header != ["t"] + [f"q{j}" for j in range(1, n + 1)]:
        raise ConfigError(f"{p}: expected the header t,q1..qn, got {','.join(header)[:60]}")
    if arr.shape[0] < 2 or not np.all(np.isfinite(arr)):
        raise ConfigError(f"{p}: expected at least 2 rows of finite numbers t,q1..qn")
    if np.any(np.abs(np.diff(arr[:, 0]) - 1.0 / rate) > 1e-6 + 1e-3 / rate):
        raise ConfigError(f"{p}: time column is not uniform at rate_hz {rate}")
    extra = {k: v for k, v in meta.items() if k not in ("rate_hz", "kind", "robot", "samples")}
    if meta["kind"] == "fourier" and {"base_hz", "q0", "a", "b"} <= set(extra):
        _check_fourier_header(y, extra, n)
    return Trajectory(arr[:, 0], arr[:, 1:], rate, str(meta["kind"]), str(meta.get("robot", "")),
                      extra)


def _finite_number(v: Any) -> bool:
    try:
        return not isinstance(v, bool) and isinstance(v, int | float) and math.isfinite(v)
    except OverflowError:
        return False


def _check_fourier_header(y: Path, h: dict[str, Any], n: int) -> None:
    """The Fourier coefficients that trajectory_states evaluates: shapes and finite values."""
    if not _finite_number(h.get("base_hz")) or not 0 < h["base_hz"] <= 1000:
        raise ConfigError(f"{y}: base_hz: expected a number in (0, 1000]")
    q0 = h.get("q0")
    if not isinstance(q0, list) or len(q0) != n or not all(_finite_number(v) for v in q0):
        raise ConfigError(f"{y}: q0: expected {n} finite numbers")
    width = None
    for key in ("a", "b"):
        rows = h.get(key)
        if (not isinstance(rows, list) or len(rows) != n
                or not all(isinstance(r, list) and r and all(_finite_number(v) for v in r)
                           for r in rows)):
            raise ConfigError(f"{y}: {key}: expected {n} rows of finite coefficients")
        widths = {len(r) for r in rows}
        if len(widths) != 1 or (width is not None and widths != {width}) or max(widths) > 1000:
            raise ConfigError(f"{y}: {key}: rows of a and b must all have one length (≤ 1000)")
        width = next(iter(widths))


def fourier_header(traj: FourierTrajectory, cond: float) -> dict[str, Any]:
    return {"base_hz": traj.base_hz, "harmonics": int(traj.a.shape[1]),
            "q0": traj.q0.tolist(), "a": traj.a.tolist(), "b": traj.b.tolist(),
            "condition_number": cond, "limits_checked": True}


def trajectory_states(traj: Trajectory, rate_hz: float
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """t, q, q̇, q̈ at ``rate_hz``: analytic for Fourier trajectories, else a cubic spline
    through the file's samples."""
    t = np.arange(traj.t[0], traj.t[-1] + 1e-12, 1.0 / rate_hz)
    h = traj.header
    if traj.kind == "fourier" and {"base_hz", "q0", "a", "b"} <= set(h):
        four = FourierTrajectory(float(h["base_hz"]), np.asarray(h["q0"], dtype=float),
                                 np.asarray(h["a"], dtype=float), np.asarray(h["b"], dtype=float))
        q, qd, qdd = four.evaluate(t)
        return t, q, qd, qdd
    if t.size == traj.t.size >= 4 and np.array_equal(t, traj.t):  # at the file's samples
        qd, qdd = _spline_at_knots(traj.t, traj.q)
        return t, traj.q.copy(), qd, qdd
    from scipy.interpolate import CubicSpline

    spline = CubicSpline(traj.t, traj.q, axis=0)
    return t, spline(t), spline(t, 1), spline(t, 2)


def _spline_at_knots(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First and second derivative, at its knots, of the not-a-knot cubic spline through the
    samples y (N, m) at x (CubicSpline's, without building its N × 4 coefficients): the slopes
    m from the spline's conditions — second derivative continuous at the inner knots,
    h_i m_{i−1} + 2 (h_{i−1} + h_i) m_i + h_{i−1} m_{i+1} = 3 (h_i δ_{i−1} + h_{i−1} δ_i), and
    the third continuous at the second and the last but one, h_1² (m_0 + m_1 − 2δ_0) =
    h_0² (m_1 + m_2 − 2δ_1) — one banded solve; the curvature at a knot from its interval's
    cubic, (6δ_i − 4m_i − 2m_{i+1})/h_i (the last knot's from its left)."""
    from scipy.linalg import solve_banded

    h = np.diff(x)
    delta = np.diff(y, axis=0) / h[:, None]
    n = x.size
    band = np.zeros((5, n))  # band[2 + i − j, j] = A[i, j]
    rhs = np.empty_like(y)
    band[2, 1:-1] = 2 * (h[:-1] + h[1:])
    band[1, 2:] = h[:-1]  # A[i, i + 1] = h_{i−1}
    band[3, :-2] = h[1:]  # A[i, i − 1] = h_i
    rhs[1:-1] = 3 * (h[1:, None] * delta[:-1] + h[:-1, None] * delta[1:])
    band[2, 0], band[1, 1], band[0, 2] = h[1] ** 2, h[1] ** 2 - h[0] ** 2, -h[0] ** 2
    rhs[0] = 2 * (h[1] ** 2 * delta[0] - h[0] ** 2 * delta[1])
    a, b = h[-1], h[-2]  # the last row, mirrored
    band[2, -1], band[3, -2], band[4, -3] = b ** 2, b ** 2 - a ** 2, -a ** 2
    rhs[-1] = 2 * (b ** 2 * delta[-1] - a ** 2 * delta[-2])
    slope = solve_banded((2, 2), band, rhs, overwrite_ab=True, overwrite_b=True,
                         check_finite=False)
    curv = np.empty_like(y)
    curv[:-1] = (6 * delta - 4 * slope[:-1] - 2 * slope[1:]) / h[:, None]
    curv[-1] = (-6 * delta[-1] + 2 * slope[-2] + 4 * slope[-1]) / h[-1]
    return slope, curv
