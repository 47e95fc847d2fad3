"""identify thermal: g(T) and K_TP from an I-V ramp, K_TP(t_s) from a z curve, C(jω) and H(jω) (§6.5.2, §6.6.2).

Truth: the ``iv-ramp`` and ``thermal-sweep`` scenarios' thermal sensor
(:meth:`afmtool.sim.probe.ProbeParams.thermal_sensor`).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from afmtool import sim
from afmtool.errors import InputError
from afmtool.estimators.sensing_gamma import auto_nperseg, combine_gamma, responses_from_chunks, scale_response
from afmtool.estimators.thermal_sensor import (
    detect_knee,
    identify_iv,
    identify_z_curve,
    monotone_k_tp,
    separation_from_current,
    thermal_dynamics,
)
from afmtool.io.capture import Chunk
from afmtool.models.thermal_sensor import ResistanceFit, steady_state
from tests.conftest import run_cli, validate_report


def write_capture(capture, path):
    """A simulated capture as an afmtool HDF5 file (what 'afmtool simulate -o' writes), in-process."""
    from afmtool.analyses.convert import convert_capture
    from afmtool.io.memory import ArrayReader

    reader = ArrayReader(capture.sample_rate_hz, capture.channels, capture.data, capture.metadata, capture.truth)
    convert_capture(reader, path, "hdf5")


PROBE = sim.scenario_defaults("iv-ramp")
SENSOR = PROBE.thermal_sensor()
T_GRID = np.linspace(25.0, 550.0, 106)


@pytest.fixture(scope="module")
def iv():
    cap = sim.simulate("iv-ramp", {}, seed=3)
    return identify_iv(cap.data["v_r"], cap.data["thermal_current"] * 1e-6)


@pytest.mark.parametrize("noise_ua", [0.0, 0.05, 0.5])
def test_iv_ramp_gives_k_tp_and_g_within_2_percent(noise_ua):
    cap = sim.simulate("iv-ramp", {"current_noise_ua": noise_ua}, seed=3)
    result = identify_iv(cap.data["v_r"], cap.data["thermal_current"] * 1e-6)
    k_true = float(SENSOR.gain.gain(PROBE.separation_nm * 1e-9))
    k_err = result.k_tp_k_per_w / k_true - 1
    g_err = np.max(np.abs(result.g_fit.resistance(T_GRID) / SENSOR.resistance.resistance(T_GRID) - 1))
    table_err = np.max(np.abs(result.table.resistance_ohm / SENSOR.resistance.resistance(result.table.temperature_c) - 1))
    print(f"noise {noise_ua} uA: K_TP {result.k_tp_k_per_w * 1e-3:.3f} K/mW (error {100 * k_err:+.3f} %), "
          f"g(T) fit max error {100 * g_err:.3f} %, table {100 * table_err:.3f} %, knee {result.knee.voltage_v:.4f} V")
    assert abs(k_err) < 0.02
    assert g_err < 0.02
    assert table_err < 0.02


def test_a_ramp_short_of_breakdown_has_no_knee():
    cap = sim.simulate("iv-ramp", {"v_r_max_v": 3.0}, seed=3)
    with pytest.raises(InputError, match="knee"):
        identify_iv(cap.data["v_r"], cap.data["thermal_current"] * 1e-6)
    with pytest.raises(InputError, match="knee"):  # a pure power law bends nowhere
        v = np.linspace(1.0, 3.0, 200)
        detect_knee(v, v**2 / 1000.0)


def test_z_curve_k_tp_within_2_percent_and_the_snap_in_offset(iv):
    cap = sim.simulate("iv-ramp", {"ramp": "z"}, seed=4)
    curve = identify_z_curve(cap.data["z_piezo"] * 1e-9, cap.data["v_r"], cap.data["thermal_current"] * 1e-6, iv.g_fit)
    n = curve.snap_in_index + 1
    ts_true = cap.truth["tip_sample_separation_nm"][:n] * 1e-9
    ts_meas = curve.snap_in_z_m - cap.data["z_piezo"][:n] * 1e-9
    k_meas = curve.per_sample_k_tp
    k_true = SENSOR.gain.gain(ts_true)[np.isfinite(k_meas)]
    err = np.max(np.abs(k_meas[np.isfinite(k_meas)] / k_true - 1))
    # the binned table against the truth averaged over the same samples
    edges = np.arange(0.0, ts_meas.max() + 10e-9, 10e-9)
    index = np.clip(np.digitize(ts_meas, edges) - 1, 0, edges.size - 2)
    counts = np.bincount(index, minlength=edges.size - 1)
    truth_binned = (np.bincount(index, SENSOR.gain.gain(ts_true), edges.size - 1) / np.maximum(counts, 1))[counts > 0]
    err_binned = np.max(np.abs(curve.k_tp_k_per_w / truth_binned - 1))
    offset = ts_true - ts_meas
    print(f"z curve: K_TP max error {100 * err:.3f} % per sample, {100 * err_binned:.3f} % binned; "
          f"t_s offset {offset.min() * 1e9:.1f}..{offset.max() * 1e9:.1f} nm (snap-in at t_s = {ts_true[-1] * 1e9:.1f} nm)")
    assert err < 0.02 and err_binned < 0.02
    # t_s from the snap-in is short by the true separation at snap-in (≈ d = 65 nm) plus the lever's bending
    assert offset[-1] == pytest.approx(ts_true[-1], abs=1e-12)
    assert ts_true[-1] == pytest.approx(PROBE.attractive_range_nm * 1e-9, rel=0.01)
    assert curve.contact_k_tp_k_per_w == pytest.approx(SENSOR.gain.contact_k_per_w, rel=0.02)


def test_separation_from_current_inverts_the_table():
    """I_R → R → T → K_TP → t_s with the exact g(T) and K_TP(t_s) returns t_s (Fig. 6.9(b) conversion)."""
    g = SENSOR.resistance
    exact = ResistanceFit(25.0, (g.room_resistance_ohm, g.room_resistance_ohm * g.alpha_per_k,
                                 g.room_resistance_ohm * g.beta_per_k2), 550.0)
    ts = np.linspace(20e-9, 600e-9, 59)
    st = steady_state(SENSOR, 3.0, ts)
    back = separation_from_current(np.full(ts.size, 3.0), st.current_a, exact, ts, SENSOR.gain.gain(ts))
    np.testing.assert_allclose(back, ts, rtol=1e-6)
    np.testing.assert_allclose(monotone_k_tp([1.0, 3.0, 2.0, 4.0]), [1.0, 2.5, 2.5, 4.0])


def _sweep_response(cap, x, ys, nperseg):
    return responses_from_chunks([Chunk(0, dict(cap.data))], cap.sample_rate_hz, x, ys, method="h1", nperseg=nperseg)


def test_c_and_h_from_a_v_r_sweep(iv):
    """C(jω) by eq. 6.11 and H(jω) by eq. 6.12, with g(T) from the I-V ramp and Γ_IR,ts from eq. 6.15."""
    vr = sim.simulate("thermal-sweep", {"input": "v_r"}, seed=5)
    near = sim.simulate("thermal-sweep", {}, seed=1)
    contact = sim.simulate("thermal-sweep", {"contact": True}, seed=2)
    model = sim.scenario_info("thermal-sweep").params_cls(input="v_r").model()
    n = auto_nperseg(vr.n_samples)
    r = _sweep_response(vr, "v_r", ("thermal_current", "deflection"), n)
    g = combine_gamma(*_sweep_response(near, "v_sub", ("thermal_current", "deflection"), n).values(),
                      _sweep_response(contact, "v_sub", ("thermal_current",), n)["thermal_current"])
    ir_ts = g.ir_ts.response  # µA/nm
    # remove the lever's motion: Γ_IR,VR = ΔI/ΔV_R − Γ_IR,ts·Δt_s/ΔV_R
    ir_vr = r["thermal_current"].response - ir_ts * r["deflection"].response
    fr = scale_response(r["thermal_current"], 1e-6)
    fr = type(fr)(fr.frequency_hz, ir_vr * 1e-6, fr.coherence, fr.magnitude_std, fr.phase_std_rad, "h1")
    dyn = thermal_dynamics(fr, float(vr.data["v_r"].mean()), float(vr.data["thermal_current"].mean()) * 1e-6,
                           iv.g_fit, scale_response(g.ir_ts, 1e3))
    f = dyn.c.frequency_hz
    band = (f >= 100) & (f <= 5e4)
    c_ratio = dyn.c.response[band] / model.c(f[band])
    h_ratio = dyn.h.response[band] / model.h(f[band])
    c_db, c_deg = np.max(np.abs(20 * np.log10(np.abs(c_ratio)))), np.max(np.abs(np.angle(c_ratio, deg=True)))
    h_db, h_deg = np.max(np.abs(20 * np.log10(np.abs(h_ratio)))), np.max(np.abs(np.angle(h_ratio, deg=True)))
    c_dc = float(np.median(np.abs(dyn.c.response[(f > 0) & (f < 500)]))) / model.operating_point.k_tp_k_per_w - 1
    print(f"C(jw): max {c_db:.3f} dB / {c_deg:.2f} deg, DC {100 * c_dc:+.2f} %; H(jw): max {h_db:.3f} dB / {h_deg:.2f} deg "
          f"(100 Hz-50 kHz); T0 {dyn.operating_point.temperature_c:.2f} (truth {model.operating_point.temperature_c:.2f}) C")
    assert c_db < 0.2 and c_deg < 2.0
    assert h_db < 0.3 and h_deg < 3.0
    assert abs(c_dc) < 0.02


def test_identify_thermal_command_end_to_end(tmp_path):
    """All three routes in one run, H from a prior 'identify gamma'; the model feeds the next run."""
    captures = {
        "iv.h5": ("iv-ramp", {}, 3),
        "z.h5": ("iv-ramp", {"ramp": "z"}, 4),
        "vr.h5": ("thermal-sweep", {"input": "v_r", "duration_s": 0.2}, 5),
        "near.h5": ("thermal-sweep", {"duration_s": 0.2}, 1),
        "contact.h5": ("thermal-sweep", {"duration_s": 0.2, "contact": True}, 2),
    }
    for name, (scenario, overrides, seed) in captures.items():
        write_capture(sim.simulate(scenario, overrides, seed=seed), tmp_path / name)
    gamma = run_cli("identify", "gamma", tmp_path / "near.h5", "--contact", tmp_path / "contact.h5",
                    "--out", tmp_path / "gamma", "-q")
    assert gamma.returncode == 0, gamma.stderr.decode()
    out = tmp_path / "thermal"
    result = run_cli("identify", "thermal", "--iv", tmp_path / "iv.h5", "--z-curve", tmp_path / "z.h5",
                     "--vr-sweep", tmp_path / "vr.h5", "--gamma", tmp_path / "gamma", "--out", out, "--json", "-q")
    assert result.returncode == 0, result.stderr.decode()
    report = json.loads(result.stdout)
    validate_report(report)
    res = report["results"]
    assert res["iv"]["k_tp_k_per_w"] == pytest.approx(float(SENSOR.gain.gain(2e-6)), rel=0.02)
    assert res["dynamics"]["lever_motion_removed"] is True
    assert res["dynamics"]["c"]["dc_gain_k_per_mw"] == pytest.approx(102.5, rel=0.02)
    assert res["dynamics"]["h"]["dc_gain_k_per_nm"] == pytest.approx(0.2231, rel=0.03)
    # issue 31: the --vr-sweep route is headlined too (it was empty)
    headline = {entry["name"]: entry for entry in report["headline"]}
    assert headline["C(jω) DC gain"]["value"] == res["dynamics"]["c"]["dc_gain_k_per_mw"]
    assert headline["H(jω) DC gain"]["units"] == "K/nm" and "K_TP in contact (z curve)" in headline
    for name in ("thermal_sensor.json", "iv.csv", "g_table.csv", "k_tp.csv", "frf_c.csv", "frf_h.csv", "iv_knee.png",
                 "g_of_t.png", "k_tp.png", "c.png", "h.png", "thermal.h5"):
        assert (out / name).is_file(), name
    saved = json.loads((out / "thermal_sensor.json").read_text())
    assert saved["g"]["coefficients_ohm"] == res["iv"]["g_fit"]["coefficients_ohm"]
    # a later run takes g(T) from the saved model
    again = run_cli("identify", "thermal", "--z-curve", tmp_path / "z.h5", "--model", out, "--out", tmp_path / "t2",
                    "--json", "-q")
    assert again.returncode == 0, again.stderr.decode()
    assert json.loads(again.stdout)["results"]["z_curve"] == res["z_curve"]
    missing = run_cli("identify", "thermal", "--z-curve", tmp_path / "z.h5", "--out", tmp_path / "t3")
    assert missing.returncode == 2 and "need g(T)" in missing.stderr.decode()


def test_the_thermal_records_write_what_the_model_file_and_the_report_held():
    """The model's record writes thermal_sensor.json's content; a response without a summary is {} (issue 29)."""
    import math

    from afmtool.models.thermal_model import ThermalModel
    from afmtool.records.thermal import CSummaryRecord, HSummaryRecord

    g = ResistanceFit(25.0, (1200.0, 1.8, 0.002), 550.0)
    model = ThermalModel(g, 550.0, 125e3, 4.2e-3, 2.9, (0.0, 1e-8), (1.2e5, 1.25e5), 0.95e5)
    assert model.record().to_json() == model.to_dict() and g.record().to_json() == g.to_dict()
    assert ThermalModel(None, 550.0).record().to_json() == ThermalModel(None, 550.0).to_dict()
    assert CSummaryRecord().to_json() == {} and HSummaryRecord.from_json({}) == HSummaryRecord()
    no_bandwidth = CSummaryRecord(dc_gain_k_per_mw=104.4, bandwidth_hz=math.nan, roll_off_db_per_decade=math.nan,
                                  roll_off_band_hz=(math.nan, math.nan)).to_json()
    assert no_bandwidth == {"dc_gain_k_per_mw": 104.4, "bandwidth_hz": None, "roll_off_db_per_decade": None,
                            "roll_off_band_hz": [None, None]}
    assert CSummaryRecord.from_json(no_bandwidth).to_json() == no_bandwidth  # null stays null, not left out
