"""Chapter-6 models and simulator pieces: the thermal sensor (eqs. 6.8-6.12), eqs. 6.6/6.7/6.14, the scenarios."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from afmtool import sim
from afmtool.errors import ConfigError
from afmtool.models.electrostatic import (
    ElectrostaticParams,
    electrostatic_force_n,
    linearise_actuation,
    pull_in_voltage_v,
    stable_deflection_m,
    static_deflection_polynomial,
    thermal_separation_polynomial,
)
from afmtool.models.thermal_sensor import (
    DiffusionLowPass,
    ResistanceFit,
    ThermalSensor,
    c_from_gamma_ir_vr,
    gamma_ir_ts,
    gamma_ir_vr,
    h_from_gammas,
    operating_point,
    steady_state,
)
from afmtool.sim.sweeps import RepeatedChirp, log_stepped_sine

PARAMS = ElectrostaticParams(0.13975, 1.64991e-21, 0.2156, 1243e-9, 711.75e-9)
F = np.logspace(1, 6, 61)


# ----------------------------------------------------------------------------- thermal sensor


def test_steady_state_solves_the_balance_and_breaks_down_at_t_k():
    sensor = ThermalSensor()
    v = np.linspace(0.1, 3.6, 200)
    for ts in (0.0, 100e-9, 2e-6):
        st = steady_state(sensor, v, ts)
        # T − T_r = K_TP(t_s)·V²/g(T)
        balance = st.temperature_c - 25.0 - st.k_tp_k_per_w * v**2 / sensor.resistance.resistance(st.temperature_c)
        assert np.max(np.abs(balance)) < 1e-9
        np.testing.assert_allclose(st.current_a, v / st.resistance_ohm)
    # the knee: T = T_k exactly where K_TP·V² = g(T_k)·ΔT_k
    g = sensor.resistance
    v_k = math.sqrt(g.breakdown_resistance_ohm * g.breakdown_rise_k / sensor.gain.gain(2e-6))
    assert float(steady_state(sensor, v_k, 2e-6).temperature_c) == pytest.approx(550.0, abs=1e-6)


def test_small_signal_equations_6_9_to_6_12_invert_each_other():
    sensor = ThermalSensor()
    op = operating_point(sensor, 3.0, 100e-9)
    d = sensor.dynamics.response(F)
    c = op.k_tp_k_per_w * d
    h = op.power_w * op.dk_tp_dts_k_per_w_m * d
    g_vr = gamma_ir_vr(c, op)
    g_ts = gamma_ir_ts(h, c, op)
    args = (op.current_a, op.resistance_ohm, op.dg_dt_ohm_per_k)
    np.testing.assert_allclose(c_from_gamma_ir_vr(g_vr, *args), c, rtol=1e-10)  # eq. 6.11
    np.testing.assert_allclose(h_from_gammas(g_ts, g_vr, *args), h, rtol=1e-10)  # eq. 6.12


def test_small_signal_matches_the_large_signal_model_at_dc():
    """ΔI/ΔV_R and ΔI/Δt_s of eqs. 6.9 and 6.10 at DC are the slopes of the quasi-static I(V_R, t_s)."""
    sensor = ThermalSensor()
    op = operating_point(sensor, 3.0, 100e-9)
    dv, dt = 1e-6, 1e-12
    di_dv = (steady_state(sensor, 3.0 + dv, 100e-9).current_a - steady_state(sensor, 3.0 - dv, 100e-9).current_a) / (2 * dv)
    di_dt = (steady_state(sensor, 3.0, 100e-9 + dt).current_a - steady_state(sensor, 3.0, 100e-9 - dt).current_a) / (2 * dt)
    c0, h0 = op.k_tp_k_per_w, op.power_w * op.dk_tp_dts_k_per_w_m
    assert float(gamma_ir_vr(c0, op)) == pytest.approx(float(di_dv), rel=1e-5)
    assert float(gamma_ir_ts(h0, c0, op)) == pytest.approx(float(di_dt), rel=1e-4)


def test_diffusion_low_pass_rolls_off_at_10_db_per_decade():
    d = DiffusionLowPass(corner_hz=5400.0)
    assert abs(d.response(np.array([0.0]))[0]) == pytest.approx(1.0)
    f = np.logspace(np.log10(20e3), np.log10(1e6), 400)
    slope = np.polyfit(np.log10(f), 20 * np.log10(np.abs(d.response(f))), 1)[0]
    assert slope == pytest.approx(-10.0, abs=0.5)
    num, den = d.tf()
    s = 2j * np.pi * f
    np.testing.assert_allclose(np.polyval(num, s) / np.polyval(den, s), d.response(f), rtol=1e-9)


def test_resistance_fit_inverse_and_refusals():
    g = ResistanceFit(25.0, (1200.0, 1.8, 2.04e-3), 550.0)
    t = np.array([25.0, 100.0, 549.0])
    np.testing.assert_allclose(g.temperature(g.resistance(t)), t, atol=1e-9)
    assert np.isnan(g.temperature(np.array([100.0]))).all()
    assert ResistanceFit.from_dict(g.to_dict()) == g
    with pytest.raises(ConfigError, match="does not increase"):
        ResistanceFit(25.0, (1200.0, -1.0), 550.0)
    with pytest.raises(ConfigError, match="max_temperature_c"):
        ResistanceFit(25.0, (1200.0, 1.0), 20.0)


# ----------------------------------------------------------------------------- electrostatics


def test_stable_deflection_solves_eq_6_6_up_to_pull_in():
    ratio = PARAMS.k_esf_f_m / PARAMS.spring_constant_n_per_m
    v_pi = pull_in_voltage_v(ratio, PARAMS.l0_m)
    v = np.linspace(0.0, 0.999 * v_pi, 50)
    p = stable_deflection_m(v, ratio, PARAMS.l0_m)
    scale = PARAMS.spring_constant_n_per_m * PARAMS.l0_m**3
    assert np.max(np.abs(static_deflection_polynomial(p, v, PARAMS))) < 1e-12 * scale
    assert np.all((p <= 0) & (p > -PARAMS.l0_m / 3))
    # at pull-in p = −ℓ0/3; beyond it no root
    assert float(stable_deflection_m(v_pi, ratio, PARAMS.l0_m)) == pytest.approx(-PARAMS.l0_m / 3, rel=1e-4)
    assert np.isnan(stable_deflection_m(1.001 * v_pi, ratio, PARAMS.l0_m))
    # eq. 6.7 is the same balance in t_s = ℓ0 + p − t_h
    ts = PARAMS.l0_m + p - PARAMS.tip_height_m
    assert np.max(np.abs(thermal_separation_polynomial(ts, v, PARAMS))) < 1e-12 * scale


def test_linearised_actuation_matches_numerical_derivatives():
    """Eq. 6.14 (corrected): κ, ω′, Q′ and L from finite differences of eq. 6.4."""
    v0, lever = -1.35, 811.75e-9
    small = linearise_actuation(PARAMS, 51858.0, 2.3715, v0, lever)
    k = PARAMS.spring_constant_n_per_m
    dp, dv = 1e-12, 1e-6
    # ℓ_s = ℓ0 + p − z: move p about the point where ℓ_s = lever
    p0 = lever - PARAMS.l0_m
    df_dp = (electrostatic_force_n(p0 + dp, v0, PARAMS) - electrostatic_force_n(p0 - dp, v0, PARAMS)) / (2 * dp)
    df_dv = (electrostatic_force_n(p0, v0 + dv, PARAMS) - electrostatic_force_n(p0, v0 - dv, PARAMS)) / (2 * dv)
    kappa = float(df_dp) / k
    assert small.stiffness_ratio == pytest.approx(kappa, rel=1e-6)
    assert small.gain_m_per_v == pytest.approx(float(df_dv) / (k * (1 - kappa)), rel=1e-6)
    assert small.f0_hz == pytest.approx(51858.0 * math.sqrt(1 - kappa))
    assert small.q == pytest.approx(2.3715 * math.sqrt(1 - kappa))
    # the response: DC gain L, and the denominator s² + (ω′/Q′)s + ω′² (docs/conventions.md fix)
    assert small.response(np.array([0.0]))[0] == pytest.approx(small.gain_m_per_v)
    assert abs(small.response(np.array([small.f0_hz]))[0]) == pytest.approx(abs(small.gain_m_per_v) * small.q)
    with pytest.raises(ConfigError, match="past snap-in"):
        linearise_actuation(PARAMS, 51858.0, 2.3715, -10.0, lever)


# ----------------------------------------------------------------------------- scenarios


def test_thermal_sweep_model_zpk_forms_equal_the_formulas():
    model = sim.scenario_defaults("thermal-sweep").model()
    np.testing.assert_allclose(model.ir_ts_zpk().response(F), model.ir_ts(F), rtol=1e-9)
    np.testing.assert_allclose(model.ir_vr_zpk().response(F), model.ir_vr(F), rtol=1e-9)
    # the orders of magnitude of §6.6: ~12 kHz bandwidth, capacitive feed-through (+90°)
    dc = abs(model.ir_ts(np.array([0.0]))[0])
    assert abs(model.ir_ts(np.array([12e3]))[0]) == pytest.approx(dc / math.sqrt(2), rel=0.05)
    assert np.angle(model.feedthrough(np.array([1e3]))[0], deg=True) == pytest.approx(90.0, abs=1.0)


def test_thermal_sweep_simulation_follows_its_model():
    """Noise-free near-sample chirp: the clean signals' response equals the continuous-time truth."""
    from afmtool.estimators.frequency_response import h1_estimate

    cap = sim.simulate("thermal-sweep", {"duration_s": 0.2, "current_noise_ua": 0.0, "deflection_noise_nm": 0.0})
    fs = cap.sample_rate_hz
    model = sim.scenario_defaults("thermal-sweep").model()
    fr = h1_estimate(cap.data["v_sub"], cap.truth["deflection_clean"], fs, nperseg=8192)
    band = (fr.frequency_hz >= 200) & (fr.frequency_hz <= 1e5)
    ratio = fr.response[band] / model.ts_v(fr.frequency_hz[band])
    assert np.max(np.abs(20 * np.log10(np.abs(ratio)))) < 0.05
    assert np.max(np.abs(np.angle(ratio, deg=True))) < 0.5
    assert cap.metadata["operating_point"]["current_a"] == pytest.approx(model.operating_point.current_a)


