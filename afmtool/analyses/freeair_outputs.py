"""The ``identify freeair`` command end to end: route, model, files, report."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import NamedTuple

import numpy as np

from afmtool.config import load_toml, resolve_from
from afmtool.config.params import FreeAirParams, SpringConstantParams, parse_interval
from afmtool.config.samples import interval_samples
from afmtool.errors import ConfigError
from afmtool.estimators.free_air_fit import free_air_from_segment
from afmtool.estimators.stages import ChannelMeans, RecordStage, ResponseStage, SegmentStage
from afmtool.io.capture import CaptureReader
from afmtool.io.units import calibration_record
from afmtool.models.free_air import FreeAirModel
from afmtool.pipeline import run_stream
from afmtool.records.common import DriveHold, FreeAirModelRecord
from afmtool.records.freeair import (
    AveragesFrom,
    Detection,
    Fluid,
    FreeAirResults,
    FreeAirRoute,
    SaderSpringConstant,
    SpringConstantParameters,
    SpringConstants,
    SweepMethod,
    ThermalFitRecord,
    ThermalSpectrumRecord,
    ThermalSpringConstant,
    ThermalVariantRecord,
    ValueSpread,
    Weighting,
)
from afmtool.report.json_report import input_record
from afmtool.report.run import finish_run
from afmtool.runtime.outputs import OutputDir

__all__ = ["run_freeair_command", "free_air_model_record"]

#: Samples per chunk of the free-air routes (read ahead two at a time).
_CHUNK_SAMPLES = 1 << 20


class _Identified(NamedTuple):
    """What a route found: the model, the report's results, what it draws in the staged folder, its warnings."""

    model: FreeAirModel
    results: FreeAirResults
    draw: Callable[[OutputDir], None] | None
    warnings: list[str]


def free_air_model_record(model: FreeAirModel) -> FreeAirModelRecord:
    """The report's copy of ``model`` (``free_air.json``'s fields; those of k only where k is known)."""
    return model.record()


def _segment_route(reader: CaptureReader, params: FreeAirParams, progress) -> _Identified:
    """The ARX fit on the free-air segment, and its Bode figure."""
    interval = parse_interval(params.free_air, "--free-air")
    free_air = reader.info.capture_metadata.free_air
    if interval is None and free_air is not None:
        interval = (free_air.start_s, free_air.end_s)
    if interval is None:
        raise ConfigError("give --free-air START:END (s) or a capture with metadata free_air")
    fs = reader.info.sample_rate_hz
    start, end = interval_samples(interval, fs, "free-air segment", reader.info.n_samples)
    stage = SegmentStage(("deflection", "dither"), start, end)
    # the capture is read only up to the segment's end
    (segment,) = run_stream(reader, [stage], channels=("deflection", "dither"), chunk_samples=_CHUNK_SAMPLES,
                            progress=progress, prologue=stage.until_end)
    model = free_air_from_segment(segment["deflection"], segment["dither"], fs)
    units = reader.info.units("deflection") or "input units"
    measured = _segment_lines(segment["deflection"], segment["dither"], fs, model.f0_hz)
    results = FreeAirResults(free_air_model=free_air_model_record(model), route=FreeAirRoute.SEGMENT,
                             segment_s=tuple(interval), segment_samples=end - start)
    return _Identified(model, results,
                       lambda staged: write_segment_bode_png(staged.path("segment_bode.png"), measured, model, units),
                       [])


