"""The ``identify thermal`` command end to end: I-V ramp, z force curve and V_R sweep routes, files, report."""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np

from afmtool.config import load_toml, resolve_from
from afmtool.config.params import ThermalParams
from afmtool.errors import ConfigError, InputError
from afmtool.estimators.frequency_response import FrequencyResponse, frf_table
from afmtool.estimators.sensing_gamma import (
    CANONICAL_UNITS,
    SensingSummary,
    auto_nperseg,
    canonical_scale,
    gamma_response_stage,
    resample_response,
    scale_response,
    sensing_summary,
)
from afmtool.estimators.stages import ChannelMeans, RecordStage
from afmtool.estimators.thermal_sensor import (
    IvIdentification,
    KtpCurve,
    ThermalDynamics,
    identify_iv,
    identify_z_curve,
    thermal_dynamics,
)
from afmtool.io.capture import CaptureReader
from afmtool.io.chunks import require_channels
from afmtool.io.gamma_results import GammaFile, read_gamma_ir_ts
from afmtool.io.results import ResultWriter
from afmtool.models.thermal_model import THERMAL_MODEL_FILE, ThermalModel, load_thermal_model
from afmtool.pipeline import run_stream
from afmtool.records.gamma import ResponseMethod
from afmtool.records.thermal import (
    CSummaryRecord,
    DynamicsRecord,
    HSummaryRecord,
    IvRecord,
    ThermalOperatingPointRecord,
    ThermalResults,
    ZCurveRecord,
)
from afmtool.report.json_report import input_record
from afmtool.report.run import finish_run
from afmtool.runtime.outputs import OutputDir

__all__ = ["run_thermal_command", "load_thermal_model", "read_gamma_ir_ts", "GammaFile", "THERMAL_MODEL_FILE"]

#: Most points drawn per scatter in the PNGs (the CSV tables keep every sample).
_PLOT_POINTS = 20000
#: Relative difference of the mean currents above which two sweeps are not at one operating point.
_SAME_POINT = 0.01


# --------------------------------------------------------------------------- files in




def _scale(reader: CaptureReader, name: str, kind: str, warnings: list) -> float:
    """Factor to µA, nm or V for channel ``name``; a warning when its units are missing."""
    factor, assumed = canonical_scale(kind, reader.info.units(name), name)
    if assumed:
        warnings.append(f"{reader.info.source}: channel {name!r} has no units; assumed {CANONICAL_UNITS[kind]}")
    return factor


def _read_all(
    reader: CaptureReader, channels: dict[str, str], params: ThermalParams, progress, warnings: list
) -> dict[str, np.ndarray]:
    """Whole quasi-static ramps in SI units: A for currents, m for lengths, V for voltages.

    The routes fit and write every sample (iv.csv, the K_TP scatter), so the
    records are kept: memory one float64 array per channel read.
    """
    require_channels(reader.info, tuple(channels))
    to_si = {"current": 1e-6, "length": 1e-9, "voltage": 1.0}
    scale = {name: _scale(reader, name, kind, warnings) * to_si[kind] for name, kind in channels.items()}
    (data,) = run_stream(reader, [RecordStage(tuple(channels))], channels=tuple(channels),
                         chunk_samples=params.chunk_samples, progress=progress)
    for name in channels:
        data[name] *= scale[name]
    return data


# --------------------------------------------------------------------------- routes


def _iv_record(iv: IvIdentification) -> IvRecord:
    return IvRecord(
        knee_voltage_v=iv.knee.voltage_v,
        knee_power_mw=iv.knee.power_w * 1e3,
        k_tp_k_per_w=iv.k_tp_k_per_w,
        k_tp_k_per_mw=iv.k_tp_k_per_w * 1e-3,
        slope_below_knee=iv.knee.slope_below,
        slope_above_knee=iv.knee.slope_above,
        knee_rms_log_residual=iv.knee.rms_log_residual,
        g_fit=iv.g_fit.record(),
        g_rms_relative_residual=iv.g_rms_relative_residual,
        samples_used=int(iv.curve.v_r_v.size),
    )


