"""The ``reep`` command end to end: parameters, run, files, report."""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from afmtool.analyses.command_inputs import CommandRun, channel_units, given_free_air_model, model_input_records
from afmtool.analyses.reep import SERIES_UNITS, ReepResult, run_reep
from afmtool.analyses.stream import run_stream_with_model
from afmtool.config.params import ReepParams
from afmtool.io.capture import CaptureReader
from afmtool.io.results import ResultWriter, row_attrs
from afmtool.io.units import calibration_record
from afmtool.records.reep import (
    ForceCurve,
    ForceCurveLeg,
    ImageMean,
    ReepResults,
    SyntheticDriveUncertainty,
    TruthTracking,
)
from afmtool.report.figure_process import FigureProcess
from afmtool.report.run import finish_run
from afmtool.runtime.outputs import OutputDir

__all__ = ["run_reep_command", "run_reep_stream"]

#: reep.h5's series kept in float64 (issue 33): time, and b1, b0, whose poles lie within 1e-4 of the
#: unit circle (f0′ and Q′ follow from them by a square root and a log); the rest is float32.
FLOAT64_SERIES = ("t", "b1", "b0")

_IMAGE_TITLES = {"f0_hz": ("f0'", "Hz"), "q": ("Q'", ""), "amplitude": ("amplitude", None), "phase_deg": ("phase", "deg")}


def run_reep_command(run: CommandRun) -> dict:
    """Resolve parameters, run REEP, write every output atomically; return the report."""
    reader = run.reader
    params = run.params(ReepParams, "reep")
    model = given_free_air_model(params.model)
    deflection_units = channel_units(reader, "deflection")
    units = dict(SERIES_UNITS, amplitude=deflection_units, sigma2=f"{deflection_units}^2" if deflection_units else "")
    capture_record = run.input_record()
    model_records = model_input_records(params.model)
    with OutputDir(run.out) as staged, run.figures.stopped_on_failure():
        with ResultWriter(staged.path("reep.h5"), units, {"afmtool_command": "reep"}, write_behind=True,
                          float64=FLOAT64_SERIES) as writer:
            result = run_reep(reader, params, writer, model=model, progress=run.progress, split=run.split,
                              on_stream_start=run.figures.on_stream_start)
            writer.set_attrs(_row_attrs(result.results))
            _write_force_curves(staged, writer, result, deflection_units, run.figures)
            _write_images(staged, writer, result, deflection_units, run.figures)
        staged.flush_early("reep.h5")  # to disk while the figures are drawn
        results = _read_back(staged, run, result, params, deflection_units, _given_spring_constant(params, model))
        if results.free_air_model is not None:
            from afmtool.models.free_air import FreeAirModel

            FreeAirModel.from_record(results.free_air_model).save(staged.path("free_air.json"))
        inputs = [{**capture_record.result(), **calibration_record(reader)}, *model_records]
        run.figures.wait()
        from afmtool.estimators.drive_lines import drive_fit_warnings

        warnings = [*result.warnings, *drive_fit_warnings(getattr(reader, "drive_fit", None))]
        return finish_run(staged, "reep", inputs, "reep", params, results, warnings)


