"""Percentiles of values read a window at a time: np.percentile's numbers without an array of
every value (a long log's typical speeds)."""

from __future__ import annotations

import numpy as np
import pytest

from robid_link.ident.data.quantiles import median, percentile_streamed


@pytest.mark.parametrize("n", [1, 2, 7, 1000, 20_001])
@pytest.mark.parametrize("kind", ["spread", "ties", "zeros", "constant"])
def test_streamed_percentile_is_numpys_to_the_bit(n, kind):
    rng = np.random.default_rng(n)
    x = np.abs(rng.normal(size=(n, 3))) * 10.0 ** rng.uniform(-6, 3, size=3)
    if kind == "ties":
        x = np.round(x, 1)
    elif kind == "zeros":
        x[rng.random(x.shape) < 0.4] = 0.0
    elif kind == "constant":
        x[:] = 2.5
    cuts = np.sort(rng.choice(np.arange(1, n), size=min(n - 1, 4), replace=False)) if n > 1 else []
    windows = np.split(x, cuts)
    for q in (0.0, 33.3, 50.0, 95.0, 100.0):
        got = percentile_streamed(range(len(windows)), lambda k: windows[k], q, 3)
        np.testing.assert_array_equal(got, np.percentile(x, q, axis=0))


def test_streamed_percentile_of_no_rows_is_nan():
    got = percentile_streamed([], lambda k: np.zeros((0, 2)), 95.0, 2)
    assert np.isnan(got).all()


@pytest.mark.parametrize("near", [1.0, 1.02, 0.98, 1.5, 0.0, np.nan])
def test_a_guess_spares_the_second_read_and_changes_no_bit(near):
    """Near the percentile, the first read keeps what the second would find; far from it (or
    no guess at all: NaN), the second read runs — the numbers are numpy's either way."""
    rng = np.random.default_rng(5)
    x = np.abs(rng.normal(size=(30_000, 3))) * [1e-3, 1.0, 40.0]
    x[rng.random(x.shape) < 0.1] = 0.0
    windows = np.array_split(x, 9)
    reads = []

    def values(k):
        reads.append(k)
        return windows[k]

    want = np.percentile(x, 95.0, axis=0)
    got = percentile_streamed(range(len(windows)), values, 95.0, 3, guess=near * want)
    np.testing.assert_array_equal(got, want)
    assert len(reads) == (9 if near in (1.0, 1.02, 0.98) else 18)


@pytest.mark.parametrize("n", [5, 1024, 1025, 4096, 100_001])
@pytest.mark.parametrize("kind", ["spread", "signed ties", "zeros", "quantized", "constant"])
def test_median_is_numpys_to_the_bit(n, kind):
    rng = np.random.default_rng(n)
    x = rng.normal(size=n) * 10.0 ** rng.uniform(-8, 4)
    if kind == "signed ties":
        x = np.round(x, 1)
    elif kind == "zeros":
        x[rng.random(n) < 0.6] = 0.0
    elif kind == "quantized":  # few distinct values: the whole array is partitioned
        x = rng.choice([-3e-6, 0.0, 3e-6, 6e-6], size=n)
    elif kind == "constant":
        x[:] = -2.5
    want = np.median(x)
    got = median(x)
    assert got == want and np.signbit(got) == np.signbit(want)
    where = rng.random(n) < 0.7  # some rows left out, the deviations from a centre
    assert median(x, where) == np.median(x[where])
    assert median(x, where, around=want) == np.median(np.abs(x[where] - want))
