"""Tests of the simulator: models, excitations, programs, the two scenarios and the registry.

Every random test is seeded; tolerances are written where they are used.
"""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from scipy import signal

from afmtool.errors import ConfigError
from afmtool.io.metadata import validate_metadata
from afmtool.models.cantilever import Cantilever
from afmtool.models.discretisation import discrete_denominator, resonance_from_denominator, zoh_numerator
from afmtool.models.forces import THESIS_FORCE_SETS, PiecewiseLinearForce, force_per_mass
from afmtool.sim import (
    SimulatedCapture,
    param,
    register_scenario,
    scenario_defaults,
    scenario_names,
    scenario_parameters,
    simulate,
)
from afmtool.sim.excitation import LinearChirp, SteppedSine, three_sine
from afmtool.sim.ltv import ltv_recursion, parameter_profile
from afmtool.sim.separation import ForceCurve, LineScan
from afmtool.sim.tapping import integrate_rk4

FS = 500e3


def _lockin(y: np.ndarray, g: np.ndarray, f_hz: float, fs: float, start: int, periods: int):
    """Complex amplitude of y and of g at f over an integer number of periods from sample ``start``.

    Least squares on [cos, sin, 1] over the window (exact for a pure tone
    even when a period is not an integer number of samples).
    """
    n = int(round(periods * fs / f_hz))
    t = np.arange(start, start + n) / fs
    basis = np.column_stack((np.cos(2 * np.pi * f_hz * t), np.sin(2 * np.pi * f_hz * t), np.ones(n)))

    def phasor(x):
        c, s, _ = np.linalg.lstsq(basis, x[start : start + n], rcond=None)[0]
        return complex(c, -s)  # x = Re{X e^{jωt}}

    return phasor(y), phasor(g)


# ----------------------------------------------------------------------------- models


def test_cantilever_response_at_resonance():
    lever = Cantilever(80318.0, 168.0)
    h = complex(lever.frequency_response(80318.0))
    assert abs(h) == pytest.approx(168.0, rel=1e-12)
    assert np.angle(h) == pytest.approx(-np.pi / 2, abs=1e-12)
    assert complex(lever.frequency_response(0.0)) == pytest.approx(1.0)
    with pytest.raises(ConfigError, match="q=-1"):
        Cantilever(80e3, -1)


