"""Filtering, differentiation, decimation, segments and the train/validation split: logs
become the prepared problem that the design (design.py) turns into regressor rows.

The filter windows say where regressor columns are filtered with the same zero-phase filter
as the torques (Gautier's parallel filtering), in chunks with overlap (bounded memory).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numba
import numpy as np

from robid_link.exceptions import DataError, DataWarning
from robid_link.ident.data.logs import Log
from robid_link.ident.model.effects import Block, Model, States
from robid_link.ident.model.robot import Robot

__all__ = [
    "DEFAULT_CUTOFF_HZ",
    "ZeroPhaseFilter",
    "Prepared",
    "Piece",
    "filter_windows",
    "prepare",
    "split",
    "motion_span",
    "held_out_ranges",
    "noise_floor",
    "Problem",
    "build_problem",
    "shift_torque",
    "check_counts",
    "butter_lowpass_sos",
    "sos_steady_state",
]

#: Default low-pass cutoff. Excitation trajectories live below ~2 Hz (Fourier base 0.05–0.2 Hz,
#: a handful of harmonics), so 10 Hz keeps them with < 0.1 % amplitude error while removing
#: the noise that double differentiation amplifies. Capped at 40 % of the Nyquist rate.
DEFAULT_CUTOFF_HZ = 10.0
FILTER_ORDER = 4
CHUNK = 65536  # samples per chunk when building design rows


@dataclass(frozen=True)
class ZeroPhaseFilter:
    """Butterworth low-pass applied forward and backward (zero phase)."""

    cutoff_hz: float
    fs: float
    order: int = FILTER_ORDER

    @property
    def active(self) -> bool:
        return self.cutoff_hz < 0.45 * self.fs

    @property
    def sos(self) -> np.ndarray:
        return butter_lowpass_sos(self.order, self.cutoff_hz, self.fs)

    @property
    def settle(self) -> int:
        """Samples after which the (doubled) impulse response has died out: 3 / fc."""
        return int(math.ceil(3.0 * self.fs / self.cutoff_hz)) if self.active else 1

    def apply(self, x: np.ndarray, edges: bool = True) -> np.ndarray:
        """Filter along axis 0 (samples); exactly scipy's sosfiltfilt with odd padding.

        ``edges=False`` skips the odd extension, for windows whose ends are discarded.
        """
        x = np.asarray(x, dtype=float)
        if not self.active:
            return x.copy()
        flat = np.ascontiguousarray(x.reshape(x.shape[0], -1))
        padlen = min(3 * self.settle, flat.shape[0] - 1) if edges else 0
        sos = np.ascontiguousarray(self.sos)
        zi = np.ascontiguousarray(sos_steady_state(sos))
        return _sosfiltfilt(sos, zi, flat, padlen, numba.get_num_threads()).reshape(x.shape)


def butter_lowpass_sos(order: int, cutoff_hz: float, fs: float) -> np.ndarray:
    """Digital Butterworth low-pass as second-order sections (bilinear, pre-warped).

    The same design as scipy.signal.butter(order, cutoff, fs=fs, output="sos"), written out
    so the worker does not pay scipy.signal's import time (≈1 s) on every run.
    """
    warped = 2.0 * fs * math.tan(math.pi * cutoff_hz / fs)
    k = np.arange(1, order + 1)
    poles_a = warped * np.exp(1j * math.pi * (2 * k + order - 1) / (2 * order))
    poles = (2.0 * fs + poles_a) / (2.0 * fs - poles_a)
    gain = float(np.real(warped**order / np.prod(2.0 * fs - poles_a)))
    upper = sorted((p for p in poles if p.imag > 1e-12), key=lambda p: -abs(1 - abs(p)))
    sections = [[1.0, 2.0, 1.0, 1.0, -2.0 * p.real, abs(p) ** 2] for p in upper]
    real = [p.real for p in poles if abs(p.imag) <= 1e-12]
    if real:
        sections.insert(0, [1.0, 1.0, 0.0, 1.0, -real[0], 0.0])
    sos = np.array(sections)
    sos[0, :3] *= gain
    return sos


def sos_steady_state(sos: np.ndarray) -> np.ndarray:
    """Initial states (ns, 2) of a unit step's steady state (scipy.signal.sosfilt_zi)."""
    zi = np.empty((sos.shape[0], 2))
    scale = 1.0
    for s, (b0, b1, b2, _a0, a1, a2) in enumerate(sos):
        lhs = np.array([[1.0 + a1, -1.0], [a2, 1.0]])
        zi[s] = scale * np.linalg.solve(lhs, np.array([b1 - a1 * b0, b2 - a2 * b0]))
        scale *= (b0 + b1 + b2) / (1.0 + a1 + a2)
    return zi