def _z_record(curve: KtpCurve) -> ZCurveRecord:
    return ZCurveRecord(
        snap_in_z_nm=curve.snap_in_z_m * 1e9,
        snap_in_jump_ua=curve.jump_a * 1e6,
        contact_k_tp_k_per_mw=curve.contact_k_tp_k_per_w * 1e-3,
        separation_range_nm=(float(curve.separation_m.min() * 1e9), float(curve.separation_m.max() * 1e9)),
        k_tp_range_k_per_mw=(float(curve.k_tp_k_per_w.min() * 1e-3), float(curve.k_tp_k_per_w.max() * 1e-3)),
        bins=int(curve.separation_m.size),
        separation_convention="t_s = z_sn - z, snap-in taken as t_s = 0 (thesis 6.5.2); the true separation at "
        "snap-in (about the attractive range d) is not seen by the thermal sensor",
    )


def _summary(fr: FrequencyResponse, mask: np.ndarray, warnings: list, label: str) -> SensingSummary | None:
    """The response's sensing summary; None (with a warning) where it has none."""
    try:
        return sensing_summary(fr, mask)
    except InputError as exc:
        warnings.append(f"{label}: no summary ({exc})")
        return None


def _c_record(s: SensingSummary | None) -> CSummaryRecord:
    """C(jω)'s summary in K/mW (``s`` in K/W); empty without one."""
    if s is None:
        return CSummaryRecord()
    return CSummaryRecord(dc_gain_k_per_mw=s.dc_sensitivity * 1e-3, bandwidth_hz=s.bandwidth_hz,
                          roll_off_db_per_decade=s.roll_off_db_per_decade, roll_off_band_hz=s.roll_off_band_hz)


def _h_record(s: SensingSummary | None) -> HSummaryRecord:
    """H(jω)'s summary in K/nm (``s`` in K/m); empty without one."""
    if s is None:
        return HSummaryRecord()
    return HSummaryRecord(dc_gain_k_per_nm=s.dc_sensitivity * 1e-9, bandwidth_hz=s.bandwidth_hz,
                          roll_off_db_per_decade=s.roll_off_db_per_decade, roll_off_band_hz=s.roll_off_band_hz)


def _without_lever_motion(ir_vr: FrequencyResponse, gamma_file, responses: dict, deflection_scale: float):
    """Γ_IR,VR with the lever's own motion removed when ``--gamma`` and a deflection allow it.

    Returns (Γ_IR,VR in µA/V, Γ_IR,ts in µA/nm or None, whether the motion was removed).
    """
    if gamma_file is None:
        return ir_vr, None, False
    ir_ts = resample_response(gamma_file.ir_ts, ir_vr.frequency_hz)  # µA/nm
    if "deflection" not in responses:
        return ir_vr, ir_ts, False
    ts_vr = scale_response(responses["deflection"], deflection_scale)  # nm/V
    # Γ_IR,VR = ΔI/ΔV_R − Γ_IR,ts·Δt_s/ΔV_R: the lever moves with α_R·ΔV_R
    lever = ir_ts.response * ts_vr.response
    ir_vr = FrequencyResponse(
        ir_vr.frequency_hz, ir_vr.response - np.where(np.isfinite(lever), lever, 0.0), ir_vr.coherence,
        ir_vr.magnitude_std, ir_vr.phase_std_rad, ir_vr.method, ir_vr.n_averages,
    )
    return ir_vr, ir_ts, True