@pytest.mark.parametrize(("f0", "q"), [(70e3, 200.0), (80318.0, 38.0), (57185.0, 1.0148), (150e3, 3.2)])
def test_discretisation_matches_cont2discrete(f0, q):
    lever = Cantilever(f0, q)
    num_d, den_d, _ = signal.cont2discrete(lever.tf_coefficients(), 1 / FS, method="zoh")
    b1, b0 = discrete_denominator(f0, q, FS)
    a2, a1, a0 = zoh_numerator(f0, q, FS)
    # closed forms agree with scipy's matrix-exponential ZOH to 1e-12 (absolute, coefficients are O(1))
    np.testing.assert_allclose(den_d, [1.0, b1, b0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.ravel(num_d), [a2, a1, a0], rtol=0, atol=1e-12)
    # eq. 3.48 inverts the pole map (relative 1e-10)
    back = resonance_from_denominator(b1, b0, FS)
    assert back.valid
    assert back.f0_hz == pytest.approx(f0, rel=1e-10)
    assert back.q == pytest.approx(q, rel=1e-10)


def test_resonance_from_denominator_flags_invalid():
    out = resonance_from_denominator(np.array([-1.9, 0.5, -2.5]), np.array([0.99, 1.2, 0.9]), FS)
    assert out.valid.tolist() == [True, False, False]
    assert np.isnan(out.f0_hz[1:]).all() and np.isnan(out.q[1:]).all()


def test_discretisation_rejects_bad_arguments():
    with pytest.raises(ConfigError, match="q=0.4"):
        discrete_denominator(70e3, 0.4, FS)
    with pytest.raises(ConfigError, match="f0_hz=300000"):
        zoh_numerator(300000.0, 100.0, FS)


def test_force_signs():
    d, wa2, wb2, ca, cb = 4.0, (0.31e6) ** 2, (3.03e6) ** 2, 0.042e6, 1e5
    l = 10.0
    # far from the surface: zero, whatever the velocity
    assert force_per_mass(5.0, 1e6, l, d, wa2, wb2, ca, cb) == 0.0
    assert force_per_mass(-5.9, -1e6, l, d, wa2, wb2, ca, cb) == 0.0  # t_s = 4.1 > d
    # attractive zone (0 <= t_s < d), at rest: negative (toward the sample), = -wa2 (d - t_s)
    f_att = force_per_mass(-8.0, 0.0, l, d, wa2, wb2, ca, cb)
    assert f_att < 0
    assert f_att == pytest.approx(-wa2 * (d - 2.0))
    # repulsive zone (t_s < 0), at rest, with wb2 > wa2: positive (away from the sample)
    f_rep = force_per_mass(-11.0, 0.0, l, d, wa2, wb2, ca, cb)
    assert f_rep > 0
    assert f_rep == pytest.approx(-wa2 * (d + 1.0) + wb2 * 1.0)
    # damping opposes velocity in both zones
    for p in (-8.0, -11.0):
        up = force_per_mass(p, 1e4, l, d, wa2, wb2, ca, cb) - force_per_mass(p, 0.0, l, d, wa2, wb2, ca, cb)
        down = force_per_mass(p, -1e4, l, d, wa2, wb2, ca, cb) - force_per_mass(p, 0.0, l, d, wa2, wb2, ca, cb)
        assert up < 0 < down
    assert force_per_mass(-11.0, 1.0, l, d, wa2, wb2, ca, cb) - force_per_mass(
        -11.0, 0.0, l, d, wa2, wb2, ca, cb
    ) == pytest.approx(-(ca + cb))
    # conservative part is continuous at t_s = d and t_s = 0 (relative 1e-9)
    for ts in (d, 0.0):
        lo = force_per_mass(ts - l - 1e-9, 0.0, l, d, wa2, wb2, ca, cb)
        hi = force_per_mass(ts - l + 1e-9, 0.0, l, d, wa2, wb2, ca, cb)
        assert abs(lo - hi) <= 2.1e-9 * (wa2 + wb2)  # the slopes times the 2e-9 nm step
    # the vectorised form agrees with the scalar one
    force = PiecewiseLinearForce(d, wa2, wb2, ca, cb)
    ps = np.linspace(-15, 0, 31)
    vs = np.linspace(-1e5, 1e5, 31)
    expected = [force_per_mass(p, v, l, d, wa2, wb2, ca, cb) for p, v in zip(ps, vs)]
    np.testing.assert_allclose(force(ps, vs, l), expected, rtol=1e-15, atol=0)


def test_thesis_force_sets():
    assert set(THESIS_FORCE_SETS) == {"attractive", "attractive-repulsive", "repulsive", "repulsive-q38", "ch4-default"}
    ch4 = THESIS_FORCE_SETS["ch4-default"]
    assert (ch4.d_nm, ch4.omega_a2, ch4.omega_b2, ch4.c_a, ch4.c_b) == pytest.approx(
        (1.65, 0.18e6**2, 4.03e6**2, 0.042e6, 1.45e6)
    )
    with pytest.raises(ConfigError, match="c_a=-1"):
        PiecewiseLinearForce(1.0, 1.0, 1.0, -1, 0.0)


# ----------------------------------------------------------------------------- excitations and programs


def test_three_sine_lines():
    exc = three_sine(0.1, 70e3, 6e3, 0.5)
    assert exc.frequencies_hz == (70e3, 76e3, 64e3)
    assert exc.amplitudes == pytest.approx((0.1, 0.05, 0.05))
    with pytest.raises(ConfigError, match="sideband_offset_hz=80000"):
        three_sine(0.1, 70e3, 80e3)


def test_chirp_and_stepped_sine_are_continuous():
    t = np.arange(0, 0.01, 1 / 20e6)  # 20 MHz: consecutive samples differ by < 2π·f·dt·A
    for exc in (LinearChirp(1.0, 50e3, 90e3, 0.008, 0.001), SteppedSine(1.0, (50e3, 60e3, 70e3), 0.003, 0.0005)):
        jump = np.max(np.abs(np.diff(exc(t))))
        assert jump < 2 * np.pi * 90e3 / 20e6 * 1.01
    chirp = LinearChirp(1.0, 50e3, 90e3, 0.008, 0.001)
    inst = np.gradient(chirp.phase_rad(t), t) / (2 * np.pi)
    assert inst[int(0.005 * 20e6)] == pytest.approx(70e3, rel=1e-6)  # halfway through the sweep
    segs = SteppedSine(1.0, (50e3, 60e3), 0.002, 0.001).segments()
    assert segs == [
        {"start_s": 0.001, "end_s": 0.003, "frequency_hz": 50e3},
        {"start_s": 0.003, "end_s": 0.005, "frequency_hz": 60e3},
    ]


def test_force_curve_program():
    fc = ForceCurve(40.0, 5.0, free_air_s=0.01, approach_s=0.02, retract_s=0.02)
    t = np.array([0.0, 0.01, 0.02, 0.03, 0.04, 0.05, 0.06])
    s = fc.sample(t)
    np.testing.assert_allclose(s.separation_nm, [40, 40, 22.5, 5, 22.5, 40, 40])
    np.testing.assert_allclose(s.z_piezo_nm, s.separation_nm - 40.0)
    assert s.direction.tolist() == [0, -1, -1, 1, 1, 0, 0]


def test_line_scan_program():
    x = np.linspace(0, 1e-6, 11)
    h = np.where((x > 0.3e-6) & (x < 0.7e-6), 5.0, 0.0)
    scan = LineScan(30.0, x, h, scan_start_s=0.001, scan_duration_s=0.01)
    np.testing.assert_allclose(scan(np.array([0.0, 0.001, 0.006, 0.011, 0.5])), [30, 30, 25, 30, 30])


# ----------------------------------------------------------------------------- tapping


def _naive_rk4(g_half, l_half, eta, nsub, fs, lever, force, p, v):
    """Plain-Python RK4 of p'' + (w0/Q)p' + w0²p = w0²g + F + eta (reference for the kernel)."""
    w0 = lever.omega0_rad_s
    h = 1 / (fs * nsub)
    out = []

    def acc(p, v, g, l, e):
        return w0 * w0 * (g - p) - w0 / lever.q * v + force_per_mass(p, v, l, *force.as_args()) + e

    for i in range(len(eta)):
        out.append(p)
        for k in range(nsub):
            j = 2 * nsub * i + 2 * k
            k1p, k1v = v, acc(p, v, g_half[j], l_half[j], eta[i])
            k2p, k2v = v + h / 2 * k1v, acc(p + h / 2 * k1p, v + h / 2 * k1v, g_half[j + 1], l_half[j + 1], eta[i])
            k3p, k3v = v + h / 2 * k2v, acc(p + h / 2 * k2p, v + h / 2 * k2v, g_half[j + 1], l_half[j + 1], eta[i])
            k4p, k4v = v + h * k3v, acc(p + h * k3p, v + h * k3v, g_half[j + 2], l_half[j + 2], eta[i])
            p = p + h / 6 * (k1p + 2 * k2p + 2 * k3p + k4p)
            v = v + h / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
    return np.array(out), p, v


def test_rk4_kernel_matches_naive_reference():
    rng = np.random.default_rng(1)
    n, nsub = 300, 4
    lever = Cantilever(80318.0, 168.0)
    force = THESIS_FORCE_SETS["ch4-default"]
    t_half = np.arange(2 * nsub * n + 1) / (2 * nsub * FS)
    g_half = 0.15 * np.sin(2 * np.pi * 80318.0 * t_half)
    l_half = np.linspace(25.0, 0.0, t_half.size)
    eta = 1e9 * rng.standard_normal(n)
    got = integrate_rk4(g_half, l_half, eta, substeps=nsub, sample_rate_hz=FS, cantilever=lever, force=force,
                        p0_nm=20.0, v0_nm_per_s=0.0)
    ref, p_end, v_end = _naive_rk4(g_half, l_half, eta, nsub, FS, lever, force, 20.0, 0.0)
    assert got.contact.any()
    # identical arithmetic up to evaluation order: 1e-11 relative to the 25 nm scale
    np.testing.assert_allclose(got.deflection_nm, ref, rtol=0, atol=25e-11)
    assert got.p_end_nm == pytest.approx(p_end, abs=25e-11)


@pytest.mark.parametrize(
    ("offset_hz", "initial_state"),
    [(0.0, "rest"), (-1000.0, "steady"), (15000.0, "steady")],
)
def test_tapping_off_sample_matches_analytic_response(offset_hz, initial_state):
    """Steady-state amplitude within 0.5 % of |G|, phase within 0.5° of ∠G (absolute)."""
    params = {
        "program": "constant",
        "separation_nm": 1000.0,  # far beyond amplitude + d: off-sample
        "drive": "sine",
        "drive_offset_hz": offset_hz,
        "duration_s": 0.03,
        "initial_state": initial_state,
    }
    cap = simulate("tapping", params, seed=3)
    assert not cap.truth["contact"].any()
    assert cap.metadata["free_air"] == {"start_s": 0.0, "end_s": 0.03}
    lever = Cantilever(80318.0, 168.0)
    f = 80318.0 + offset_hz
    # start after 10 decay times 2Q/ω0 (6.7 ms), average over 1000 periods (12.5 ms)
    start = int(10 * lever.time_constant_s * FS)
    y, g = _lockin(cap.data["deflection"], cap.data["dither"], f, FS, start, periods=1000)
    expected = complex(lever.frequency_response(f))
    ratio = y / g
    assert abs(ratio) == pytest.approx(abs(expected), rel=5e-3)
    assert math.degrees(abs(np.angle(ratio / expected))) < 0.5
    if offset_hz == 0.0:
        assert abs(y) == pytest.approx(25.0, rel=5e-3)  # amplitude_nm default


def test_thermal_noise_obeys_equipartition():
    """Undriven, off-sample: std of p within 10 % of sqrt(k_B·T/k) (about 540 decay times averaged)."""
    cap = simulate("tapping", {"program": "constant", "separation_nm": 1000.0, "amplitude_nm": 0.0,
                               "duration_s": 0.4, "measurement_noise_nm": 0.0, "spring_constant_n_per_m": 0.2},
                   seed=1)
    p = cap.truth["deflection_clean"][20000:]
    assert np.std(p) == pytest.approx(math.sqrt(1.380649e-23 * 300.0 / 0.2) * 1e9, rel=0.1)


def test_tapping_chunking_does_not_change_the_result():
    from afmtool.sim.tapping import TappingParams, simulate_tapping

    params = TappingParams(duration_s=0.004, program="force-curve", separation_nm=30.0, turn_separation_nm=0.0,
                           free_air_fraction=0.25)
    whole = simulate_tapping(params, 5, chunk_samples=10_000)
    pieces = simulate_tapping(params, 5, chunk_samples=333)
    for name in whole.data:
        np.testing.assert_array_equal(whole.data[name], pieces.data[name])
    for name in whole.truth:
        np.testing.assert_array_equal(whole.truth[name], pieces.truth[name])


def test_force_curve_contact_truth():
    cap = simulate("tapping", {"duration_s": 0.02, "free_air_fraction": 0.2, "separation_nm": 40.0,
                               "turn_separation_nm": 0.0}, seed=0)
    truth = cap.truth
    assert cap.channel_names == ("dither", "deflection", "z_piezo")
    sep = truth["separation_nm"]
    np.testing.assert_allclose(cap.data["z_piezo"], sep - sep[0], atol=1e-12)
    assert cap.data["z_piezo"].min() == pytest.approx(-40.0, abs=0.01)
    assert truth["contact"].dtype == np.uint8
    # off-sample segment: no contact; near the turn (l < 2 nm, below d = 4 nm, amplitude collapsed):
    # contact in every sample period; at l > 30 nm (beyond amplitude + d) on either ramp: none
    free = int(0.004 * FS)
    assert not truth["contact"][:free].any()
    assert truth["contact"][sep < 2.0].all()
    assert not truth["contact"][sep > 30.0].any()
    assert cap.metadata["free_air"] == {"start_s": 0.0, "end_s": 0.004}
    # contact means t_s = p + l < d at some point of the period; at the sample instants this is a subset
    d = THESIS_FORCE_SETS["attractive"].d_nm
    inside = truth["deflection_clean"] + sep < d
    assert truth["contact"][inside].all()
    assert set(np.unique(truth["ramp_direction"])) == {-1, 0, 1}
    validate_metadata(json.loads(json.dumps(dict(cap.metadata))))


def test_tapping_other_programs_and_drives():
    steps = simulate("tapping", {"duration_s": 0.004, "program": "steps", "step_levels_nm": [40, 10],
                                 "drive": "stepped", "sweep_steps": 4}, seed=0)
    # the piezo moves the sample by the steps, so the steps program records z as a force curve does
    assert steps.data["z_piezo"][0] == 0.0 and set(np.unique(steps.data["z_piezo"])) == {0.0, -30.0}
    assert steps.metadata["free_air"] == {"start_s": 0.0, "end_s": 0.002}
    assert len(steps.metadata["segments"]) == 4
    scan = simulate("tapping", {"duration_s": 0.004, "program": "line-scan", "free_air_fraction": 0.25,
                                "drive": "chirp"}, seed=0)
    assert scan.truth["topography_nm"].max() == pytest.approx(5.0)
    for cap in (steps, scan):
        validate_metadata(json.loads(json.dumps(dict(cap.metadata))))


# ----------------------------------------------------------------------------- ltv


def test_ltv_constant_equals_exact_zoh_solution():
    cap = simulate("ltv", {"step_f0_hz": 70000.0, "step_q": 200.0, "initial_state": "rest", "duration_s": 0.01,
                           "drive_hold": "zoh"})
    assert cap.metadata["free_air"] == {"start_s": 0.0, "end_s": 0.01}
    lever = Cantilever(70000.0, 200.0)
    num, den, _ = signal.cont2discrete(lever.tf_coefficients(), 1 / FS, method="zoh")
    expected = signal.lfilter(np.ravel(num), den, cap.data["dither"])
    clean = cap.truth["deflection_clean"]
    # relative to the signal scale: 1e-9
    np.testing.assert_allclose(clean, expected, rtol=0, atol=1e-9 * np.max(np.abs(expected)))
    # the recorded deflection carries 0.05 nm rms white noise (±5 % on the estimate from 5000 samples)
    assert np.std(cap.data["deflection"] - clean) == pytest.approx(0.05, rel=0.05)


def test_ltv_steady_start_equals_long_preroll():
    params = {"step_f0_hz": 70000.0, "step_q": 200.0, "duration_s": 0.004, "measurement_noise_nm": 0.0,
              "drive_hold": "zoh"}
    cap = simulate("ltv", params)
    # from rest 40 ms earlier: the transient has decayed by e^-44
    pre = 20000
    exc, _, _ = dataclasses.replace(scenario_defaults("ltv"), drive_hold="zoh").dither()
    g = exc((np.arange(pre + cap.n_samples) - pre) / FS)
    lever = Cantilever(70000.0, 200.0)
    num, den, _ = signal.cont2discrete(lever.tf_coefficients(), 1 / FS, method="zoh")
    expected = signal.lfilter(np.ravel(num), den, g)[pre:]
    np.testing.assert_allclose(cap.truth["deflection_clean"], expected, rtol=0, atol=1e-9 * 25)
    envelope = np.max(np.abs(expected))
    assert 24.0 < envelope < 27.0  # about 25 nm plus the ±1 nm three-sine beat


def test_ltv_step_truth_and_recursion():
    cap = simulate("ltv", {"duration_s": 0.01, "step_time_s": 0.004, "step_f0_hz": 69500.0, "step_q": 120.0})
    truth = cap.truth
    k = int(0.004 * FS)
    assert np.all(truth["f0_hz"][:k] == 70000.0) and np.all(truth["f0_hz"][k:] == 69500.0)
    assert np.all(truth["q"][:k] == 200.0) and np.all(truth["q"][k:] == 120.0)
    b1, b0 = discrete_denominator(truth["f0_hz"], truth["q"], FS)
    np.testing.assert_array_equal(truth["b1"], b1)
    np.testing.assert_array_equal(truth["b0"], b0)
    assert cap.metadata["free_air"] == {"start_s": 0.0, "end_s": 0.004}
    # the numba recursion equals a plain-Python loop (1e-12 relative to 25 nm)
    rng = np.random.default_rng(0)
    u = rng.standard_normal(500)
    bb1 = np.linspace(-1.2, -1.3, 500)
    bb0 = np.linspace(0.99, 0.98, 500)
    got = ltv_recursion(u, bb1, bb0, 0.3, -0.2)
    p1, p2, ref = 0.3, -0.2, []
    for n in range(500):
        p = u[n] - bb1[n] * p1 - bb0[n] * p2
        ref.append(p)
        p1, p2 = p, p1
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12 * 25)
    # and the constant-coefficient (lfilter) path equals the kernel path
    const = ltv_recursion(u, np.full(500, -1.2), np.full(500, 0.99), 0.3, -0.2)
    from afmtool.sim.ltv import _ltv_kernel

    np.testing.assert_allclose(const, _ltv_kernel(u, np.full(500, -1.2), np.full(500, 0.99), 0.3, -0.2,
                                                  np.empty(500)), rtol=0, atol=1e-12)


