"""A motion program as URScript for Universal Robots: the neutral trajectory as a C² cubic spline
(knots every ``h``, a multiple of 8 ms, with their curvature terms) that the script evaluates at
every controller step and hands to ``servoj``; an RTDE output register marks the path.

Why this shape: ``servoj`` wants a new target every controller step (``get_steptime()``: 8 ms on
CB3, 2 ms on e-Series) for smooth tracking; a list of all samples at that rate would make scripts
of megabytes (the controller compiles slowly and such scripts are reported to fail), while spline
knots a few tens of milliseconds apart reproduce the path within ``tolerance_rad`` and its
acceleration within ``ACCEL_SHARE`` of each joint's peak (positions checked on every sample of
the program, the knot-rate ripple in acceleration four knots away from the ends; coarsest knots
first; a program no spacing meets in acceleration, a step or a fast sine, gets the closest).
The spline is C²: a C¹ curve (Catmull-Rom) jumps in acceleration at every knot, a torque ripple
at the knot rate that identification reads as a resonance. Time runs on integer step counters
(URScript floats are 32 bit: a summed ``t += dt`` would drift); the knot spacing is a whole
number of steps on both generations, so the script's timing is the program's.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

from robid_link.exceptions import DriverError
from robid_link.jobs import ProgramTrajectory

__all__ = ["KNOT_STEPS", "STEP_S", "ACCEL_SHARE", "Knots", "plan_knots", "spline",
           "render_script", "marker_tag", "script_name"]

#: the coarsest common controller step (CB3); e-Series steps are 2 ms and divide it
STEP_S = 0.008
#: knot spacings tried, in controller steps of 8 ms (coarsest first: 200 ms … 8 ms)
KNOT_STEPS = (25, 20, 16, 12, 10, 8, 6, 5, 4, 3, 2, 1)
#: largest acceleration error of the spline, as a share of each joint's peak acceleration
ACCEL_SHARE = 0.01


@dataclass(frozen=True)
class Knots:
    """Knots every ``h`` seconds (``values``: ``m + 1`` rows for ``m`` intervals) and their
    curvature terms ``h²/6 · q̈`` (``curvature``): the C² cubic spline through them."""

    h: float
    values: np.ndarray
    curvature: np.ndarray
    error_rad: float  # largest distance of the curve from the program's samples
    accel_error: float  # largest acceleration error, as a share of the joint's peak

    @property
    def intervals(self) -> int:
        return self.values.shape[0] - 1

    @property
    def duration_s(self) -> float:
        return self.intervals * self.h


def spline(knots: Knots, t: np.ndarray, derivative: int = 0) -> np.ndarray:
    """The spline at times ``t`` (from the first knot), or its first or second derivative:
    what the script computes (``c0 + c1 u + c2 u² + c3 u³`` per interval, ``u`` in [0, 1))."""
    h, p, w = knots.h, knots.values, knots.curvature
    i = np.clip(np.floor(t / h).astype(int), 0, knots.intervals - 1)
    u = (t / h - i)[:, None]
    a, b, wa, wb = p[i], p[i + 1], w[i], w[i + 1]
    c1, c2, c3 = b - a - 2.0 * wa - wb, 3.0 * wa, wb - wa
    if derivative == 1:
        return ((3.0 * c3 * u + 2.0 * c2) * u + c1) / h
    if derivative == 2:
        return (6.0 * c3 * u + 2.0 * c2) / (h * h)
    return ((c3 * u + c2) * u + c1) * u + a


def _knots_for(traj: ProgramTrajectory, steps: int, fine: object) -> Knots:
    from scipy.interpolate import CubicSpline

    t = traj.t - traj.t[0]
    n = traj.q.shape[1]
    h = steps * STEP_S
    m = max(1, int(np.ceil(t[-1] / h - 1e-9)))
    tk = np.arange(m + 1) * h
    if fine is None:  # one sample: stand still
        values = np.repeat(traj.q[:1], m + 1, axis=0)
        return Knots(h, values, np.zeros_like(values), 0.0, 0.0)
    values = fine(np.minimum(tk, t[-1]))  # type: ignore[operator]
    v0 = fine(0.0, 1)  # type: ignore[operator]
    v1 = fine(t[-1], 1) if tk[-1] <= t[-1] + 1e-9 else np.zeros(n)  # type: ignore[operator]
    clamped = CubicSpline(tk, values, axis=0, bc_type=((1, v0), (1, v1)))
    k = Knots(h, values, clamped(tk, 2) * h * h / 6.0, 0.0, 0.0)
    err = float(np.abs(spline(k, t) - traj.q).max())
    # the acceleration error as the ripple at the knot rate it amounts to: the curve's distance
    # from the program between the knots × (2π/h)². Measured in position on a dense grid (the
    # program's own accelerations are known only as well as its sampling allows), four knots
    # away from the ends, where the curve follows its end conditions (rest)
    dense = np.arange(4 * h, tk[-1] - 4 * h, h / 8)
    if dense.size == 0:
        return Knots(h, values, k.curvature, err, 0.0)
    peak = np.maximum(np.abs(fine(t, 2)).max(axis=0), 1e-3)  # type: ignore[operator]
    dev = np.abs(spline(k, dense) - fine(dense)).max(axis=0)  # type: ignore[operator]
    ripple = dev * (2.0 * np.pi / h) ** 2
    return Knots(h, values, k.curvature, err, float((ripple / peak).max()))


def plan_knots(traj: ProgramTrajectory, tolerance_rad: float,
               qd_max: np.ndarray | None = None) -> Knots:
    """The coarsest knots whose spline stays within ``tolerance_rad`` of every program sample
    and within ``ACCEL_SHARE`` of its accelerations; a program whose accelerations no spacing
    meets (a step in acceleration, a fast sine) gets the knots that come closest. DriverError
    when no spacing meets ``tolerance_rad``, or (given ``qd_max``) the curve would exceed a
    joint's speed limit."""
    from scipy.interpolate import CubicSpline

    t = traj.t - traj.t[0]
    fine = CubicSpline(t, traj.q, axis=0) if t.size >= 2 else None
    candidates = [_knots_for(traj, steps, fine) for steps in KNOT_STEPS]
    inside = [k for k in candidates if k.error_rad <= tolerance_rad]
    if not inside:
        best = min(candidates, key=lambda k: k.error_rad)
        raise DriverError(f"URScript rendering: even knots every {best.h * 1000:g} ms leave the "
                          f"path {best.error_rad:.2e} rad off the program (tolerance "
                          f"{tolerance_rad:g}; raise driver.path_tolerance_rad or sample the "
                          "program finer)")
    smooth = [k for k in inside if k.accel_error <= ACCEL_SHARE]
    best = smooth[0] if smooth else min(inside, key=lambda k: k.accel_error)
    if qd_max is not None:
        tt = np.arange(0.0, best.duration_s, STEP_S / 4)
        speed = np.abs(spline(best, tt, 1)).max(axis=0)
        over = np.flatnonzero(speed > np.asarray(qd_max) * (1 + 1e-3))
        if over.size:
            j = int(over[0])
            raise DriverError(f"URScript rendering: the interpolated path reaches "
                              f"{speed[j]:.3f} rad/s on joint {j + 1}, above its limit "
                              f"{float(np.asarray(qd_max)[j]):.3f}")
    return best