def test_quasi_static_snap_in_is_the_electrostatic_pull_in_without_tip_force():
    cap = sim.simulate("es-approach", {"attractive_stiffness_n_per_m": 0.0, "deflection_noise_nm": 0.0,
                                       "current_noise_ua": 0.0, "duration_s": 2.0})
    p = cap.truth["deflection_clean"] * 1e-9
    v = cap.data["v_sub"]
    k = int(np.argmax(np.abs(np.diff(p[: v.argmax()]))))
    ratio = PARAMS.k_esf_f_m / PARAMS.spring_constant_n_per_m
    v_pi = pull_in_voltage_v(ratio, PARAMS.l0_m) + PARAMS.alpha_r * 3.0
    assert v[k] == pytest.approx(v_pi, abs=2 * (v[1] - v[0]))
    assert p[k] == pytest.approx(-PARAMS.l0_m / 3, rel=0.02)
    # snap-off later, at a lower V_sub (hysteresis), and back on the free branch at the end
    assert cap.truth["contact"][v.argmax()] == 1.0 and cap.truth["contact"][-1] == 0.0


def test_sweeps_are_phase_continuous():
    steps = log_stepped_sine(1.0, 100.0, 1e5, 10, 0.5, 1e-3)
    assert sum(steps.dwells_s) == pytest.approx(0.5)
    assert steps.frequencies_hz[0] == 100.0 and steps.frequencies_hz[-1] == pytest.approx(1e5)
    low = np.array(steps.dwells_s[:5]) * np.array(steps.frequencies_hz[:5])
    np.testing.assert_allclose(low, low[0])  # equal periods per low step
    for exc, edges in ((steps, [s["end_s"] for s in steps.segments()[:-1]]), (RepeatedChirp(1.0, 50.0, 2e5, 0.01), [0.01, 0.02])):
        for t in edges:
            eps = 1e-10
            jump = exc.phase_rad(np.array([t + eps]))[0] - exc.phase_rad(np.array([t - eps]))[0]
            assert abs(jump) < 1e-3