def test_ltv_ramp_truth():
    cap = simulate("ltv", {"duration_s": 0.01, "step_time_s": 0.002, "ramp_s": 0.004, "measurement_noise_nm": 0.0})
    f0 = cap.truth["f0_hz"]
    k0, k1 = int(0.002 * FS), int(0.006 * FS)
    assert np.all(f0[:k0 + 1] == 70000.0) and np.all(f0[k1:] == 69800.0)
    assert np.all(np.diff(f0[k0:k1 + 1]) < 0)  # strictly decreasing along the ramp
    assert f0[int(0.004 * FS)] == pytest.approx(69900.0)


def test_parameter_profile_ramps_and_repeats():
    t = np.array([0.0, 1.0, 1.5, 2.0, 3.0, 3.5, 4.0, 5.5])
    s = parameter_profile(t, step_time_s=1.0, ramp_s=1.0, step_repeat_s=2.0)
    np.testing.assert_allclose(s, [0, 0, 0.5, 1, 1, 0.5, 0, 0.5])


# ----------------------------------------------------------------------------- registry and determinism


@pytest.mark.parametrize("name", ["tapping", "ltv"])
def test_determinism_by_seed(name):
    short = {"duration_s": 0.002}
    a = simulate(name, short, seed=7)
    b = simulate(name, short, seed=7)
    c = simulate(name, short, seed=8)
    for key in a.data:
        np.testing.assert_array_equal(a.data[key], b.data[key])
    assert not np.array_equal(a.data["deflection"], c.data["deflection"])
    assert a.metadata["seed"] == 7 and a.metadata["scenario"] == name
    validate_metadata(json.loads(json.dumps(dict(a.metadata))))
    assert isinstance(a, SimulatedCapture)


