"""The torque's measurement noise, and whether a residual is only that: a noise estimate that an
unmodelled effect cannot inflate (robust scale of the raw torque's third differences) and the
whiteness of a residual (its autocorrelation against the 99 % band, Ljung–Box)."""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from robid_link.ident.data.preprocess import Piece
from robid_link.ident.data.quantiles import median
from robid_link.ident.model.threads import in_slots

__all__ = ["noise_floor", "Whiteness", "LagSums", "chi2_quantile", "DIFF_ORDER", "LAGS", "Z99",
           "AT_FLOOR", "COLOURED_MIN"]

#: order of the differences the noise is read from: a torque the motion or any catalog effect
#: makes (≤ ~20 Hz) is attenuated by (2·sin(πf/fs))³ — under 1/50 of its amplitude at 250 Hz —
#: while white noise keeps a known share, C(6, 3) = 20 times its variance
DIFF_ORDER = 3
#: lags of the whiteness test (as MATLAB's resid)
LAGS = 25
#: two-sided 99 % quantile of the normal distribution: the band is ±Z99/√N
Z99 = 2.5758
#: a validation RMSE up to this multiple of the noise estimate is "at the estimate"
AT_FLOOR = 1.2
#: autocorrelations under this size are immaterial even when a long log makes them
#: significant: the coloured part then holds under ~5 % of the residual's variance
COLOURED_MIN = 0.05
#: scale of a normal distribution from its median absolute deviation
_MAD = 1.482602218505602
#: differences beyond this many robust scales are left out of the noise's variance …
TRIM = 3.5
#: … which keeps this share of a normal variable's variance: 1 − 2cφ(c)/(2Φ(c) − 1)
_TRIMMED_VAR = 1.0 - 2 * TRIM * math.exp(-TRIM**2 / 2) / math.sqrt(2 * math.pi) / math.erf(
    TRIM / math.sqrt(2))


def noise_floor(pieces: Sequence[Piece]) -> np.ndarray | None:
    """Per joint, the torque measurement noise (N·m, standard deviation) from the raw torque's
    third differences on the pieces' rows: white noise of σ gives differences of σ·√20, while
    the motion's torque and any effect a model could name are smooth at the sampling rate and
    vanish from them. A robust scale (1.4826 × the median absolute deviation, then the standard
    deviation within TRIM of it) ignores the few samples where a friction step or a stick-slip
    makes a difference large. Rows without a joint's torque (``tau_mask``) are left out. None
    without rows.

    It estimates white noise; coloured noise (fewer high frequencies) reads lower, and the
    residual's whiteness test says so. A torque smoothed before logging reads its own, small,
    remaining noise."""
    if not any(pc.hi - pc.lo > DIFF_ORDER + 1 for pc in pieces):
        return None
    n = pieces[0].prep.log.q.shape[1]
    out = np.full(n, np.nan)

    def work(j: int, slot: int) -> None:  # one joint's differences: a long log's are (N, n)
        d, ok = _joint_diffs(pieces, j)
        if not ok.any():
            return  # a joint without a torque on these rows
        where = None if ok.all() else ok  # its medians without a copy: two slots' temporaries
        first = _MAD * median(d, where, around=median(d, where))  # stay small
        # then the standard deviation of the differences within TRIM robust scales (nearly as
        # efficient as the standard deviation), corrected for the normal tails left out
        size = np.abs(d, out=d)
        inside = ok & (size <= TRIM * max(first, 1e-300))
        size *= size
        size[~inside] = 0.0
        out[j] = np.sum(size) / max(int(inside.sum()), 1)

    in_slots(range(n), work)
    if np.isnan(out).any():
        return None
    return np.asarray(np.sqrt(out / _TRIMMED_VAR / math.comb(2 * DIFF_ORDER, DIFF_ORDER)))


def _joint_diffs(pieces: Sequence[Piece], j: int) -> tuple[np.ndarray, np.ndarray]:
    """Joint j's raw torque differences of DIFF_ORDER over the pieces' rows, and where they
    count: the log holds the torque and every row of the difference enters the equation."""
    order = DIFF_ORDER
    used = [pc for pc in pieces if pc.hi - pc.lo > order + 1]
    total = sum(pc.hi - pc.lo - order for pc in used)
    d, ok = np.empty(total), np.empty(total, bool)
    at = 0
    for pc in used:
        m = pc.hi - pc.lo - order
        tau = pc.prep.tau[:, j]
        for a in range(0, m, _DIFF_CHUNK):  # np.diff's numbers, without its (N,) temporaries
            b = min(m, a + _DIFF_CHUNK)
            d[at + a: at + b] = np.diff(tau[pc.lo + a: pc.lo + b + order], order)
        ok[at: at + m] = bool(pc.prep.log.held[j])
        mask = pc.prep.tau_mask
        if mask is not None:
            for k in range(order + 1):
                ok[at: at + m] &= mask[pc.lo + k: pc.hi - order + k, j]
        at += m
    return d, ok


#: rows of a piece differenced at once
_DIFF_CHUNK = 1 << 16


@functools.lru_cache(maxsize=64)
def chi2_quantile(p: float, df: int) -> float:
    """The p-quantile of the χ² distribution with ``df`` degrees of freedom (scipy's
    ``chi2.ppf`` to ~1e-14): bisection on the regularized lower incomplete gamma function
    P(df/2, x/2), summed as its series — the one quantile a result needs, without the import
    time and memory of scipy.stats."""
    a = 0.5 * df

    def cdf(x: float) -> float:
        h = 0.5 * x
        term = total = 1.0 / a
        k = 0
        while term > 1e-17 * total:
            k += 1
            term *= h / (a + k)
            total += term
        return total * math.exp(a * math.log(h) - h - math.lgamma(a))

    lo, hi = 0.0, float(df) + 1.0
    while cdf(hi) < p:
        lo, hi = hi, 2.0 * hi
    while True:
        mid = 0.5 * (lo + hi)
        if mid in (lo, hi):
            return hi
        lo, hi = (mid, hi) if cdf(mid) < p else (lo, mid)


