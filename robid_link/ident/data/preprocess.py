"""Filtering, differentiation, decimation, segments and the train/validation split: logs
become the prepared problem that the design (design.py) turns into regressor rows.

The filter windows say where regressor columns are filtered with the same zero-phase filter
as the torques (Gautier's parallel filtering), in chunks with overlap (bounded memory).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from robid_link.exceptions import DataError, DataWarning
from robid_link.ident.data.filtering import (
    FILTER_ORDER,
    Channels,
    Track,
    ZeroPhaseFilter,
    butter_lowpass_sos,
    sos_steady_state,
)
from robid_link.ident.data.logs import Log
from robid_link.ident.data.quantiles import percentile_streamed
from robid_link.ident.model.effects import V_REST, Block, Model, States
from robid_link.ident.model.robot import Robot
from robid_link.ident.model.threads import in_slots

__all__ = [
    "DEFAULT_CUTOFF_HZ",
    "ZeroPhaseFilter",
    "Prepared",
    "Piece",
    "filter_windows",
    "prepare",
    "split",
    "motion_span",
    "typical_speeds",
    "held_out_ranges",
    "Problem",
    "build_problem",
    "shift_torque",
    "check_counts",
    "check_torque_coverage",
    "butter_lowpass_sos",
    "sos_steady_state",
    "FILTER_ORDER",
]

#: Default low-pass cutoff. Excitation trajectories live below ~2 Hz (Fourier base 0.05–0.2 Hz,
#: a handful of harmonics), so 10 Hz keeps them with < 0.1 % amplitude error while removing
#: the noise that double differentiation amplifies. Capped at 40 % of the Nyquist rate.
DEFAULT_CUTOFF_HZ = 10.0
#: samples per chunk when building design rows: a chunk's compact columns (8192 × the
#: design's non-zeros, one per slot of ``threads.in_slots``) are the largest buffers of a
#: pass, whatever the log's length
CHUNK = 8192


@dataclass(frozen=True)
class Prepared:
    """One log after filtering: states for the regressor, raw and filtered torques. Frozen:
    a step that changes a torque (known torques, drive currents, the model's predictions)
    returns a new one (``dataclasses.replace``) and ``Problem.with_preps`` re-points pieces.

    The filtered positions, velocities, accelerations and torques are read by window
    (``states``, ``tau_f_rows``, ``rows``): a window is computed from the filter's stored
    states and equals, to the bit, the rows of the whole arrays (``q``, ``qd``, ``qdd``,
    ``tau_f``), which are only made when someone reads them.
    """

    log: Log
    filt: ZeroPhaseFilter
    transmission: np.ndarray | None = None  # set for motor-side logs
    tau_rigid: np.ndarray | None = None  # the current model's rigid torque (diagnosis)
    tau_rate: np.ndarray | None = None  # … and its torque rate
    tau_model: np.ndarray | None = None  # the current model's torque on every raw sample
    #: known torques (model file), already subtracted from ``tau`` and ``tau_f``
    tau_known: np.ndarray | None = None
    #: (N, n) rows × joints whose torque enters the joint's equation (None: all): False for a
    #: partial log's missing torques and where a joint sticks (friction at rest is static)
    tau_mask: np.ndarray | None = None
    #: (N, n) int8: where the filtered velocity touches zero (changes sign and back faster than
    #: the filter resolves), the sign the joint's motion has on both sides (0 elsewhere): the
    #: states' velocity keeps it there (``data/sticks.py``)
    qd_sign: np.ndarray | None = None
    channels: Channels = field(default_factory=Channels, compare=False, repr=False)

    @property
    def tau(self) -> np.ndarray:
        """The torque left for the model: measured minus known torques."""
        return self.log.tau

    @property
    def tau_measured(self) -> np.ndarray:
        return self.log.tau if self.tau_known is None else self.log.tau + self.tau_known

    def _track(self, name: str, src: np.ndarray) -> Track:
        return self.channels.track(name, src, self.filt, self.log.segments)

    @property
    def filtered_segments(self) -> list[tuple[int, int]]:
        """Segments [a, b) long enough to be filtered (rows elsewhere read zero)."""
        return self._track("q", self.log.q).segments

    def kinematics(self, lo: int, hi: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Filtered q, q̇ (the filtered log's q̇, else the derivative of q) and q̈ (the
        derivative of q̇) at rows [lo, hi); zero outside the filtered segments."""
        return self._kinematics(lo, hi, True)

    @property
    def velocity_source(self) -> np.ndarray:
        """What q̇ is filtered from: the logged q̇, else q (its derivative): the source its
        channels are kept under."""
        return self.log.q if self.log.qd is None else self.log.qd

    def typical_speed(self) -> np.ndarray:
        """Each joint's typical speed: the 95th percentile of |q̇| over the filtered rows (made
        once per log, ``typical_speeds``)."""
        return self.channels.whole("typical_speed", self.velocity_source,
                                   lambda: typical_speeds([self]))

    def speeds_at(self, rows: np.ndarray, j: int) -> np.ndarray:
        """Joint j's |q̇| at the log's rows where ``rows`` (N,) is True, in row order (rows
        outside the filtered segments read zero), from the windows that hold such rows."""
        parts = []
        for lo in range(0, len(self.log), CHUNK):
            hit = np.flatnonzero(rows[lo: lo + CHUNK])
            if hit.size:
                vel = self._kinematics(lo, lo + int(hit[-1]) + 1, False)[1]
                parts.append(np.abs(vel[hit, j]))
        return np.concatenate(parts) if parts else np.zeros(0)

    def speed_windows(self) -> list[tuple[int, int]]:
        """The windows [lo, hi) the filtered segments' rows are read in, in order."""
        return [(lo, min(b, lo + CHUNK)) for a, b in self.filtered_segments
                for lo in range(a, b, CHUNK)]

    def velocity(self, lo: int, hi: int) -> np.ndarray:
        """q̇ at rows [lo, hi) (``kinematics``' without the q̈)."""
        return self._kinematics(lo, hi, False)[1]

    def velocity_signs(self) -> np.ndarray:
        """(N, n) int8: the sign of q̇ on every row (0 outside the filtered segments): what the
        typical speeds' pass kept (``typical_speeds``; handed over once), else read here
        window by window."""
        kept = (self.channels.take("velocity_sign", self.velocity_source)
                if self.qd_sign is None else None)
        if kept is not None:
            return kept
        out = np.zeros(self.log.q.shape, np.int8)
        for lo, hi in self.speed_windows():
            out[lo:hi] = np.sign(self.velocity(lo, hi))
        return out

    def speed(self, lo: int, hi: int) -> np.ndarray:
        """|q̇| at rows [lo, hi)."""
        return np.abs(self._kinematics(lo, hi, False)[1])

    def _kinematics(self, lo: int, hi: int, acc: bool
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``kinematics``; q̈ left at zero unless ``acc``."""
        n_j = self.log.q.shape[1]
        q, qd, qdd = (np.zeros((max(hi - lo, 0), n_j)) for _ in range(3))
        dt = 1.0 / self.filt.fs
        for a, b in self.filtered_segments:
            r0, r1 = max(a, lo), min(b, hi)
            if r0 >= r1:
                continue
            # q̈ at [r0, r1) needs q̇ one row beyond, which needs q one row further
            v0, v1 = max(a, r0 - 1), min(b, r1 + 1)
            p0, p1 = max(a, v0 - 1), min(b, v1 + 1)
            qf = self._track("q", self.log.q).window(p0, p1)
            q[r0 - lo: r1 - lo] = qf[r0 - p0: r1 - p0]
            if self.log.qd is not None:
                vel = self._track("qd", self.log.qd).window(v0, v1)
            else:
                vel = _gradient(qf, p0, v0, v1, a, b, dt)
            qd[r0 - lo: r1 - lo] = vel[r0 - v0: r1 - v0]
            if acc:
                qdd[r0 - lo: r1 - lo] = _gradient(vel, v0, r0, r1, a, b, dt)
        if self.qd_sign is not None:  # a touch of zero speed keeps the motion's sign
            keep = self.qd_sign[lo:hi]
            at = keep != 0
            qd[at] = keep[at] * np.maximum(np.abs(qd[at]), 2.0 * V_REST)
        return q, qd, qdd

    def tau_f_rows(self, lo: int, hi: int) -> np.ndarray:
        """The filtered torque at rows [lo, hi)."""
        return self._track("tau", self.log.tau).window(lo, hi)

    def states(self, lo: int, hi: int) -> States:
        """The states at rows [lo, hi): rows of the whole filtered arrays when they are made
        already (the same numbers), else computed for the window."""
        kept = [a for a in (self.channels.kept(*self._key(k)) for k in range(3))
                if a is not None]
        q, qd, qdd = (a[lo:hi] for a in kept) if len(kept) == 3 else self.kinematics(lo, hi)
        # time since the log's start: effects that change over the log (friction drift)
        return States(q, qd, qdd, self.log.t[lo:hi] - self.log.t[0], self.transmission,
                      None if self.tau_rigid is None else self.tau_rigid[lo:hi],
                      None if self.tau_rate is None else self.tau_rate[lo:hi])

    def rows(self, sl: slice, chunk: int = CHUNK
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """q, q̇, q̈ and the filtered torque at the rows of ``sl`` (a slice with a positive
        step), computed chunk by chunk."""
        idx = np.arange(*sl.indices(len(self.log)))
        parts: list[tuple[np.ndarray, ...]] = []
        for a in range(0, idx.size, max(1, chunk // max(1, sl.step or 1))):
            sel = idx[a: a + max(1, chunk // max(1, sl.step or 1))]
            lo, hi = int(sel[0]), int(sel[-1]) + 1
            q, qd, qdd = self.kinematics(lo, hi)
            tf = self.tau_f_rows(lo, hi)
            parts.append(tuple(arr[sel - lo] for arr in (q, qd, qdd, tf)))
        if not parts:
            empty = np.zeros((0, self.log.q.shape[1]))
            return empty, empty, empty, empty
        q, qd, qdd, tf = (np.concatenate([p[k] for p in parts]) for k in range(4))
        return q, qd, qdd, tf

    def _key(self, k: int) -> tuple[str, np.ndarray]:
        """The name and source of the whole array of q (k = 0), q̇ (1) or q̈ (2)."""
        src = self.log.q if k == 0 else self.velocity_source
        name = ("q", "qd", "qdd")[k]
        return (name if k != 1 or self.qd_sign is None else f"qd~{id(self.qd_sign)}"), src

    def _whole(self, k: int) -> np.ndarray:
        kept = self.channels.kept(*self._key(k))
        return kept if kept is not None else self.keep_kinematics()[k]

    def keep_kinematics(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The whole filtered q, q̇ and q̈ (``q``, ``qd``, ``qdd``), made in one read and kept:
        ``states`` reads its windows from them from then on (for passes that read every row
        several times)."""
        made = self.kinematics(0, len(self.log))
        for k, arr in enumerate(made):
            self.channels.put(*self._key(k), arr)
        return made

    @property
    def q(self) -> np.ndarray:
        """Filtered positions, every row (made on first read; read-only)."""
        return self._whole(0)

    @property
    def qd(self) -> np.ndarray:
        return self._whole(1)

    @property
    def qdd(self) -> np.ndarray:
        return self._whole(2)

    @property
    def tau_f(self) -> np.ndarray:
        """Filtered torque, every row (made on first read; read-only)."""
        return self.channels.whole("tau_f", self.log.tau,
                                   lambda: self.tau_f_rows(0, len(self.log)))


def _gradient(f: np.ndarray, f0: int, g0: int, g1: int, a: int, b: int, dt: float
              ) -> np.ndarray:
    """``np.gradient(x[a:b], dt)`` at rows [g0, g1) of segment [a, b), to the bit, from
    ``f`` = x at rows [f0, f0 + len(f)) (one row beyond [g0, g1) where the segment has it)."""
    out = np.empty((g1 - g0, f.shape[1]))
    i0, i1 = max(g0, a + 1), min(g1, b - 1)
    if i1 > i0:
        out[i0 - g0: i1 - g0] = (f[i0 + 1 - f0: i1 + 1 - f0] - f[i0 - 1 - f0: i1 - 1 - f0]) \
            / (2.0 * dt)
    if g0 == a:
        out[0] = (f[a + 1 - f0] - f[a - f0]) / dt
    if g1 == b:
        out[-1] = (f[b - 1 - f0] - f[b - 2 - f0]) / dt
    return out


@dataclass(frozen=True)
class Piece:
    """Rows [lo, hi) of one prepared log; ``ctx`` is the segment filtering runs over."""

    prep: Prepared
    lo: int
    hi: int
    ctx_lo: int
    ctx_hi: int

    def __len__(self) -> int:
        return self.hi - self.lo


def prepare(log: Log, cutoff_hz: float | None, interval: int = 1,
            transmission: np.ndarray | None = None) -> Prepared:
    """Filter positions, derive velocities/accelerations, filter torques (per segment).
    A note (cutoff lowered for decimation) goes to the prepared log's copy, never to ``log``.
    The filters run here once (their states are kept); rows are read by window."""
    fs = log.fs
    fc = DEFAULT_CUTOFF_HZ if cutoff_hz is None else float(cutoff_hz)
    if fc <= 0:
        raise DataError(f"--cutoff must be positive, got {fc}")
    if cutoff_hz is None:
        fc = min(fc, 0.4 * fs / 2.0)
    if interval > 1 and fc > 0.8 * fs / (2 * interval):
        fc = 0.8 * fs / (2 * interval)  # anti-alias before decimation
        log = replace(log, notes=[*log.notes,
                                  f"cutoff lowered to {fc:.3g} Hz for --interval {interval}"])
    prep = Prepared(log, ZeroPhaseFilter(fc, fs), transmission)
    channels = [("q", log.q), ("tau", log.tau)] + ([] if log.qd is None else [("qd", log.qd)])

    def track(channel: tuple[str, np.ndarray], slot: int) -> None:
        prep._track(*channel)

    in_slots(channels, track)
    return prep


#: a sample moves when some joint's filtered speed exceeds this fraction of its typical speed
#: (95th percentile of |q̇| over the log)
MOVING_FRACTION = 0.05


def typical_speeds(preps: Sequence[Prepared]) -> np.ndarray:
    """Each joint's 95th percentile of |q̇| over the filtered rows of the logs
    (np.percentile's numbers, read window by window: no array of every row; one read when the
    raw positions' guess is near, ``_speed_guess``). The read keeps each log's signs of q̇ for
    the touches of zero speed (``Prepared.velocity_signs``)."""
    tasks = [(k, w) for k, prep in enumerate(preps) for w in prep.speed_windows()]
    signs = [np.zeros(p.log.q.shape, np.int8) if p.qd_sign is None else None for p in preps]

    def speeds(task: tuple[int, tuple[int, int]]) -> np.ndarray:
        k, (lo, hi) = task
        vel = preps[k].velocity(lo, hi)
        sign = signs[k]
        if sign is not None:
            sign[lo:hi] = np.sign(vel)
        return np.abs(vel, out=vel)

    out = percentile_streamed(tasks, speeds, 95.0, preps[0].log.q.shape[1],
                              guess=_speed_guess(preps))
    for prep, sign in zip(preps, signs, strict=True):
        if sign is not None:
            prep.channels.put("velocity_sign", prep.velocity_source, sign)
    return out


def _speed_guess(preps: Sequence[Prepared]) -> np.ndarray | None:
    """Near each joint's typical speed: the 95th percentile of |q̇| from central differences
    of the raw positions over one period of the cutoff (or the logged q̇), on ~20,000 rows of
    each log's filtered segments. Where ``typical_speeds`` looks for the exact one."""
    parts = []
    for prep in preps:
        log = prep.log
        h = max(1, int(round(prep.filt.fs / prep.filt.cutoff_hz / 2)))
        step = max(1, len(log) // 20_000)
        for a, b in prep.filtered_segments:
            rows = np.arange(a + h, b - h, step)
            parts.append(np.abs(log.qd[rows]) if log.qd is not None else
                         np.abs(log.q[rows + h] - log.q[rows - h]) * (prep.filt.fs / (2 * h)))
    speeds = np.concatenate(parts) if parts else np.zeros((0, 0))
    return np.percentile(speeds, 95.0, axis=0) if speeds.size else None


def motion_span(prep: Prepared) -> tuple[int, int]:
    """Rows [first, last) of a prepared log between its first and last moving sample (rest at
    the start or the end of a motion excluded); the whole log when nothing moves. The
    windows are read from each end until a moving row."""
    n = len(prep.log)
    windows = prep.speed_windows()  # rows of too-short segments were never filtered
    if not windows:
        return 0, n
    typical = prep.typical_speed()
    active = np.flatnonzero(typical > 1e-6 * max(float(typical.max()), 1e-300))
    if not active.size:
        return 0, n
    level = MOVING_FRACTION * typical[active]

    def moving(window: tuple[int, int]) -> np.ndarray:
        lo, hi = window
        return lo + np.flatnonzero((prep.speed(lo, hi)[:, active] > level).any(axis=1))

    first = next((int(m[0]) for m in map(moving, windows) if m.size), None)
    if first is None:
        return 0, n
    last = next(int(m[-1]) for m in map(moving, reversed(windows)) if m.size)
    return first, last + 1


def split(preps: Sequence[Prepared], validate: Sequence[Prepared] | None,
          holdout: float = 0.2, spans: Sequence[tuple[int, int]] | None = None
          ) -> tuple[list[Piece], list[Piece]]:
    """Training and validation pieces: the ``validate`` logs, else the last 20 % of each log's
    motion (``motion_span``: a robot standing still at the end is not a test of the model) with
    a gap of the filter's settling length on each side (no leak); rest after the motion trains.
    ``spans``: each log's ``motion_span`` when the caller has it already.
    """
    train: list[Piece] = []
    valid: list[Piece] = []
    for k, prep in enumerate(preps):
        trim = prep.filt.settle
        n = len(prep.log)
        first, last = (0, n) if validate or holdout <= 0 else \
            spans[k] if spans is not None else motion_span(prep)
        cut = n if validate else first + int(round((1.0 - holdout) * (last - first)))
        end = n if validate or holdout <= 0 else last
        for seg in prep.log.segments:
            lo, hi = seg.start + trim, seg.stop - trim
            if hi - lo < 2 * trim:
                continue
            if lo < cut - trim:
                train.append(Piece(prep, lo, min(hi, cut - trim), seg.start, seg.stop))
            if not validate and hi > cut and min(hi, end) - max(lo, cut) > trim:
                valid.append(Piece(prep, max(lo, cut), min(hi, end), seg.start, seg.stop))
            if end < n and hi > end + trim and hi - max(lo, end + trim) > 2 * trim:
                train.append(Piece(prep, max(lo, end + trim), hi, seg.start, seg.stop))
    for prep in validate or ():
        trim = prep.filt.settle
        for seg in prep.log.segments:
            lo, hi = seg.start + trim, seg.stop - trim
            if hi - lo > 2 * trim:
                valid.append(Piece(prep, lo, hi, seg.start, seg.stop))
    if not train:
        names = ", ".join(str(prep.log.path) for prep in preps)
        raise DataError(f"{names}: no training data left after trimming the filter's edges "
                        f"({', '.join(f'{len(prep.log)} samples' for prep in preps)}; a longer "
                        "log or a higher --cutoff)")
    return train, valid


def held_out_ranges(valid: Sequence[Piece]) -> str:
    """Which time range of which file the validation used, for the result's notes."""
    by_file: dict[str, list[str]] = {}
    for pc in valid:
        t = pc.prep.log.t
        by_file.setdefault(Path(pc.prep.log.path).name, []).append(
            f"{t[pc.lo]:.4g}–{t[pc.hi - 1]:.4g} s")
    return "; ".join(f"{name} {', '.join(r)}" for name, r in by_file.items())


def filter_windows(piece: Piece, interval: int = 1, chunk: int = CHUNK
                   ) -> Iterator[tuple[int, int, int, int, bool]]:
    """Chunks [a, b) of a piece's rows kept at ``interval`` (on the grid of its filtering
    segment; about ``chunk`` raw rows each, whatever the interval), each with the window
    [ca, cb) to filter over — padded so the filter has settled
    at a and b — and whether the window reaches the segment's edge (odd extension only there,
    as in τ's filtering)."""
    pad = 3 * piece.prep.filt.settle if piece.prep.filt.active else 0
    first = piece.lo + (-(piece.lo - piece.ctx_lo) % interval)
    span = max(1, chunk // interval) * interval  # ≤ chunk raw rows: the filter needs them all
    for a in range(first, piece.hi, span):
        b = min(a + span, piece.hi)
        ca, cb = max(piece.ctx_lo, a - pad), min(piece.ctx_hi, b + pad)
        yield a, b, ca, cb, ca == piece.ctx_lo or cb == piece.ctx_hi


def check_counts(n_rows: int, n_params: int, where: str) -> None:
    if n_rows < 5 * n_params:
        raise DataError(f"{where}: {n_rows} training samples×joints for {n_params} parameters; "
                        f"need at least {5 * n_params} (longer log or smaller --interval)")


@dataclass(frozen=True)
class Problem:
    """Everything the estimators and the diagnosis share for one set of inputs. Frozen: the
    identification's steps each return a new one (``with_preps``, ``dataclasses.replace``)."""

    robot: Robot
    model: Model
    blocks: list[Block]
    train: list[Piece]
    valid: list[Piece]
    preps: list[Prepared]
    vpreps: list[Prepared]
    interval: int
    block_len: int
    validation_source: str
    notes: list[str]
    transmission: np.ndarray | None = None

    def with_preps(self, preps: Sequence[Prepared], vpreps: Sequence[Prepared],
                   notes: Sequence[str] = ()) -> Problem:
        """The same problem on new prepared logs (one for each of ``preps`` and ``vpreps``, in
        order), its training and validation pieces pointing at them; ``notes`` appended."""
        fresh = {id(old): new for old, new in zip((*self.preps, *self.vpreps),
                                                  (*preps, *vpreps), strict=True)}

        def moved(pieces: Sequence[Piece]) -> list[Piece]:
            return [replace(pc, prep=fresh[id(pc.prep)]) for pc in pieces]

        return replace(self, train=moved(self.train), valid=moved(self.valid),
                       preps=list(preps), vpreps=list(vpreps), notes=[*self.notes, *notes])


def build_problem(robot: Robot, data: Sequence[Log], model: Model, *,
                  validate: Sequence[Log] | None = None, cutoff_hz: float | None = None,
                  interval: int = 1, motor_side: bool = False) -> Problem:
    """Prepare the logs (filter, differentiate, split) for a model's identification."""
    if interval < 1:
        raise DataError(f"--interval must be at least 1, got {interval}")
    check_torque_coverage(robot, data)
    transmission = robot.transmission if motor_side else None
    shift = sum(float(s.opts.get("seconds", 0.0)) for s in model.specs if s.name == "delay")
    if shift:
        data = [shift_torque(lg, shift) for lg in data]
        validate = [shift_torque(lg, shift) for lg in validate or ()] or None
    preps = [prepare(lg, cutoff_hz, interval, transmission) for lg in data]
    vpreps = [prepare(lg, cutoff_hz, 1, transmission) for lg in validate or ()]
    spans = None if vpreps else [motion_span(pr) for pr in preps]
    train, valid = split(preps, vpreps or None, spans=spans)
    notes = [n for pr in (*preps, *vpreps) for n in pr.log.notes]
    fs = preps[0].filt.fs
    fc = preps[0].filt.cutoff_hz
    block_len = max(1, math.ceil(2.0 * fs / interval / fc))
    if validate:
        source = "files " + ", ".join(Path(v.path).name for v in validate)
    else:
        source = ("last 20 % of the motion of each data file (gap of the filter's length): "
                  + (held_out_ranges(valid) or "none left"))
        assert spans is not None
        rest = [f"{Path(pr.log.path).name} {pr.log.t[-1] - pr.log.t[last - 1]:.3g} s"
                for pr, (_, last) in zip(preps, spans, strict=True) if last < len(pr.log)
                and pr.log.t[-1] - pr.log.t[last - 1] > 0.5]
        if rest:
            notes.append("the robot stands still at the end of " + ", ".join(rest) + ": that "
                         "rest is not held out (it would test gravity alone) but trains")
    joined = joined_logs_note([*data, *(validate or ())])
    if joined:
        notes.append(joined)
    if len(data) > 1 and not validate:
        notes.append("validation holds out the end of each file; use --validate with a "
                     "different motion for an honest check of generalisation")
    return Problem(robot, model, model.blocks(robot), train, valid, preps, vpreps, interval,
                   block_len, source, notes, transmission)


def check_torque_coverage(robot: Robot, data: Sequence[Log]) -> None:
    """Partial logs (each holding some joints' torque) are joined: joint j's equation takes its
    rows from the logs that hold its torque. A joint that no data log holds is refused."""
    held = np.zeros(robot.n, dtype=bool)
    for lg in data:
        held |= lg.held
    if held.all():
        return
    j = int(np.flatnonzero(~held)[0])
    files = ", ".join(Path(lg.path).name for lg in data)
    raise DataError(f"joint {j + 1} ({robot.joint_names[j]}): no log holds its torque "
                    f"(tau{j + 1} in none of {files})")


def joined_logs_note(data: Sequence[Log]) -> str | None:
    """What a joined identification says of its partial logs (None: every log is full)."""
    parts = [f"{Path(lg.path).name} τ{','.join(str(j + 1) for j in np.flatnonzero(lg.held))}"
             for lg in data if lg.partial]
    if not parts:
        return None
    return ("partial logs joined (each joint's equation from the logs that hold its "
            "torque): " + "; ".join(parts))


def shift_torque(log: Log, seconds: float) -> Log:
    """Undo a torque log that lags the positions by ``seconds``: τ'(t) = τ(t + seconds)."""
    def shifted(a: np.ndarray) -> np.ndarray:
        return np.stack([np.interp(log.t + seconds, log.t, a[:, j])
                         for j in range(a.shape[1])], axis=1)

    return replace(log, tau=shifted(log.tau),
                   currents=None if log.currents is None else shifted(log.currents),
                   notes=[*log.notes,
                                        f"torque log shifted by {1e3 * seconds:.3g} ms (delay)"])


def warn(msg: str) -> None:
    warnings.warn(msg, DataWarning, stacklevel=2)