def marker_tag(exp_id: str, nonce: str) -> int:
    """The value the script keeps in the marker register while on the path (1 … 2³¹−1); its
    negative says the path ended."""
    digest = hashlib.sha256(f"{exp_id}\0{nonce}".encode()).digest()
    return int.from_bytes(digest[:4], "big") % 0x7FFFFFFF + 1


def script_name(exp_id: str, nonce: str) -> str:
    return "robid_" + "".join(c if c.isalnum() else "_" for c in f"{exp_id}_{nonce}")[:50]


def _num(x: float) -> str:
    text = f"{x:.6f}".rstrip("0").rstrip(".")
    return "0" if text in ("", "-0", "-") else text


def _sci(x: float) -> str:
    """A curvature term: small numbers, fixed notation with six significant digits."""
    if x == 0 or abs(x) < 1e-12:
        return "0"
    digits = max(6, 5 - int(np.floor(np.log10(abs(x)))))
    return f"{x:.{min(digits, 15)}f}".rstrip("0").rstrip(".")


def _horner(j: int) -> str:
    return f"((c3[{j}] * u + c2[{j}]) * u + c1[{j}]) * u + c0[{j}]"


def render_script(knots: Knots, *, exp_id: str, nonce: str, robot: str, kind: str,
                  register: int, speed_rad_s: float, acceleration_rad_s2: float,
                  lookahead_s: float, gain: float) -> bytes:
    """The URScript program (``def …: … end``) of one attempt."""
    tag = marker_tag(exp_id, nonce)
    q0 = ", ".join(_num(x) for x in knots.values[0])
    last = ", ".join(_num(x) for x in knots.values[-1])
    servo = f"t = dt, lookahead_time = {lookahead_s:g}, gain = {gain:g}"
    lines = [
        f"def {script_name(exp_id, nonce)}():",
        f"  # robid_link: experiment {exp_id}, nonce {nonce}, robot {robot}, {kind} path of "
        f"{knots.duration_s:.3f} s",
        f"  # C2 cubic spline through {knots.intervals + 1} knots every {knots.h:.3f} s (at most "
        f"{knots.error_rad:.1e} rad and {100 * knots.accel_error:.1f} % of the peak "
        "acceleration off the program), servoj at every controller step;",
        f"  # output_int_register_{register} = {tag} while on the path, -{tag} once it is done",
        f'  textmsg("robid_link experiment {exp_id} nonce {nonce}")',
        f"  k = [{', '.join(_num(x) for x in knots.values.reshape(-1))}]",
        f"  w = [{', '.join(_sci(x) for x in knots.curvature.reshape(-1))}]",
        f"  m = {knots.intervals}",
        "  dt = get_steptime()",
        f"  n = floor({knots.h:.3f} / dt + 0.5)",
        "  du = 1.0 / n",
        "  c0 = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]",
        "  c1 = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]",
        "  c2 = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]",
        "  c3 = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]",
        f"  movej([{q0}], a = {acceleration_rad_s2:g}, v = {speed_rad_s:g})",
        f"  write_output_integer_register({register}, {tag})",
        "  i = 0",
        "  while i < m:",
        "    b = 6 * i",
        "    j = 0",
        "    while j < 6:",
        "      c0[j] = k[b + j]",
        "      c1[j] = k[b + 6 + j] - k[b + j] - 2.0 * w[b + j] - w[b + 6 + j]",
        "      c2[j] = 3.0 * w[b + j]",
        "      c3[j] = w[b + 6 + j] - w[b + j]",
        "      j = j + 1",
        "    end",
        "    s = 0",
        "    while s < n:",
        "      u = s * du",
        f"      servoj([{', '.join(_horner(j) for j in range(6))}], {servo})",
        "      s = s + 1",
        "    end",
        "    i = i + 1",
        "  end",
        f"  servoj([{last}], {servo})",
        f"  write_output_integer_register({register}, -{tag})",
        f"  stopj({acceleration_rad_s2 * 4:g})",
        "end",
        "",
    ]
    return "\n".join(lines).encode()
