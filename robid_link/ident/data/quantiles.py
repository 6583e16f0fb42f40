"""Exact percentiles of values read a window at a time, without an array of every value:
np.percentile's numbers (its linear method) from two passes over the windows — a histogram of
the values' leading bits, then the values of the buckets that hold the two ranks it reads.
With a guess of the percentile, the first pass also keeps the values near it, and the second
pass is needed only when the ranks fall outside what it kept.

A long log's statistics (its joints' typical speeds) then cost one or two reads of its windows
and a few megabytes, not an array of every row.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import TypeVar

import numpy as np

from robid_link.ident.model.threads import SLOTS, in_slots

__all__ = ["percentile_streamed", "median", "median_of_blocks"]

T = TypeVar("T")

#: a float64's leading bits kept as its bucket (sign, exponent and 4 bits of mantissa): the
#: bits of a value ≥ 0 read as an integer grow with it, so buckets are ordered as the values
_SHIFT = 48
_BUCKETS = 1 << (64 - _SHIFT - 1)


#: a guess keeps the values within this factor of it (either side) in the first pass
GUESS_BAND = 1.05


def percentile_streamed(tasks: Sequence[T], values: Callable[[T], np.ndarray], q: float,
                        width: int, guess: np.ndarray | None = None) -> np.ndarray:
    """Per column, ``np.percentile(all_rows, q, axis=0)`` of the rows of ``values(task)`` over
    every task ((m, width) arrays of finite values ≥ 0, e.g. speeds), in ``in_slots``: each
    task read twice, or once when ``guess`` (width,) is near enough — the values within
    GUESS_BAND of it are kept from the first read, and suffice when they hold both ranks.
    NaN for a column when there are no rows."""
    counts = [np.zeros((width, _BUCKETS), dtype=np.int64) for _ in range(SLOTS)]
    found: list[list[np.ndarray]] = [[] for _ in tasks]
    band = None  # (2, width): the first and last bucket kept from the first read
    if guess is not None and np.all(np.isfinite(guess)) and np.all(np.asarray(guess) >= 0):
        near = np.asarray(guess, dtype=float)[None, :]
        band = np.concatenate((_bucket_ids(near / GUESS_BAND), _bucket_ids(near * GUESS_BAND)),
                              axis=1).T

    def count(k: int, slot: int) -> None:
        v = values(tasks[k])
        ids = _bucket_ids(v)
        for j in range(width):
            counts[slot][j] += np.bincount(ids[j], minlength=_BUCKETS)
        if band is not None:
            found[k] = [v[(ids[j] >= band[0, j]) & (ids[j] <= band[1, j]), j]
                        for j in range(width)]

    in_slots(range(len(tasks)), count)
    hist = np.sum(counts, axis=0)
    total = int(hist[0].sum())
    if total == 0:
        return np.full(width, np.nan)
    # the ranks np.percentile reads (its _get_indexes and _get_gamma, linear method)
    virtual = (total - 1) * np.true_divide(q, 100)
    prev = int(np.floor(virtual))
    nxt = prev + 1
    if virtual >= total - 1:
        prev = nxt = total - 1
    gamma = virtual - (np.floor(virtual) if virtual < total - 1 else -1.0)
    cum = np.cumsum(hist, axis=1)
    lo = np.array([np.searchsorted(cum[j], prev, side="right") for j in range(width)])
    hi = np.array([np.searchsorted(cum[j], nxt, side="right") for j in range(width)])
    if band is None or np.any(lo < band[0]) or np.any(hi > band[1]):
        def collect(k: int, slot: int) -> None:
            v = values(tasks[k])
            ids = _bucket_ids(v)
            found[k] = [v[(ids[j] >= lo[j]) & (ids[j] <= hi[j]), j] for j in range(width)]

        in_slots(range(len(tasks)), collect)
    out = np.empty(width)
    for j in range(width):
        kept = np.concatenate([f[j] for f in found if f])
        if band is not None:  # the band's values: those of the ranks' buckets
            ids = _bucket_ids(kept[:, None])[0]
            kept = kept[(ids >= lo[j]) & (ids <= hi[j])]
        kept = np.sort(kept)
        below = int(cum[j, lo[j] - 1]) if lo[j] > 0 else 0
        a, b = kept[prev - below], kept[nxt - below]
        out[j] = _lerp(a, b, gamma)
    return out


#: a signed value's bucket: its order-preserving key's leading 16 bits (sign, exponent and 4
#: bits of mantissa), offset to start at 0
_SIGNED_BUCKETS = 1 << 16
#: values bucketed at a time (the keys' temporaries stay small)
_BLOCK = 1 << 16


def median(x: np.ndarray, where: np.ndarray | None = None, around: float | None = None
           ) -> float:
    """``np.median(x[where])`` of a 1-D float64 array of finite values — with ``around`` = m,
    ``np.median(np.abs(x[where] - m))`` — to the bit, in under half its time on a long array
    and without a copy of it (``median_of_blocks``)."""
    def blocks() -> Iterator[np.ndarray]:
        for a in range(0, x.size, _BLOCK):
            v = x[a: a + _BLOCK] if around is None else np.abs(x[a: a + _BLOCK] - around)
            yield v if where is None else v[where[a: a + _BLOCK]]

    return median_of_blocks(blocks)


def median_of_blocks(blocks: Callable[[], Iterable[np.ndarray]]) -> float:
    """``np.median`` of the values ``blocks()`` yields (1-D float64 arrays of finite values,
    read twice), to the bit: a histogram of the values' buckets (the leading 16 bits of an
    order-preserving integer key) finds the one or two that hold the middle ranks, and only
    their values are partitioned. A quantized signal's few values (more than half of them in
    those buckets) are gathered and handed to np.median."""
    counts = np.zeros(_SIGNED_BUCKETS, np.int64)
    for v in blocks():
        counts += np.bincount(_signed_ids(v), minlength=_SIGNED_BUCKETS)
    cum = np.cumsum(counts)
    n = int(cum[-1])
    if n == 0:
        return float(np.median(np.zeros(0)))  # numpy's NaN (and its warning)
    ranks = [n // 2] if n % 2 else [n // 2 - 1, n // 2]
    lo, hi = (int(np.searchsorted(cum, r, side="right")) for r in (ranks[0], ranks[-1]))
    below = int(cum[lo - 1]) if lo > 0 else 0
    if cum[hi] - below > n // 2:
        return float(np.median(np.concatenate(list(blocks())), overwrite_input=True))
    kept = []
    for v in blocks():
        ids = _signed_ids(v)
        kept.append(v[(ids >= lo) & (ids <= hi)])
    at = [r - below for r in ranks]
    # np.median's own last steps: the mean of the middle one or two values
    return float(np.mean(np.partition(np.concatenate(kept), at)[at]))


def _signed_ids(v: np.ndarray) -> np.ndarray:
    """The bucket (0 … 2¹⁶ − 1, in the values' order) of every value of a 1-D float64 array."""
    key = np.ascontiguousarray(v).view(np.int64)
    key = key ^ ((key >> 63) & 0x7FFFFFFFFFFFFFFF)
    return (key >> 48) + (_SIGNED_BUCKETS >> 1)


def _bucket_ids(v: np.ndarray) -> np.ndarray:
    """(width, m) bucket of every value of v (m, width), ≥ 0."""
    return np.ascontiguousarray(v.T).view(np.int64) >> _SHIFT


def _lerp(a: float, b: float, t: float) -> float:
    """np.percentile's interpolation between the ranks' values (numpy's _lerp)."""
    diff = np.float64(b) - np.float64(a)
    if t >= 0.5:
        return float(np.float64(b) - diff * (1 - t))
    return float(np.float64(a) + diff * t)
