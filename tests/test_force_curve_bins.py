"""Force-curve binning (:mod:`afmtool.estimators.force_curve_bins`) against a plain-Python reading of its definition."""

from __future__ import annotations

import math

import numpy as np
import pytest

from afmtool.analyses.accumulators import ForceCurveAccumulator


def naive_bins(z, values, z_bin):
    """The module docstring's definition, one sample at a time: {leg: {bin: [count, sums...]}}."""
    bins = ({}, {})
    previous, direction, approach = math.nan, 0, 0
    for i, zi in enumerate(z):
        step = zi - previous
        previous = zi
        if step > 0:
            direction = 1
        elif step < 0:
            direction = -1
        if approach == 0 and direction != 0:
            approach = direction
        row = [v[i] for v in values]
        if direction == 0 or not math.isfinite(zi) or not all(math.isfinite(v) for v in row):
            continue
        leg = bins[0 if direction == approach else 1]
        sums = leg.setdefault(math.floor(zi / z_bin), [0.0] * (len(row) + 1))
        sums[0] += 1.0
        for r, v in enumerate(row):
            sums[r + 1] += v
    return bins


def _accumulated(z, values, z_bin, cuts):
    acc = ForceCurveAccumulator(z_bin, tuple(f"v{r}" for r in range(len(values))))
    for a, b in zip([0, *cuts], [*cuts, len(z)]):
        acc.add(z[a:b], {f"v{r}": v[a:b] for r, v in enumerate(values)})
    return acc


def _z_cases(rng, n):
    t = np.arange(n)
    triangle = -30.0 * (1.0 - np.abs(2.0 * t / n - 1.0))  # one approach and retract
    noisy = triangle + rng.normal(0.0, 2.0, n)  # direction flips every sample, many bins
    held = np.repeat(triangle[::10], 10)[:n]  # flat stretches: the direction is held
    gaps = noisy.copy()
    gaps[rng.integers(0, n, 40)] = np.nan  # a NaN z is skipped, and holds the direction
    outlier = triangle.copy()
    outlier[n // 3] = 1e9  # a bin range far wider than the chunk: the sparse path
    return {"triangle": triangle, "noisy": noisy, "held": held, "gaps": gaps, "outlier": outlier}


@pytest.mark.parametrize("case", ["triangle", "noisy", "held", "gaps", "outlier"])
def test_bins_equal_the_definition_for_any_chunking(rng, case):
    n = 5000
    z = _z_cases(rng, n)[case]
    values = [rng.normal(size=n), rng.normal(size=n) * 1e3]
    values[1][rng.integers(0, n, 30)] = np.nan  # a sample with a NaN value is not counted
    expected = naive_bins(z, values, 0.5)
    for cuts in ([], [1, 2, 1777, 4999], sorted(rng.choice(np.arange(1, n), 25, replace=False).tolist())):
        acc = _accumulated(z, values, 0.5, cuts)
        for leg in (0, 1):
            assert set(acc._bins[leg]) == set(expected[leg]), (case, cuts, leg)
            for b, sums in expected[leg].items():
                if not cuts:  # one chunk: added in sample order, as the definition adds them, to the last bit
                    np.testing.assert_array_equal(acc._bins[leg][b], sums)
                else:  # a bin's sum is the sum of its chunks' sums
                    np.testing.assert_allclose(acc._bins[leg][b], sums, rtol=1e-12)


def test_tables_from_the_bins():
    z = np.concatenate([np.linspace(0.0, -2.0, 9), np.linspace(-2.0, 0.0, 9)[1:]])
    acc = _accumulated(z, [2.0 * z], 0.5, [5])
    tables = acc.tables()
    approach, retract = tables["approach"], tables["retract"]
    np.testing.assert_array_equal(approach.z, [-1.75, -1.25, -0.75, -0.25])
    np.testing.assert_allclose(approach.means["v0"], 2.0 * approach.z, atol=0.5)
    assert approach.count.sum() == 8 and retract.count.sum() == 8  # the first sample has no direction yet
