"""Thermal-noise route: SHO-plus-floor fit, spring constant, the --psd CSV reader, real spectrum."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from afmtool.errors import ConfigError, InputError
from afmtool.estimators.thermal_noise import (
    BOLTZMANN_J_PER_K,
    fit_thermal_spectrum,
    free_air_from_thermal,
    sho_psd,
)
from afmtool.io.psd import read_psd_csv
from afmtool.models.free_air import FreeAirModel

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
REAL_SPECTRUM = SHARED / "data" / "thermal_tune_acl_a.csv"

# a synthetic spectrum shaped like the real one: 38.147 Hz bins to 320 kHz
DF = 38.147
F0 = 180e3
Q = 450.0
K_N_PER_M = 40.0
T_K = 295.0
FLOOR_ASD = 1.1e-13


def _dc_psd(k=K_N_PER_M, f0=F0, q=Q, temperature_k=T_K):
    """A such that the oscillator part's area (π/2)·A·f0·Q is k_B·T/k."""
    return 2 * BOLTZMANN_J_PER_K * temperature_k / k / (math.pi * f0 * q)


def _noisy_spectrum(rng, averages, f=None):
    """SHO + floor PSD times χ²_{2M}/(2M) (an average of M periodograms), as an ASD."""
    f = np.arange(0.0, 320e3, DF) if f is None else f
    psd = sho_psd(f, F0, Q, _dc_psd(), FLOOR_ASD**2)
    return f, np.sqrt(psd * rng.chisquare(2 * averages, f.size) / (2 * averages))


def test_sho_psd_area_and_peak():
    f = np.linspace(0, 20 * F0, 2_000_001)
    psd = sho_psd(f, F0, Q, 1.0)
    assert sho_psd(F0, F0, Q, 1.0) == pytest.approx(Q**2)
    assert np.trapezoid(psd, f) == pytest.approx(math.pi / 2 * F0 * Q, rel=1e-3)


def test_fit_recovers_synthetic_sho(rng):
    f, asd = _noisy_spectrum(rng, averages=1000)
    fit = fit_thermal_spectrum(f, asd, temperature_k=T_K, n_averages=1000)
    assert fit.f0_hz == pytest.approx(F0, rel=1e-3)
    assert fit.q == pytest.approx(Q, rel=0.05)
    assert fit.floor_asd_m_per_sqrt_hz == pytest.approx(FLOOR_ASD, rel=0.01)
    assert fit.peak_asd_m_per_sqrt_hz == pytest.approx(math.sqrt(_dc_psd()) * Q, rel=0.05)
    assert fit.spring_constant_n_per_m == pytest.approx(K_N_PER_M, rel=0.05)
    # the standard errors are of the size of the actual scatter (1/√1000 per bin)
    assert 1e-6 < fit.f0_std_hz / F0 < 5e-5
    assert 0.002 < fit.q_std / Q < 0.03
    assert fit.rms_log_residual == pytest.approx(1 / math.sqrt(1000), rel=0.15)
    lo, hi = fit.band_hz
    assert lo < F0 - 10 * F0 / (2 * Q) and hi > F0 + 10 * F0 / (2 * Q)
    assert hi - lo < F0


def test_fit_skips_near_dc_artefacts(rng):
    f, asd = _noisy_spectrum(rng, averages=1000)
    # a DC spike and a 1/f rise above the resonance peak (≈ 4e-13 m/√Hz) up to
    # ≈ 2.5 kHz, as in real spectra; negligible near f0
    rise = 2e-12 * 500.0 / np.maximum(f, 1.0)
    asd = np.sqrt(asd**2 + rise**2)
    asd[0] = 1e-9
    assert np.max(asd[f > 1e3]) > np.max(asd[f > 100e3])
    fit = fit_thermal_spectrum(f, asd)
    assert fit.f0_hz == pytest.approx(F0, rel=1e-3)
    assert fit.q == pytest.approx(Q, rel=0.05)


