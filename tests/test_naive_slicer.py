"""The slicer kernel equals its procedural twin (tests/naive_slicer.py), filterpy's way."""

from __future__ import annotations

import numpy as np
import pytest

from afmtool.estimators.bitslicer import SlicerConfig, SlicerState, acquire_clock, slicer_update
from tests.naive_slicer import naive_slicer


def _bit_stream(rng, n_bits: int, period: float, drift: float) -> tuple[np.ndarray, np.ndarray]:
    """NRZ levels 0/1 on a clock whose period drifts by ``drift`` over the record, smoothed and noisy; and an aux."""
    bits = rng.integers(0, 2, n_bits)
    edges = np.cumsum(period * (1 + drift * np.linspace(0, 1, n_bits)))
    n = int(edges[-1])
    levels = bits[np.minimum(np.searchsorted(edges, np.arange(n), side="right"), n_bits - 1)].astype(float)
    kernel = np.exp(-np.arange(12) / 3.0)
    primary = np.convolve(levels, kernel / kernel.sum())[:n] + rng.normal(0, 0.08, n)
    aux = 2.0 * levels + rng.normal(0, 0.3, n)
    return primary, aux


def _run_chunked(config: SlicerConfig, state: SlicerState, primary, aux, chunk: int):
    parts = []
    for start in range(0, primary.size, chunk):
        step = slicer_update(config, state, primary[start : start + chunk], aux[start : start + chunk])
        state = step.state
        parts.append(step.block)
    return [np.concatenate([getattr(b, name) for b in parts])
            for name in ("centre_samples", "soft_primary", "soft_aux", "transitions_samples")]


@pytest.mark.parametrize("period, drift, gains, delays", [
    (33.3, 0.004, (0.05, 0.001), (3, 0)),
    (7.7, -0.01, (0.2, 0.01), (0, 5)),
    (120.0, 0.0, (0.0, 0.0), (2, 2)),
])
def test_slicer_kernel_equals_the_naive_slicer(period, drift, gains, delays):
    rng = np.random.default_rng(29)
    primary, aux = _bit_stream(rng, 400, period, drift)
    smooth = max(1, round(0.25 * period))
    config = SlicerConfig(0.3, 0.5, 0.7, smooth, 0.6, gains[0], gains[1], delays[0], delays[1])
    settings = dict(lo=0.3, mid=0.5, hi=0.7, smooth=smooth, fraction=0.6, phase_gain=gains[0], rate_gain=gains[1],
                    delay_primary=delays[0], delay_aux=delays[1])
    # transitions only (the clock acquisition's pass)
    found = _run_chunked(config, SlicerState.unlocked(config), primary, aux, 1001)
    naive = naive_slicer(primary, aux, **settings)
    assert found[0].size == 0 and len(naive[0]) == 0
    np.testing.assert_allclose(found[3], naive[3], rtol=0, atol=1e-9)
    # locked to the acquired clock: the cells, their soft values and the PLL's transitions
    clock = acquire_clock(found[3], 1.0, rate_range_hz=(0.5 / period, 2.0 / period))
    cells = _run_chunked(config, SlicerState.locked_to(config, clock), primary, aux, 777)
    naive = naive_slicer(primary, aux, **settings, clock=(clock.first_boundary, clock.period_samples))
    assert cells[0].size == len(naive[0]) > 300
    for name, ours, theirs in zip(("centres", "soft primary", "soft aux", "transitions"), cells, naive):
        np.testing.assert_allclose(ours, theirs, rtol=1e-12, atol=1e-9, err_msg=name)


def test_the_naive_comparison_can_fail():
    """A kernel with another phase gain differs from the twin: the comparison sees the PLL."""
    rng = np.random.default_rng(3)
    primary, aux = _bit_stream(rng, 300, 33.3, 0.004)
    config = SlicerConfig(0.3, 0.5, 0.7, 8, 0.6, 0.05, 0.001, 3, 0)
    found = slicer_update(config, SlicerState.unlocked(config), primary, aux).block.transitions_samples
    clock = acquire_clock(found, 1.0, rate_range_hz=(0.015, 0.06))
    ours = slicer_update(config, SlicerState.locked_to(config, clock), primary, aux).block.centre_samples
    naive = naive_slicer(primary, aux, lo=0.3, mid=0.5, hi=0.7, smooth=8, fraction=0.6, phase_gain=0.2,
                         rate_gain=0.001, delay_primary=3, clock=(clock.first_boundary, clock.period_samples))[0]
    assert ours.size != len(naive) or not np.allclose(ours, naive, rtol=1e-12, atol=1e-9)
