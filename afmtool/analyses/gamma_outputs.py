"""The ``identify gamma`` command end to end: read both sweeps, estimate every Γ, write files and report."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import NamedTuple

import numpy as np

from afmtool.config import load_toml, resolve_from
from afmtool.config.params import GammaParams
from afmtool.errors import InputError
from afmtool.estimators.frequency_response import FrequencyResponse, frf_table
from afmtool.estimators.sensing_gamma import (
    CANONICAL_UNITS,
    GammaResponses,
    SensingSummary,
    auto_nperseg,
    canonical_scale,
    combine_gamma,
    feedthrough_rise,
    fit_feedthrough,
    gamma_response_stage,
    scale_response,
    sensing_summary,
    usable_band,
    usable_mask,
)
from afmtool.estimators.stages import ChannelMeans, progress_offset
from afmtool.io.capture import CaptureReader
from afmtool.io.chunks import require_channels
from afmtool.io.results import ResultWriter
from afmtool.io.units import calibration_record
from afmtool.pipeline import run_stream
from afmtool.records.gamma import (
    FeedthroughFitRecord,
    FeedthroughRiseRecord,
    GammaOperatingPoint,
    GammaResults,
    GammaSamples,
    GammaUnits,
    ResponseMethod,
    SensingSummaryRecord,
)
from afmtool.report.json_report import input_record
from afmtool.report.run import finish_run
from afmtool.runtime.outputs import OutputDir

__all__ = ["run_gamma_command", "GAMMA_UNITS"]

#: Units of the Γ responses once the channels are in µA, nm and V.
GAMMA_UNITS = {"ir_v": "uA/V", "ts_v": "nm/V", "feedthrough": "uA/V", "ir_ts": "uA/nm", "ir_ts_uncorrected": "uA/nm"}
#: H1 segment length for a sweep read from a stream, whose length is not known in advance.
_STREAM_NPERSEG = 1 << 14
_TITLES = {
    "ir_v": "Gamma_IR,V near the sample",
    "ts_v": "Gamma_ts,V (optical deflection)",
    "feedthrough": "Gamma_sp, tip in contact (feed-through)",
    "ir_ts": "Gamma_IR,ts (eq. 6.15)",
    "ir_ts_uncorrected": "Gamma_IR,V / Gamma_ts,V (eq. 6.16, uncorrected)",
}


def _method(params: GammaParams, sweep: CaptureReader, contact: CaptureReader) -> str:
    if params.method != "auto":
        return params.method
    both = "segments" in sweep.info.metadata and "segments" in contact.info.metadata
    return "stepped" if both else "h1"


def _scales(reader: CaptureReader, channels: Mapping[str, str], warnings: list[str]) -> dict[str, float]:
    factors = {}
    for name, kind in channels.items():
        factor, assumed = canonical_scale(kind, reader.info.units(name), name)
        if assumed:
            warnings.append(f"{reader.info.source}: channel {name!r} has no units; assumed {CANONICAL_UNITS[kind]}")
        factors[name] = factor
    return factors


def _estimate(
    reader: CaptureReader, ys: tuple[str, ...], params: GammaParams, method: str, nperseg: int, progress
) -> tuple[dict[str, FrequencyResponse], ChannelMeans]:
    """One pass over ``reader``: the responses from v_sub to ``ys`` and the channels' means (flat memory)."""
    segments = reader.info.metadata.get("segments") if method == "stepped" else None
    stage = gamma_response_stage(
        "v_sub", ys, method=method, nperseg=nperseg, segments=segments,
        settle_fraction=params.settle_fraction, min_periods=params.min_periods,
    )
    responses, means = run_stream(reader, [stage, ChannelMeans()], channels=("v_sub", *ys),
                                  chunk_samples=params.chunk_samples, progress=progress)
    return responses, means


class GammaFacts(NamedTuple):
    """What the results say about the run beside the summary: the method, its resolution, the operating point."""

    method: ResponseMethod
    nperseg: int | None
    frequency_resolution_hz: float | None
    n_frequencies: int
    samples: GammaSamples
    operating_point: GammaOperatingPoint


