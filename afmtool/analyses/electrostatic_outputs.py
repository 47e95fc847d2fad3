"""The ``identify electrostatic`` command end to end: curve, region before snap-in, fit, files, report."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from afmtool.config import load_toml, resolve_from
from afmtool.config.params import ElectrostaticFitParams
from afmtool.errors import ConfigError, InputError
from afmtool.estimators.electrostatic_fit import ElectrostaticFit, fit_electrostatic, select_before_snap_in
from afmtool.estimators.sensing_gamma import canonical_scale
from afmtool.estimators.stages import RecordStage
from afmtool.estimators.thermal_sensor import separation_from_current
from afmtool.io.capture import CaptureReader
from afmtool.io.units import calibration_record
from afmtool.models.thermal_model import THERMAL_MODEL_FILE, load_thermal_model
from afmtool.pipeline import run_stream
from afmtool.records.electrostatic import (
    ElectrostaticParameters,
    ElectrostaticResults,
    IdentifiabilityRecord,
    NullDirectionRecord,
    ParameterRecord,
    ParameterStatus,
    RegionRecord,
    Sensor,
    ThesisEquation,
)
from afmtool.report.json_report import input_record
from afmtool.report.run import finish_run
from afmtool.runtime.outputs import OutputDir

__all__ = ["run_electrostatic_command"]

#: Most points drawn per curve in electrostatic_fit.png (the CSV keeps every sample).
_PLOT_POINTS = 20000
_NOTES = {
    "spring_constant_n_per_m": "k and K_esf enter eqs. 6.6/6.7 only as K_esf/k: a static curve cannot separate "
    "them; give --spring-constant (e.g. from a thermal-noise fit) to get K_esf",
}


def _sensor(params: ElectrostaticFitParams, reader: CaptureReader, model_path) -> str:
    if params.sensor != "auto":
        return params.sensor
    if "deflection" in reader.info.channel_names:
        return "optical"
    if "thermal_current" in reader.info.channel_names and model_path:
        return "thermal"
    raise ConfigError("the capture has no deflection channel: give a thermal_current capture with --thermal-model")


def _read(reader: CaptureReader, names: tuple[str, ...]) -> dict[str, np.ndarray]:
    """The whole approach curve of ``names``.

    The fit picks the part before snap-in and the CSV keeps every sample, so
    the records are kept: memory one float64 array per channel.
    """
    (data,) = run_stream(reader, [RecordStage(names)], channels=names, chunk_samples=1 << 20)
    return data


def _v_r(params: ElectrostaticFitParams, reader: CaptureReader, data: Mapping[str, np.ndarray]) -> float:
    if params.v_r_v != 0:
        return params.v_r_v
    if "v_r" in data:
        return float(np.mean(data["v_r"]))
    ramp_v_r_v = reader.info.capture_metadata.ramp.v_r_v
    if ramp_v_r_v is not None:
        return ramp_v_r_v
    raise ConfigError("V_R is unknown: the capture has no v_r channel; give --v-r VOLTS")


def _curve(sensor: str, reader: CaptureReader, model_path, warnings: list) -> tuple[dict, np.ndarray, str]:
    """The channels and the measured curve in m: deflection p (optical) or t_s through K_TP (thermal)."""
    names = ["v_sub"] + (["v_r"] if "v_r" in reader.info.channel_names else [])
    if sensor == "optical":
        data = _read(reader, tuple(names + ["deflection"]))
        scale, assumed = canonical_scale("length", reader.info.units("deflection"), "deflection")
        if assumed:
            warnings.append("channel 'deflection' has no units; assumed nm")
        return data, data["deflection"] * scale * 1e-9, "6.6"
    if not model_path:
        raise ConfigError("the thermal route needs --thermal-model (thermal_sensor.json from 'identify thermal')")
    model = load_thermal_model(Path(model_path))
    if model.g_fit is None or model.k_tp_separation_m is None:
        raise InputError(f"{model_path}: the thermal model needs g(T) (--iv) and a K_TP(t_s) table (--z-curve)")
    if "v_r" not in reader.info.channel_names:
        raise InputError(f"{reader.info.source}: the thermal route needs the v_r channel")
    data = _read(reader, tuple(names + ["thermal_current"]))
    scale, _ = canonical_scale("current", reader.info.units("thermal_current"), "thermal_current")
    ts = separation_from_current(data["v_r"], data["thermal_current"] * scale * 1e-6, model.g_fit,
                                 model.k_tp_separation_m, model.k_tp_table_k_per_w)
    outside = int(np.count_nonzero(~np.isfinite(ts)))
    if outside:
        warnings.append(f"{outside} samples are outside the K_TP(t_s) table and were not converted to t_s")
    warnings.append("thermal t_s is measured from the z-curve snap-in (t_s = 0 there): any snap-in distance "
                    "shows up in t_h")
    return data, ts, "6.7"


def _parameter(fit: ElectrostaticFit, name: str) -> ParameterRecord:
    est = fit.estimates[name]
    status = ParameterStatus(est.status)
    note = None
    if status is ParameterStatus.NOT_IDENTIFIABLE and name in ("spring_constant_n_per_m", "k_esf_f_m"):
        note = _NOTES["spring_constant_n_per_m"]
    return ParameterRecord(value=est.value, std=est.std, relative_std=est.relative_std, status=status, note=note)


def _parameters(fit: ElectrostaticFit) -> ElectrostaticParameters:
    return ElectrostaticParameters(
        spring_constant_n_per_m=_parameter(fit, "spring_constant_n_per_m"),
        l0_m=_parameter(fit, "l0_m"),
        k_esf_f_m=_parameter(fit, "k_esf_f_m"),
        alpha_r=_parameter(fit, "alpha_r"),
        tip_height_m=_parameter(fit, "tip_height_m") if "tip_height_m" in fit.estimates else None,
        k_esf_over_k_m3_per_v2=_parameter(fit, "k_esf_over_k_m3_per_v2"),
    )


def _identifiability(fit: ElectrostaticFit) -> IdentifiabilityRecord:
    ident = fit.identifiability
    return IdentifiabilityRecord(
        method="SVD of the Jacobian in relative parameters (d ln theta; alpha_R: d theta/|theta|), residuals "
        "in noise units",
        parameters=ident.names,
        singular_values=tuple(float(s) for s in ident.singular_values),
        condition_number=ident.condition_number if math.isfinite(ident.condition_number) else None,
        directions=tuple(tuple(float(x) for x in row) for row in ident.directions),
        non_identifiable=tuple(
            NullDirectionRecord(
                parameters=d.parameters,
                weights=d.weights,
                identifiable_combination=d.identifiable_combination,
                relative_singular_value=d.singular_value / float(ident.singular_values[0]),
            )
            for d in ident.null_directions
        ),
        fixed_in_fit=tuple(fit.fixed),
        poorly_identifiable=tuple(n for n, e in fit.estimates.items() if e.status == "poorly identifiable"),
    )


def _write(staged: OutputDir, fit: ElectrostaticFit, v_sub, y_m, v_r: float, region, sensor: str,
           results: ElectrostaticResults):
    from afmtool.io.rows import RowWriter
    from afmtool.report.images import write_line_plot_png

    in_fit = np.zeros(v_sub.size)
    in_fit[region.start : region.stop] = 1.0
    model = np.full(v_sub.size, np.nan)
    model[: region.turn_index + 1] = fit.predict(v_sub[: region.turn_index + 1], v_r)
    model[region.snap_index + 1 if region.snap_index is not None else region.turn_index + 1 :] = np.nan
    label = "deflection_nm" if sensor == "optical" else "separation_nm"
    table = {"v_sub_v": v_sub, label: y_m * 1e9, "model_nm": model * 1e9, "residual_nm": (y_m - model) * 1e9,
             "in_fit": in_fit}
    with open(staged.path("fit.csv"), "w", encoding="utf-8", newline="") as handle, RowWriter(handle, "csv") as rows:
        rows.append(table)
    staged.path("electrostatic.json").write_text(
        json.dumps({"sensor": sensor, "v_r_v": v_r, "parameters": results.parameters.to_json(),
                    "identifiability": results.identifiability.to_json()}, indent=2, allow_nan=False) + "\n",
        encoding="utf-8",
    )
    markers = [] if region.snap_index is None else [(float(v_sub[region.snap_index]), "snap-in")]
    step = max(1, v_sub.size // _PLOT_POINTS)  # Agg draws a bounded number of vertices per path
    approach = slice(0, region.turn_index + 1, step)
    fitted = slice(region.start, region.stop, step)
    write_line_plot_png(
        staged.path("electrostatic_fit.png"),
        [
            (v_sub[::step], y_m[::step] * 1e9, "measured", {"color": "0.6", "linewidth": 0.8}),
            (v_sub[fitted], y_m[fitted] * 1e9, "fitted region",
             {"color": "C0", "linestyle": "none", "marker": ".", "markersize": 2}),
            (v_sub[approach], model[approach] * 1e9, f"eq. {results.thesis_equation.value} fit", {"color": "C3"}),
        ],
        x_label="V_sub (V)",
        y_label="deflection p (nm)" if sensor == "optical" else "t_s from snap-in (nm)",
        title=f"Electrostatic approach curve ({sensor})",
        markers=markers,
    )


def run_electrostatic_command(
    reader: CaptureReader,
    source: str | Path,
    out: Path,
    config: Path | None,
    flags: Mapping,
    thermal_model: Path | None,
) -> dict:
    """Fit eq. 6.6 or 6.7 to the region before snap-in; write electrostatic.json, fit.csv, a plot and report."""
    params = resolve_from(ElectrostaticFitParams, "identify.electrostatic", load_toml(config) if config else None,
                          flags)
    warnings: list[str] = []
    sensor = _sensor(params, reader, thermal_model)
    data, y_m, equation = _curve(sensor, reader, thermal_model, warnings)
    v_r = _v_r(params, reader, data)
    v_sub = data["v_sub"]
    region = select_before_snap_in(v_sub, y_m, margin_fraction=params.snap_margin)
    if region.snap_index is None:
        warnings.append("no snap-in found: the whole approach leg is fitted")
    part = slice(region.start, region.stop)
    ok = np.isfinite(y_m[part])
    fit = fit_electrostatic(
        v_sub[part][ok], y_m[part][ok], v_r, sensor=sensor,
        spring_constant_n_per_m=params.spring_constant_n_per_m or None,
        rank_tolerance=params.rank_tolerance, max_relative_std=params.max_relative_std,
    )
    if fit.residual_autocorrelation > 0.5:
        warnings.append(
            f"the residuals are strongly correlated (lag-1 {fit.residual_autocorrelation:.2f}): a systematic misfit; "
            "the region may reach into the tip-sample force or contact (raise snap_margin)"
        )
    for name, est in fit.estimates.items():
        if est.status == "poorly identifiable":
            warnings.append(f"{name} is poorly identifiable (relative std {est.relative_std:.3g})")
    results = ElectrostaticResults(
        sensor=Sensor(sensor),
        thesis_equation=ThesisEquation(equation),
        v_r_v=v_r,
        region=RegionRecord(
            v_sub_range_v=(float(v_sub[region.start]), float(v_sub[region.stop - 1])),
            points=int(np.count_nonzero(ok)),
            snap_in_v_sub_v=region.snap_v_sub_v,
            snap_in_jump_nm=region.jump * 1e9,
            margin_fraction=params.snap_margin,
        ),
        parameters=_parameters(fit),
        identifiability=_identifiability(fit),
        correlation=fit.correlation,
        rms_residual_nm=fit.rms_residual_m * 1e9,
        residual_lag1_autocorrelation=fit.residual_autocorrelation,
    )
    inputs = [{**input_record(source), **calibration_record(reader)}]
    if sensor == "thermal":
        path = Path(thermal_model)
        inputs.append(input_record(path / THERMAL_MODEL_FILE if path.is_dir() else path, "thermal-model"))
    with OutputDir(out) as staged:
        _write(staged, fit, v_sub, y_m, v_r, region, sensor, results)
        return finish_run(staged, "identify electrostatic", inputs, "identify.electrostatic", params, results,
                          warnings)