def _read_back(staged: OutputDir, run: CommandRun, result: ReepResult, params: ReepParams, deflection_units: str,
               spring_constant: tuple[float, str]) -> ReepResults:
    """The stage's results with what the command reads back from the finished reep.h5.

    A synthesised drive's share of the uncertainty, the tracking error against
    ``/truth``, the interaction series, the force curve's extremes and the images' means.
    """
    from afmtool.analyses.interaction_outputs import add_interaction_series

    reader, results = run.reader, result.results
    drive_fit = getattr(reader, "drive_fit", None)
    if drive_fit is not None:
        # the synthesised drive's phase uncertainty is REEP's too (eq. D.3)
        results = results.replace(synthetic_drive_uncertainty=_widen_reep_std(
            staged.path("reep.h5"), drive_fit, float(results.drive_frequency_hz)))
    results = results.replace(truth_tracking=_time_series(staged, reader, result, deflection_units, run.figures))
    interaction = add_interaction_series(staged.path("reep.h5"), results, reader.info.capture_metadata,
                                         deflection_units, *spring_constant)
    results = results.replace(interaction=interaction)
    interaction_extremes = {}
    if interaction.written:
        interaction_extremes = _write_interaction_bins(staged, result, params, reader.info.sample_rate_hz,
                                                       run.figures)
    if result.force_curves:
        results = results.replace(force_curve=_curve_summary(result, _free_f0_hz(results), interaction_extremes))
    if result.geometry is not None:
        results = results.replace(images={name: ImageMean(mean=_finite_mean(image))
                                          for name, image in sorted(result.images.items())})
    return results


def _row_attrs(results: ReepResults) -> dict:
    """reep.h5's root attributes: the rows' spacing and rate, what set them, and REEP's own rate (issue 33)."""
    return {**row_attrs(results.rows, results.row_every_samples, results.row_rate_hz, results.sample_rate_hz),
            "reep_rate_hz": results.estimator.reep_rate_hz, "rate_reduction": results.estimator.rate_reduction}


def _widen_reep_std(path, fit, drive_hz: float, block: int = 1 << 20) -> SyntheticDriveUncertainty:
    """Add a synthesised drive's share to reep.h5's ``f0_std_hz`` and ``q_std`` in quadrature.

    ``fit`` is the drive's :class:`~afmtool.estimators.drive_lines.DrivePhaseFit`; the share per row is
    :func:`afmtool.estimators.drive_lines.drive_std_rows` (eq. D.3).

    Returns what the report records: σ_φ and the largest shares added.
    """
    from afmtool.estimators.drive_lines import drive_phase_std, drive_std_rows
    from afmtool.io.result_files import open_result_file

    phase_std = drive_phase_std(fit, drive_hz)
    record = SyntheticDriveUncertainty(
        main_line_phase_std_deg=math.degrees(phase_std), added_to=("f0_std_hz", "q_std"),
        formula="df0' = f0' dphi/(2Q'), dQ'/Q' = 2Q'|f0' - f_d|/f_d dphi + dphi^2/2")
    if phase_std <= 0:
        return record.replace(added_to=())
    largest = [0.0, 0.0]
    with open_result_file(path, mode="r+", required=("f0_hz", "q", "f0_std_hz", "q_std"), what="reep output") as f:
        n = f["f0_hz"].shape[0]
        for start in range(0, n, block):
            stop = min(n, start + block)
            f0_add, q_add = drive_std_rows(f["f0_hz"][start:stop], f["q"][start:stop], drive_hz, phase_std)
            for k, (name, add) in enumerate((("f0_std_hz", f0_add), ("q_std", q_add))):
                f[name][start:stop] = np.hypot(f[name][start:stop], add)
                if np.isfinite(add).any():
                    largest[k] = max(largest[k], float(np.nanmax(add)))
    return record.replace(largest_f0_std_added_hz=largest[0], largest_q_std_added=largest[1])


def _given_spring_constant(params: ReepParams, model) -> tuple[float, str]:
    """k (N/m) and where it came from: ``--spring-constant``, else the ``--model``'s k; (0, "") for neither.

    A ``free_air.json`` from ``identify freeair --psd`` carries the thermal (or
    Sader) k, so it need not be copied into ``--spring-constant`` by hand.
    """
    if params.spring_constant_n_per_m:
        return params.spring_constant_n_per_m, "--spring-constant"
    if model is not None and model.spring_constant_n_per_m:
        source = model.spring_constant_source or model.source
        return float(model.spring_constant_n_per_m), f"--model {params.model} ({source})"
    return 0.0, ""


