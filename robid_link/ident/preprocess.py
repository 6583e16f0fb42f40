"""Filtering, differentiation, train/validation split, and parallel-filtered design rows.

Regressor columns are filtered with the same zero-phase filter as the torques (Gautier's
parallel filtering), in chunks with overlap so that long logs stream in bounded memory.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np
import scipy.signal as sig

from robid_link.exceptions import DataError, DataWarning
from robid_link.ident.data import Log
from robid_link.ident.effects import Block, States
from robid_link.ident.robot import Robot

__all__ = [
    "DEFAULT_CUTOFF_HZ",
    "ZeroPhaseFilter",
    "Prepared",
    "Piece",
    "prepare",
    "split",
    "design_chunks",
    "block_columns",
]

#: Default low-pass cutoff. Excitation trajectories live below ~2 Hz (Fourier base 0.05–0.2 Hz,
#: a handful of harmonics), so 10 Hz keeps them with < 0.1 % amplitude error while removing
#: the noise that double differentiation amplifies. Capped at 40 % of the Nyquist rate.
DEFAULT_CUTOFF_HZ = 10.0
FILTER_ORDER = 4
CHUNK = 4096  # samples per chunk when building design rows


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
        return sig.butter(self.order, self.cutoff_hz, fs=self.fs, output="sos")

    @property
    def settle(self) -> int:
        """Samples after which the (doubled) impulse response has died out: 3 / fc."""
        return int(math.ceil(3.0 * self.fs / self.cutoff_hz)) if self.active else 1

    def apply(self, x: np.ndarray, axis: int = 0) -> np.ndarray:
        if not self.active:
            return np.array(x, dtype=float, copy=True)
        n = x.shape[axis]
        padlen = min(3 * self.settle, n - 1)
        return sig.sosfiltfilt(self.sos, x, axis=axis, padtype="odd", padlen=padlen)


@dataclass
class Prepared:
    """One log after filtering: states for the regressor, raw and filtered torques."""

    log: Log
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    tau_f: np.ndarray
    filt: ZeroPhaseFilter

    @property
    def tau(self) -> np.ndarray:
        return self.log.tau

    def states(self, lo: int, hi: int) -> States:
        return States(self.q[lo:hi], self.qd[lo:hi], self.qdd[lo:hi], self.log.t[lo:hi])


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


def design_chunks(robot: Robot, blocks: Sequence[Block], piece: Piece, interval: int = 1,
                  filtered: bool = True, chunk: int = CHUNK
                  ) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Yield (W (m, n, P), τ (m, n), sample index (m,)) for a piece, in chunks.

    With ``filtered`` the columns and the torque are parallel-filtered and decimated by
    ``interval`` (training rows); otherwise columns come from the filtered states at the
    full rate against the raw torques (validation rows).
    """
    prep = piece.prep
    pad = 3 * prep.filt.settle if filtered and prep.filt.active else 0
    step = interval if filtered else 1
    first = piece.lo + (-(piece.lo - piece.ctx_lo) % step) if filtered else piece.lo
    for a in range(first, piece.hi, chunk * step):
        b = min(a + chunk * step, piece.hi)
        if not filtered:
            w = block_columns(robot, blocks, prep.states(a, b))
            yield w, prep.tau[a:b], np.arange(a, b)
            continue
        ca, cb = max(piece.ctx_lo, a - pad), min(piece.ctx_hi, b + pad)
        w = block_columns(robot, blocks, prep.states(ca, cb))
        shape = w.shape
        w = prep.filt.apply(w.reshape(shape[0], -1), axis=0).reshape(shape)
        idx = np.arange(a, b, step)
        yield w[idx - ca], prep.tau_f[idx], idx


def check_counts(n_rows: int, n_params: int, where: str) -> None:
    if n_rows < 5 * n_params:
        raise DataError(f"{where}: {n_rows} training samples×joints for {n_params} parameters; "
                        f"need at least {5 * n_params} (longer log or smaller --interval)")


def warn(msg: str) -> None:
    warnings.warn(msg, DataWarning, stacklevel=2)
