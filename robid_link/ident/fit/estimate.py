"""Least-squares estimators (OLS, WLS, robust IRLS) on streamed, parallel-filtered rows.

Rows are reduced to per-joint, per-time-block Gram matrices in one pass; covariances carry a
per-joint long-run-variance factor, honest when filtering correlates neighbouring residuals.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numba
import numpy as np

from robid_link.exceptions import ConditioningWarning, EstimationError
from robid_link.ident.data.preprocess import filter_windows
from robid_link.ident.fit.design import Design, design_chunks, design_rows
from robid_link.ident.model.threads import SLOTS, in_slots

if TYPE_CHECKING:  # pieces only pass through to design_chunks
    from robid_link.ident.data.preprocess import Piece

__all__ = ["WEIGHTS", "TUNING", "RANK_TOL", "Grams", "accumulate", "GramSet",
           "accumulate_sets", "joint_stats", "solve", "Fit",
           "fit", "long_run_factor", "batch_factor"]

#: Robust weight functions of r = residual / (tuning · robust scale), as in MATLAB's
#: robustfit; the tuning constants give 95 % efficiency at Gaussian noise.
TUNING = {"andrews": 1.339, "bisquare": 4.685, "cauchy": 2.385, "fair": 1.400,
          "huber": 1.345, "logistic": 1.205, "talwar": 2.795, "welsch": 2.985}


def _safe_ratio(f: Callable[[np.ndarray], np.ndarray]) -> Callable[[np.ndarray], np.ndarray]:
    def w(r: np.ndarray) -> np.ndarray:
        r = np.where(np.abs(r) < 1e-12, 1e-12, r)
        return f(r) / r
    return w


WEIGHTS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "andrews": lambda r: np.where(np.abs(r) < math.pi, _safe_ratio(np.sin)(r), 0.0),
    "bisquare": lambda r: np.where(np.abs(r) < 1.0, (1.0 - r * r) ** 2, 0.0),
    "cauchy": lambda r: 1.0 / (1.0 + r * r),
    "fair": lambda r: 1.0 / (1.0 + np.abs(r)),
    "huber": lambda r: 1.0 / np.maximum(1.0, np.abs(r)),
    "logistic": _safe_ratio(np.tanh),
    "talwar": lambda r: (np.abs(r) < 1.0).astype(float),
    "welsch": lambda r: np.exp(-r * r),
}

RowWeight = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]


@dataclass
class Grams:
    """Per joint j and time block b: G[j, b] = Σ [x, y, 1]ᵀ[x, y, 1] over that block's rows."""

    g: np.ndarray  # (n, K, p + 2, p + 2)
    n_rows: np.ndarray  # (n,) rows per joint (samples)
    _total: np.ndarray | None = field(default=None, init=False, repr=False, compare=False)

    @property
    def p(self) -> int:
        return self.g.shape[2] - 2

    def total(self) -> np.ndarray:
        """(n, p+2, p+2): each joint's Gram over all the blocks (summed once; read-only)."""
        if self._total is None:
            self._total = self.g.sum(axis=1)
            self._total.flags.writeable = False
        return self._total


def _n_rows(piece: Piece, interval: int) -> int:
    first = piece.lo + (-(piece.lo - piece.ctx_lo) % interval)
    return max(0, len(range(first, piece.hi, interval)))


def accumulate(design: Design, pieces: Sequence[Piece], interval: int, block_len: int,
               row_weight: RowWeight | None = None, max_blocks: int = 128,
               smooth: bool = False) -> Grams:
    """One pass over the training rows into per-joint, per-time-block augmented Grams.

    Joint j's rows are non-zero only in its structural columns, so its Gram is built on
    those alone (a large saving for the outer joints of a serial robot). The chunks of the
    pass go to ``SLOTS`` threads (``in_slots``), each summing into Grams of its own; the
    slots' Grams are added in slot order. ``smooth``: the smooth blocks' columns are read at
    the kept rows unfiltered (``design_rows``).
    """
    return accumulate_sets(design, pieces, interval, block_len, [GramSet(max_blocks)],
                           row_weight, smooth)[0]