class LagSums:
    """Streams a residual (chunks of contiguous rows, samples × joints) into the sums its
    autocorrelation over lags 0..LAGS needs (products across chunk edges are left out)."""

    def __init__(self, n: int, lags: int = LAGS) -> None:
        self.lags = lags
        self.prod = np.zeros((lags + 1, n))
        self.head = np.zeros((lags + 1, n))  # Σ e_k over the first index of each lag's pairs
        self.tail = np.zeros((lags + 1, n))  # … and over the second
        self.pairs = np.zeros((lags + 1, n))
        self.total = np.zeros(n)
        self.count = np.zeros(n)

    def add(self, e: np.ndarray, mask: np.ndarray | None = None) -> None:
        """``mask`` (m, n): which joints' rows count (None: all); a pair counts when both do."""
        m = e.shape[0]
        # joints × rows: numpy sums a (rows, 6) array along its rows ten times slower
        e_t = np.array(e.T, order="C")
        if mask is None:
            total = e_t.sum(axis=1)
            self.total += total
            self.count += m
            top = min(self.lags, m - 1) + 1
            # a lag's first and second indices leave out the chunk's last and first k rows:
            # the sums from the whole chunk's, less those few rows (not a pass per lag)
            first = np.cumsum(e_t[:, : top - 1], axis=1)
            last = np.cumsum(e_t[:, m - 1: m - top: -1], axis=1)
            for k in range(top):
                self.prod[k] += np.einsum("ij,ij->i", e_t[:, : m - k], e_t[:, k:])
                self.head[k] += total - last[:, k - 1] if k else total
                self.tail[k] += total - first[:, k - 1] if k else total
                self.pairs[k] += m - k
            return
        w = np.array(np.broadcast_to(mask, e.shape).T, order="C", dtype=float)
        e_t[w == 0] = 0.0  # a joint a log does not hold: NaN there
        self.total += e_t.sum(axis=1)
        self.count += w.sum(axis=1)
        for k in range(min(self.lags, m - 1) + 1):
            both = w[:, : m - k] * w[:, k:]
            a, b = e_t[:, : m - k] * both, e_t[:, k:] * both
            self.prod[k] += np.einsum("ij,ij->i", a, b)
            self.head[k] += a.sum(axis=1)
            self.tail[k] += b.sum(axis=1)
            self.pairs[k] += both.sum(axis=1)

    def merge(self, other: LagSums) -> None:
        """Add another chunk's sums (pairs across the chunks' edge are left out)."""
        for name in ("prod", "head", "tail", "pairs", "total", "count"):
            getattr(self, name).__iadd__(getattr(other, name))

    def result(self) -> Whiteness | None:
        if self.count.min() <= self.lags + 1:
            return None
        mu = self.total / self.count
        pairs = np.maximum(self.pairs, 1.0)
        cov = (self.prod - mu * (self.head + self.tail) + self.pairs * mu * mu) / pairs
        var = np.maximum(cov[0], 1e-300)
        return Whiteness(cov[1:] / var, int(self.count.min()))


@dataclass(frozen=True)
class Whiteness:
    """The autocorrelation (lags 1..L × joints) of a residual of ``n`` samples, judged against
    white noise: the 99 % band ±Z99/√n per lag and the Ljung–Box statistic over all lags."""

    acf: np.ndarray
    n: int

    @property
    def band(self) -> float:
        return Z99 / math.sqrt(self.n)

    @property
    def q_stat(self) -> np.ndarray:
        lags = np.arange(1, self.acf.shape[0] + 1)[:, None]
        return self.n * (self.n + 2) * np.sum(self.acf ** 2 / (self.n - lags), axis=0)

    @property
    def q_bound(self) -> float:
        """The Ljung–Box statistic's 99 % point for white noise."""
        return chi2_quantile(0.99, self.acf.shape[0])

    @property
    def white(self) -> np.ndarray:
        """Per joint: the autocorrelation within its 99 % band taken over all lags (Ljung–Box
        at 1 %), or too small to matter (every lag under COLOURED_MIN)."""
        return (self.q_stat <= self.q_bound) | (np.abs(self.acf).max(axis=0) < COLOURED_MIN)

    def joint(self, j: int) -> dict[str, Any]:
        """The figures of joint ``j`` (from 0) for the JSON."""
        k = int(np.argmax(np.abs(self.acf[:, j])))
        return {"white": bool(self.white[j]), "lag1": round(float(self.acf[0, j]), 4),
                "largest": round(float(self.acf[k, j]), 4), "largest_lag": k + 1,
                "band": round(self.band, 4), "ljung_box": round(float(self.q_stat[j]), 2),
                "ljung_box_99": round(self.q_bound, 2), "n": self.n}

    def sentence(self, j: int) -> str:
        """Why joint ``j``'s residual is not white, in figures."""
        f = self.joint(j)
        return (f"its residual is not white (autocorrelation {f['largest']:.2g} at lag "
                f"{f['largest_lag']} against a 99 % band of ±{f['band']:.2g}; Ljung–Box "
                f"{f['ljung_box']:.4g} > {f['ljung_box_99']:.4g})")