def run_reep_stream(reader: CaptureReader, config: Path | None, flags: Mapping, fmt: str) -> None:
    """Run REEP and write decimated rows to stdout as each chunk completes (``--stream``)."""

    run_stream_with_model(run_reep, ReepParams, "reep", reader, config, flags, fmt)


def _time_series(staged: OutputDir, reader: CaptureReader, result: ReepResult, deflection_units: str,
                 figures: FigureProcess) -> TruthTracking | None:
    """``reep_time_series.png`` (rows from the stream) and the tracking error read back from reep.h5.

    With ``/truth`` f0_hz and q, ``truth_tracking``: the error against them
    after the warm-up.  (``segments``, f0' and Q' in and after the free-air
    segment, come from the stream: ``run_reep``.)
    """
    from afmtool.analyses.reep_timeseries import tracking_error, truth_at_rows, write_reep_time_series_png

    fs = reader.info.sample_rate_hz
    warmup_s = result.results.summary_after_warmup_samples / fs
    segment = result.results.free_air_segment_s
    reep_h5 = staged.path("reep.h5")
    wanted = ("f0_hz", "q", "amplitude", "phase_deg")
    truth = {}
    if any(name in reader.info.truth_names for name in wanted):
        truth = {name: values for name, values in reader.truth().items() if name in wanted}
    tracking = tracking_error(reep_h5, truth, fs, warmup_s)
    figures.draw(
        write_reep_time_series_png, staged.path("reep_time_series.png"), result.plot_rows,
        amplitude_units=deflection_units, truth=truth_at_rows(result.plot_rows.t, truth, fs) if truth else None,
        free_air_segment_s=segment, warmup_s=warmup_s,
    )
    return tracking


def _finite_mean(values: np.ndarray) -> float | None:
    finite = values[np.isfinite(values)]
    return float(finite.mean()) if finite.size else None


def _free_f0_hz(results: ReepResults) -> float | None:
    """The free-air f0' a force curve's shift is taken from: REEP's own in the free-air segment, else the model's."""
    segment = results.segments.free_air
    if segment is not None and np.isfinite(segment.f0_hz.mean):
        return float(segment.f0_hz.mean)
    return results.free_air_model.f0_hz if results.free_air_model is not None else None


def _extreme(z: np.ndarray, values: np.ndarray, how: str) -> tuple[float, float]:
    """(value, z) of the largest (``max``), smallest (``min``) or largest-magnitude (``abs``) finite bin; NaN without one."""
    finite = np.isfinite(values) & np.isfinite(z)
    if not finite.any():
        return math.nan, math.nan
    index = np.flatnonzero(finite)
    pick = {"max": np.argmax, "min": np.argmin, "abs": lambda v: np.argmax(np.abs(v))}[how](values[index])
    return float(values[index[pick]]), float(z[index[pick]])


def _curve_summary(result: ReepResult, free_f0_hz: float | None, interaction: Mapping[str, dict]) -> ForceCurve:
    """Per leg: ranges, sensitivities and the extremes a reader looks for, with the z where they occur.

    ``largest_df0_hz`` is the bin mean of f0' farthest from the free-air f0'
    (signed), ``smallest_q`` the lowest bin mean of Q'; ``interaction``
    adds the largest dissipated energy per cycle and force gradient.
    """
    legs = {}
    for leg, table in result.force_curves.items():
        extremes: dict = {}
        if free_f0_hz is not None:
            extremes["largest_df0_hz"], extremes["largest_df0_z"] = _extreme(
                table.z, table.means["f0_hz"] - free_f0_hz, "abs")
        low_q, where = _extreme(table.z, table.means["q"], "min")
        slopes = {name: float(np.nanmax(np.abs(table.sensitivities[name]))) if len(table.z) > 1 else None
                  for name in ("f0_hz", "q", "amplitude")}
        legs[leg] = ForceCurveLeg(
            bins=int(len(table.z)),
            z_range=(float(table.z.min()), float(table.z.max())),
            z_units=result.z_units,
            f0_hz_range=(float(np.nanmin(table.means["f0_hz"])), float(np.nanmax(table.means["f0_hz"]))),
            q_range=(float(np.nanmin(table.means["q"])), float(np.nanmax(table.means["q"]))),
            max_abs_df0_dz=slopes["f0_hz"], max_abs_dq_dz=slopes["q"], max_abs_da_dz=slopes["amplitude"],
            smallest_q=low_q, smallest_q_z=where,
            **extremes, **interaction.get(leg, {}),
        )
    return ForceCurve(**legs)


