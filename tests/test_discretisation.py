"""Sampled models for a held and a continuous drive (issue 14, item 1), and the simulators' free-air phase.

Acceptance: the free-air phase at resonance is −90° ± 1° in every simulator
scenario that drives a cantilever continuously (the default).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from afmtool.errors import ConfigError
from afmtool.models.discretisation import (
    classify_hold,
    discrete_denominator,
    line_numerator,
    sampled_numerator,
    sampled_response,
    zoh_numerator,
)
from afmtool.sim import simulate
from tests import reference_sim as rs

FS = 500e3


def _g(f0, q, f):
    w, w0 = 2 * np.pi * np.asarray(f, float), 2 * np.pi * f0
    return w0**2 / (w0**2 - w**2 + 1j * w * w0 / q)


@pytest.mark.parametrize(("f0", "q"), [(70e3, 200.0), (80318.0, 168.0), (30e3, 400.0), (150e3, 100.0)])
def test_line_numerator_is_exact_at_the_line_and_dc(f0, q):
    num = line_numerator(f0, q, FS)
    den = discrete_denominator(f0, q, FS)
    at_line = sampled_response(num, den, f0, FS) / _g(f0, q, f0)
    assert abs(at_line - 1) < 1e-12
    assert abs(sampled_response(num, den, 0.0, FS) - 1) < 1e-12
    sides = sampled_response(num, den, [f0 - 6e3, f0 + 6e3], FS) / _g(f0, q, [f0 - 6e3, f0 + 6e3])
    print(f"f0 {f0:g} Q {q:g}: side lines |H/G| - 1 = {np.abs(sides) - 1}, phase {np.degrees(np.angle(sides))} deg")
    # smooth through the resonance: < 0.1 % in gain, < 0.02 deg at ±6 kHz below 100 kHz
    if f0 < 100e3:
        assert np.max(np.abs(np.abs(sides) - 1)) < 1e-3
        assert np.max(np.abs(np.degrees(np.angle(sides)))) < 0.02
    # the zero-order hold is half a sample late at the line
    zoh = sampled_response(zoh_numerator(f0, q, FS), den, f0, FS) / _g(f0, q, f0)
    assert abs(math.degrees(np.angle(zoh)) + 180 * f0 / FS) < 0.2


def test_line_numerator_delay_and_match_line():
    f0, q = 70e3, 200.0
    num = line_numerator(f0, q, FS, match_hz=72e3, delay_s=1e-6)
    h = sampled_response(num, discrete_denominator(f0, q, FS), 72e3, FS)
    assert abs(h / (_g(f0, q, 72e3) * np.exp(-2j * np.pi * 72e3 * 1e-6)) - 1) < 1e-12
    assert sampled_numerator(f0, q, FS, "zoh") == zoh_numerator(f0, q, FS)
    assert sampled_numerator(f0, q, FS, "continuous") == line_numerator(f0, q, FS)
    with pytest.raises(ConfigError, match="hold"):
        sampled_numerator(f0, q, FS, "foh")
    with pytest.raises(ConfigError, match="match_hz"):
        line_numerator(f0, q, FS, match_hz=300e3)


@pytest.mark.parametrize("hold", ["continuous", "zoh"])
def test_classify_hold_on_reference_captures(hold):
    """The hold of an independent capture is told from its free-air phase at the drive."""
    from afmtool.analyses.freeair_route import line_response

    f0, q = 70e3, 200.0
    cap = rs.simulate(f0_hz=f0, q=q, gain_nm_per_v=0.1, sample_rate_hz=FS, duration_s=4e-3,
                      drive=rs.Sine(f0 + 500.0, 1.0), hold=hold, noise_nm=0.1, seed=2)
    h = line_response(cap.channels["deflection"], cap.channels["dither"], FS, [f0 + 500.0])
    decision = classify_hold(h, f0, q, f0 + 500.0, FS)
    print(decision.reason)
    assert decision.hold == hold
    expected_excess = 0.0 if hold == "continuous" else decision.zoh_excess_deg
    assert abs(decision.excess_phase_deg - expected_excess) < 0.5


def _free_air_phase_deg(deflection, dither, f_hz):
    t = np.arange(len(deflection)) / FS
    basis = np.column_stack([np.cos(2 * np.pi * f_hz * t), np.sin(2 * np.pi * f_hz * t), np.ones_like(t)])
    coef, *_ = np.linalg.lstsq(basis, np.column_stack([deflection, dither]), rcond=None)
    y = complex(coef[0, 0], -coef[1, 0])
    u = complex(coef[0, 1], -coef[1, 1])
    return math.degrees(np.angle(y / u))


SCENARIOS = {
    "ltv": {"drive": "sine", "duration_s": 0.004, "step_time_s": 0.004, "measurement_noise_nm": 0.0},
    "tapping": {"drive": "sine", "duration_s": 0.004, "program": "constant", "force_set": "none",
                "temperature_k": 0.0, "measurement_noise_nm": 0.0},
    "raster": {"drive": "sine", "duration_s": 0.004, "lines": 1, "temperature_k": 0.0, "measurement_noise_nm": 0.0},
}


@pytest.mark.parametrize("scenario", sorted(SCENARIOS))
@pytest.mark.parametrize("hold", ["continuous", "zoh"])
def test_simulator_free_air_phase_at_resonance(scenario, hold):
    params = {**SCENARIOS[scenario], "drive_hold": hold}
    cap = simulate(scenario, params, seed=0)
    f0 = cap.metadata["cantilever"]["f0_hz"]
    assert cap.metadata["drive"]["frequency_hz"] == f0
    assert cap.metadata["drive"]["hold"] == hold
    end = int(cap.metadata["free_air"]["end_s"] * FS) if "free_air" in cap.metadata else cap.n_samples
    phase = _free_air_phase_deg(cap.data["deflection"][:end], cap.data["dither"][:end], f0)
    print(f"{scenario} {hold}: free-air phase at resonance {phase:.3f} deg")
    expected = -90.0 if hold == "continuous" else -90.0 - 180.0 * f0 / FS
    assert abs(phase - expected) < 1.0


@pytest.mark.parametrize(("f0", "q", "fs"), [(70e3, 200.0, 500e3), (30e3, 20.0, 125e3), (300e3, 600.0, 2e6)])
def test_resonance_std_is_the_first_order_propagation(f0, q, fs):
    """resonance_std_scalar against central differences of eq. 3.48 through the covariance."""
    from afmtool.models.discretisation import resonance_scalar, resonance_std_scalar

    b1, b0 = discrete_denominator(f0, q, fs)
    cov = np.array([[3e-10, -2e-10], [-2e-10, 2.5e-10]])
    f0_std, q_std = resonance_std_scalar(b1, b0, cov[0, 0], cov[0, 1], cov[1, 1], 1.0 / fs)
    step = 1e-8
    grads = np.empty((2, 2))
    for k in range(2):
        delta = np.zeros(2)
        delta[k] = step
        plus = resonance_scalar(b1 + delta[0], b0 + delta[1], 1.0 / fs)
        minus = resonance_scalar(b1 - delta[0], b0 - delta[1], 1.0 / fs)
        grads[:, k] = (np.array(plus) - np.array(minus)) / (2 * step)
    expected = np.sqrt(np.einsum("ij,jk,ik->i", grads, cov, grads))
    np.testing.assert_allclose([f0_std, q_std], expected, rtol=1e-5)
    assert all(math.isnan(v) for v in resonance_std_scalar(0.5, 1.2, *cov.ravel()[[0, 1, 3]], 1.0 / fs))


def test_a_drive_at_dc_is_refused_not_a_singular_matrix():
    # hostile case [reep] drive_frequency_hz = 1e-300: e^{-jωT} = 1 makes the line's equation DC's
    from afmtool.errors import ConfigError
    from afmtool.models.discretisation import line_numerator

    with pytest.raises(ConfigError, match="too close to DC"):
        line_numerator(70e3, 200.0, 500e3, match_hz=1e-300)


def test_a_line_fit_that_runs_away_is_none():
    # lines a hundred octaves below the resonance: Gauss-Newton overflowed math.exp (an internal error)
    from afmtool.models.discretisation import fit_continuous_lines

    # what kalman-bank's segment route gave it for [kalman-bank] drive_frequency_hz = 1e-300 (hostile case)
    lines = np.array([1e-300, 80317.91666666666, 86317.91666666666])
    responses = np.array([-52.403435037765504 + 5.4981886227641899e-10j, -9.8346785686724402e-03 - 167.84045385061864j,
                          -6.4691014079361855 - 0.25902786316719184j])
    assert fit_continuous_lines(lines, responses, 80318.39743372834, 166.6813989300005) is None


def test_the_row_spacing_of_a_window_of_1e16_samples_is_found_at_once():
    # lam = 1 - 1e-16: the rule tried 2.5e14 spacings (a hang); it tries at most 4096, the top of the range
    import time

    from afmtool.config import resolve
    from afmtool.config.params import ReepParams
    from afmtool.estimators.reep_estimator import _row_spacing

    params = resolve(ReepParams, {})
    started = time.process_time()
    spacing = _row_spacing(params, None, 500e3, 70e3, 2e10, 1)  # a 2e10 s window: 1e16 samples
    assert time.process_time() - started < 1.0
    longest = int(2e10 * 500e3 / 8)
    assert longest - 4096 < spacing <= longest


def test_a_window_no_capture_can_hold_is_refused_by_the_parameter_that_set_it():
    # lam = 1 - 1e-16 is a window of 9e15 samples: named as lam, not as the warm-up it later made too long
    from afmtool.config import resolve
    from afmtool.config.params import ReepParams
    from afmtool.estimators.reep_estimator import ReepEstimator

    params = resolve(ReepParams, {"lam": 0.9999999999999999, "use_input": False})
    with pytest.raises(ConfigError, match=r"^lam=0\.9999999999999999 is 9\.007e\+15 samples"):
        ReepEstimator.build(params, sample_rate_hz=500e3, resonance_hz=70e3, drive_hz=70e3)


def test_the_step_response_of_a_window_too_long_to_simulate_is_left_out_with_a_note():
    # window_us = 1e12 (5e11 samples at 500 kHz): the simulation asked for 55 TiB (a MemoryError)
    from afmtool.analyses import reep as reep_analysis
    from afmtool.config import resolve
    from afmtool.config.params import ReepParams
    from afmtool.estimators.reep_estimator import ReepEstimator, settling_samples

    params = resolve(ReepParams, {"window_us": 1e12, "use_input": False})
    estimator = ReepEstimator.build(params, sample_rate_hz=500e3, resonance_hz=70e3, drive_hz=70e3)
    assert settling_samples(estimator) > reep_analysis._MOST_SETTLING_SAMPLES
    default = ReepEstimator.build(resolve(ReepParams, {"use_input": False}), sample_rate_hz=2e6, resonance_hz=70e3,
                                  drive_hz=70e3)
    assert settling_samples(default) < reep_analysis._MOST_SETTLING_SAMPLES  # the defaults are simulated