def estimate_from_captures(
    sweep: CaptureReader, contact: CaptureReader, params: GammaParams, progress: Callable[[int], None], warnings: list
) -> tuple[GammaResponses, GammaFacts]:
    """Every Γ in µA, nm and V from the near-sample and contact sweeps, and facts about the run."""
    require_channels(sweep.info, ("v_sub", "thermal_current", "deflection"))
    require_channels(contact.info, ("v_sub", "thermal_current"))
    s_near = _scales(sweep, {"v_sub": "voltage", "thermal_current": "current", "deflection": "length"}, warnings)
    s_far = _scales(contact, {"v_sub": "voltage", "thermal_current": "current"}, warnings)
    method = _method(params, sweep, contact)
    n_sweep = sweep.info.n_samples or 0
    if params.nperseg:
        nperseg = params.nperseg
    elif n_sweep:
        nperseg = auto_nperseg(n_sweep)
    else:
        nperseg = _STREAM_NPERSEG
        warnings.append(f"the sweep's length is unknown (a stream): nperseg={nperseg}; set nperseg to choose")
    if sweep.info.sample_rate_hz != contact.info.sample_rate_hz and method == "h1":
        warnings.append("the sweeps have different sample rates; Gamma_sp is interpolated onto the sweep's grid")
    near, near_means = _estimate(sweep, ("thermal_current", "deflection"), params, method, nperseg, progress)
    far, contact_means = _estimate(contact, ("thermal_current",), params, method, nperseg,
                                   progress_offset(progress, n_sweep))
    gamma = combine_gamma(
        scale_response(near["thermal_current"], s_near["thermal_current"] / s_near["v_sub"]),
        scale_response(near["deflection"], s_near["deflection"] / s_near["v_sub"]),
        scale_response(far["thermal_current"], s_far["thermal_current"] / s_far["v_sub"]),
    )
    facts = GammaFacts(
        method=ResponseMethod(method),
        nperseg=nperseg if method == "h1" else None,
        frequency_resolution_hz=sweep.info.sample_rate_hz / nperseg if method == "h1" else None,
        n_frequencies=int(gamma.frequency_hz.size),
        samples=GammaSamples(sweep=near_means.count, contact=contact_means.count),
        operating_point=GammaOperatingPoint(
            v_sub_mean_v=near_means.mean("v_sub") * s_near["v_sub"],
            thermal_current_mean_ua=near_means.mean("thermal_current") * s_near["thermal_current"],
            deflection_mean_nm=near_means.mean("deflection") * s_near["deflection"],
            contact_thermal_current_mean_ua=contact_means.mean("thermal_current") * s_far["thermal_current"],
        ),
    )
    return gamma, facts


def _summary_record(summary: SensingSummary) -> SensingSummaryRecord:
    return SensingSummaryRecord(
        dc_sensitivity_ua_per_nm=summary.dc_sensitivity,
        bandwidth_hz=summary.bandwidth_hz,
        roll_off_db_per_decade=summary.roll_off_db_per_decade,
        roll_off_band_hz=summary.roll_off_band_hz,
        dc_band_hz=summary.dc_band_hz,
    )


def _feedthrough_fit(gamma: GammaResponses, params: GammaParams, warnings: list) -> FeedthroughFitRecord | None:
    """The feed-through's first-order fit; None (with a warning) where the contact sweep is too little coherent."""
    try:
        sp = fit_feedthrough(gamma.feedthrough, params.min_coherence)
    except InputError as exc:
        warnings.append(f"feed-through: no fit ({exc})")
        return None
    return FeedthroughFitRecord(
        capacitance_pf=sp.capacitance_pf,
        pole_hz=sp.pole_hz,
        numerator_ua_per_v=tuple(sp.fit.numerator),
        denominator=tuple(sp.fit.denominator),
        rms_residual_ua_per_v=sp.fit.rms_residual,
        band_hz=sp.band_hz,
        form="(b1 s + b0)/(s + a0), s in rad/s",
    )