def _segment_lines(deflection: np.ndarray, dither: np.ndarray, fs: float, f0_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """(Hz, complex H) of the segment at each line of its dither near f0: one DFT bin at each line's frequency."""
    from afmtool.estimators.drive_lines import excitation_lines

    lines = np.asarray(excitation_lines(dither, fs, f0_hz), dtype=np.float64)
    t = np.arange(deflection.size) / fs
    response = []
    for f in lines:
        kernel = np.exp(-2j * np.pi * f * t)
        response.append(np.dot(deflection, kernel) / np.dot(dither, kernel))
    return lines, np.asarray(response, dtype=np.complex128)


def _discrete_response(model: FreeAirModel, frequency_hz: np.ndarray) -> np.ndarray:
    """The fitted ARX model on the unit circle (eq. 3.40), numerator and hold included; else the continuous G."""
    if model.numerator is None or model.denominator is None or not model.sample_rate_hz:
        return model_response(model, frequency_hz)
    z_inv = np.exp(-2j * np.pi * np.asarray(frequency_hz, dtype=np.float64) / model.sample_rate_hz)
    numerator = sum(c * z_inv**k for k, c in enumerate(model.numerator))
    b1, b0 = model.denominator
    return numerator / (1.0 + b1 * z_inv + b0 * z_inv**2)


def write_segment_bode_png(path: Path, measured: tuple[np.ndarray, np.ndarray], model: FreeAirModel, units: str) -> None:
    """The segment route's figure: the fitted model (±1σ) and the segment's response at its drive lines."""
    from afmtool.report.bode import BodeCurve, write_bode_png

    span = max(5.0 * model.f0_hz / model.q, 0.05 * model.f0_hz)
    lines_hz = measured[0]
    low = min([model.f0_hz - span, *(lines_hz - 0.1 * span)])
    high = max([model.f0_hz + span, *(lines_hz + 0.1 * span)])
    fine = np.linspace(max(low, 1.0), high, 2000)
    curves = [BodeCurve(fine, _discrete_response(model, fine), f"ARX fit: f0 = {model.f0_hz:.1f} Hz, Q = {model.q:.1f}",
                        {"color": "C3"}, model_magnitude_std(model, fine))]
    if lines_hz.size:
        curves.append(BodeCurve(lines_hz, measured[1], "segment, at the drive lines",
                                {"color": "C0", "linestyle": "none", "marker": "o"}))
    write_bode_png(path, curves, title="Free-air model from the off-sample segment",
                   magnitude_label=f"|H| (dB re 1 {units})", markers=[(model.f0_hz, "f0")])


def model_response(model: FreeAirModel, frequency_hz: np.ndarray) -> np.ndarray:
    """gain·G(j2πf)·e^(−j2πfτ): eq. 3.1's second-order G with the model's gain and drive delay τ."""
    s = 2j * np.pi * np.asarray(frequency_hz, dtype=np.float64)
    w0 = 2 * np.pi * model.f0_hz
    return model.gain * w0 * w0 / (s * s + (w0 / model.q) * s + w0 * w0) * np.exp(-s * model.delay_s)


def model_magnitude_std(model: FreeAirModel, frequency_hz: np.ndarray) -> np.ndarray:
    """±1σ of |H| of :func:`model_response` from the standard errors of f0, Q and gain.

    First-order propagation with independent errors: σ² = Σ_k (|H(p + σ_k e_k)| − |H(p)|)²,
    each parameter moved by its own standard error (a missing one counts as 0).
    """
    base = np.abs(model_response(model, frequency_hz))
    variance = np.zeros_like(base)
    for name, std_name in (("f0_hz", "f0_std_hz"), ("q", "q_std"), ("gain", "gain_std")):
        std = getattr(model, std_name)
        if std:
            moved = dataclasses.replace(model, **{name: getattr(model, name) + std})
            variance += (np.abs(model_response(moved, frequency_hz)) - base) ** 2
    return np.sqrt(variance)


def write_sweep_bode_png(path: Path, fr, model: FreeAirModel, units: str) -> None:
    """Measured response (±1σ) with the fitted second-order model (±1σ from its parameters' errors)."""
    from afmtool.report.bode import BodeCurve, write_bode_png

    f = np.asarray(fr.frequency_hz, dtype=np.float64)
    # the bins the fit may use (coherence >= 0.5, a finite response); elsewhere the drive put in no power
    keep = (f > 0) & np.isfinite(fr.response) & (np.asarray(fr.coherence) >= 0.5)
    if np.count_nonzero(keep) < 2:
        keep = f > 0
    fine = np.geomspace(f[keep][0], f[keep][-1], 2000)
    write_bode_png(
        path,
        [BodeCurve(f[keep], fr.response[keep], f"measured ({fr.method})", {"color": "C0"}, fr.magnitude_std[keep]),
         BodeCurve(fine, model_response(model, fine), f"fit: f0 = {model.f0_hz:.1f} Hz, Q = {model.q:.1f}",
                   {"color": "C3", "linestyle": "--"}, model_magnitude_std(model, fine))],
        title="Free-air frequency response and its second-order fit",
        magnitude_label=f"|H| (dB re 1 {units})",
        markers=[(model.f0_hz, "f0")],
    )


def _sweep_stage(reader: CaptureReader, params: FreeAirParams):
    """The stage measuring the sweep in one pass, with flat memory where the method allows.

    ``h1`` on a capture of known length: Welch cross spectra accumulated per
    segment (memory O(nperseg + chunk)); ``stepped`` with metadata segments:
    lock-in sums per step (memory O(steps)).  The ``record`` fit (a DFT of the
    whole record), a stepped sine whose steps are found from the dither, and
    H1 on a stream of unknown length (its segment length depends on it) keep
    the dither and deflection records: memory two float64 arrays of the
    capture's length.
    """
    from afmtool.estimators.sweep_spectral import default_nperseg

    method, n = params.sweep_method, reader.info.n_samples
    segments = reader.info.metadata.get("segments") if method == "stepped" else None
    if method == "h1" and n:
        return ResponseStage("dither", ("deflection",), method="h1", nperseg=default_nperseg(n))
    if method == "stepped" and segments is not None:
        return ResponseStage("dither", ("deflection",), method="stepped", segments=segments)
    return RecordStage(("dither", "deflection"))


def _identify_sweep(reader: CaptureReader, params: FreeAirParams, progress):
    """(SweepIdentification, samples read): one pass over the capture through :func:`_sweep_stage`."""
    from afmtool.estimators.sweep_record import check_sweep_options, identify_sweep, identify_sweep_response

    check_sweep_options(params.sweep_method, params.drive_hold)
    stage = _sweep_stage(reader, params)
    measured, means = run_stream(reader, [stage, ChannelMeans()], channels=("dither", "deflection"),
                                 chunk_samples=_CHUNK_SAMPLES, progress=progress)
    if isinstance(stage, ResponseStage):
        return identify_sweep_response(measured["deflection"]), means.count
    segments = reader.info.metadata.get("segments") if params.sweep_method == "stepped" else None
    found = identify_sweep(
        measured["dither"], measured["deflection"], reader.info.sample_rate_hz, method=params.sweep_method,
        segments=segments, hold=params.drive_hold,
    )
    return found, means.count


def _sweep_route(reader: CaptureReader, params: FreeAirParams, progress) -> _Identified:
    """The sweep's model; the record fit draws its measurement against the model, the spectral methods a Bode figure."""
    found, samples = _identify_sweep(reader, params, progress)
    results = FreeAirResults(free_air_model=free_air_model_record(found.model), route=FreeAirRoute.SWEEP,
                             sweep_method=SweepMethod(params.sweep_method), samples=samples,
                             drive_hold=DriveHold(found.hold), drive_hold_reason=found.hold_reason)
    if params.sweep_method == "record":
        fit, fs = found.fit, reader.info.sample_rate_hz
        results = results.replace(
            band_hz=tuple(fit.band_hz), n_bins=fit.n_bins, transient_order=fit.transient_order,
            delay_std_s=fit.delay_std_s, noise_std=fit.noise_std, drive_edges_s=tuple(fit.drive_edges_s),
        )
        return _Identified(found.model, results, lambda staged: _write_sweep_fit(staged, fit, fs), list(found.warnings))
    info = reader.info
    units = f"{info.units('deflection')}/{info.units('dither')}".strip("/") or "input units"

    def draw(staged: OutputDir) -> None:  # once the folder is staged
        write_sweep_bode_png(staged.path("sweep_bode.png"), found.response, found.model, units)

    return _Identified(found.model, results, draw, list(found.warnings))


def _write_sweep_fit(staged: OutputDir, fit, sample_rate_hz: float) -> None:
    """sweep_frf.csv and sweep_bode.png: the transient-corrected measurement against the fitted model."""
    from afmtool.io.rows import RowWriter
    from afmtool.report.bode import BodeCurve, write_bode_png

    f = np.asarray(fit.frequency_hz)
    measured = np.asarray(fit.measured_response)
    model = fit.response(f, sample_rate_hz)
    table = {
        "frequency_hz": f,
        "measured_magnitude": np.abs(measured),
        "measured_phase_deg": np.degrees(np.angle(measured)),
        "model_magnitude": np.abs(model),
        "model_phase_deg": np.degrees(np.angle(model)),
    }
    with (
        open(staged.path("sweep_frf.csv"), "w", encoding="utf-8", newline="") as handle,
        RowWriter(handle, "csv") as rows,
    ):
        rows.append(table)
    write_bode_png(
        staged.path("sweep_bode.png"),
        [
            BodeCurve(f, measured, "measured, transient removed", {"color": "C0", "marker": ".", "linestyle": "none"}),
            BodeCurve(f, model, f"model ({fit.hold} drive): f0 {fit.f0_hz:.1f} Hz, Q {fit.q:.1f}", {"color": "C3"}),
        ],
        title="identify freeair --sweep: whole-record fit",
        magnitude_label="|G| (dB re 1 unit/unit)",
    )


def write_thermal_fit_png(path: Path, frequency_hz: np.ndarray, asd: np.ndarray, fit) -> None:
    """The measured thermal ASD with the fitted oscillator-plus-floor model over it, fit band shaded."""
    from afmtool.report.images import write_multi_panel_png

    f = np.asarray(frequency_hz, dtype=np.float64)
    measured = np.where(np.asarray(asd) > 0, asd, np.nan)
    lo, hi = fit.band_hz
    wide = (f >= max(f[0], lo - 2 * (hi - lo))) & (f <= hi + 2 * (hi - lo))
    panels = [{
        "y_label": "ASD (m/√Hz)",
        "y_scale": "log",
        "series": [
            (f[wide] / 1e3, measured[wide], "measured", {"color": "C0", "linewidth": 0.8}),
            (f[wide] / 1e3, fit.asd(f[wide]), f"fit: f0 = {fit.f0_hz:.1f} ± {fit.f0_std_hz:.2g} Hz, "
             f"Q = {fit.q:.1f} ± {fit.q_std:.2g}", {"color": "C3", "linewidth": 1.4}),
            (f[wide] / 1e3, np.full(np.count_nonzero(wide), fit.floor_asd_m_per_sqrt_hz), "white floor",
             {"color": "0.4", "linestyle": ":"}),
        ],
    }]
    write_multi_panel_png(path, panels, x_label="frequency (kHz)", spans=[(lo / 1e3, hi / 1e3, "fitted band")],
                          title="Thermal-noise spectrum and its simple-harmonic-oscillator fit")


def _psd_spectrum(psd: Path, params: FreeAirParams, invols_nm_per_v: float | None):
    """The ``--psd`` table as a :class:`~afmtool.estimators.thermal_record.ThermalSpectrum` (m/√Hz)."""
    from afmtool.estimators.thermal_record import ThermalSpectrum
    from afmtool.io.psd import read_psd_csv

    table = read_psd_csv(psd, invols_nm_per_v)
    averages = params.averages or table.n_averages
    scaled = bool(invols_nm_per_v and table.source_unit and "V" in table.source_unit)
    details = ThermalSpectrumRecord(
        columns=tuple(table.columns), spectrum=f"{table.source_kind.upper()} in {table.source_unit}",
        n_averages_from=AveragesFrom.GIVEN if params.averages else (
            AveragesFrom.FILE if table.n_averages else AveragesFrom.ESTIMATED),
        invols_nm_per_v=invols_nm_per_v if scaled else None,
    )
    return ThermalSpectrum(table.frequency_hz, table.asd_m_per_sqrt_hz, averages, details)


def _record_spectrum(reader: CaptureReader, params: FreeAirParams, progress):
    """The Welch spectrum of a thermal-noise time record's deflection (streamed, flat memory)."""
    from afmtool.estimators.thermal_record import WelchPsdStage

    if "deflection" not in reader.info.channel_names:
        raise ConfigError("--thermal: the capture has no deflection channel (map one with --channel deflection=...)")
    stage = WelchPsdStage("deflection", resolution_hz=params.resolution_hz)
    (spectrum,) = run_stream(reader, [stage], channels=("deflection",), chunk_samples=_CHUNK_SAMPLES,
                             progress=progress)
    return spectrum


def _thermal_route(spectrum, params: FreeAirParams, spring: SpringConstantParams) -> _Identified:
    """The ML fit of a thermal spectrum, with the spring constant in the model, and its figure."""
    from afmtool.config.params import parse_band
    from afmtool.estimators.thermal_noise import fit_thermal_spectrum

    frequency, asd = spectrum.frequency_hz, spectrum.asd_m_per_sqrt_hz
    fit = fit_thermal_spectrum(frequency, asd, band=parse_band(params.band), temperature_k=params.temperature_k,
                               n_averages=spectrum.n_averages)
    springs = _spring_constants(fit, spring)
    warnings = fit.warnings() + _spring_constant_warnings(springs)
    model = dataclasses.replace(fit.free_air_model(), **_model_spring_constant(springs))
    resolution = float(np.median(np.diff(frequency)))
    if resolution > fit.f0_hz / (2 * fit.q) / 3:
        warnings.append(f"the spectrum's resolution {resolution:.3g} Hz is coarse against the peak's half-width "
                        f"{fit.f0_hz / (2 * fit.q):.3g} Hz: Q is biased low by the window (record longer, or "
                        "give --resolution)")
    results = FreeAirResults(
        free_air_model=free_air_model_record(model), route=FreeAirRoute.THERMAL, spectrum=spectrum.details,
        fit=_thermal_fit_record(fit), floor_asd_m_per_sqrt_hz=fit.floor_asd_m_per_sqrt_hz,
        peak_asd_m_per_sqrt_hz=fit.peak_asd_m_per_sqrt_hz, band_hz=tuple(fit.band_hz), n_bins=fit.n_bins,
        rms_log_residual=fit.rms_log_residual, spring_constant_n_per_m=fit.spring_constant_n_per_m,
        spring_constant_note="equipartition, assuming the ASD is calibrated tip displacement (m/sqrt(Hz))",
        temperature_k=params.temperature_k, spring_constant=springs,
    )

    def draw(staged: OutputDir) -> None:
        write_thermal_fit_png(staged.path("thermal_fit.png"), frequency, asd, fit)

    return _Identified(model, results, draw, warnings)


def _thermal_fit_record(fit) -> ThermalFitRecord:
    """The ML fit's goodness of fit and its spread over bands and weightings, for report.json."""
    return ThermalFitRecord(
        estimator="maximum likelihood, each bin Gamma(M) distributed (averaged periodogram)",
        n_averages=fit.n_averages, n_averages_estimated=fit.n_averages_estimated, deviance=fit.deviance,
        dof=fit.dof, p_value=fit.p_value, dispersion=fit.dispersion, bin_correlation=fit.bin_correlation,
        f0_hz=ValueSpread(value=fit.f0_hz, std=fit.f0_std_hz, systematic=fit.f0_systematic_hz,
                          spread=fit.f0_spread_hz),
        q=ValueSpread(value=fit.q, std=fit.q_std, systematic=fit.q_systematic, spread=fit.q_spread),
        variants=tuple(ThermalVariantRecord(band_hz=tuple(v.band_hz), weighting=Weighting(v.weighting),
                                            f0_hz=v.f0_hz, q=v.q, mean_square_m2=v.mean_square_m2)
                       for v in fit.variants),
    )


def _model_spring_constant(springs: SpringConstants) -> dict:
    """The free_air.json fields of k: the thermal value (statistical and systematic std combined), else Sader's."""
    thermal, sader = springs.thermal, springs.sader
    if thermal.value_n_per_m is not None:
        std = math.hypot(thermal.std_n_per_m or 0.0, thermal.systematic_n_per_m or 0.0)
        source = f"thermal: equipartition, {thermal.detection.value} factor {thermal.factor:.4g}"
        return {"spring_constant_n_per_m": thermal.value_n_per_m, "spring_constant_std_n_per_m": std,
                "spring_constant_source": source}
    if sader is not None:
        return {"spring_constant_n_per_m": sader.value_n_per_m, "spring_constant_std_n_per_m": sader.std_n_per_m,
                "spring_constant_source": "Sader (plan-view length and width, f0 and Q in the fluid)"}
    return {}


def _spring_constant_warnings(springs: SpringConstants) -> list[str]:
    """A warning when the thermal and Sader k differ by more than twice their combined standard uncertainty."""
    thermal, sader = springs.thermal, springs.sader
    if sader is None or thermal.value_n_per_m is None:
        return []
    combined = math.sqrt((thermal.std_n_per_m or 0.0) ** 2 + (thermal.systematic_n_per_m or 0.0) ** 2
                         + (sader.std_n_per_m or 0.0) ** 2)
    difference = abs(thermal.value_n_per_m - sader.value_n_per_m)
    if difference <= 2.0 * combined:
        return []
    return [f"the thermal spring constant {thermal.value_n_per_m:.4g} N/m and the Sader one "
            f"{sader.value_n_per_m:.4g} N/m differ by {difference:.3g} N/m, more than twice their combined "
            f"uncertainty {combined:.2g} N/m: check the InvOLS, the detection factor, and the length and width"]


def _spring_constants(fit, spring: SpringConstantParams) -> SpringConstants:
    """The thermal (Butt–Jaschke corrected) and, with L and b, the Sader spring constants (N/m)."""
    from afmtool.estimators.spring_constant import thermal_factor

    factor = thermal_factor(spring.detection)
    thermal = ThermalSpringConstant(
        method="equipartition of mode 1, k = factor * k_B T / <p^2>",
        detection=Detection(spring.detection),
        factor=factor,
        factor_source="Butt & Jaschke, Nanotechnology 6, 1 (1995): 12/(alpha_1 L)^4 / chi^2 (optical lever, "
        "static InvOLS) or 12/(alpha_1 L)^4 (displacement)",
        temperature_k=fit.temperature_k,
        value_n_per_m=None if fit.spring_constant_n_per_m is None else factor * fit.spring_constant_n_per_m,
        std_n_per_m=None if fit.spring_constant_std is None else factor * fit.spring_constant_std,
        systematic_n_per_m=None if fit.spring_constant_systematic is None
        else factor * fit.spring_constant_systematic,
    )
    parameters = SpringConstantParameters(
        detection=Detection(spring.detection), length_um=spring.length_um, width_um=spring.width_um,
        fluid=Fluid(spring.fluid), fluid_density_kg_per_m3=spring.fluid_density_kg_per_m3,
        fluid_viscosity_pa_s=spring.fluid_viscosity_pa_s,
    )
    sader = _sader(fit, spring) if spring.length_um > 0 and spring.width_um > 0 else None
    return SpringConstants(thermal=thermal, sader=sader, parameters=parameters)


def _sader(fit, spring: SpringConstantParams) -> SaderSpringConstant:
    """Sader's spring constant from the lever's plan view and the fit's f0 and Q in the fluid."""
    from afmtool.estimators.spring_constant import FLUIDS, sader_spring_constant

    density = spring.fluid_density_kg_per_m3 or FLUIDS[spring.fluid][0]
    viscosity = spring.fluid_viscosity_pa_s or FLUIDS[spring.fluid][1]
    # Sader's k is proportional to Q: its std carries Q's systematic spread too
    sader = sader_spring_constant(
        fit.f0_hz, fit.q, spring.length_um * 1e-6, spring.width_um * 1e-6, fluid=spring.fluid,
        density_kg_per_m3=density, viscosity_pa_s=viscosity,
        f0_std_hz=math.hypot(fit.f0_std_hz, fit.f0_systematic_hz), q_std=math.hypot(fit.q_std, fit.q_systematic),
    )
    return SaderSpringConstant(
        method="Sader, Chon & Mulvaney, Rev. Sci. Instrum. 70, 3967 (1999): "
        "k = 0.1906 rho_f b^2 L Q Gamma_i(Re) omega^2",
        value_n_per_m=sader.spring_constant_n_per_m, std_n_per_m=sader.spring_constant_std,
        length_um=spring.length_um, width_um=spring.width_um, fluid=Fluid(spring.fluid),
        fluid_density_kg_per_m3=density, fluid_viscosity_pa_s=viscosity, reynolds=sader.reynolds,
        gamma_imag=sader.gamma_imag,
    )


def run_freeair_command(
    reader: CaptureReader | None,
    source: str | Path,
    out: Path,
    config: Path | None,
    flags: Mapping,
    progress: Callable[[int], None],
) -> dict:
    """Identify the free-air model by the chosen route and write free_air.json + report.

    The thermal route reads a spectrum table (``--psd``, ``reader`` None) or
    computes the spectrum of a thermal-noise time record (``--thermal``,
    ``reader`` open on it).
    """
    user_config = load_toml(config) if config else None
    params = resolve_from(
        FreeAirParams, "identify.freeair", user_config,
        {k: v for k, v in flags.items() if k not in ("spring", "invols_nm_per_v")},
    )
    if params.route == "thermal":
        spring = resolve_from(SpringConstantParams, "identify.spring_constant", user_config, flags.get("spring", {}))
        if reader is None:
            spectrum = _psd_spectrum(Path(source), params, flags.get("invols_nm_per_v"))
            inputs = [input_record(source, "psd")]
        else:
            spectrum = _record_spectrum(reader, params, progress)
            inputs = [{**input_record(source, "thermal record"), **calibration_record(reader)}]
        found = _thermal_route(spectrum, params, spring)
    else:
        route = _sweep_route if params.route == "sweep" else _segment_route
        found = route(reader, params, progress)
        inputs = [{**input_record(source), **calibration_record(reader)}]
    with OutputDir(out) as staged:
        found.model.save(staged.path("free_air.json"))
        if found.draw is not None:
            found.draw(staged)
        return finish_run(staged, "identify freeair", inputs, "identify.freeair", params, found.results,
                          found.warnings)
