"""numpy-only filter design and spectra (afmtool.estimators.filters) against scipy.signal."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import butter, group_delay, sosfreqz, welch

from afmtool.estimators.filters import butterworth_lowpass_sos, sos_group_delay, welch_psd

FS_HZ = 500e3


@pytest.mark.parametrize("order", range(1, 9))
@pytest.mark.parametrize("cutoff_hz", [350.0, 7e3, 5e4, 2.2e5])
def test_butterworth_design_matches_scipy(order, cutoff_hz):
    """Our own design (no scipy.signal import at start-up) against scipy.signal.butter.

    Even orders: the same sections to 1e-12.  Odd orders: scipy shares the
    zeros between sections differently, so the frequency responses are compared.
    """
    ours = butterworth_lowpass_sos(order, cutoff_hz, FS_HZ)
    theirs = butter(order, cutoff_hz, fs=FS_HZ, output="sos")
    if order % 2 == 0:
        np.testing.assert_allclose(ours, theirs, rtol=1e-12, atol=0)
    _, h_ours = sosfreqz(ours, 2048, fs=FS_HZ)
    _, h_theirs = sosfreqz(theirs, 2048, fs=FS_HZ)
    np.testing.assert_allclose(h_ours, h_theirs, rtol=0, atol=1e-10)


@pytest.mark.parametrize("order", [1, 2, 3, 4, 6])
def test_group_delay_matches_the_phase_slope(order):
    """Against −dφ/dω of scipy's own sections (central difference); scipy.signal.group_delay
    works on the transfer-function form, which loses digits at order 6 (it warns)."""
    cutoff_hz = 4e3
    sos = butter(order, cutoff_hz, fs=FS_HZ, output="sos")
    for f in (cutoff_hz / 100.0, cutoff_hz):
        df = f * 1e-4
        _, h = sosfreqz(sos, worN=[f - df, f + df], fs=FS_HZ)
        slope = -np.diff(np.unwrap(np.angle(h)))[0] / (2 * np.pi * 2 * df / FS_HZ)
        ours = sos_group_delay(butterworth_lowpass_sos(order, cutoff_hz, FS_HZ), f, FS_HZ)
        assert ours == pytest.approx(slope, rel=1e-6)
    if order <= 4:
        b, a = butter(order, cutoff_hz, fs=FS_HZ)
        _, theirs = group_delay((b, a), w=[cutoff_hz / 100.0], fs=FS_HZ)
        assert sos_group_delay(sos, cutoff_hz / 100.0, FS_HZ) == pytest.approx(theirs[0], rel=1e-7)


@pytest.mark.parametrize(("n", "nperseg"), [(10_000, 1024), (10_001, 1024), (5_000, 333), (700, 1024), (4_096, 4_096)])
def test_welch_matches_scipy(n, nperseg):
    x = np.random.default_rng(n).standard_normal(n) + 0.3  # an offset, which both detrend
    theirs_f, theirs = welch(x, fs=2e6, nperseg=min(nperseg, n))
    ours_f, ours = welch_psd(x, 2e6, nperseg)
    np.testing.assert_array_equal(ours_f, theirs_f)
    np.testing.assert_allclose(ours, theirs, rtol=1e-12, atol=1e-15 * theirs.max())


def test_welch_of_white_noise_is_its_variance_over_half_the_rate():
    """Ground truth: white noise of variance σ² has the one-sided density 2σ²/f_s."""
    sigma, fs = 0.3, 1e6
    x = sigma * np.random.default_rng(1).standard_normal(1 << 20)
    _, psd = welch_psd(x, fs, 1024)
    assert psd[1:-1].mean() == pytest.approx(2 * sigma**2 / fs, rel=0.01)