@pytest.mark.parametrize(
    "name, overrides, message",
    [
        ("thermal-sweep", {"separation_nm": 50.0}, "separation_nm=50.0 must exceed attractive_range_nm"),
        ("thermal-sweep", {"stop_hz": 600e3}, "stop_hz=600000.0 must be below sample_rate_hz/2"),
        ("thermal-sweep", {"v_sub_v": 20.0}, "past snap-in"),
        ("thermal-sweep", {"drive": "noise"}, "drive='noise'"),
        ("iv-ramp", {"ramp": "x"}, "ramp='x'"),
        ("es-approach", {"sample_z_nm": 600.0}, "sample_z_nm=600.0 must leave a gap"),
        ("es-approach", {"intrinsic_exponent": 1.5}, "intrinsic_exponent=1.5"),
    ],
)
def test_scenarios_refuse_bad_parameters(name, overrides, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        sim.simulate(name, overrides)


def test_scenarios_are_deterministic():
    for name in ("thermal-sweep", "iv-ramp", "es-approach"):
        a = sim.simulate(name, {"duration_s": 0.005}, seed=3)
        b = sim.simulate(name, {"duration_s": 0.005}, seed=3)
        for key in a.data:
            np.testing.assert_array_equal(a.data[key], b.data[key])
    assert dataclasses.is_dataclass(sim.scenario_defaults("iv-ramp"))