def _write_force_curves(staged: OutputDir, writer: ResultWriter, result: ReepResult, deflection_units: str,
                        figures: FigureProcess) -> None:
    if not result.force_curves:
        return
    from afmtool.report.images import APPROACH_STYLE, RETRACT_STYLE, write_multi_panel_png

    for leg, table in result.force_curves.items():
        writer.put(f"force_curve/{leg}/z", table.z, result.z_units)
        writer.put(f"force_curve/{leg}/count", table.count)
        for name, values in table.means.items():
            writer.put(f"force_curve/{leg}/{name}", values, SERIES_UNITS.get(name, ""))
            writer.put(f"force_curve/{leg}/d_{name}_dz", table.sensitivities[name])
    styles = {"approach": dict(APPROACH_STYLE), "retract": dict(RETRACT_STYLE)}  # plain dicts pickle (FigureProcess)
    amplitude_units = deflection_units or "input units"
    z_units = result.z_units or "z units"
    # (quantity, units) per panel; a sensitivity's units are the quantity's per z unit
    labels = {"f0_hz": ("f0'", "Hz"), "q": ("Q'", ""), "amplitude": ("amplitude", amplitude_units), "phase_deg": ("phase", "deg")}
    for prefix, key in (("", "means"), ("d", "sensitivities")):
        panels = []
        for name, (quantity, units) in labels.items():
            series = [
                (table.z, getattr(table, key)[name], leg, styles[leg]) for leg, table in result.force_curves.items()
            ]
            if prefix:
                label = f"d{quantity}/dz ({units or '1'}/{z_units})"
            else:
                label = f"{quantity} ({units or 'dimensionless'})"
            panels.append({"y_label": label, "series": series})
        name = "force_curve.png" if not prefix else "force_curve_sensitivity.png"
        figures.draw(
            write_multi_panel_png,
            staged.path(name),
            panels,
            x_label=f"z_piezo ({result.z_units})" if result.z_units else "z_piezo",
            title="REEP force curve" + (" sensitivities (by differences)" if prefix else ""),
        )


def _write_images(staged: OutputDir, writer: ResultWriter, result: ReepResult, deflection_units: str,
                  figures: FigureProcess) -> None:
    if result.geometry is None:
        return
    from afmtool.report.images import ImageStyle, write_scan_images

    def style(quantity: str) -> ImageStyle:
        if quantity == "z":  # the height image of a raster capture with z_piezo
            return ImageStyle("height (z_piezo)", result.z_units, stem="height")
        title, units = _IMAGE_TITLES[quantity]
        return ImageStyle(title, deflection_units if units is None else units)

    write_scan_images(staged.path, result.images, result.geometry, style, writer.put, figures)


#: Image titles of the /interaction quantities (afmtool.models.interaction).
_INTERACTION_TITLES = {
    "k_e_n_per_m": "k_e", "force_gradient_n_per_m": "force gradient k_e - k", "damping_n_s_per_m": "damping c_e",
    "damping_ts_n_s_per_m": "tip-sample damping c_ts", "phi_c_n": "Phi_c", "phi_d_n": "Phi_d",
    "energy_per_cycle_ev": "E_ts per cycle", "power_w": "dissipated power", "virial_j": "virial",
}


