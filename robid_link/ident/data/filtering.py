"""Zero-phase low-pass filtering: the Butterworth design, a forward–backward kernel (scipy's
sosfiltfilt with odd padding) that runs in place over contiguous columns, and checkpointed
tracks that give any window of a filtered log channel exactly as filtering its whole segment,
and a prepared log's channels (its tracks and, when asked for, whole filtered arrays).

A track stores the filter's state every ``TRACK_EVERY`` samples of a segment in both passes;
a window is then two short passes from the nearest states — to the bit the rows the whole
segment's filtering gives — so a long log is filtered window by window in bounded memory.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numba
import numpy as np

from robid_link.ident.model.threads import kernel_threads

__all__ = ["FILTER_ORDER", "ZeroPhaseFilter", "Track", "Channels", "butter_lowpass_sos",
           "sos_steady_state", "TRACK_EVERY", "load_compiler"]

FILTER_ORDER = 4
#: samples between the stored filter states of a track
TRACK_EVERY = 512


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

    def padlen(self, n: int, edges: bool = True) -> int:
        return min(3 * self.settle, n - 1) if edges else 0

    def apply(self, x: np.ndarray, edges: bool = True) -> np.ndarray:
        """Filter along axis 0 (samples); exactly scipy's sosfiltfilt with odd padding.

        ``edges=False`` skips the odd extension, for windows whose ends are discarded.
        """
        x = np.asarray(x, dtype=float)
        if not self.active:
            return x.copy()
        out = np.array(x.reshape(x.shape[0], -1), dtype=float, order="C", copy=True)
        self.apply_inplace(out, edges)
        return out.reshape(x.shape)

    def apply_inplace(self, x: np.ndarray, edges: bool = True) -> None:
        """``apply`` on a C-contiguous (N, m) float array the caller owns, in place."""
        if not self.active or x.shape[0] == 0:
            return
        sos = np.ascontiguousarray(self.sos)
        zi = np.ascontiguousarray(sos_steady_state(sos))
        threads = kernel_threads()
        if threads == 1 or x.shape[1] < 32:  # one column group either way: no thread launch
            _filtfilt_part(sos, zi, x, self.padlen(x.shape[0], edges), 0, x.shape[1])
        else:
            _filtfilt_inplace(sos, zi, x, self.padlen(x.shape[0], edges), threads)


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


# ----------------------------------------------------------------------------- kernels
# Direct form II transposed, section after section: section s runs over the whole sequence
# before section s + 1 reads its output (the same numbers as sample after sample, and the
# column loop vectorizes). The state z is (ns, 2, m). Every pass below does the same
# operations in the same order, which is what makes a track's windows exact.


@numba.njit(cache=True, nogil=True)
def _run(sos, s, z, x, k0, k1, step, c0, c1):
    """Section s over rows k0, k0 + step, … (k1 excluded) of x, columns [c0, c1), in place."""
    b0, b1, b2, a1, a2 = sos[s, 0], sos[s, 1], sos[s, 2], sos[s, 4], sos[s, 5]
    z0 = z[s, 0, c0:c1]
    z1 = z[s, 1, c0:c1]
    w = c1 - c0
    for k in range(k0, k1, step):
        row = x[k, c0:c1]
        for c in range(w):
            v = row[c]
            y = b0 * v + z0[c]
            z0[c] = b1 * v - a1 * y + z1[c]
            z1[c] = b2 * v - a2 * y
            row[c] = y


@numba.njit(cache=True, nogil=True)
def _init(zi, z, row, c0, c1):
    """Every section's state at the steady state of the first input row (scipy's zi·x0)."""
    for s in range(zi.shape[0]):
        for c in range(c0, c1):
            z[s, 0, c] = zi[s, 0] * row[c]
            z[s, 1, c] = zi[s, 1] * row[c]


@numba.njit(cache=True, nogil=True)
def _filtfilt_part(sos, zi, x, padlen, c0, c1):
    """Columns [c0, c1) of x (N, m), in place: forward over the head extension, the rows and
    the tail extension, backward over the tail extension and the rows (the head's backward
    output is never used)."""
    n, m = x.shape
    ns = sos.shape[0]
    z = np.empty((ns, 2, m))
    head = np.empty((max(padlen, 1), m))
    tail = np.empty((max(padlen, 1), m))
    for k in range(padlen):
        for c in range(c0, c1):
            head[k, c] = 2.0 * x[0, c] - x[padlen - k, c]
            tail[k, c] = 2.0 * x[n - 1, c] - x[n - 2 - k, c]
    _init(zi, z, head[0] if padlen > 0 else x[0], c0, c1)
    for s in range(ns):
        _run(sos, s, z, head, 0, padlen, 1, c0, c1)
        _run(sos, s, z, x, 0, n, 1, c0, c1)
        _run(sos, s, z, tail, 0, padlen, 1, c0, c1)
    _init(zi, z, tail[padlen - 1] if padlen > 0 else x[n - 1], c0, c1)
    for s in range(ns):
        _run(sos, s, z, tail, padlen - 1, -1, -1, c0, c1)
        _run(sos, s, z, x, n - 1, -1, -1, c0, c1)


@numba.njit(cache=True, nogil=True, parallel=True)
def _filtfilt_inplace(sos, zi, x, padlen, n_threads):
    """Zero-phase filter of every column of x (N, m) along axis 0, in place; column groups
    go to threads. Exactly scipy's sosfiltfilt(padtype="odd", padlen)."""
    m = x.shape[1]
    n_par = max(1, min(m // 16, n_threads))
    for part in numba.prange(n_par):
        _filtfilt_part(sos, zi, x, padlen, part * m // n_par, (part + 1) * m // n_par)


@numba.njit(cache=True, nogil=True)
def _track_states(sos, zi, x, padlen, every):
    """States of a segment's zero-phase filtering at rows 0, every, 2·every, …, N: forward
    (before the row) and backward (after the rows from there on, extension included)."""
    n, m = x.shape
    nb = (n + every - 1) // every
    ns = sos.shape[0]
    fwd = np.empty((nb + 1, ns, 2, m))
    bwd = np.empty((nb + 1, ns, 2, m))
    z = np.empty((ns, 2, m))
    head = np.empty((max(padlen, 1), m))
    tail = np.empty((max(padlen, 1), m))
    blk = np.empty((every, m))
    for k in range(padlen):
        for c in range(m):
            head[k, c] = 2.0 * x[0, c] - x[padlen - k, c]
            tail[k, c] = 2.0 * x[n - 1, c] - x[n - 2 - k, c]
    _init(zi, z, head[0] if padlen > 0 else x[0], 0, m)
    for s in range(ns):  # forward, block by block, the states at block starts kept
        _run(sos, s, z, head, 0, padlen, 1, 0, m)
    for b in range(nb):
        lo, hi = b * every, min(n, (b + 1) * every)
        fwd[b] = z
        blk[: hi - lo] = x[lo:hi]
        for s in range(ns):
            _run(sos, s, z, blk, 0, hi - lo, 1, 0, m)
    fwd[nb] = z
    for s in range(ns):
        _run(sos, s, z, tail, 0, padlen, 1, 0, m)
    _init(zi, z, tail[padlen - 1] if padlen > 0 else blk[(n - 1) % every], 0, m)
    for s in range(ns):
        _run(sos, s, z, tail, padlen - 1, -1, -1, 0, m)
    bwd[nb] = z
    zf = np.empty((ns, 2, m))
    for b in range(nb - 1, -1, -1):  # backward: each block's forward output again
        lo, hi = b * every, min(n, (b + 1) * every)
        zf[:] = fwd[b]
        blk[: hi - lo] = x[lo:hi]
        for s in range(ns):
            _run(sos, s, zf, blk, 0, hi - lo, 1, 0, m)
        for s in range(ns):
            _run(sos, s, z, blk, hi - lo - 1, -1, -1, 0, m)
        bwd[b] = z
    return fwd, bwd


@numba.njit(cache=True, nogil=True)
def _track_window(sos, x, fwd, bwd, every, b0, b1, out):
    """Rows [b0·every, min(N, b1·every)) of the filtered segment into out, from the states."""
    n = x.shape[0]
    m = x.shape[1]
    lo, hi = b0 * every, min(n, b1 * every)
    out[: hi - lo] = x[lo:hi]
    z = np.empty(fwd.shape[1:])
    z[:] = fwd[b0]
    for s in range(sos.shape[0]):
        _run(sos, s, z, out, 0, hi - lo, 1, 0, m)
    z[:] = bwd[b1]
    for s in range(sos.shape[0]):
        _run(sos, s, z, out, hi - lo - 1, -1, -1, 0, m)


def load_compiler() -> None:
    """Load numba's compiler now (its registries load with the first kernel a process takes
    from the cache, ~0.3 s): for a caller that wants it done at a time of its choosing."""
    _init(np.zeros((1, 2)), np.zeros((1, 2, 1)), np.zeros(1), 0, 1)


class Track:
    """One channel of a log (N, m) low-pass filtered per segment, window by window: rows of
    ``window`` equal those of filtering each whole segment (``ZeroPhaseFilter.apply``).
    Segments shorter than ``min_len`` are not filtered (their rows read as zero)."""

    def __init__(self, x: np.ndarray, filt: ZeroPhaseFilter, segments: Sequence[slice],
                 min_len: int, every: int = TRACK_EVERY) -> None:
        self.source = x
        self.filt = filt
        self.every = every
        self.segments = [(s.start, s.stop) for s in segments if s.stop - s.start >= min_len]
        self._states: list[tuple[np.ndarray, np.ndarray] | None] = []
        self._sos = np.ascontiguousarray(filt.sos)
        zi = np.ascontiguousarray(sos_steady_state(self._sos))
        for a, b in self.segments:
            if not filt.active:
                self._states.append(None)
                continue
            seg = np.ascontiguousarray(x[a:b], dtype=float)
            self._states.append(_track_states(self._sos, zi, seg, filt.padlen(b - a), every))

    def window(self, lo: int, hi: int) -> np.ndarray:
        """Filtered rows [lo, hi) (N, m); zero outside the filtered segments."""
        out = np.zeros((max(hi - lo, 0), self.source.shape[1]))
        for (a, b), st in zip(self.segments, self._states, strict=True):
            s0, s1 = max(a, lo), min(b, hi)
            if s0 >= s1:
                continue
            if st is None:
                out[s0 - lo: s1 - lo] = self.source[s0:s1]
                continue
            r0, r1 = s0 - a, s1 - a
            b0, b1 = r0 // self.every, -(-r1 // self.every)
            seg = self.source[a:b]
            if not seg.flags.c_contiguous or seg.dtype != np.float64:
                seg = np.ascontiguousarray(self.source[a + b0 * self.every:
                                                       min(b, a + b1 * self.every)], float)
                buf = np.empty_like(seg)
                _track_window(self._sos, seg, st[0][b0:], st[1][b0:], self.every, 0,
                              b1 - b0, buf)
            else:
                buf = np.empty((min(b - a, b1 * self.every) - b0 * self.every, seg.shape[1]))
                _track_window(self._sos, seg, st[0], st[1], self.every, b0, b1, buf)
            out[s0 - lo: s1 - lo] = buf[r0 - b0 * self.every: r1 - b0 * self.every]
        return out


class Channels:
    """The filtered channels of one prepared log: a ``Track`` per source array (made at
    ``prepare``; made again when a step replaces the source, e.g. the torque) and, only when
    someone asks for them, the whole filtered arrays."""

    def __init__(self) -> None:
        self._tracks: dict[str, Track] = {}
        self._whole: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self._lock = threading.Lock()

    def track(self, name: str, src: np.ndarray, filt: ZeroPhaseFilter,
              segments: Sequence[slice]) -> Track:
        with self._lock:
            hit = self._tracks.get(name)
        if hit is not None and hit.source is src:
            return hit
        made = Track(src, filt, segments, 3 * filt.settle)  # outside the lock: channels at once
        with self._lock:
            hit = self._tracks.get(name)
            if hit is None or hit.source is not src:
                hit = self._tracks[name] = made
            return hit

    def whole(self, name: str, src: np.ndarray, make: Callable[[], np.ndarray]) -> np.ndarray:
        """The whole array ``name`` made from ``src``: kept, else made by ``make`` and kept."""
        hit = self.kept(name, src)
        if hit is not None:
            return hit
        out = make()
        self.put(name, src, out)
        return out

    def kept(self, name: str, src: np.ndarray) -> np.ndarray | None:
        """The whole array ``name`` made from ``src`` when it is made already, else None."""
        with self._lock:
            hit = self._whole.get(name)
        return hit[1] if hit is not None and hit[0] is src else None

    def put(self, name: str, src: np.ndarray, out: np.ndarray) -> None:
        """Keep ``out`` (made from ``src``) as the whole array ``name``."""
        out.flags.writeable = False  # shared by every copy of the prepared log
        with self._lock:
            self._whole[name] = (src, out)

    def take(self, name: str, src: np.ndarray) -> np.ndarray | None:
        """The whole array ``name`` made from ``src``, handed over once (None: not kept)."""
        with self._lock:
            hit = self._whole.pop(name, None)
        return None if hit is None or hit[0] is not src else hit[1]