@numba.njit(cache=True, nogil=True)
def _biquads(sos: np.ndarray, z: np.ndarray, row: np.ndarray, out: np.ndarray) -> None:
    """One sample through the cascade for every column (direct form II transposed)."""
    for s in range(sos.shape[0]):
        b0, b1, b2, a1, a2 = sos[s, 0], sos[s, 1], sos[s, 2], sos[s, 4], sos[s, 5]
        z0, z1 = z[s, 0], z[s, 1]
        for c in range(row.shape[0]):
            v = row[c]
            y = b0 * v + z0[c]
            z0[c] = b1 * v - a1 * y + z1[c]
            z1[c] = b2 * v - a2 * y
            out[c] = y
        row = out


@numba.njit(cache=True, parallel=True, nogil=True)
def _sosfiltfilt(sos: np.ndarray, zi: np.ndarray, x: np.ndarray, padlen: int,
                 n_threads: int) -> np.ndarray:
    """Zero-phase second-order-section filter of every column of x (N, m) along axis 0.

    Exactly scipy's sosfiltfilt(padtype="odd"): odd extension, steady-state initial
    conditions for the first sample of each pass. Sample-major, so the inner loop runs over
    contiguous columns; column groups go to threads.
    """
    n, m = x.shape
    total = n + 2 * padlen
    ns = sos.shape[0]
    out = np.empty((n, m))
    n_par = max(1, min(m // 8, n_threads))
    for part in numba.prange(n_par):
        c0 = part * m // n_par
        c1 = (part + 1) * m // n_par
        w = c1 - c0
        buf = np.empty((total, w))
        for k in range(padlen):  # odd extension at both ends
            for c in range(w):
                buf[k, c] = 2.0 * x[0, c0 + c] - x[padlen - k, c0 + c]
                buf[padlen + n + k, c] = 2.0 * x[n - 1, c0 + c] - x[n - 2 - k, c0 + c]
        for k in range(n):
            for c in range(w):
                buf[padlen + k, c] = x[k, c0 + c]
        z = np.empty((ns, 2, w))
        for direction in range(2):
            start = 0 if direction == 0 else total - 1
            for s in range(ns):
                for c in range(w):
                    z[s, 0, c] = zi[s, 0] * buf[start, c]
                    z[s, 1, c] = zi[s, 1] * buf[start, c]
            if direction == 0:
                for k in range(total):
                    _biquads(sos, z, buf[k], buf[k])
            else:
                for k in range(total - 1, -1, -1):
                    _biquads(sos, z, buf[k], buf[k])
        for k in range(n):
            for c in range(w):
                out[k, c0 + c] = buf[k + padlen, c]
    return out


@dataclass(frozen=True)
class Prepared:
    """One log after filtering: states for the regressor, raw and filtered torques. Frozen:
    a step that changes a torque (known torques, drive currents, the model's predictions)
    returns a new one (``dataclasses.replace``) and ``Problem.with_preps`` re-points pieces."""

    log: Log
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    tau_f: np.ndarray
    filt: ZeroPhaseFilter
    transmission: np.ndarray | None = None  # set for motor-side logs
    tau_rigid: np.ndarray | None = None  # the current model's rigid torque (diagnosis)
    tau_rate: np.ndarray | None = None  # … and its torque rate
    tau_model: np.ndarray | None = None  # the current model's torque on every raw sample
    #: known torques (model file), already subtracted from ``tau`` and ``tau_f``
    tau_known: np.ndarray | None = None

    @property
    def tau(self) -> np.ndarray:
        """The torque left for the model: measured minus known torques."""
        return self.log.tau

    @property
    def tau_measured(self) -> np.ndarray:
        return self.log.tau if self.tau_known is None else self.log.tau + self.tau_known

    def states(self, lo: int, hi: int) -> States:
        # time since the log's start: effects that change over the log (friction drift)
        return States(self.q[lo:hi], self.qd[lo:hi], self.qdd[lo:hi],
                      self.log.t[lo:hi] - self.log.t[0],
                      self.transmission,
                      None if self.tau_rigid is None else self.tau_rigid[lo:hi],
                      None if self.tau_rate is None else self.tau_rate[lo:hi])


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
    A note (cutoff lowered for decimation) goes to the prepared log's copy, never to ``log``."""
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
    filt = ZeroPhaseFilter(fc, fs)
    q = np.empty_like(log.q)
    qd = np.empty_like(log.q)
    qdd = np.empty_like(log.q)
    tau_f = np.empty_like(log.tau)
    dt = 1.0 / fs
    for seg in log.segments:
        if seg.stop - seg.start < 3 * filt.settle:
            continue
        q[seg] = filt.apply(log.q[seg])
        qd[seg] = filt.apply(log.qd[seg]) if log.qd is not None else np.gradient(q[seg], dt, axis=0)
        qdd[seg] = np.gradient(qd[seg], dt, axis=0)
        tau_f[seg] = filt.apply(log.tau[seg])
    return Prepared(log, q, qd, qdd, tau_f, filt, transmission)


#: a sample moves when some joint's filtered speed exceeds this fraction of its typical speed
#: (95th percentile of |q̇| over the log)
MOVING_FRACTION = 0.05


def motion_span(prep: Prepared) -> tuple[int, int]:
    """Rows [first, last) of a prepared log between its first and last moving sample (rest at
    the start or the end of a motion excluded); the whole log when nothing moves."""
    n = len(prep.log)
    ok = np.zeros(n, bool)
    for seg in prep.log.segments:
        if seg.stop - seg.start >= 3 * prep.filt.settle:
            ok[seg] = True  # rows of too-short segments were never filtered
    if not ok.any():
        return 0, n
    speed = np.abs(prep.qd[ok])
    typical = np.percentile(speed, 95, axis=0)
    active = typical > 1e-6 * max(float(typical.max()), 1e-300)
    if not active.any():
        return 0, n
    moving = np.zeros(n, bool)
    moving[ok] = np.any(speed[:, active] > MOVING_FRACTION * typical[active], axis=1)
    idx = np.flatnonzero(moving)
    return (int(idx[0]), int(idx[-1]) + 1) if idx.size else (0, n)


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


def _rejected_share(filt: ZeroPhaseFilter, points: int = 4096) -> float:
    """Share of white noise's variance in ``raw − filtered`` for the zero-phase filter:
    the mean over the band of (1 − |H|²)² (|H|² because the filter runs twice)."""
    w = np.linspace(0.0, math.pi, points)
    z1 = np.exp(-1j * w)
    h = np.ones_like(z1)
    for b0, b1, b2, _, a1, a2 in filt.sos:
        h = h * (b0 + b1 * z1 + b2 * z1**2) / (1.0 + a1 * z1 + a2 * z1**2)
    return float(np.mean((1.0 - np.abs(h) ** 2) ** 2))


def noise_floor(pieces: Sequence[Piece]) -> np.ndarray | None:
    """Per joint, the torque measurement noise (N·m, standard deviation) that no model of
    the motion can explain: the raw torque's content above the filter's cutoff, where an
    excitation (a few Hz) has none, scaled to the whole band as white noise. Validation RMSE
    on raw torque cannot fall below it. None when the filter is off (nothing to compare)."""
    if not pieces or not pieces[0].prep.filt.active:
        return None
    acc, rows = 0.0, 0
    for pc in pieces:
        d = pc.prep.tau[pc.lo:pc.hi] - pc.prep.tau_f[pc.lo:pc.hi]
        acc = acc + np.sum(d * d, axis=0)
        rows += d.shape[0]
    if rows == 0:
        return None
    share = _rejected_share(pieces[0].prep.filt)
    return np.asarray(np.sqrt(acc / rows / max(share, 1e-12)))


def filter_windows(piece: Piece, interval: int = 1, chunk: int = CHUNK
                   ) -> Iterator[tuple[int, int, int, int, bool]]:
    """Chunks [a, b) of a piece's rows kept at ``interval`` (on the grid of its filtering
    segment), each with the window [ca, cb) to filter over — padded so the filter has settled
    at a and b — and whether the window reaches the segment's edge (odd extension only there,
    as in τ's filtering)."""
    pad = 3 * piece.prep.filt.settle if piece.prep.filt.active else 0
    first = piece.lo + (-(piece.lo - piece.ctx_lo) % interval)
    for a in range(first, piece.hi, chunk * interval):
        b = min(a + chunk * interval, piece.hi)
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
    if len(data) > 1 and not validate:
        notes.append("validation holds out the end of each file; use --validate with a "
                     "different motion for an honest check of generalisation")
    return Problem(robot, model, model.blocks(robot), train, valid, preps, vpreps, interval,
                   block_len, source, notes, transmission)


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