def _write_interaction_bins(staged: OutputDir, result: ReepResult, params: ReepParams, sample_rate_hz: float,
                            figures: FigureProcess) -> dict:
    """The /interaction series binned as f0', Q' are: force-curve tables, images, PNG and .gsf.

    The binned quantities are in reep.h5 beside f0', Q', with their units; the
    force-curve panels are drawn in ``force_curve_interaction.png``.  Returns,
    per leg, the largest dissipated energy per cycle and the force gradient of
    largest magnitude, with the z of each (for the report's ``force_curve``).
    """
    from afmtool.analyses.interaction_maps import bin_interaction_series
    from afmtool.io.result_files import open_result_file

    path = staged.path("reep.h5")
    binned = bin_interaction_series(
        path, sample_rate_hz=sample_rate_hz, warmup_samples=int(result.results.summary_after_warmup_samples),
        z_bin=params.z_bin if result.force_curves else None, geometry=result.geometry,
    )
    if binned is None:
        return {}
    with open_result_file(path, mode="r+", what="reep output") as f:
        for leg, table in binned.force_curves.items():
            for name, values in table.means.items():
                f.put(f"force_curve/{leg}/{name}", values, binned.units[name])
        for key, image in sorted(binned.images.items()):
            f.put(f"images/{key}", image, binned.units[key.split("/")[0]], {"row0": "first line scanned"})
    if binned.images:
        from afmtool.report.images import ImageStyle, write_scan_images

        write_scan_images(staged.path, binned.images, result.geometry,
                          lambda quantity: ImageStyle(_INTERACTION_TITLES.get(quantity, quantity), binned.units[quantity]),
                          figures=figures)
    if binned.force_curves:
        _draw_interaction_curves(staged, binned, result.z_units, figures)
    return {leg: _interaction_extremes(table) for leg, table in binned.force_curves.items()}


def _interaction_extremes(table) -> dict[str, float]:
    """The largest energy per cycle and the force gradient of largest magnitude of one leg, with their z.

    Keyed by :class:`~afmtool.records.reep.ForceCurveLeg`'s fields (NaN where no bin is finite).
    """
    out: dict = {}
    for name, how, key in (("energy_per_cycle_ev", "max", "largest_energy_per_cycle"),
                           ("force_gradient_n_per_m", "abs", "largest_force_gradient")):
        if name in table.means:
            value, where = _extreme(table.z, table.means[name], how)
            units = name.split("_per_cycle_")[-1] if "per_cycle" in name else "n_per_m"
            out[f"{key}_{units}"], out[f"{key}_z"] = value, where
    return out


#: The interaction quantities drawn against z, with their labels.
_INTERACTION_PANELS = (
    ("force_gradient_n_per_m", "force gradient k_e − k"), ("damping_ts_n_s_per_m", "tip–sample damping c_ts"),
    ("phi_c_n", "Φ_c (conservative)"), ("energy_per_cycle_ev", "E_ts per cycle"),
)


def _draw_interaction_curves(staged: OutputDir, binned, z_units: str, figures: FigureProcess) -> None:
    """``force_curve_interaction.png``: force gradient, damping, Φ_c and energy per cycle against z."""
    from afmtool.report.images import APPROACH_STYLE, RETRACT_STYLE, write_multi_panel_png

    styles = {"approach": dict(APPROACH_STYLE), "retract": dict(RETRACT_STYLE)}
    panels = []
    for name, label in _INTERACTION_PANELS:
        series = [(table.z, table.means[name], leg, styles[leg]) for leg, table in binned.force_curves.items()
                  if name in table.means]
        if series:
            panels.append({"y_label": f"{label} ({binned.units[name]})", "series": series})
    if panels:
        figures.draw(write_multi_panel_png, staged.path("force_curve_interaction.png"), panels,
                     x_label=f"z_piezo ({z_units})" if z_units else "z_piezo", title="Tip–sample interaction from REEP")
