"""Frequency-response estimation: H1 (batch and streaming), stepped sine, rational and second-order fits.

Test signals: the ZOH-discretised cantilever (f0 = 70 kHz, Q = 200) sampled at
500 kHz, driven by white noise, a linear chirp or a stepped sine (evaluated
analytically, so a pure delay is the drive evaluated at t − τ).  The exact
response of that discrete system is ``freqz`` of its coefficients; it carries
the zero-order hold's half-sample delay (1 µs), which the delay fit absorbs.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.signal

from afmtool.errors import ConfigError, InputError
from afmtool.estimators.frequency_response import FrequencyResponse, H1Accumulator, frf_table, h1_estimate
from afmtool.estimators.stepped_sine import SineSegment, detect_segments, stepped_sine_response
from afmtool.estimators.sweep_record import free_air_from_sweep
from afmtool.estimators.transfer_function_fit import fit_second_order, fit_transfer_function
from afmtool.models.discretisation import discrete_denominator, zoh_numerator
from afmtool.models.free_air import FreeAirModel
from afmtool.sim.excitation import LinearChirp, SteppedSine

FS = 500e3
F0 = 70e3
Q = 200.0
_NUM = zoh_numerator(F0, Q, FS)
_DEN = discrete_denominator(F0, Q, FS)
B = [_NUM.a2, _NUM.a1, _NUM.a0]
A = [1.0, _DEN.b1, _DEN.b0]
HALF_SAMPLE_S = 0.5 / FS  # delay of the zero-order hold


def true_response(f_hz, delay_s=0.0):
    """Exact response of the sampled cantilever (plus a pure delay)."""
    f_hz = np.asarray(f_hz, dtype=float)
    _, h = scipy.signal.freqz(B, A, worN=f_hz, fs=FS)
    return h * np.exp(-2j * np.pi * f_hz * delay_s)


def chirp_capture(rng, delay_s=0.0, n=1 << 20, noise=0.5):
    """Chirp 50–90 kHz (amplitude 1) and the deflection of the delayed drive plus white noise."""
    chirp = LinearChirp(1.0, 50e3, 90e3, n / FS)
    t = np.arange(n) / FS
    y = scipy.signal.lfilter(B, A, chirp(t - delay_s)) + noise * rng.standard_normal(n)
    return chirp(t), y


def stepped_capture(rng, frequencies, dwell_s=0.01, noise=0.5, drive_noise=0.0):
    steps = SteppedSine(1.0, tuple(float(f) for f in frequencies), dwell_s)
    n = int(round(len(frequencies) * dwell_s * FS))
    x = steps(np.arange(n) / FS)
    y = scipy.signal.lfilter(B, A, x) + noise * rng.standard_normal(n)
    return x + drive_noise * rng.standard_normal(n), y, steps.segments()


# --------------------------------------------------------------------------- H1


@pytest.fixture(scope="module")
def white_noise_capture():
    rng = np.random.default_rng(7)
    n = 1 << 20
    x = rng.standard_normal(n)
    y = scipy.signal.lfilter(B, A, x) + 0.5 * rng.standard_normal(n)
    return x, y


def test_h1_recovers_resonance(white_noise_capture):
    x, y = white_noise_capture
    fr = h1_estimate(x, y, FS, nperseg=1 << 14)
    near = (np.abs(fr.frequency_hz - F0) < 2000) & (fr.coherence > 0.95)
    assert np.count_nonzero(near) > 100
    ratio = fr.response[near] / true_response(fr.frequency_hz[near])
    assert np.max(np.abs(20 * np.log10(np.abs(ratio)))) < 0.5  # dB
    assert np.max(np.abs(np.degrees(np.angle(ratio)))) < 3.0  # degrees


def test_h1_without_input_is_nan(rng):
    fr = h1_estimate(np.zeros(4096), rng.standard_normal(4096), FS, nperseg=1024)
    assert np.all(np.isnan(fr.response)) and np.all(np.isnan(fr.coherence))


def test_h1_error_estimates_match_scatter(white_noise_capture):
    x, y = white_noise_capture
    fr = h1_estimate(x, y, FS, nperseg=1 << 14)
    assert fr.n_averages == pytest.approx(127 / 1.056, rel=0.01)  # Hann, 50 %: ρ² ≈ 0.028
    band = (fr.frequency_hz > 20e3) & (fr.frequency_hz < 200e3)
    err = fr.response[band] - true_response(fr.frequency_hz[band])
    # radial and tangential errors, each normalised by its predicted standard deviation
    radial = np.real(err * np.conj(fr.response[band])) / np.abs(fr.response[band]) / fr.magnitude_std[band]
    tangential = np.imag(err * np.conj(fr.response[band])) / np.abs(fr.response[band]) ** 2 / fr.phase_std_rad[band]
    assert 0.8 < np.std(radial) < 1.25
    assert 0.8 < np.std(tangential) < 1.25


@pytest.mark.parametrize(
    ("nperseg", "noverlap", "detrend", "window"),
    [(4096, None, "constant", "hann"), (1001, 300, "linear", ("tukey", 0.25)), (512, 0, False, "boxcar")],
)
def test_streaming_accumulator_equals_batch(rng, nperseg, noverlap, detrend, window):
    n = 60_000
    x = rng.standard_normal(n)
    y = scipy.signal.lfilter(B, A, x) + 0.1 * rng.standard_normal(n) + 3.0  # an offset for detrend
    batch = h1_estimate(x, y, FS, nperseg=nperseg, noverlap=noverlap, window=window, detrend=detrend)
    acc = H1Accumulator(FS, nperseg, noverlap=noverlap, window=window, detrend=detrend)
    # chunks of any size: empty, single samples, shorter and longer than a segment
    sizes = [0, 1, 7, nperseg - 1, 3, 2 * nperseg + 5, 1]
    edges = np.cumsum(sizes + list(rng.integers(1, 3 * nperseg, size=200)))
    edges = np.concatenate(([0], edges[edges < n], [n]))
    for a, b in zip(edges[:-1], edges[1:]):
        acc.add(x[a:b], y[a:b])
    stream = acc.result()
    ok = np.isfinite(batch.response)
    np.testing.assert_array_equal(np.isfinite(stream.response), ok)
    np.testing.assert_allclose(stream.response[ok], batch.response[ok], rtol=1e-10, atol=0)
    np.testing.assert_allclose(stream.coherence[ok], batch.coherence[ok], rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(stream.magnitude_std[ok], batch.magnitude_std[ok], rtol=1e-8)
    assert stream.n_averages == pytest.approx(batch.n_averages, rel=1e-12)
    # and the accumulated densities are scipy's
    spectra = acc.spectra()
    kwargs = dict(
        fs=FS, window=scipy.signal.get_window(window, nperseg), nperseg=nperseg, noverlap=noverlap, detrend=detrend
    )
    _, pxy = scipy.signal.csd(x, y, **kwargs)
    _, pxx = scipy.signal.welch(x, **kwargs)
    np.testing.assert_allclose(spectra.pxy, pxy, rtol=1e-10, atol=1e-12 * np.abs(pxy).max())
    np.testing.assert_allclose(spectra.pxx, pxx, rtol=1e-10, atol=1e-12 * pxx.max())


def test_accumulator_needs_a_segment():
    acc = H1Accumulator(FS, 1024)
    acc.add(np.zeros(1000), np.zeros(1000))
    with pytest.raises(InputError, match="nperseg=1024"):
        acc.result()


def test_h1_does_not_modify_inputs(rng):
    x = rng.standard_normal(5000)
    y = rng.standard_normal(5000)
    x.setflags(write=False)
    y.setflags(write=False)
    h1_estimate(x, y, FS, nperseg=1024)
    acc = H1Accumulator(FS, 1024)
    acc.add(x, y)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"nperseg": 1}, "nperseg=1"),
        ({"nperseg": 1024, "noverlap": 1024}, "noverlap=1024"),
        ({"nperseg": 1024, "detrend": "quadratic"}, "detrend='quadratic'"),
        ({"nperseg": 1024, "window": "nonsense"}, "window='nonsense'"),
    ],
)
def test_h1_rejects_bad_parameters(rng, kwargs, message):
    x = rng.standard_normal(4096)
    with pytest.raises(ConfigError, match=message):
        h1_estimate(x, x, FS, **kwargs)


def test_h1_rejects_bad_records(rng):
    x = rng.standard_normal(4096)
    with pytest.raises(InputError, match="same length"):
        h1_estimate(x, x[:-1], FS, nperseg=1024)
    with pytest.raises(InputError, match="fewer than nperseg=8192"):
        h1_estimate(x, x, FS, nperseg=8192)
    bad = x.copy()
    bad[5] = np.nan
    with pytest.raises(InputError, match="index 5"):
        h1_estimate(bad, x, FS, nperseg=1024)
    with pytest.raises(ConfigError, match="sample_rate_hz=-1"):
        h1_estimate(x, x, -1, nperseg=1024)


# --------------------------------------------------------------------------- stepped sine


def test_stepped_sine_and_chirp_agree():
    rng = np.random.default_rng(11)
    nperseg = 1 << 15
    x, y = chirp_capture(rng)
    chirp_fr = h1_estimate(x, y, FS, nperseg=nperseg)
    # step frequencies on the H1 grid k·fs/nperseg, ±2 kHz around f0
    bins = np.arange(int(68e3 * nperseg / FS), int(72e3 * nperseg / FS), 8)
    xs, ys, segments = stepped_capture(rng, bins * FS / nperseg)
    stepped = stepped_sine_response(xs, ys, FS, segments)
    np.testing.assert_allclose(stepped.frequency_hz, chirp_fr.frequency_hz[bins])
    both = (stepped.coherence > 0.95) & (chirp_fr.coherence[bins] > 0.95)
    assert np.count_nonzero(both) >= 0.9 * bins.size
    diff_db = 20 * np.log10(np.abs(stepped.response[both] / chirp_fr.response[bins][both]))
    assert np.max(np.abs(diff_db)) < 0.5
    # the stepped sine itself is close to exact after settling
    exact = true_response(stepped.frequency_hz)
    assert np.max(np.abs(20 * np.log10(np.abs(stepped.response / exact)))) < 0.05
    assert np.max(np.abs(np.degrees(np.angle(stepped.response / exact)))) < 0.5


def test_stepped_sine_quality_reflects_noise(rng):
    freqs = np.linspace(60e3, 80e3, 5)
    _, clean, segments = stepped_capture(rng, freqs, noise=0.0)
    x, noisy, _ = stepped_capture(rng, freqs, noise=5.0)
    fr_clean = stepped_sine_response(x, clean, FS, segments)
    fr_noisy = stepped_sine_response(x, noisy, FS, segments)
    assert np.all(fr_clean.coherence > 0.99)  # what is left is the decaying transient
    assert np.all(fr_noisy.coherence < fr_clean.coherence)
    assert np.all(fr_noisy.magnitude_std > fr_clean.magnitude_std)


def test_detect_segments_finds_the_steps(rng):
    freqs = np.linspace(68e3, 72e3, 21)
    x, _, segments = stepped_capture(rng, freqs, dwell_s=0.008, drive_noise=0.01)  # 40 dB drive SNR
    found = detect_segments(x, FS)
    assert len(found) == len(segments)
    # with 0.01 rad of phase noise per sample the 200 Hz steps are located to
    # ~±20 samples; 40 samples is 1 % of a step
    for got, want in zip(found, segments):
        assert got.start_s == pytest.approx(want["start_s"], abs=40 / FS)
        assert got.end_s == pytest.approx(want["end_s"], abs=40 / FS)
        assert got.frequency_hz == pytest.approx(want["frequency_hz"], abs=0.1)
    # a clean drive: boundaries to a sample
    clean, _, _ = stepped_capture(rng, freqs, dwell_s=0.008)
    for got, want in zip(detect_segments(clean, FS), segments):
        assert got.start_s == pytest.approx(want["start_s"], abs=1.5 / FS)
        assert got.frequency_hz == pytest.approx(want["frequency_hz"], abs=1e-3)


def test_detect_segments_rejects_chirps_and_splits_at_gaps(rng):
    t = np.arange(int(0.2 * FS)) / FS
    assert detect_segments(LinearChirp(1.0, 50e3, 90e3, 0.2)(t), FS) == ()
    assert detect_segments(LinearChirp(1.0, 69.9e3, 70.1e3, 0.2)(t), FS) == ()
    x, _, segments = stepped_capture(rng, [65e3, 70e3, 75e3], dwell_s=0.01)
    x[1500:2500] = 0.0  # the drive is off for 2 ms inside the first step
    found = detect_segments(x, FS)
    assert [round(s.frequency_hz) for s in found] == [65000, 65000, 70000, 75000]
    assert found[0].end_s <= 1500 / FS and found[1].start_s >= 2500 / FS


def test_stepped_response_with_detected_segments(rng):
    x, y, segments = stepped_capture(rng, np.linspace(69e3, 71e3, 9))
    from_meta = stepped_sine_response(x, y, FS, segments)
    detected = stepped_sine_response(x, y, FS, detect_segments(x, FS))
    np.testing.assert_allclose(detected.frequency_hz, from_meta.frequency_hz, atol=1e-3)
    np.testing.assert_allclose(detected.response, from_meta.response, rtol=1e-3)


@pytest.mark.parametrize(
    ("segments", "message"),
    [
        ([{"start_s": 0.0, "end_s": 0.01}], "lacks 'frequency_hz'"),
        ([{"start_s": 0.01, "end_s": 0.0, "frequency_hz": 7e4}], "start_s < end_s"),
        ([{"start_s": 0.0, "end_s": 1.0, "frequency_hz": 7e4}], "after the records end"),
        ([{"start_s": 0.0, "end_s": 1e-4, "frequency_hz": 7e4}], "fewer than min_periods=10"),
        ([], "non-empty"),
    ],
)
def test_stepped_sine_rejects_bad_segments(rng, segments, message):
    x, y, _ = stepped_capture(rng, [7e4])
    with pytest.raises(InputError, match=message):
        stepped_sine_response(x, y, FS, segments)


def test_stepped_sine_rejects_bad_settle_fraction(rng):
    x, y, segments = stepped_capture(rng, [7e4])
    with pytest.raises(ConfigError, match="settle_fraction=1.0"):
        stepped_sine_response(x, y, FS, segments, settle_fraction=1.0)


# --------------------------------------------------------------------------- fits


def test_second_order_fit_is_exact_on_noise_free_data():
    f = np.linspace(60e3, 80e3, 101)
    s = 2j * np.pi * f
    w0 = 2 * np.pi * F0
    h = -2.5 * w0**2 / (s**2 + (w0 / Q) * s + w0**2) * np.exp(-s * 3.3e-6)
    fit = fit_second_order(f, h)
    assert fit.f0_hz == pytest.approx(F0, rel=1e-9)
    assert fit.q == pytest.approx(Q, rel=1e-7)
    assert fit.gain == pytest.approx(-2.5, rel=1e-7)
    assert fit.delay_s == pytest.approx(3.3e-6, rel=1e-7)
    np.testing.assert_allclose(fit.response(f), h, rtol=1e-7)


def test_free_air_from_chirp_recovers_f0_and_q():
    rng = np.random.default_rng(5)
    x, y = chirp_capture(rng, delay_s=5e-6)
    model = free_air_from_sweep(x, y, FS)
    assert isinstance(model, FreeAirModel) and model.source == "sweep"
    assert model.f0_hz == pytest.approx(F0, rel=5e-4)
    assert model.q == pytest.approx(Q, rel=0.03)
    assert model.delay_s == pytest.approx(5e-6 + HALF_SAMPLE_S, abs=0.1e-6)
    # the zero-order hold's droop near f0 (sin(πf/fs)/(πf/fs) ≈ 0.97) is part of the gain
    assert model.gain == pytest.approx(1.0, rel=0.05)
    assert 0 < model.f0_std_hz < 5 and 0 < model.q_std < 2


def test_leaving_the_delay_out_biases_f0():
    rng = np.random.default_rng(6)
    x, y = chirp_capture(rng, delay_s=5e-6)
    # the spectral (H1) fit of fit_second_order, whose docstring makes this claim
    with_delay = free_air_from_sweep(x, y, FS, method="h1", delay=True)
    without = free_air_from_sweep(x, y, FS, method="h1", delay=False)
    assert abs(with_delay.f0_hz / F0 - 1) < 5e-5
    assert abs(with_delay.q / Q - 1) < 0.01
    assert abs(without.f0_hz / F0 - 1) > 5e-4  # more than 35 Hz off
    assert abs(without.q / Q - 1) > 0.05


def test_free_air_from_stepped_sweep(rng):
    x, y, segments = stepped_capture(rng, np.linspace(68e3, 72e3, 41))
    for given in (segments, None):
        model = free_air_from_sweep(x, y, FS, method="stepped", segments=given)
        assert model.f0_hz == pytest.approx(F0, rel=5e-4)
        assert model.q == pytest.approx(Q, rel=0.03)


def test_free_air_from_sweep_rejects_bad_options(rng):
    x, y = rng.standard_normal(4096), rng.standard_normal(4096)
    with pytest.raises(ConfigError, match="method='lms'"):
        free_air_from_sweep(x, y, FS, method="lms")
    with pytest.raises(ConfigError, match="segments apply"):
        free_air_from_sweep(x, y, FS, method="h1", segments=[])
    with pytest.raises(ConfigError, match="segments and nperseg apply"):
        free_air_from_sweep(x, y, FS, segments=[])
    with pytest.raises(ConfigError, match="hold='zoh' needs method='record'"):
        free_air_from_sweep(x, y, FS, method="h1", hold="zoh")
    with pytest.raises(ConfigError, match="hold='foh'"):
        free_air_from_sweep(x, y, FS, hold="foh")
    for method in ("record", "h1"):
        with pytest.raises(ConfigError, match="band="):
            free_air_from_sweep(x, y, FS, method=method, band=(5.0, 1.0))


def _lowpass_10db_per_decade():
    """3 poles and 2 zeros interleaved from 12 to 300 kHz: ≈ −11 dB/decade, DC gain 111."""
    poles = 2 * np.pi * np.array([12e3, 60e3, 300e3])
    zeros = 2 * np.pi * np.array([30e3, 150e3])
    num = 111.0 * np.prod(poles) / np.prod(zeros) * np.poly(-zeros)
    return num, np.poly(-poles), poles, zeros


def test_rational_fit_recovers_a_third_order_lowpass_with_delay():
    num, den, poles, zeros = _lowpass_10db_per_decade()
    f = np.geomspace(100, 1e6, 200)
    s = 2j * np.pi * f
    h = np.polyval(num, s) / np.polyval(den, s) * np.exp(-s * 2e-6)
    slope = np.diff(20 * np.log10(np.abs(h[np.searchsorted(f, [20e3, 200e3])])))[0]
    assert -13 < slope < -9  # dB per decade
    fit = fit_transfer_function(f, h, 2, 3, delay=True, delay_bounds_s=(0, 10e-6))
    assert fit.converged
    assert fit.delay_s == pytest.approx(2e-6, rel=1e-6)
    np.testing.assert_allclose(np.sort(-fit.poles.real), np.sort(poles), rtol=1e-6)
    np.testing.assert_allclose(np.sort(-fit.zeros.real), np.sort(zeros), rtol=1e-6)
    np.testing.assert_allclose(fit.numerator / fit.numerator[0], num / num[0], rtol=1e-6)
    assert fit.denominator[0] == 1.0
    np.testing.assert_allclose(fit.response(f), h, rtol=1e-6)


def test_rational_fit_with_relative_noise(rng):
    num, den, poles, zeros = _lowpass_10db_per_decade()
    f = np.geomspace(100, 1e6, 200)
    s = 2j * np.pi * f
    h = np.polyval(num, s) / np.polyval(den, s)
    noisy = h * (1 + 1e-3 * (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size)))
    fit = fit_transfer_function(f, noisy, 2, 3, weights=1 / np.abs(noisy) ** 2)
    np.testing.assert_allclose(np.sort(-fit.poles.real), np.sort(poles), rtol=0.02)
    np.testing.assert_allclose(np.sort(-fit.zeros.real), np.sort(zeros), rtol=0.02)
    assert np.max(np.abs(fit.response(f) / h - 1)) < 3e-3


@pytest.mark.parametrize(
    ("args", "kwargs", "error", "message"),
    [
        ((3, 2), {}, ConfigError, "n_num=3"),
        ((0, 0), {}, ConfigError, "n_den=0"),
        ((0, 2), {"delay": "yes"}, ConfigError, "delay='yes'"),
        ((0, 2), {"delay": True, "delay_bounds_s": (2e-6, 1e-6)}, ConfigError, "delay_bounds_s"),
        ((0, 2), {"weights": -np.ones(5)}, InputError, "weights"),
    ],
)
def test_rational_fit_rejects_bad_arguments(args, kwargs, error, message):
    f = np.linspace(1e3, 5e3, 5)
    with pytest.raises(error, match=message):
        fit_transfer_function(f, 1 / (1 + 1j * f / 1e3), *args, **kwargs)


def test_rational_fit_rejects_nan_response():
    f = np.linspace(1e3, 5e3, 5)
    h = 1 / (1 + 1j * f / 1e3)
    h[2] = np.nan
    with pytest.raises(InputError, match="index 2"):
        fit_transfer_function(f, h, 0, 1)


# --------------------------------------------------------------------------- tables


def test_frf_table_columns():
    fr = FrequencyResponse(
        frequency_hz=np.array([1.0, 2.0]),
        response=np.array([10.0 + 0j, -1j]),
        coherence=np.array([1.0, 0.5]),
        magnitude_std=np.array([0.0, 0.1]),
        phase_std_rad=np.array([0.0, 0.1]),
        method="stepped",
    )
    table = frf_table(fr)
    assert list(table)[:5] == ["frequency_hz", "magnitude", "magnitude_db", "phase_deg", "coherence"]
    np.testing.assert_allclose(table["magnitude_db"], [20.0, 0.0])
    np.testing.assert_allclose(table["phase_deg"], [0.0, -90.0])
    np.testing.assert_allclose(table["phase_std_deg"], [0.0, np.degrees(0.1)])
    assert all(len(v) == 2 for v in table.values())


def test_sine_segment_accepts_tuples(rng):
    x, y, segments = stepped_capture(rng, [7e4, 7.1e4])
    as_tuples = [SineSegment(s["start_s"], s["end_s"], s["frequency_hz"]) for s in segments]
    a = stepped_sine_response(x, y, FS, segments)
    b = stepped_sine_response(x, y, FS, as_tuples)
    np.testing.assert_array_equal(a.response, b.response)
