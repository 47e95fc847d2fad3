"""The ``identify freeair`` command end to end: route, model, files, report."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np

from afmtool.analyses.freeair import free_air_from_segment, read_segment
from afmtool.config import load_toml, resolve_from
from afmtool.config.params import FreeAirParams, SpringConstantParams, parse_interval
from afmtool.errors import ConfigError
from afmtool.io.capture import CaptureReader
from afmtool.io.chunks import iter_chunks
from afmtool.io.units import calibration_record
from afmtool.models.free_air import FreeAirModel
from afmtool.report.json_report import input_record
from afmtool.report.outputs import OutputDir
from afmtool.report.run import finish_run

__all__ = ["run_freeair_command"]


def _segment_route(reader: CaptureReader, params: FreeAirParams, progress) -> tuple[FreeAirModel, dict]:
    interval = parse_interval(params.free_air, "--free-air")
    if interval is None and "free_air" in reader.info.metadata:
        meta = reader.info.metadata["free_air"]
        interval = (float(meta["start_s"]), float(meta["end_s"]))
    if interval is None:
        raise ConfigError("give --free-air START:END (s) or a capture with metadata free_air")
    fs = reader.info.sample_rate_hz
    start, end = round(interval[0] * fs), round(interval[1] * fs)
    chunks = iter_chunks(reader, ("deflection", "dither"), 1 << 20, progress=progress)
    segment, _ = read_segment(chunks, ("deflection", "dither"), start, end)
    model = free_air_from_segment(segment["deflection"], segment["dither"], fs)
    return model, {"segment_s": list(interval), "segment_samples": end - start}


def _sweep_route(reader: CaptureReader, params: FreeAirParams, progress) -> tuple[FreeAirModel, dict]:
    from afmtool.estimators.frequency_response import free_air_from_sweep

    chunks = list(iter_chunks(reader, ("dither", "deflection"), 1 << 20, progress=progress))
    dither = np.concatenate([c.data["dither"] for c in chunks])
    deflection = np.concatenate([c.data["deflection"] for c in chunks])
    segments = reader.info.metadata.get("segments") if params.sweep_method == "stepped" else None
    model = free_air_from_sweep(
        dither, deflection, reader.info.sample_rate_hz, method=params.sweep_method, segments=segments
    )
    return model, {"sweep_method": params.sweep_method, "samples": len(dither)}


def _thermal_route(psd: Path, params: FreeAirParams, spring: SpringConstantParams) -> tuple[FreeAirModel, dict, tuple]:
    from afmtool.estimators.thermal_noise import fit_thermal_spectrum
    from afmtool.io.psd import read_psd_csv

    frequency, asd = read_psd_csv(psd)
    fit = fit_thermal_spectrum(frequency, asd, temperature_k=params.temperature_k)
    model = fit.free_air_model()
    details = {
        "floor_asd_m_per_sqrt_hz": fit.floor_asd_m_per_sqrt_hz,
        "peak_asd_m_per_sqrt_hz": fit.peak_asd_m_per_sqrt_hz,
        "band_hz": list(fit.band_hz),
        "n_bins": fit.n_bins,
        "rms_log_residual": fit.rms_log_residual,
        "spring_constant_n_per_m": fit.spring_constant_n_per_m,
        "spring_constant_note": "equipartition, assuming the ASD is calibrated tip displacement (m/sqrt(Hz))",
        "temperature_k": params.temperature_k,
        "spring_constant": _spring_constants(fit, spring),
    }
    return model, details, (frequency, asd, fit)


def _spring_constants(fit, spring: SpringConstantParams) -> dict:
    """The thermal (Butt–Jaschke corrected) and, with L and b, the Sader spring constants (N/m)."""
    from afmtool.estimators.spring_constant import FLUIDS, sader_spring_constant, thermal_factor

    factor = thermal_factor(spring.detection)
    thermal = {
        "method": "equipartition of mode 1, k = factor * k_B T / <p^2>",
        "detection": spring.detection,
        "factor": factor,
        "factor_source": "Butt & Jaschke, Nanotechnology 6, 1 (1995): 12/(alpha_1 L)^4 / chi^2 (optical lever, "
        "static InvOLS) or 12/(alpha_1 L)^4 (displacement)",
        "temperature_k": fit.temperature_k,
        "value_n_per_m": None if fit.spring_constant_n_per_m is None else factor * fit.spring_constant_n_per_m,
        "std_n_per_m": None if fit.spring_constant_std is None else factor * fit.spring_constant_std,
    }
    result = {"thermal": thermal, "sader": None, "parameters": dataclasses.asdict(spring)}
    if spring.length_um > 0 and spring.width_um > 0:
        density = spring.fluid_density_kg_per_m3 or FLUIDS[spring.fluid][0]
        viscosity = spring.fluid_viscosity_pa_s or FLUIDS[spring.fluid][1]
        sader = sader_spring_constant(
            fit.f0_hz, fit.q, spring.length_um * 1e-6, spring.width_um * 1e-6, fluid=spring.fluid,
            density_kg_per_m3=density, viscosity_pa_s=viscosity, f0_std_hz=fit.f0_std_hz, q_std=fit.q_std,
        )
        result["sader"] = {
            "method": "Sader, Chon & Mulvaney, Rev. Sci. Instrum. 70, 3967 (1999): "
            "k = 0.1906 rho_f b^2 L Q Gamma_i(Re) omega^2",
            "value_n_per_m": sader.spring_constant_n_per_m,
            "std_n_per_m": sader.spring_constant_std,
            "length_um": spring.length_um,
            "width_um": spring.width_um,
            "fluid": spring.fluid,
            "fluid_density_kg_per_m3": density,
            "fluid_viscosity_pa_s": viscosity,
            "reynolds": sader.reynolds,
            "gamma_imag": sader.gamma_imag,
        }
    return result


def _plot_thermal(path: Path, spectrum: tuple) -> None:
    from afmtool.report.images import write_line_plot_png

    frequency, asd, fit = spectrum
    positive = (frequency > 0) & (asd > 0)
    lo, hi = fit.band_hz
    band = positive & (frequency >= lo) & (frequency <= hi)
    write_line_plot_png(
        path,
        [
            (frequency[positive] / 1e3, np.log10(asd[positive]), "spectrum", {"color": "0.55", "linewidth": 0.7}),
            (frequency[band] / 1e3, np.log10(fit.asd(frequency[band])),
             f"fit: f0 {fit.f0_hz / 1e3:.4g} kHz, Q {fit.q:.4g}", {"color": "C3"}),
        ],
        x_label="frequency (kHz)",
        y_label="log10 ASD (m/sqrt(Hz))",
        title="Thermal spectrum and simple-harmonic-oscillator fit",
        markers=[(lo / 1e3, "band"), (hi / 1e3, "band")],
    )


def run_freeair_command(
    reader: CaptureReader | None,
    source: str | Path,
    out: Path,
    config: Path | None,
    flags: Mapping,
    progress: Callable[[int], None],
) -> dict:
    """Identify the free-air model by the chosen route and write free_air.json + report."""
    user_config = load_toml(config) if config else None
    params = resolve_from(
        FreeAirParams, "identify.freeair", user_config, {k: v for k, v in flags.items() if k != "spring"}
    )
    spectrum = None
    if params.route == "thermal":
        spring = resolve_from(SpringConstantParams, "identify.spring_constant", user_config, flags.get("spring", {}))
        model, details, spectrum = _thermal_route(Path(source), params, spring)
        inputs = [input_record(source, "psd")]
    elif params.route == "sweep":
        model, details = _sweep_route(reader, params, progress)
        inputs = [{**input_record(source), **calibration_record(reader)}]
    else:
        model, details = _segment_route(reader, params, progress)
        inputs = [{**input_record(source), **calibration_record(reader)}]
    with OutputDir(out) as staged:
        model.save(staged.path("free_air.json"))
        if spectrum is not None:
            _plot_thermal(staged.path("thermal_fit.png"), spectrum)
        results = {"free_air_model": model.to_dict(), "route": params.route, **details}
        return finish_run(staged, "identify freeair", inputs, "identify.freeair", params, results, [])