def test_simulate_rejects_bad_parameters():
    with pytest.raises(ConfigError, match=r"unknown parameter 'durration_s'=1"):
        simulate("tapping", {"durration_s": 1})
    with pytest.raises(ConfigError, match=r"q=-3"):
        simulate("ltv", {"q": -3})
    with pytest.raises(ConfigError, match=r"duration_s='long'"):
        simulate("ltv", {"duration_s": "long"})
    with pytest.raises(ConfigError, match=r"program='spiral'"):
        simulate("tapping", {"program": "spiral"})
    with pytest.raises(ConfigError, match=r"substeps=2.5"):
        simulate("tapping", {"substeps": 2.5})
    with pytest.raises(ConfigError, match=r"d_nm=2.0 is only used with force_set='custom'"):
        simulate("tapping", {"d_nm": 2.0})
    with pytest.raises(ConfigError, match=r"unknown scenario 'tap'"):
        simulate("tap")
    with pytest.raises(ConfigError, match=r"seed=-1"):
        simulate("ltv", seed=-1)


def test_registry_is_open_and_describes_parameters(monkeypatch):
    import afmtool.sim

    monkeypatch.setattr(afmtool.sim, "_REGISTRY", dict(afmtool.sim._REGISTRY))  # leave no test scenario behind
    assert {"tapping", "ltv"} <= set(scenario_names())
    for name in ("tapping", "ltv"):
        for info in scenario_parameters(name):
            assert info.help and info.type in ("float", "int", "bool", "str", "tuple[float, ...]")
    assert scenario_defaults("ltv").f0_hz == 70000.0

    @dataclasses.dataclass(frozen=True)
    class _Params:
        level: float = param(1.0, "a level", "nm")

    def _run(params, seed):
        x = np.full(4, params.level)
        return SimulatedCapture(1.0, (), {}, {}, {"x": x})

    register_scenario("test-constant", _Params, _run)
    assert "test-constant" in scenario_names()
    assert simulate("test-constant", {"level": 2}).metadata["parameters"] == {"level": 2.0}
    with pytest.raises(ValueError, match="already registered"):
        register_scenario("test-constant", _Params, _run)