def _vr_route(
    reader: CaptureReader, g_fit, gamma_path: Path | None, params: ThermalParams, progress, warnings: list
) -> tuple[ThermalDynamics, DynamicsRecord, FrequencyResponse]:
    require_channels(reader.info, ("v_r", "thermal_current"))
    i_scale = _scale(reader, "thermal_current", "current", warnings)
    v_scale = _scale(reader, "v_r", "voltage", warnings)
    method = params.method
    if method == "auto":
        method = "stepped" if "segments" in reader.info.metadata else "h1"
    outputs = ["thermal_current"] + (["deflection"] if "deflection" in reader.info.channel_names else [])
    d_scale = _scale(reader, "deflection", "length", warnings) if "deflection" in outputs else 1.0
    nperseg = params.nperseg or auto_nperseg(reader.info.n_samples or 0)
    stage = gamma_response_stage(
        "v_r", outputs, method=method, nperseg=nperseg,
        segments=reader.info.metadata.get("segments") if method == "stepped" else None,
        settle_fraction=params.settle_fraction, min_periods=params.min_periods,
    )
    responses, chunks = run_stream(reader, [stage, ChannelMeans()], channels=("v_r", *outputs),
                                   chunk_samples=params.chunk_samples, progress=progress)
    ir_vr = scale_response(responses["thermal_current"], i_scale / v_scale)  # µA/V
    gamma_file = read_gamma_ir_ts(gamma_path) if gamma_path is not None else None
    ir_vr, ir_ts, removed = _without_lever_motion(ir_vr, gamma_file, responses, d_scale / v_scale)
    if not removed:
        warnings.append(
            "C(jw) includes the lever's motion under alpha_R*dV_R (give --gamma and a deflection channel to remove it)"
        )
    v0 = chunks.mean("v_r") * v_scale
    i0 = chunks.mean("thermal_current") * i_scale * 1e-6
    if gamma_path is not None and abs(gamma_file.thermal_current_mean_ua * 1e-6 / i0 - 1) > _SAME_POINT:
        warnings.append(
            f"the gamma sweep ran at {gamma_file.thermal_current_mean_ua:.6g} uA, the V_R sweep at {i0 * 1e6:.6g} uA: "
            "eq. 6.12 needs both at one operating point"
        )
    dyn = thermal_dynamics(
        scale_response(ir_vr, 1e-6),  # A/V
        v0,
        i0,
        g_fit,
        None if ir_ts is None else scale_response(ir_ts, 1e3),  # µA/nm -> A/m
    )
    f = dyn.c.frequency_hz
    with np.errstate(invalid="ignore"):
        mask = (f > 0) & np.isfinite(dyn.c.response) & (ir_vr.coherence >= params.min_coherence)
    c = _c_record(_summary(dyn.c, mask, warnings, "C(jw)"))
    h = None
    if dyn.h is not None:
        h_mask = mask & np.isfinite(dyn.h.response)
        h = _h_record(_summary(dyn.h, h_mask, warnings, "H(jw)"))
    dynamics = DynamicsRecord(method=ResponseMethod(method),
                              operating_point=ThermalOperatingPointRecord(**dyn.operating_point._asdict()),
                              lever_motion_removed=removed, c=c, h=h)
    return dyn, dynamics, ir_vr


# --------------------------------------------------------------------------- files out