@dataclass(frozen=True)
class GramSet:
    """One set of Grams a pass sums (``accumulate_sets``): at most ``max_blocks`` time
    blocks, over the equations ``mask(piece)`` keeps (rows × joints; None: the piece's own
    ``tau_mask``, rows without a joint's torque left out)."""

    max_blocks: int = 128
    mask: Callable[[Piece], np.ndarray | None] | None = None


def accumulate_sets(design: Design, pieces: Sequence[Piece], interval: int, block_len: int,
                    sets: Sequence[GramSet], row_weight: RowWeight | None = None,
                    smooth: bool = False) -> list[Grams]:
    """``accumulate`` of several sets of Grams in one pass: each chunk's rows are built and
    filtered once and summed into every set (the same numbers as a pass per set)."""
    total = sum(_n_rows(pc, interval) for pc in pieces)
    # a partial log's piece gives rows only to the joints whose torque it holds
    held = {id(pc): np.ascontiguousarray(pc.prep.log.held, dtype=np.uint8) for pc in pieces}
    masks = [{id(pc): pc.prep.tau_mask if gs.mask is None else gs.mask(pc) for pc in pieces}
             for gs in sets]
    n_rows = np.zeros(design.robot.n, dtype=np.int64)
    for pc in pieces:
        n_rows += _n_rows(pc, interval) * held[id(pc)].astype(np.int64)
    k_blocks = [int(min(gs.max_blocks, max(2, total // max(1, block_len)))) for gs in sets]
    p, n = design.p, design.robot.n
    offsets = np.asarray(design.offsets, dtype=np.int64)
    # joint j's Grams, (K, s_j + 2, s_j + 2) with s_j its support, one after the other in a
    # slot's flat array (not n × the widest joint's: an outer joint's support is small)
    widths = np.diff(offsets) + 2
    starts = [np.concatenate(([0], np.cumsum(k * widths * widths))).astype(np.int64)
              for k in k_blocks]
    tasks: list[tuple[Piece, tuple[int, int, int, int, bool], int]] = []  # + first row
    first = 0
    for pc in pieces:
        for window in filter_windows(pc, interval):
            tasks.append((pc, window, first))
            first += len(range(window[0], window[1], interval))
    n_slots = min(SLOTS, len(tasks))
    slots = [[np.zeros(int(st[-1])) for _ in range(n_slots)] for st in starts]
    rows = max((len(range(w[0], w[1], interval)) if smooth else w[3] - w[2]
                for _, w, _ in tasks), default=0)
    bufs: list[np.ndarray | None] = [None] * n_slots  # one chunk buffer per slot
    no_weight = np.ones((0, n))
    # rows without a joint's torque, per set and slot
    left_out = [[np.zeros(n) for _ in range(n_slots)] for _ in sets]

    def work(task: tuple[Piece, tuple[int, int, int, int, bool], int], slot: int) -> None:
        pc, window, at = task
        if bufs[slot] is None:
            bufs[slot] = np.empty((rows, design.nnz))
        c, y, idx = design_rows(design, pc, window, interval, bufs[slot], smooth)
        y_c = np.ascontiguousarray(y)
        sw_rows = np.sqrt(row_weight(c, y, idx)) if row_weight is not None else no_weight
        for s, k in enumerate(k_blocks):
            bid = (np.arange(at, at + c.shape[0]) * k) // total
            sw, mask, rows_c, y_s = sw_rows, masks[s][id(pc)], c, y_c
            if mask is not None:  # rows without a joint's torque: not its equation
                mw = mask[idx].astype(float)
                kept = np.array(mw.T, order="C").sum(axis=1)  # (numpy sums along rows slowly)
                left_out[s][slot] += (c.shape[0] - kept) * held[id(pc)]
                if s > 0 and not kept.any():  # nothing of this chunk in the set: zeros
                    continue
                sw = mw if row_weight is None else sw_rows * mw
                some = np.flatnonzero(mw.any(axis=1))
                if some.size < c.shape[0] // 2:  # a set of few rows (the reversals'): those
                    rows_c, y_s, sw, bid = c[some], y_c[some], sw[some], bid[some]
            _gram_serial(rows_c, y_s, np.ascontiguousarray(sw), bid, offsets, held[id(pc)],
                         slots[s][slot], starts[s], k, _TILE)

    in_slots(tasks, work)
    bufs.clear()
    out = []
    for s, k_b in enumerate(k_blocks):
        gc = slots[s][0]
        for extra in slots[s][1:]:
            gc += extra
        slots[s].clear()
        g = np.zeros((n, k_b, p + 2, p + 2))
        for j in range(n):
            sup = np.concatenate((design.support[j], [p, p + 1]))
            sz = sup.size
            upper = gc[starts[s][j]: starts[s][j + 1]].reshape(k_b, sz, sz)
            full = upper + np.triu(upper, 1).transpose(0, 2, 1)
            g[j][np.ix_(np.arange(k_b), sup, sup)] = full
        out.append(Grams(g, n_rows - sum(left_out[s])))
    return out


#: rows per tile of the Gram kernel (transposed into a small contiguous block); passed to the
#: kernel at run time: with the tile's length a compile-time constant LLVM unrolls the dot
#: products instead of vectorizing them (2.8× slower)
_TILE = 64


@numba.njit(cache=True, nogil=True, fastmath={"reassoc", "contract", "nsz", "arcp"})
def _gram_joint(c, y, sw, j, off, s, bid, g, tile):
    """Joint j's augmented rows [x, y, 1] (× √w when sw has rows) into g[block] (upper
    triangle), tile by tile: a tile's rows transposed, then 2 × 2 dot products."""
    m = c.shape[0]
    width = s + 2
    even = (width + 1) // 2 * 2
    tt = np.zeros((even, tile))
    weighted = sw.shape[0] > 0
    r = 0
    while r < m:
        b = bid[r]
        end = r
        while end < m and bid[end] == b:
            end += 1
        gb = g[b]
        for r0 in range(r, end, tile):
            t = min(tile, end - r0)
            for i in range(t):
                w = sw[r0 + i, j] if weighted else 1.0
                for q in range(s):
                    tt[q, i] = c[r0 + i, off + q] * w if weighted else c[r0 + i, off + q]
                tt[s, i] = y[r0 + i, j] * w if weighted else y[r0 + i, j]
                tt[s + 1, i] = w
            for i in range(t, tile):
                for q in range(width):
                    tt[q, i] = 0.0
            for a in range(0, even, 2):
                ta0, ta1 = tt[a], tt[a + 1]
                for bb in range(a, even, 2):
                    tb0, tb1 = tt[bb], tt[bb + 1]
                    s00 = 0.0
                    s01 = 0.0
                    s10 = 0.0
                    s11 = 0.0
                    for i in range(tile):
                        u0, u1, v0, v1 = ta0[i], ta1[i], tb0[i], tb1[i]
                        s00 += u0 * v0
                        s01 += u0 * v1
                        s10 += u1 * v0
                        s11 += u1 * v1
                    gb[a, bb] += s00
                    if bb + 1 < width:
                        gb[a, bb + 1] += s01
                    if a + 1 < width:
                        if bb > a:  # on the diagonal it is s01's mirror
                            gb[a + 1, bb] += s10
                        if bb + 1 < width:
                            gb[a + 1, bb + 1] += s11
        r = end


@numba.njit(cache=True, nogil=True)
def _gram_serial(c, y, sw, bid, offsets, held, g, starts, k_blocks, tile):
    """Every held joint's rows of a chunk into its Grams, on this thread: joint j's are
    g[starts[j]:starts[j + 1]] as (K, s + 2, s + 2), s its support's size (``held[j]`` 0: the
    chunk's log holds no torque of joint j, its rows are left out)."""
    for j in range(offsets.size - 1):
        if held[j]:
            s = offsets[j + 1] - offsets[j]
            gj = g[starts[j]: starts[j + 1]].reshape((k_blocks, s + 2, s + 2))
            _gram_joint(c, y, sw, j, offsets[j], s, bid, gj, tile)


#: relative eigenvalue floor of a column-scaled Gram (cond(X) up to 1e6 is kept)
RANK_TOL = 1e-12


def solve(a: np.ndarray, b: np.ndarray, names: Sequence[str] | None = None,
          warn: bool = True) -> tuple[np.ndarray, np.ndarray, float]:
    """Solve the normal equations with column equilibration; returns θ, A⁻¹, cond(scaled X)."""
    d = np.sqrt(np.clip(np.diag(a), 1e-300, None))
    zero = np.diag(a) <= 0
    if zero.any():
        nm = names[int(np.argmax(zero))] if names is not None else str(int(np.argmax(zero)))
        raise EstimationError(f"parameter {nm} has an all-zero regressor column: not excited")
    s = a / np.outer(d, d)
    evals, evecs = np.linalg.eigh(s)
    cond = math.sqrt(max(evals[-1], 0.0) / max(evals[0], 1e-300))
    # a Gram squares the condition number: directions below 1e-12 of the largest eigenvalue
    # (cond(X) > 1e6) are rounding noise of the accumulated sums, not information
    keep = evals > evals[-1] * RANK_TOL
    if not keep.all() and warn:
        warnings.warn(f"regressor is numerically rank deficient ({int((~keep).sum())} "
                      "directions dropped); some parameters are not identifiable from this log",
                      ConditioningWarning, stacklevel=3)
    inv = (evecs[:, keep] / evals[keep]) @ evecs[:, keep].T
    theta = (inv @ (b / d)) / d
    return theta, inv / np.outer(d, d), cond


@dataclass
class Fit:
    theta: np.ndarray
    cov: np.ndarray
    cond: float
    rss: np.ndarray  # per joint, weighted rows for IRLS
    mean_res: np.ndarray  # per joint
    n_rows: np.ndarray
    joint_weights: np.ndarray
    method: str
    iterations: int = 1


def joint_stats(tot: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-joint RSS and mean residual from augmented Grams at θ."""
    p = theta.size
    v = np.concatenate((-theta, [1.0]))
    rss = np.einsum("i,jik,k->j", v, tot[:, : p + 1, : p + 1], v)
    sum_e = tot[:, p + 1, p] - tot[:, p + 1, :p] @ theta
    return np.maximum(rss, 0.0), sum_e / np.maximum(tot[:, p + 1, p + 1], 1.0)


def _weighted_solve(grams: Grams, wj: np.ndarray, names: Sequence[str] | None, warn: bool
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    tot = grams.total()
    p = grams.p
    a = np.einsum("j,jik->ik", wj, tot[:, :p, :p])
    b = np.einsum("j,ji->i", wj, tot[:, :p, p])
    theta, a_inv, cond = solve(a, b, names, warn)
    kappa, var = long_run_factor(grams, theta)
    meat = np.einsum("j,jik->ik", wj * wj * kappa * var, tot[:, :p, :p])
    cov = a_inv @ meat @ a_inv
    return theta, cov, a_inv, cond


def long_run_factor(grams: Grams, theta: np.ndarray, cols: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Per joint: κ = long-run variance / variance of the residual, and the variance.

    Filtering correlates neighbouring residuals, so σ²(XᵀX)⁻¹ would be too optimistic.
    The long-run variance comes from batch means over the time blocks (the block sums of
    residuals are in the augmented Grams); with regressor columns that are smooth over the
    residual's correlation time, Cov = A⁻¹ (Σ_j w_j² κ_j σ_j² G_j) A⁻¹. ``cols``: θ is of
    these columns only (None: of all).
    """
    return batch_factor(grams.total(), grams.g[:, :, grams.p + 1, :], theta, cols)


def batch_factor(total: np.ndarray, last: np.ndarray, theta: np.ndarray,
                 cols: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``long_run_factor`` from what it reads of the Grams: the joints' totals (n, p+2, p+2)
    and each block's last row (n, K, p+2: its rows' count, sums of columns and torque)."""
    p = total.shape[1] - 2
    cols = np.arange(p) if cols is None else np.asarray(cols)
    sums = last[:, :, p] - last[:, :, cols] @ theta  # (n, K)
    counts = last[:, :, p + 1]
    idx = np.concatenate((cols, [p, p + 1]))
    rss, mean = joint_stats(total[:, idx[:, None], idx[None, :]], theta)
    n = np.maximum(counts.sum(axis=1), 1.0)
    var = rss / n - mean**2
    lrv = ((sums - counts * mean[:, None]) ** 2).sum(axis=1) / n
    kappa = np.where(var > 0, lrv / np.maximum(var, 1e-300), 1.0)
    return np.maximum(kappa, 1.0), np.maximum(var, 0.0)


def fit(design: Design, pieces: Sequence[Piece], interval: int, block_len: int,
        method: str = "ols", weight: str = "bisquare",
        names: Sequence[str] | None = None, grams: Grams | None = None, warn: bool = True,
        max_iter: int = 30) -> tuple[Fit, Grams]:
    """OLS, WLS (Gautier's two steps: per-joint noise variance) or IRLS."""
    if method not in ("ols", "wls", "irls"):
        raise EstimationError(f"unknown method '{method}' (ols, wls, irls)")
    if grams is None:
        grams = accumulate(design, pieces, interval, block_len)
    n = design.robot.n
    wj = np.ones(n)
    theta, cov, _, cond = _weighted_solve(grams, wj, names, warn)
    tot = grams.total()
    rss, mean_e = joint_stats(tot, theta)
    if method == "wls":
        dof = np.maximum(grams.n_rows - design.p / n, 1.0)
        var = rss / dof
        wj = 1.0 / np.maximum(var, 1e-12 * max(var.max(), 1e-300))
        wj = wj / wj.max()
        theta, cov, _, cond = _weighted_solve(grams, wj, names, warn)
        rss, mean_e = joint_stats(tot, theta)
    iterations = 1
    if method == "irls":
        if weight not in WEIGHTS:
            raise EstimationError(f"unknown weight function '{weight}' ({', '.join(WEIGHTS)})")
        wfun, tune = WEIGHTS[weight], TUNING[weight]
        for iterations in range(2, max_iter + 1):  # noqa: B007
            scale = _robust_scale(design, pieces, interval, theta)

            def row_weight(c: np.ndarray, y: np.ndarray, idx: np.ndarray, th=theta,
                           sc=scale) -> np.ndarray:
                r = (y - design.predict(c, th)) / (tune * sc)
                return wfun(r)

            wgrams = accumulate(design, pieces, interval, block_len, row_weight)
            new, cov, _, cond = _weighted_solve(wgrams, wj, names, warn)
            step = np.max(np.abs(new - theta) / (np.abs(theta) + 1e-9 * np.abs(theta).max()))
            theta = new
            if step < 1e-6:
                break
        rss, mean_e = joint_stats(tot, theta)
    return Fit(theta, cov, cond, rss, mean_e, grams.n_rows, wj, method, iterations), grams


def _robust_scale(design: Design, pieces: Sequence[Piece], interval: int,
                  theta: np.ndarray) -> np.ndarray:
    """Per-joint robust residual scale: 1.4826 · MAD (joint torques differ by 60×)."""
    res = [
        y - design.predict(c, theta)
        for pc in pieces
        for c, y, _ in design_chunks(design, pc, interval=interval, filtered=True)
    ]
    r = np.concatenate(res, axis=0)  # NaN where a partial log holds no torque
    med = np.nanmedian(r, axis=0)
    mad = 1.4826 * np.nanmedian(np.abs(r - med), axis=0)
    return np.maximum(mad, 1e-9 * max(float(np.nanmax(np.abs(r))), 1e-12))
