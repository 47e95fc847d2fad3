"""The ``identify freeair`` command end to end: route, model, files, report."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np

from afmtool.analyses.freeair import free_air_from_segment, read_segment
from afmtool.config import load_toml, resolve_from
from afmtool.config.params import FreeAirParams, parse_interval
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


def _thermal_route(psd: Path, params: FreeAirParams) -> tuple[FreeAirModel, dict]:
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
    }
    return model, details


def run_freeair_command(
    reader: CaptureReader | None,
    source: str | Path,
    out: Path,
    config: Path | None,
    flags: Mapping,
    progress: Callable[[int], None],
) -> dict:
    """Identify the free-air model by the chosen route and write free_air.json + report."""
    params = resolve_from(FreeAirParams, "identify.freeair", load_toml(config) if config else None, flags)
    if params.route == "thermal":
        model, details = _thermal_route(Path(source), params)
        inputs = [input_record(source, "psd")]
    elif params.route == "sweep":
        model, details = _sweep_route(reader, params, progress)
        inputs = [{**input_record(source), **calibration_record(reader)}]
    else:
        model, details = _segment_route(reader, params, progress)
        inputs = [{**input_record(source), **calibration_record(reader)}]
    with OutputDir(out) as staged:
        model.save(staged.path("free_air.json"))
        results = {"free_air_model": model.to_dict(), "route": params.route, **details}
        return finish_run(staged, "identify freeair", inputs, "identify.freeair", params, results, [])
