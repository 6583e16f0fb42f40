"""Filtering, differentiation, train/validation split, and parallel-filtered design rows.

Regressor columns are filtered with the same zero-phase filter as the torques (Gautier's
parallel filtering), in chunks with overlap so that long logs stream in bounded memory.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numba
import numpy as np

from robid_link.exceptions import DataError, DataWarning
from robid_link.ident.data import Log
from robid_link.ident.effects import Block, States
from robid_link.ident.regressor import rigid_regressor
from robid_link.ident.robot import Robot

__all__ = [
    "DEFAULT_CUTOFF_HZ",
    "ZeroPhaseFilter",
    "Prepared",
    "Piece",
    "filter_windows",
    "prepare",
    "split",
    "design_chunks",
    "block_columns",
    "Design",
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


@dataclass
class Prepared:
    """One log after filtering: states for the regressor, raw and filtered torques."""

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

    @property
    def tau(self) -> np.ndarray:
        return self.log.tau

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


def prepare(log: Log, cutoff_hz: float | None, interval: int = 1) -> Prepared:
    """Filter positions, derive velocities/accelerations, filter torques (per segment)."""
    fs = log.fs
    fc = DEFAULT_CUTOFF_HZ if cutoff_hz is None else float(cutoff_hz)
    if fc <= 0:
        raise DataError(f"--cutoff must be positive, got {fc}")
    if cutoff_hz is None:
        fc = min(fc, 0.4 * fs / 2.0)
    if interval > 1 and fc > 0.8 * fs / (2 * interval):
        fc = 0.8 * fs / (2 * interval)  # anti-alias before decimation
        log.notes.append(f"cutoff lowered to {fc:.3g} Hz for --interval {interval}")
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
    return Prepared(log, q, qd, qdd, tau_f, filt)


def split(preps: Sequence[Prepared], validate: Sequence[Prepared] | None,
          holdout: float = 0.2) -> tuple[list[Piece], list[Piece]]:
    """Training and validation pieces: the ``validate`` logs, else the last 20 % of each
    log with a gap of the filter's settling length between the two (no leak)."""
    train: list[Piece] = []
    valid: list[Piece] = []
    for prep in preps:
        trim = prep.filt.settle
        n = len(prep.log)
        cut = n if validate else int(round((1.0 - holdout) * n))
        for seg in prep.log.segments:
            lo, hi = seg.start + trim, seg.stop - trim
            if hi - lo < 2 * trim:
                continue
            if lo < cut - trim:
                train.append(Piece(prep, lo, min(hi, cut - trim), seg.start, seg.stop))
            if not validate and hi > cut:
                valid.append(Piece(prep, max(lo, cut), hi, seg.start, seg.stop))
    for prep in validate or ():
        trim = prep.filt.settle
        for seg in prep.log.segments:
            lo, hi = seg.start + trim, seg.stop - trim
            if hi - lo > 2 * trim:
                valid.append(Piece(prep, lo, hi, seg.start, seg.stop))
    if not train:
        raise DataError("no training data left after trimming the filter's edges")
    return train, valid


def block_columns(robot: Robot, blocks: Sequence[Block], st: States) -> np.ndarray:
    """(N, n, P): the columns of every block side by side."""
    return np.concatenate([b.effect.columns(robot, st, b.joint, b.opts) for b in blocks], axis=2)


class Design:
    """The model's base columns, evaluated compactly.

    Joint j's torque row is non-zero only in some base columns (its support); the compact
    matrix holds, joint after joint, just those entries: (N, nnz) instead of (N, n, p).
    """

    def __init__(self, robot: Robot, blocks: Sequence[Block], cols: np.ndarray,
                 mask: np.ndarray) -> None:
        self.robot = robot
        self.blocks = tuple(blocks)
        self.cols = np.asarray(cols)
        self.mask = np.asarray(mask, dtype=bool)  # (n, p)
        self.support = [np.flatnonzero(self.mask[j]) for j in range(robot.n)]
        sizes = [s.size for s in self.support]
        self.offsets = np.concatenate(([0], np.cumsum(sizes))).astype(int)
        self._gathers = self._plan()

    @property
    def p(self) -> int:
        return int(self.cols.size)

    @property
    def nnz(self) -> int:
        return int(self.offsets[-1])

    def joint_slice(self, j: int) -> slice:
        return slice(int(self.offsets[j]), int(self.offsets[j + 1]))

    def _plan(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per block: (compact destination columns, flat source index in that block)."""
        widths = [len(b.effect.param_names(self.robot, b.joint, b.opts)) for b in self.blocks]
        starts = np.concatenate(([0], np.cumsum(widths))).astype(int)
        plan = []
        for bi, width in enumerate(widths):
            dst, src = [], []
            for j in range(self.robot.n):
                for pos, k in enumerate(self.support[j]):
                    c = int(self.cols[k])
                    if starts[bi] <= c < starts[bi] + width:
                        dst.append(self.offsets[j] + pos)
                        src.append(j * width + c - starts[bi])
            plan.append((np.array(dst, dtype=int), np.array(src, dtype=int)))
        return plan

    def compact(self, st: States) -> np.ndarray:
        """(N, nnz) base-column entries of every joint row, joint after joint."""
        n_samp = len(st)
        out = np.empty((n_samp, self.nnz))
        n = self.robot.n
        for blk, (dst, src) in zip(self.blocks, self._gathers, strict=True):
            if dst.size == 0:
                continue
            if blk.effect.name == "rigid_body":  # the kernel writes straight into place
                dest = np.full(n * 10 * n, -1, dtype=np.int64)
                dest[src] = dst
                rigid_regressor(self.robot, st.q, st.qd, st.qdd, out=out,
                                dest=dest.reshape(n, 10 * n))
            else:
                vals = blk.effect.columns(self.robot, st, blk.joint, blk.opts)
                out[:, dst] = vals.reshape(n_samp, -1)[:, src]
        return out

    def predict(self, c: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """Torques (N, n) from compact columns and base parameters."""
        return np.stack([c[:, self.joint_slice(j)] @ theta[self.support[j]]
                         for j in range(self.robot.n)], axis=1)

    def expand(self, c: np.ndarray) -> np.ndarray:
        """(N, n, p) dense base regressor from compact columns."""
        out = np.zeros((c.shape[0], self.robot.n, self.p))
        for j in range(self.robot.n):
            out[:, j, self.support[j]] = c[:, self.joint_slice(j)]
        return out


def design_chunks(design: Design, piece: Piece, interval: int = 1, filtered: bool = True,
                  chunk: int = CHUNK) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Yield (compact columns (m, nnz), τ (m, n), sample index (m,)) for a piece, in chunks.

    With ``filtered`` the columns and the torque are parallel-filtered and decimated by
    ``interval`` (training rows); otherwise columns come from the filtered states at the
    full rate against the raw torques (validation rows).
    """
    prep = piece.prep
    if not filtered:
        for a in range(piece.lo, piece.hi, chunk):
            b = min(a + chunk, piece.hi)
            yield design.compact(prep.states(a, b)), prep.tau[a:b], np.arange(a, b)
        return
    for a, b, ca, cb, at_edge in filter_windows(piece, interval, chunk):
        c = prep.filt.apply(design.compact(prep.states(ca, cb)), edges=at_edge)
        yield c[a - ca: b - ca: interval], prep.tau_f[a:b:interval], np.arange(a, b, interval)


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


def warn(msg: str) -> None:
    warnings.warn(msg, DataWarning, stacklevel=2)