def test_explicit_band(rng):
    f, asd = _noisy_spectrum(rng, averages=1000)
    fit = fit_thermal_spectrum(f, asd, band=(170e3, 190e3))
    assert fit.band_hz == (170e3, 190e3)
    assert fit.n_bins == np.count_nonzero((f >= 170e3) & (f <= 190e3))
    assert fit.f0_hz == pytest.approx(F0, rel=1e-3)


def test_ml_fit_has_no_log_bias_for_few_averages(rng):
    # M = 2: a least-squares fit of ln P puts A and W low by e^(ψ(2) − ln 2) ≈ 0.76 (E[ln χ²_4/4]);
    # the Gamma likelihood (eq. T.2) is maximised by the same S whatever M, with no bias
    f = np.arange(100e3, 260e3, DF)
    f, asd = _noisy_spectrum(rng, averages=2, f=f)
    plain = fit_thermal_spectrum(f, asd, band=(100e3, 260e3))
    told = fit_thermal_spectrum(f, asd, band=(100e3, 260e3), n_averages=2)
    assert (plain.floor_asd_m_per_sqrt_hz / FLOOR_ASD) ** 2 == pytest.approx(1.0, abs=0.06)
    assert told.q == plain.q and told.f0_hz == plain.f0_hz and told.floor_asd_m_per_sqrt_hz == plain.floor_asd_m_per_sqrt_hz
    assert plain.f0_hz == pytest.approx(F0, rel=1e-3)
    # M estimated from the scatter when not given: Var(P/S) = 1/M
    assert plain.n_averages_estimated and plain.n_averages == pytest.approx(2.0, rel=0.15)
    assert not told.n_averages_estimated and told.n_averages == 2 and 0.001 < told.p_value <= 1.0


def test_free_air_from_thermal_has_unit_gain(rng):
    f, asd = _noisy_spectrum(rng, averages=1000)
    model = free_air_from_thermal(f, asd)
    assert isinstance(model, FreeAirModel)
    assert model.source == "thermal" and model.gain == 1.0 and model.gain_std is None
    assert model.f0_hz == pytest.approx(F0, rel=1e-3) and model.f0_std_hz > 0
    assert model.q == pytest.approx(Q, rel=0.05) and model.q_std > 0


def test_without_temperature_no_spring_constant(rng):
    f, asd = _noisy_spectrum(rng, averages=1000)
    fit = fit_thermal_spectrum(f, asd, temperature_k=None)
    assert fit.spring_constant_n_per_m is None and fit.spring_constant_std is None
    assert fit.mean_square_m2 > 0


@pytest.mark.parametrize(
    ("kwargs", "error", "message"),
    [
        ({"temperature_k": -3.0}, ConfigError, "temperature_k=-3.0"),
        ({"n_averages": 0}, ConfigError, "n_averages=0"),
        ({"band": (2e5, 1e5)}, ConfigError, "band="),
        ({"band": (1e6, 2e6)}, ConfigError, "outside the spectrum"),
        ({"band": (179e3, 179.2e3)}, InputError, "only 5 usable bins"),
    ],
)
def test_fit_rejects_bad_arguments(rng, kwargs, error, message):
    f, asd = _noisy_spectrum(rng, averages=1000)
    with pytest.raises(error, match=message):
        fit_thermal_spectrum(f, asd, **kwargs)


def test_fit_rejects_bad_spectra():
    f = np.arange(100.0)
    with pytest.raises(InputError, match="strictly increasing"):
        fit_thermal_spectrum(f[::-1], np.ones(100))
    with pytest.raises(InputError, match="differ in length"):
        fit_thermal_spectrum(f, np.ones(99))
    with pytest.raises(InputError, match="no resonance peak"):
        fit_thermal_spectrum(f * 1e3, np.exp(-f / 50))


# --------------------------------------------------------------------------- real spectrum


@pytest.fixture
def real_spectrum():
    if not REAL_SPECTRUM.is_file():
        pytest.skip(f"{REAL_SPECTRUM} is not available")
    return read_psd_csv(REAL_SPECTRUM)