def _write_iv(staged: OutputDir, writer: ResultWriter, iv: IvIdentification, params: ThermalParams) -> None:
    from afmtool.io.rows import RowWriter
    from afmtool.report.images import write_line_plot_png

    c = iv.curve
    columns = {"v_r_v": c.v_r_v, "current_a": c.current_a, "resistance_ohm": c.resistance_ohm,
               "power_w": c.power_w, "temperature_c": iv.temperature_c}
    units = {"v_r_v": "V", "current_a": "A", "resistance_ohm": "ohm", "power_w": "W", "temperature_c": "degC"}
    for name, values in columns.items():
        writer.put(f"iv/{name}", values, units[name])
    t = iv.table
    table = {"temperature_c": t.temperature_c, "resistance_ohm": t.resistance_ohm,
             "resistance_sem_ohm": t.resistance_sem_ohm, "count": t.count.astype(np.float64),
             "g_fit_ohm": iv.g_fit.resistance(t.temperature_c)}
    for name, values in table.items():
        writer.put(f"g_table/{name}", values)
    for name, data in (("iv.csv", columns), ("g_table.csv", table)):
        with open(staged.path(name), "w", encoding="utf-8", newline="") as handle, RowWriter(handle, "csv") as rows:
            rows.append(data)
    order = np.argsort(c.v_r_v)[:: max(1, c.v_r_v.size // _PLOT_POINTS)]
    write_line_plot_png(
        staged.path("iv_knee.png"),
        [(c.v_r_v[order], c.power_w[order] * 1e3, "P = V_R I_R", {"linestyle": "none", "marker": ".", "markersize": 2})],
        x_label="V_R (V)", y_label="P (mW)", title=f"I-V ramp: knee P_k = {iv.knee.power_w * 1e3:.4g} mW",
        markers=[(iv.knee.voltage_v, f"knee {iv.knee.voltage_v:.4g} V")],
    )
    grid = np.linspace(params.room_temperature_c, params.breakdown_temperature_c, 200)
    write_line_plot_png(
        staged.path("g_of_t.png"),
        [
            (t.temperature_c, t.resistance_ohm, "table (binned)", {"linestyle": "none", "marker": "o", "markersize": 3}),
            (grid, iv.g_fit.resistance(grid), f"fit, degree {params.g_order}", {"color": "C3"}),
        ],
        x_label="T (degC)", y_label="R (ohm)", title=f"g(T) with K_TP = {iv.k_tp_k_per_w * 1e-3:.4g} K/mW",
    )


def _write_z(staged: OutputDir, writer: ResultWriter, curve: KtpCurve) -> None:
    from afmtool.io.rows import RowWriter
    from afmtool.report.images import write_line_plot_png

    table = {"separation_nm": curve.separation_m * 1e9, "k_tp_k_per_mw": curve.k_tp_k_per_w * 1e-3,
             "k_tp_std_k_per_mw": curve.k_tp_std_k_per_w * 1e-3, "count": curve.count.astype(np.float64)}
    for name, values in table.items():
        writer.put(f"k_tp/{name}", values)
    with open(staged.path("k_tp.csv"), "w", encoding="utf-8", newline="") as handle, RowWriter(handle, "csv") as rows:
        rows.append(table)
    step = max(1, curve.per_sample_separation_m.size // _PLOT_POINTS)
    write_line_plot_png(
        staged.path("k_tp.png"),
        [
            (curve.per_sample_separation_m[::step] * 1e9, curve.per_sample_k_tp[::step] * 1e-3, "samples",
             {"linestyle": "none", "marker": ".", "markersize": 1, "alpha": 0.3}),
            (table["separation_nm"], table["k_tp_k_per_mw"], "binned", {"color": "C3"}),
        ],
        x_label="t_s from snap-in (nm)", y_label="K_TP (K/mW)", title="K_TP against tip-sample separation (z curve)",
    )


def _write_dynamics(staged: OutputDir, writer: ResultWriter, dyn: ThermalDynamics, ir_vr: FrequencyResponse) -> None:
    from afmtool.io.rows import RowWriter
    from afmtool.report.bode import BodeCurve, write_bode_png

    f = dyn.c.frequency_hz
    writer.put("dynamics/frequency_hz", f, "Hz")
    writer.put("dynamics/ir_vr", ir_vr.response, "uA/V")
    writer.put("dynamics/coherence_ir_vr", ir_vr.coherence)
    writer.put("dynamics/c", dyn.c.response, "K/W", {"description": "C(jw), eq. 6.11"})
    with open(staged.path("frf_c.csv"), "w", encoding="utf-8", newline="") as handle, RowWriter(handle, "csv") as rows:
        rows.append(frf_table(dyn.c))
    keep = f > 0
    write_bode_png(staged.path("c.png"), [BodeCurve(f[keep], dyn.c.response[keep] * 1e-3, "C(jw), eq. 6.11", None,
                                                         dyn.c.magnitude_std[keep] * 1e-3)],
                   title="Power to temperature C(jw)", magnitude_label="|C| (dB re 1 K/mW)")
    if dyn.h is not None:
        writer.put("dynamics/h", dyn.h.response, "K/m", {"description": "H(jw), eq. 6.12"})
        with open(staged.path("frf_h.csv"), "w", encoding="utf-8", newline="") as handle, RowWriter(handle, "csv") as rows:
            rows.append(frf_table(dyn.h))
        finite = keep & np.isfinite(dyn.h.response)
        write_bode_png(staged.path("h.png"), [BodeCurve(f[finite], dyn.h.response[finite] * 1e-9, "H(jw), eq. 6.12", None,
                                                             dyn.h.magnitude_std[finite] * 1e-9)],
                       title="Separation to temperature H(jw)", magnitude_label="|H| (dB re 1 K/nm)")


# --------------------------------------------------------------------------- command


def run_thermal_command(
    readers: Mapping[str, CaptureReader | None],
    sources: Mapping[str, str | Path | None],
    out: Path,
    config: Path | None,
    flags: Mapping,
    progress: Callable[[int], None],
) -> dict:
    """Run the routes whose captures are given (``iv``, ``z``, ``vr``) and write the thermal model and report.

    ``sources`` also holds ``gamma`` (gamma.h5 for H) and ``model`` (a
    thermal_sensor.json supplying g(T) when there is no I-V ramp).
    """
    params = resolve_from(ThermalParams, "identify.thermal", load_toml(config) if config else None, flags)
    if not any(readers.get(k) for k in ("iv", "z", "vr")):
        raise ConfigError("give at least one of --iv, --z-curve and --vr-sweep")
    warnings: list[str] = []
    inputs = []
    prior = load_thermal_model(Path(sources["model"])) if sources.get("model") else None
    if prior is not None:
        inputs.append(input_record(_model_file(Path(sources["model"])), "model"))
    iv = curve = dyn = ir_vr = dynamics = None
    if readers.get("iv"):
        data = _read_all(readers["iv"], {"v_r": "voltage", "thermal_current": "current"}, params, progress, warnings)
        iv = identify_iv(data["v_r"], data["thermal_current"], breakdown_temperature_c=params.breakdown_temperature_c,
                         room_temperature_c=params.room_temperature_c, g_order=params.g_order,
                         table_bins=params.g_table_bins, knee_fit_fraction=params.knee_fit_fraction)
        inputs.append(input_record(sources["iv"], "iv-ramp"))
    g_fit = iv.g_fit if iv is not None else (prior.g_fit if prior is not None else None)
    if g_fit is None and (readers.get("z") or readers.get("vr")):
        raise ConfigError("the z-curve and V_R-sweep routes need g(T): give --iv RAMP or --model thermal_sensor.json")
    if readers.get("z"):
        data = _read_all(readers["z"], {"z_piezo": "length", "v_r": "voltage", "thermal_current": "current"}, params,
                         progress, warnings)
        curve = identify_z_curve(data["z_piezo"], data["v_r"], data["thermal_current"], g_fit,
                                 bin_m=params.z_bin_nm * 1e-9)
        inputs.append(input_record(sources["z"], "z-curve"))
    if readers.get("vr"):
        gamma_path = Path(sources["gamma"]) if sources.get("gamma") else None
        dyn, dynamics, ir_vr = _vr_route(readers["vr"], g_fit, gamma_path, params, progress, warnings)
        inputs.append(input_record(sources["vr"], "vr-sweep"))
        if gamma_path is not None:
            inputs.append(input_record(gamma_path if gamma_path.is_file() else gamma_path / "gamma.h5", "gamma"))
    model = _merged_model(params, iv, curve, prior)
    with OutputDir(out) as staged:
        staged.path(THERMAL_MODEL_FILE).write_text(json.dumps(model.to_dict(), indent=2) + "\n", encoding="utf-8")
        with ResultWriter(staged.path("thermal.h5"), {}, {"afmtool_command": "identify thermal"}) as writer:
            if iv is not None:
                _write_iv(staged, writer, iv, params)
            if curve is not None:
                _write_z(staged, writer, curve)
            if dyn is not None:
                _write_dynamics(staged, writer, dyn, ir_vr)
        results = ThermalResults(
            breakdown_temperature_c=params.breakdown_temperature_c, room_temperature_c=params.room_temperature_c,
            iv=None if iv is None else _iv_record(iv), z_curve=None if curve is None else _z_record(curve),
            dynamics=dynamics, thermal_sensor=model.record(),
        )
        return finish_run(staged, "identify thermal", inputs, "identify.thermal", params, results, warnings)


def _model_file(path: Path) -> Path:
    return path / THERMAL_MODEL_FILE if path.is_dir() else path


def _merged_model(params: ThermalParams, iv, curve, prior: ThermalModel | None) -> ThermalModel:
    """This run's findings, completed by the prior model's for the routes not run."""
    base = prior if prior is not None else ThermalModel(None, params.breakdown_temperature_c)
    if iv is not None:
        base = base._replace(g_fit=iv.g_fit, k_tp_k_per_w=iv.k_tp_k_per_w, knee_power_w=iv.knee.power_w,
                             knee_voltage_v=iv.knee.voltage_v, breakdown_temperature_c=params.breakdown_temperature_c)
    if curve is not None:
        base = base._replace(
            k_tp_separation_m=tuple(curve.separation_m.tolist()),
            k_tp_table_k_per_w=tuple(curve.k_tp_k_per_w.tolist()),
            contact_k_tp_k_per_w=curve.contact_k_tp_k_per_w,
        )
    return base