def summarise(
    gamma: GammaResponses, facts: GammaFacts, params: GammaParams, warnings: list
) -> tuple[GammaResults, np.ndarray]:
    """The results: the facts, the usable band, DC sensitivity, bandwidth, roll-off, the uncorrected view; and the mask."""
    mask = usable_mask(gamma, params.min_coherence)
    band = usable_band(gamma.frequency_hz, mask)
    kwargs = {"roll_off_start_factor": params.roll_off_start_factor, "roll_off_stop_factor": params.roll_off_stop_factor}
    corrected = sensing_summary(gamma.ir_ts, mask, **kwargs)
    try:
        uncorrected = _summary_record(sensing_summary(gamma.ir_ts_uncorrected, mask, **kwargs))
    except InputError as exc:
        uncorrected = None
        warnings.append(f"uncorrected Gamma (eq. 6.16): no summary ({exc})")
    rise = feedthrough_rise(gamma.ir_ts, gamma.ir_ts_uncorrected, mask)
    results = GammaResults(
        **facts._asdict(),
        units=GammaUnits(**GAMMA_UNITS),
        min_coherence=params.min_coherence,
        usable_band_hz=band,
        usable_bins=int(np.count_nonzero(mask)),
        dc_sensitivity_ua_per_nm=corrected.dc_sensitivity,
        bandwidth_hz=corrected.bandwidth_hz,
        roll_off_db_per_decade=corrected.roll_off_db_per_decade,
        roll_off_band_hz=corrected.roll_off_band_hz,
        dc_band_hz=corrected.dc_band_hz,
        uncorrected=uncorrected,
        feedthrough_rise=FeedthroughRiseRecord(
            excess_db=rise.excess_db,
            uncorrected_slope_db_per_decade=rise.uncorrected_slope_db_per_decade,
            corrected_slope_db_per_decade=rise.corrected_slope_db_per_decade,
            band_hz=rise.band_hz,
        ),
        feedthrough_fit=_feedthrough_fit(gamma, params, warnings),
    )
    if not np.isfinite(corrected.bandwidth_hz):
        warnings.append("|Gamma_IR,ts| never falls 3 dB below its DC value in the usable band: no bandwidth")
    return results, mask


def _write_tables(staged: OutputDir, gamma: GammaResponses, facts: GammaFacts) -> None:
    from afmtool.io.rows import RowWriter

    attrs = {"afmtool_command": "identify gamma",
             "thermal_current_mean_ua": facts.operating_point.thermal_current_mean_ua}
    with ResultWriter(staged.path("gamma.h5"), {}, attrs) as writer:
        writer.put("frf/frequency_hz", gamma.frequency_hz, "Hz")
        for name, units in GAMMA_UNITS.items():
            fr: FrequencyResponse = getattr(gamma, name)
            writer.put(f"frf/{name}", fr.response, units, {"description": _TITLES[name]})
            writer.put(f"frf/coherence_{name}", fr.coherence, "")
            writer.put(f"frf/magnitude_std_{name}", fr.magnitude_std, units)
            with open(staged.path(f"frf_{name}.csv"), "w", encoding="utf-8", newline="") as handle:
                with RowWriter(handle, "csv") as rows:
                    rows.append(frf_table(fr))


def _feedthrough_model(fit: FeedthroughFitRecord | None, frequency_hz: np.ndarray) -> np.ndarray | None:
    """The fitted feed-through (b1 s + b0)/(s + a0), s = j2πf in rad/s, µA/V; None without a fit."""
    if fit is None:
        return None
    (b1, b0), (_, a0) = fit.numerator_ua_per_v, fit.denominator
    s = 2j * np.pi * np.asarray(frequency_hz, dtype=np.float64)
    return (b1 * s + b0) / (s + a0)


