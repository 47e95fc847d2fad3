"""RunningMoments against numpy on the same values, for any cutting of the stream."""

from __future__ import annotations

import math

import numpy as np
import pytest

from afmtool.estimators.moments import RunningMoments


def test_moments_equal_numpy_on_the_finite_unflagged_values(rng):
    x = 3e5 + rng.standard_normal(100_000)  # an f0′ near 300 kHz with a 1 Hz spread: Σx² would lose it
    x[::97] = np.nan
    x[5] = np.inf
    flags = (rng.random(x.size) < 0.1).astype(np.uint8)
    kept = x[(flags == 0) & np.isfinite(x)]
    moments = RunningMoments()
    for a, b in ((0, 1), (1, 777), (777, 50_000), (50_000, 100_000)):
        moments.add(x[a:b], flags[a:b])
    assert moments.count == kept.size
    assert math.isclose(moments.mean, kept.mean(), rel_tol=1e-14)
    assert math.isclose(moments.std(), kept.std(), rel_tol=1e-9)
    assert math.isclose(moments.std(ddof=1), kept.std(ddof=1), rel_tol=1e-9)
    assert (moments.low, moments.high) == (kept.min(), kept.max())


def test_moments_take_a_row_range_and_no_flags():
    moments = RunningMoments()
    moments.add(np.arange(10.0), start=3, stop=7)
    assert (moments.count, moments.mean, moments.low, moments.high) == (4, 4.5, 3.0, 6.0)
    assert moments.std(ddof=4) is None


def test_empty_moments_and_mismatched_flags():
    moments = RunningMoments()
    moments.add(np.array([np.nan]))
    assert moments.count == 0 and math.isnan(moments.mean) and moments.std() is None
    with pytest.raises(ValueError, match="flags"):
        moments.add(np.zeros(3), np.zeros(2, dtype=np.uint8))
