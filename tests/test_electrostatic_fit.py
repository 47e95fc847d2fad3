"""identify electrostatic: eqs. 6.6 and 6.7 by nonlinear least squares, with what the curve cannot identify.

Truth: the ``es-approach`` scenario's probe (Table 6.1, thermal column:
k = 0.13975 N/m, ℓ0 = 1243 nm, K_esf = 1.64991e-21 F·m, α_R = 0.2156,
t_h = 711.75 nm) at V_R = 3 V.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from afmtool import sim
from afmtool.estimators.electrostatic_fit import fit_electrostatic, select_before_snap_in
from afmtool.estimators.identifiability import analyse_identifiability, relative_jacobian
from afmtool.estimators.thermal_sensor import identify_iv, identify_z_curve, separation_from_current
from afmtool.models.thermal_sensor import ResistanceFit
from tests.conftest import run_cli, validate_report
from tests.test_thermal_identify import write_capture

PROBE = sim.scenario_defaults("es-approach")
TRUTH = {
    "l0_m": PROBE.l0_nm * 1e-9,
    "alpha_r": PROBE.alpha_r,
    "tip_height_m": PROBE.tip_height_nm * 1e-9,
    "k_esf_over_k_m3_per_v2": PROBE.k_esf_f_m / PROBE.spring_constant_n_per_m,
    "k_esf_f_m": PROBE.k_esf_f_m,
    "spring_constant_n_per_m": PROBE.spring_constant_n_per_m,
}
QUIET = {"deflection_noise_nm": 0.0, "current_noise_ua": 0.0}


def _region(cap, y):
    region = select_before_snap_in(cap.data["v_sub"], y)
    part = slice(region.start, region.stop)
    ok = np.isfinite(y[part])
    return cap.data["v_sub"][part][ok], y[part][ok], region


def _check(fit, tolerance, label):
    errors = {}
    for name, est in fit.estimates.items():
        if est.status in ("identified", "fixed"):
            errors[name] = est.value / TRUTH[name] - 1
            assert abs(errors[name]) < tolerance, (name, errors[name])
    print(label, {k: f"{100 * v:+.4f} %" for k, v in errors.items()})
    return errors


@pytest.mark.parametrize("noisy, tolerance", [(False, 0.02), (True, 0.05)])
def test_optical_fit_recovers_the_identifiable_parameters(noisy, tolerance):
    cap = sim.simulate("es-approach", {"deflection_noise_nm": 0.5} if noisy else QUIET, seed=11)
    v, y, _ = _region(cap, cap.data["deflection"] * 1e-9)
    fit = fit_electrostatic(v, y, 3.0, sensor="optical")
    errors = _check(fit, tolerance, f"optical, {'noisy' if noisy else 'noise-free'}:")
    assert set(errors) == {"l0_m", "alpha_r", "k_esf_over_k_m3_per_v2"}
    # k and K_esf are reported as not identifiable, with no number, and why
    for name in ("spring_constant_n_per_m", "k_esf_f_m"):
        assert fit.estimates[name].status == "not identifiable" and fit.estimates[name].value is None
    (null,) = fit.identifiability.null_directions
    assert set(null.parameters) == {"spring_constant_n_per_m", "k_esf_f_m"}
    assert null.identifiable_combination == "k_esf_f_m/spring_constant_n_per_m"
    assert null.singular_value < 1e-7 * fit.identifiability.singular_values[0]
    if noisy:  # the stated uncertainties cover the errors
        for name in errors:
            est = fit.estimates[name]
            assert abs(est.value - TRUTH[name]) < 5 * est.std, name


@pytest.mark.parametrize("noisy, tolerance", [(False, 0.02), (True, 0.05)])
def test_a_known_spring_constant_separates_k_esf(noisy, tolerance):
    cap = sim.simulate("es-approach", {"deflection_noise_nm": 0.5} if noisy else QUIET, seed=12)
    v, y, _ = _region(cap, cap.data["deflection"] * 1e-9)
    fit = fit_electrostatic(v, y, 3.0, sensor="optical", spring_constant_n_per_m=PROBE.spring_constant_n_per_m)
    errors = _check(fit, tolerance, f"optical with k given, {'noisy' if noisy else 'noise-free'}:")
    assert "k_esf_f_m" in errors and fit.estimates["spring_constant_n_per_m"].status == "fixed"


def _exact_thermal_separation(cap):
    """t_s from the thermal current through the true g(T) and a fine true K_TP(t_s) table."""
    sensor = PROBE.thermal_sensor()
    g = sensor.resistance
    g_fit = ResistanceFit(g.room_temperature_c, (g.room_resistance_ohm, g.room_resistance_ohm * g.alpha_per_k,
                                                 g.room_resistance_ohm * g.beta_per_k2), g.breakdown_temperature_c)
    table = np.linspace(0.0, 800e-9, 1601)
    return separation_from_current(cap.data["v_r"], cap.data["thermal_current"] * 1e-6, g_fit, table,
                                   sensor.gain.gain(table))


@pytest.mark.parametrize("noisy, tolerance", [(False, 0.02), (True, 0.05)])
def test_thermal_fit_of_eq_6_7_recovers_the_identifiable_parameters(noisy, tolerance):
    cap = sim.simulate("es-approach", {} if noisy else QUIET, seed=13)
    ts = _exact_thermal_separation(cap)
    v, y, region = _region(cap, ts)
    fit = fit_electrostatic(v, y, 3.0, sensor="thermal")
    errors = _check(fit, tolerance, f"thermal (exact calibration), {'noisy' if noisy else 'noise-free'}:")
    assert set(errors) == {"l0_m", "alpha_r", "tip_height_m", "k_esf_over_k_m3_per_v2"}
    assert fit.estimates["k_esf_f_m"].value is None
    assert region.snap_index is not None


def test_thermal_chain_puts_the_snap_in_distance_into_t_h():
    """g(T), K_TP(t_s) identified from the thermal current alone (I-V ramp, z curve), then eq. 6.7.

    The z-curve t_s is counted from the snap-in, which the tip-sample force
    triggers at t_s ≈ d = 65 nm, not 0 (§6.5.2 assumes 0): eq. 6.7 then fits
    t_h too large by that distance, while ℓ0, α_R and K_esf/k stay close.
    """
    iv_cap = sim.simulate("iv-ramp", {}, seed=3)
    iv = identify_iv(iv_cap.data["v_r"], iv_cap.data["thermal_current"] * 1e-6)
    z_cap = sim.simulate("iv-ramp", {"ramp": "z"}, seed=4)
    curve = identify_z_curve(z_cap.data["z_piezo"] * 1e-9, z_cap.data["v_r"], z_cap.data["thermal_current"] * 1e-6,
                             iv.g_fit)
    snap_distance = z_cap.truth["tip_sample_separation_nm"][curve.snap_in_index] * 1e-9
    cap = sim.simulate("es-approach", {}, seed=14)
    ts = separation_from_current(cap.data["v_r"], cap.data["thermal_current"] * 1e-6, iv.g_fit, curve.separation_m,
                                 curve.k_tp_k_per_w)
    v, y, _ = _region(cap, ts)
    fit = fit_electrostatic(v, y, 3.0, sensor="thermal")
    th_shift = fit.estimates["tip_height_m"].value - TRUTH["tip_height_m"]
    others = {n: fit.estimates[n].value / TRUTH[n] - 1 for n in ("l0_m", "alpha_r", "k_esf_over_k_m3_per_v2")}
    print(f"thermal chain: t_h {1e9 * th_shift:+.1f} nm (snap-in at t_s = {1e9 * snap_distance:.1f} nm); "
          + ", ".join(f"{n} {100 * e:+.2f} %" for n, e in others.items()))
    assert th_shift == pytest.approx(snap_distance, abs=10e-9)
    assert all(abs(e) < 0.05 for e in others.values())


def test_identifiability_finds_a_product_and_a_dead_parameter():
    """y = a·b·x + c·x²: only a·b is identifiable; d, which the model ignores, not at all."""
    x = np.linspace(0.0, 1.0, 50)

    def residual(theta):
        a, b, c, d = theta
        return a * b * x + c * x**2 + 0.0 * d

    jac = relative_jacobian(residual, np.array([2.0, 3.0, 0.5, 1.0]), [True, True, True, False])
    ident = analyse_identifiability(jac, ["a", "b", "c", "d"])
    combos = {d.parameters: d.identifiable_combination for d in ident.null_directions}
    assert combos == {("a", "b"): "a*b", ("d",): None}


def test_without_v_r_alpha_r_is_not_identifiable():
    cap = sim.simulate("es-approach", {**QUIET, "v_r_v": 0.0}, seed=15)
    v, y, _ = _region(cap, cap.data["deflection"] * 1e-9)
    fit = fit_electrostatic(v, y, 0.0, sensor="optical")
    assert fit.estimates["alpha_r"].status == "not identifiable"
    assert fit.estimates["l0_m"].value == pytest.approx(TRUTH["l0_m"], rel=1e-6)


def test_region_before_snap_in():
    cap = sim.simulate("es-approach", QUIET, seed=16)
    p = cap.truth["deflection_clean"]
    region = select_before_snap_in(cap.data["v_sub"], cap.data["deflection"])
    true_snap = int(np.argmax(np.abs(np.diff(p[: cap.n_samples // 2]))))
    assert region.snap_index == true_snap
    assert cap.data["v_sub"][region.stop - 1] <= 0.95 * cap.data["v_sub"][true_snap] + 1e-9
    assert np.all(cap.truth["contact"][: region.stop] == 0)


def test_identify_electrostatic_command(tmp_path):
    capture = tmp_path / "es.h5"
    write_capture(sim.simulate("es-approach", {}, seed=17), capture)
    out = tmp_path / "es"
    result = run_cli("identify", "electrostatic", capture, "--out", out, "--json", "-q")
    assert result.returncode == 0, result.stderr.decode()
    report = json.loads(result.stdout)
    validate_report(report)
    res = report["results"]
    assert res["sensor"] == "optical" and res["thesis_equation"] == "6.6"
    assert res["parameters"]["spring_constant_n_per_m"]["value"] is None
    assert "K_esf/k" in res["parameters"]["k_esf_f_m"]["note"]
    assert res["parameters"]["l0_m"]["value"] == pytest.approx(TRUTH["l0_m"], rel=0.02)
    (null,) = res["identifiability"]["non_identifiable"]
    assert null["identifiable_combination"] == "k_esf_f_m/spring_constant_n_per_m"
    for name in ("electrostatic.json", "fit.csv", "electrostatic_fit.png"):
        assert (out / name).is_file()
    given = run_cli("identify", "electrostatic", capture, "--spring-constant", "0.13975", "--out", tmp_path / "k",
                    "--json", "-q")
    assert given.returncode == 0, given.stderr.decode()
    k_esf = json.loads(given.stdout)["results"]["parameters"]["k_esf_f_m"]
    assert k_esf["value"] == pytest.approx(TRUTH["k_esf_f_m"], rel=0.02) and k_esf["status"] == "identified"
    thermal = run_cli("identify", "electrostatic", capture, "--sensor", "thermal", "--out", tmp_path / "t")
    assert thermal.returncode == 2 and "--thermal-model" in thermal.stderr.decode()


def test_a_region_reaching_into_contact_is_flagged_as_a_misfit():
    cap = sim.simulate("es-approach", {}, seed=18)
    y = cap.data["deflection"] * 1e-9
    v, yy, region = _region(cap, y)
    good = fit_electrostatic(v, yy, 3.0, sensor="optical")
    leg = slice(0, region.turn_index + 1)  # the whole approach, contact included
    bad = fit_electrostatic(cap.data["v_sub"][leg], y[leg], 3.0, sensor="optical")
    print(f"lag-1 residual autocorrelation: before snap-in {good.residual_autocorrelation:.3f}, "
          f"with contact {bad.residual_autocorrelation:.3f}")
    assert good.residual_autocorrelation < 0.2 < 0.5 < bad.residual_autocorrelation