def _write_plots(staged: OutputDir, gamma: GammaResponses, results: GammaResults, mask: np.ndarray) -> None:
    """Bode plots; Γ_IR,ts and eq. 6.16 are drawn over the usable bins only (noise elsewhere)."""
    from afmtool.report.bode import BodeCurve, write_bode_png

    f = gamma.frequency_hz
    markers = [(results.bandwidth_hz, "-3 dB")] if np.isfinite(results.bandwidth_hz) else []

    def usable(fr: FrequencyResponse) -> np.ndarray:
        return np.where(mask, fr.response, np.nan)

    write_bode_png(
        staged.path("gamma_ir_ts.png"),
        [
            BodeCurve(f, usable(gamma.ir_ts), "corrected, eq. 6.15", {"color": "C0"}, gamma.ir_ts.magnitude_std),
            BodeCurve(f, usable(gamma.ir_ts_uncorrected), "uncorrected, eq. 6.16", {"color": "C3", "linestyle": "--"}),
        ],
        title="Sensing transfer function Gamma_IR,ts",
        magnitude_label="|Gamma_IR,ts| (dB re 1 uA/nm)",
        markers=markers,
    )
    lo, hi = results.usable_band_hz
    driven = (f >= lo) & (f <= hi)  # the feed-through's own coherence is low at low f: drawn, not masked
    feedthrough_curves = [
        BodeCurve(f[driven], gamma.ir_v.response[driven], "Gamma_IR,V near the sample", {"color": "C0"},
                  gamma.ir_v.magnitude_std[driven]),
        BodeCurve(f[driven], gamma.feedthrough.response[driven], "Gamma_sp in contact (feed-through)",
                  {"color": "C3"}, gamma.feedthrough.magnitude_std[driven]),
    ]
    fit = results.feedthrough_fit
    in_fit_band = (f >= fit.band_hz[0]) & (f <= fit.band_hz[1]) if fit is not None else driven
    fitted = _feedthrough_model(fit, f[in_fit_band])
    if fitted is not None and fitted.size:
        feedthrough_curves.append(BodeCurve(f[in_fit_band], fitted, "fitted (b1 s + b0)/(s + a0), fit band",
                                            {"color": "k", "linestyle": ":"}))
    write_bode_png(
        staged.path("feedthrough.png"),
        feedthrough_curves,
        title="V_sub to thermal current: near the sample and in contact",
        magnitude_label="|Gamma| (dB re 1 uA/V)",
    )
    write_bode_png(
        staged.path("gamma_ts_v.png"),
        [BodeCurve(f[driven], gamma.ts_v.response[driven], "Gamma_ts,V", {"color": "C2"}, gamma.ts_v.magnitude_std[driven])],
        title="V_sub to tip-sample separation (optical deflection)",
        magnitude_label="|Gamma_ts,V| (dB re 1 nm/V)",
    )


def run_gamma_command(
    sweep: CaptureReader,
    contact: CaptureReader,
    sources: tuple[str | Path, str | Path],
    out: Path,
    config: Path | None,
    flags: Mapping,
    progress: Callable[[int], None],
) -> dict:
    """Estimate Γ_IR,V, Γ_ts,V, Γ_sp, Γ_IR,ts (eq. 6.15) and eq. 6.16; write gamma.h5, CSV, PNG and report."""
    params = resolve_from(GammaParams, "identify.gamma", load_toml(config) if config else None, flags)
    warnings: list[str] = []
    gamma, facts = estimate_from_captures(sweep, contact, params, progress, warnings)
    results, mask = summarise(gamma, facts, params, warnings)
    inputs = [
        {**input_record(sources[0], "sweep"), **calibration_record(sweep)},
        {**input_record(sources[1], "contact"), **calibration_record(contact)},
    ]
    with OutputDir(out) as staged:
        _write_tables(staged, gamma, facts)
        _write_plots(staged, gamma, results, mask)
        return finish_run(staged, "identify gamma", inputs, "identify.gamma", params, results, warnings)