def test_real_thermal_tune(real_spectrum):
    f, asd = real_spectrum[:2]
    fit = fit_thermal_spectrum(f, asd, temperature_k=295.0, n_averages=1000)
    print(
        f"\nthermal_tune_acl_a: f0 = {fit.f0_hz:.1f} ± {fit.f0_std_hz:.1f} Hz, Q = {fit.q:.1f} ± {fit.q_std:.1f}, "
        f"floor = {fit.floor_asd_m_per_sqrt_hz:.4g} m/√Hz, peak = {fit.peak_asd_m_per_sqrt_hz:.4g} m/√Hz "
        f"({fit.peak_to_floor_db:.1f} dB), band = {fit.band_hz[0]:.0f}–{fit.band_hz[1]:.0f} Hz "
        f"({fit.n_bins} bins), k = {fit.spring_constant_n_per_m:.2f} N/m, "
        f"rms log residual = {fit.rms_log_residual:.3f}"
    )
    # pinned from the run above (f0 = 179716.5 Hz, Q = 378.8, 16.5 dB)
    assert fit.f0_hz == pytest.approx(179_716.5, rel=2e-3)
    assert fit.q == pytest.approx(378.8, rel=0.10)
    # the floor (≈ 1.09e-13 m/√Hz) is far below the peak; this spectrum's
    # peak stands 16.5 dB above it, so 20 dB would not hold
    assert fit.peak_to_floor_db > 15.0
    assert fit.floor_asd_m_per_sqrt_hz == pytest.approx(1.09e-13, rel=0.05)
    # the measured peak bin lies within the fitted resonance's half-power width
    peak_bin = f[np.argmax(np.where(f > 10e3, asd, 0))]
    assert abs(peak_bin - fit.f0_hz) < fit.f0_hz / (2 * fit.q)
    model = free_air_from_thermal(f, asd)
    assert model.f0_hz == pytest.approx(fit.f0_hz) and model.q == pytest.approx(fit.q)


# --------------------------------------------------------------------------- CSV reader


def _write(tmp_path, text, name="psd.csv"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_read_psd_csv(tmp_path):
    path = _write(tmp_path, "# thermal tune\nasd_m_per_sqrt_hz, frequency_hz ,note\n1e-13,0,a\n2e-13,38.1,b\n\n")
    f, asd = read_psd_csv(path)[:2]
    np.testing.assert_array_equal(f, [0.0, 38.1])
    np.testing.assert_array_equal(asd, [1e-13, 2e-13])


def test_read_real_psd_csv(real_spectrum):
    f, asd = real_spectrum[:2]
    assert f.size == 8369 and f[0] == 0.0 and f[1] == pytest.approx(38.147)
    assert np.all(np.diff(f) > 0) and np.all(asd >= 0)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", "empty file"),
        ("frequency_hz,asd_m_per_sqrt_hz\n", "no data rows"),
        ("frequency_hz,asd\n1,2\n", "column 'asd' has no units"),
        ("frequency_hz,note\n1,2\n", "missing a spectral density column"),
        ("frequency_hz,asd_m_per_sqrt_hz\n1,abc\n", "line 2: asd_m_per_sqrt_hz='abc' is not a number"),
        ("frequency_hz,asd_m_per_sqrt_hz\n1,nan\n", "must be a finite number >= 0"),
        ("frequency_hz,asd_m_per_sqrt_hz\n1,-2\n", "must be a finite number >= 0"),
        ("frequency_hz,asd_m_per_sqrt_hz\n2,1\n1,1\n", "line 3: frequency_hz=1.0 is not above the previous 2.0"),
        ("frequency_hz,asd_m_per_sqrt_hz\n2,1\n2,1\n", "strictly increasing"),
        ("frequency_hz,asd_m_per_sqrt_hz\n1,2,3\n", "line 2 has 3 fields, the header has 2"),
    ],
)
def test_read_psd_csv_errors(tmp_path, text, message):
    path = _write(tmp_path, text)
    with pytest.raises(InputError) as info:
        read_psd_csv(path)
    text = str(info.value)
    assert text.startswith(str(path)) and "\n" not in text
    assert message in text


def test_read_psd_csv_missing_file(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        read_psd_csv(tmp_path / "absent.csv")
