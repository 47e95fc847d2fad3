"""The streaming lock-in: amplitude and phase of a known sinusoid, chunking, and its two kernels."""

from __future__ import annotations

import numpy as np
import pytest

from afmtool.estimators.lockin import LockIn, _lockin_kernel, _lockin_order4_kernel

FS_HZ = 500e3
DRIVE_HZ = 70e3


def test_amplitude_and_phase_of_a_sinusoid():
    n = 200_000
    t = np.arange(n) / FS_HZ
    x = 2.5 * np.cos(2 * np.pi * DRIVE_HZ * t + 0.7)  # 2.5 units, 0.7 rad at the first sample
    lockin = LockIn(DRIVE_HZ, FS_HZ, 5e3)
    (block,), _ = lockin.process(x, lockin.initial_state(1), keep_every=7)
    settled = slice(len(block.amplitude) // 2, None)
    np.testing.assert_allclose(block.amplitude[settled], 2.5, rtol=1e-4)
    np.testing.assert_allclose(block.phase_rad[settled], 0.7, atol=1e-4)


@pytest.mark.parametrize("n_signals", [1, 2, 3])
def test_chunked_equals_one_call(n_signals):
    rng = np.random.default_rng(n_signals)
    x = rng.standard_normal((n_signals, 30_001))
    lockin = LockIn(DRIVE_HZ, FS_HZ, 5e3)
    whole, _ = lockin.process(x, lockin.initial_state(n_signals), keep_every=7)
    state, parts = lockin.initial_state(n_signals), []
    for start in range(0, x.shape[1], 4_099):  # not a divisor of the resync interval or of 7
        blocks, state = lockin.process(x[:, start : start + 4_099], state, keep_every=7)
        parts.append(blocks)
    for c in range(n_signals):
        np.testing.assert_array_equal(np.concatenate([p[c].amplitude for p in parts]), whole[c].amplitude)


@pytest.mark.parametrize("n_signals", [1, 2])
def test_order4_kernel_is_bit_for_bit_the_generic_one(n_signals):
    """The scalar-state fast path (order 4, one or two signals) must not change a single bit."""
    rng = np.random.default_rng(7)
    x = rng.standard_normal((n_signals, 50_000))
    sos = LockIn(DRIVE_HZ, FS_HZ, 5e3)._sos
    outputs = []
    for order4 in (True, False):
        zi = np.full((n_signals, 2, 2), 0.1 + 0.2j)  # a carried state, mid-stream (start not on a resync)
        out = np.empty((n_signals, x.shape[1] // 7 + 1), dtype=np.complex128)
        if order4:  # one call per signal, as LockIn runs it
            kept = [
                _lockin_order4_kernel(x[r], 12_345, DRIVE_HZ / FS_HZ, sos, zi[r : r + 1], 7, out[r : r + 1])
                for r in range(n_signals)
            ][0]
        else:
            kept = _lockin_kernel(x, 12_345, DRIVE_HZ / FS_HZ, sos, zi, 7, out)
        outputs.append((out[:, :kept], zi))
    np.testing.assert_array_equal(outputs[0][0], outputs[1][0])
    np.testing.assert_array_equal(outputs[0][1], outputs[1][1])


def test_phase_against_a_reference_channel():
    """process_against: the signal's amplitude, its phase minus the reference's, wrapped."""
    n = 200_000
    t = np.arange(n) / FS_HZ
    signal = 2.5 * np.cos(2 * np.pi * DRIVE_HZ * t + 3.0)
    reference = 0.1 * np.cos(2 * np.pi * DRIVE_HZ * t - 1.0)  # 4 rad apart: wraps to 4 - 2π
    lockin = LockIn(DRIVE_HZ, FS_HZ, 5e3)
    block, state = lockin.process_against(signal, reference, lockin.initial_state(2), keep_every=7)
    settled = slice(len(block.amplitude) // 2, None)
    np.testing.assert_allclose(block.amplitude[settled], 2.5, rtol=1e-4)
    np.testing.assert_allclose(block.phase_rad[settled], 4.0 - 2 * np.pi, atol=1e-4)
    assert state.samples_seen == n
