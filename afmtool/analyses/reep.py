"""``afmtool reep``: equivalent f0′ and Q′ every sample, beside amplitude and phase.

capture → chunks → BCEWRLS kernel (eq. 3.39, θ = [b1, b0], numerator fixed at
its free-air value, §3.3.3) → f0′, Q′ by eq. 3.48 → decimated series in
``reep.h5``, force-curve tables and scan images, and a summary for
``report.json``.  Every filter carries its state across chunks, so the
output does not depend on the chunk size.  Samples whose fit cannot be
trusted are flagged (:mod:`afmtool.analyses.reep_validity`) and left out of
everything but ``reep.h5``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from afmtool.analyses.accumulators import ForceCurveAccumulator, ImageAccumulator, ScanGeometry
from afmtool.analyses.freeair import replay_held
from afmtool.analyses.reep_validity import (
    FlagCounter,
    FreeAirLevels,
    OffsetDrift,
    ValidityLimits,
    free_air_levels,
    validity_flags,
)
from afmtool.config.params import ReepParams
from afmtool.errors import InputError
from afmtool.io.capture import CaptureReader, Chunk
from afmtool.io.chunks import iter_chunks
from afmtool.io.prefetch import prefetch
from afmtool.io.results import ResultWriter
from afmtool.models.free_air import FreeAirModel
from afmtool.report.results import JsonResults

__all__ = ["ReepResult", "run_reep", "excitation_lines", "SERIES_UNITS"]

#: Quantities kept per decimated sample, with their units ("" = dimensionless).
SERIES_UNITS = {
    "t": "s",
    "f0_hz": "Hz",
    "q": "",
    "b1": "",
    "b0": "",
    "sigma2": "deflection units^2",
    "amplitude": "deflection units",
    "phase_deg": "deg",
    "offset": "deflection units",
    "flag": "",
}
_IMAGE_QUANTITIES = ("f0_hz", "q", "amplitude", "phase_deg")
_CURVE_QUANTITIES = ("f0_hz", "q", "amplitude", "phase_deg")
#: Chunks read ahead in a background thread while the kernels run on the current one.
_READ_AHEAD = 2


@dataclass
class _Summary:
    """Running sums of the post-warm-up series (mean, std, min, max)."""

    count: int = 0
    total: float = 0.0
    total_sq: float = 0.0
    low: float = math.inf
    high: float = -math.inf

    def add(self, values: np.ndarray) -> None:
        values = values[np.isfinite(values)]
        if values.size:
            self.count += values.size
            self.total += float(values.sum())
            self.total_sq += float(np.square(values).sum())  # not np.dot: BLAS start-up costs ms per call
            self.low = min(self.low, float(values.min()))
            self.high = max(self.high, float(values.max()))

    def as_dict(self) -> dict:
        if not self.count:
            return {"count": 0, "mean": None, "std": None, "min": None, "max": None}
        mean = self.total / self.count
        var = max(self.total_sq / self.count - mean * mean, 0.0)
        return {"count": self.count, "mean": mean, "std": math.sqrt(var), "min": self.low, "max": self.high}


@dataclass(frozen=True)
class ReepResult(JsonResults):
    """What ``run_reep`` found; the command turns it into files and a report."""

    results: dict
    warnings: tuple[str, ...]
    images: dict[str, np.ndarray] = field(default_factory=dict)
    geometry: ScanGeometry | None = None
    force_curves: dict = field(default_factory=dict)
    z_units: str = ""


def excitation_lines(dither: np.ndarray, sample_rate_hz: float, f0_hz: float) -> list[float]:
    """Frequencies (Hz) of the distinct spectral lines of the dither near resonance.

    A line is a local maximum of the Hann-windowed periodogram within ±25 %
    of f0 and within 30 dB of the strongest one; of two maxima closer than
    500 Hz only the higher counts.  REEP's five-parameter free-air
    identification needs three (§3.3.2).

    numpy only (``scipy.signal.periodogram``/``find_peaks`` would import
    scipy.signal, the largest part of REEP's start-up).
    """
    n = min(len(dither), 1 << 16)
    if n < 64:
        return []
    x = np.asarray(dither[:n], dtype=np.float64)
    window = np.hanning(n + 1)[:-1]  # periodic Hann, as scipy's periodogram uses
    power = np.abs(np.fft.rfft((x - x.mean()) * window)) ** 2
    freqs = np.fft.rfftfreq(n, 1.0 / sample_rate_hz)
    band = (freqs > 0.75 * f0_hz) & (freqs < 1.25 * f0_hz)
    if not band.any() or power[band].max() <= 0:
        return []
    power = np.where(band, power, 0.0)
    threshold = power.max() * 1e-3
    inner = power[1:-1]
    maxima = np.flatnonzero((inner > power[:-2]) & (inner >= power[2:]) & (inner >= threshold)) + 1
    min_bins = max(1, int(500 * n / sample_rate_hz))
    kept: list[int] = []
    for index in sorted(maxima, key=lambda i: -power[i]):  # highest first, as find_peaks(distance=...)
        if all(abs(index - other) >= min_bins for other in kept):
            kept.append(index)
    return [float(freqs[i]) for i in sorted(kept)]


def _spectral_peak_hz(x: np.ndarray, sample_rate_hz: float) -> float:
    from afmtool.estimators.filters import welch_psd

    freqs, power = welch_psd(x, sample_rate_hz, min(len(x), 1 << 14))
    power[freqs < 1e3] = 0.0
    return float(freqs[int(np.argmax(power))])


class _Bandpass:
    """Causal Butterworth band-pass with carried state (output-only mode)."""

    def __init__(self, centre_hz: float, half_width_hz: float, sample_rate_hz: float) -> None:
        from scipy.signal import butter, sosfilt_zi

        low = max(centre_hz - half_width_hz, 1.0)
        high = min(centre_hz + half_width_hz, 0.49 * sample_rate_hz)
        self.sos = butter(2, [low, high], btype="bandpass", fs=sample_rate_hz, output="sos")
        self.zi = sosfilt_zi(self.sos) * 0.0

    def __call__(self, x: np.ndarray) -> np.ndarray:
        from scipy.signal import sosfilt

        y, self.zi = sosfilt(self.sos, x, zi=self.zi)
        return y


def _resolve_model(reader: CaptureReader, params: ReepParams, model: FreeAirModel | None, chunks):
    """Return (model or None, chunks to process, free-air segment seconds or None, FreeAirRoute or None).

    The route (``f0-q``, ``model``, ``segment``) and the drive's hold are
    :func:`~afmtool.analyses.freeair_route.resolve_free_air`'s.
    """
    from afmtool.analyses.freeair_route import resolve_free_air

    if not params.use_input:
        return model, chunks, None, None
    route, chunks = resolve_free_air(
        reader, chunks, given=model, free_air=params.free_air, f0_hz=params.f0_hz, q=params.q,
        drive_hold=params.drive_hold, drive_frequency_hz=params.drive_frequency_hz,
        required=model is None,
    )
    if route is None:
        return model, chunks, None, None
    segment_s = route.segment.interval_s if route.segment is not None else None
    return route.model, chunks, segment_s, route


def _segment_levels(segment, params: ReepParams, numerator, lockin, bandpass_factory) -> FreeAirLevels:
    """σ̂² and amplitude in free air, by the run's own estimators over the free-air segment."""
    from afmtool.estimators.rls import ReepState, reep_update

    p = segment.data["deflection"]
    g = segment.data.get("dither") if params.use_input else None
    bandpass = bandpass_factory()
    block = reep_update(
        ReepState.initial(lam=params.lam, p0=params.p0, static_offset=params.static_offset),
        bandpass(p) if bandpass is not None else p, g, numerator,
        bias_compensation=params.bias_compensation, use_input=params.use_input,
    ).block
    if params.use_input:
        demod, _ = lockin.process_against(p, g, lockin.initial_state(2))
    else:
        demod = lockin.process(p, lockin.initial_state(1))[0][0]
    warmup = int(params.warmup_windows / (1.0 - params.lam))
    return free_air_levels(block.sigma2, demod.amplitude, min(warmup, len(p) // 2))


def _metadata_levels(reader: CaptureReader) -> FreeAirLevels:
    """Without a free-air segment: the free amplitude from metadata (when the deflection is in nm)."""
    amplitude = reader.info.capture_metadata.drive.free_amplitude_nm
    if amplitude and reader.info.units("deflection") == "nm":
        return FreeAirLevels(float(amplitude), None, "metadata")
    return FreeAirLevels(None, None, "none")


def run_reep(
    reader: CaptureReader,
    params: ReepParams,
    writer: ResultWriter,
    *,
    model: FreeAirModel | None = None,
    progress: Callable[[int], None] | None = None,
) -> ReepResult:
    """Run REEP over a whole capture, streaming, and write the decimated series.

    Parameters
    ----------
    reader : CaptureReader
        Needs ``deflection``, and ``dither`` unless ``params.use_input`` is off.
    params : ReepParams
        Effective parameters.
    writer : ResultWriter
        Receives ``t``, ``f0_hz``, ``q``, ``b1``, ``b0``, ``sigma2``,
        ``amplitude``, ``phase_deg`` (and ``z`` for force curves), decimated.
    model : FreeAirModel, optional
        A given free-air model; otherwise it is identified from the
        free-air segment (``params.free_air`` or the capture metadata).
    """
    from afmtool.estimators.lockin import LockIn, default_lowpass_hz
    from afmtool.estimators.rls import ReepState, reep_update
    from afmtool.models.discretisation import resonance_from_denominator

    info = reader.info
    fs = info.sample_rate_hz
    warnings: list[str] = []
    z_mode = params.vs == "z" or (params.vs == "auto" and "z_piezo" in info.channel_names)
    channels = ["deflection"] + (["dither"] if params.use_input else []) + (["z_piezo"] if z_mode else [])
    chunks: Iterator[Chunk] = iter_chunks(reader, channels, params.chunk_samples, progress=progress)
    model, chunks, segment_s, resolved = _resolve_model(reader, params, model, chunks)
    route = resolved.report if resolved is not None else None
    warnings.extend(resolved.warnings if resolved is not None else ())
    segment = resolved.segment if resolved is not None else None
    first = next(chunks, None)
    if first is None:
        raise InputError(f"{info.source}: the capture has no samples")
    first_deflection = first.data["deflection"]
    first_dither = first.data.get("dither")
    chunks = replay_held([first], chunks)
    del first  # the stream hands it on once; keep no reference for the whole run

    metadata_drive_hz = info.capture_metadata.drive.frequency_hz
    if params.drive_frequency_hz:
        drive_hz = params.drive_frequency_hz
    elif metadata_drive_hz is not None:
        drive_hz = metadata_drive_hz
    elif model is not None:
        drive_hz = model.f0_hz
    else:
        drive_hz = _spectral_peak_hz(first_deflection, fs)
    if not 0 < drive_hz < fs / 2:
        raise InputError(f"drive frequency {drive_hz:g} Hz is not below the Nyquist frequency {fs / 2:g} Hz")
    lowpass_hz = params.lockin_lowpass_hz or default_lowpass_hz(drive_hz, info.capture_metadata.drive.sideband_offset_hz)
    decimate = params.decimate or max(1, round(fs / drive_hz))

    numerator = model.numerator_at(fs) if (model is not None and params.use_input) else None
    lines: list[float] = []
    if params.use_input:
        lines = excitation_lines(first_dither, fs, model.f0_hz)
        if len(lines) < 3:
            warnings.append(
                f"the dither has {len(lines)} spectral line(s) near resonance; REEP's free-air model needs "
                "three to be persistently exciting for five parameters (thesis §3.3.2)"
            )
    if model is not None and params.use_input and model.delay_s > 1.5 / fs and (route or {}).get("route") != "f0-q":
        warnings.append(
            f"the free-air model has a drive delay of {model.delay_s * 1e6:.2f} us (> 1.5 samples) that the "
            "fixed numerator does not model; f0' and Q' may be biased"
        )
    def make_bandpass():
        if not params.use_input and params.bandpass_half_width_hz > 0:
            return _Bandpass(drive_hz, params.bandpass_half_width_hz, fs)
        return None

    bandpass = make_bandpass()

    del first_deflection, first_dither
    state = ReepState.initial(lam=params.lam, p0=params.p0, static_offset=params.static_offset)
    lockin = LockIn(drive_hz, fs, lowpass_hz)
    lock_state = lockin.initial_state(2 if params.use_input else 1)
    warmup = int(params.warmup_windows / (1.0 - params.lam))
    limits = ValidityLimits(params.min_amplitude_fraction, params.max_sigma2_ratio, params.max_offset_drift)
    offset_drift = OffsetDrift(params.lam, decimate) if params.static_offset else None
    if segment is not None:
        levels = _segment_levels(segment, params, numerator, lockin, make_bandpass)
    else:
        levels = _metadata_levels(reader)
    del segment
    for check, level, name in (
        (limits.min_amplitude_fraction, levels.amplitude, "free amplitude"),
        (limits.max_sigma2_ratio, levels.sigma2, "free-air sigma^2"),
    ):
        if check and level is None:
            warnings.append(f"no {name} known (no free-air segment): that validity check is off")
    summaries = {name: _Summary() for name in ("f0_hz", "q", "amplitude", "phase_deg", "sigma2")}
    flag_counter = FlagCounter()
    n_total = 0
    geometry = ScanGeometry.from_scan(info.capture_metadata.scan)
    image_acc = ImageAccumulator(geometry, _IMAGE_QUANTITIES) if geometry else None
    curve_acc = ForceCurveAccumulator(params.z_bin, _CURVE_QUANTITIES) if z_mode else None

    with ThreadPoolExecutor(max_workers=1) as pool:
        for chunk in prefetch(chunks, _READ_AHEAD):
            p = chunk.data["deflection"]
            g = chunk.data.get("dither")
            # the lock-in runs in the worker thread beside REEP (both kernels release the GIL)
            if params.use_input:
                demodulating = pool.submit(lockin.process_against, p, g, lock_state, decimate)
            else:
                demodulating = pool.submit(lockin.process, p, lock_state, decimate)
            try:
                p_for_rls = bandpass(p) if bandpass is not None else p
                block, state = reep_update(
                    state, p_for_rls, g, numerator, bias_compensation=params.bias_compensation,
                    use_input=params.use_input, keep_every=decimate,
                )
            finally:
                demodulated, lock_state = demodulating.result()
            demod = demodulated if params.use_input else demodulated[0]
            # Everything below runs on the kept samples only: n with (n + 1) % decimate == 0.
            first_kept = (-(chunk.start + 1)) % decimate
            kept_index = np.arange(chunk.start + first_kept, chunk.start + len(p), decimate)
            f0, q, valid = resonance_from_denominator(block.b1, block.b0, fs)
            offset = None
            if block.c is not None:
                # p̄ = c / (1 + b1 + b0), the static deflection offset (reep_update, Notes)
                with np.errstate(divide="ignore", invalid="ignore"):
                    offset = block.c / (1.0 + block.b1 + block.b0)
            offset_variance = offset_drift(offset) if offset_drift is not None else None
            flags = validity_flags(valid, demod.amplitude, block.sigma2, levels, limits, offset_variance)
            columns = {
                "t": kept_index / fs,
                "f0_hz": f0,
                "q": q,
                "b1": block.b1,
                "b0": block.b0,
                "sigma2": block.sigma2,
                "amplitude": demod.amplitude,
                "phase_deg": np.degrees(demod.phase_rad),
            }
            if offset is not None:
                columns["offset"] = offset
            columns["flag"] = flags
            if z_mode:
                columns["z"] = chunk.data["z_piezo"][first_kept::decimate]
            writer.append(columns)
            # reep.h5 keeps the fitted values; everything else sees NaN where the fit is flagged
            trusted = dict(columns, f0_hz=np.where(flags == 0, f0, np.nan), q=np.where(flags == 0, q, np.nan))
            first_settled = int(np.searchsorted(kept_index, warmup))
            flag_counter.add(flags[first_settled:])  # counted over what the summary covers
            for name, summary in summaries.items():
                summary.add(trusted[name][first_settled:])
            if image_acc is not None:
                image_acc.add(columns["t"], trusted)
            if curve_acc is not None:
                settled = kept_index >= warmup
                curve_acc.add(columns["z"], {k: np.where(settled, trusted[k], np.nan) for k in _CURVE_QUANTITIES})
            n_total = chunk.start + len(p)

    window = 1.0 / (1.0 - params.lam)
    results = {
        "free_air_model": model.to_dict() if model is not None else None,
        "free_air_segment_s": list(segment_s) if segment_s else None,
        "free_air_route": route,
        "forgetting_factor": params.lam,
        "window_samples": window,
        "window_us": window / fs * 1e6,
        "bias_compensation": params.bias_compensation,
        "use_input": params.use_input,
        "n_samples": n_total,
        "duration_s": n_total / fs,
        "sample_rate_hz": fs,
        "decimate": decimate,
        "drive_frequency_hz": drive_hz,
        "lockin": {"lowpass_hz": lowpass_hz, "order": lockin.order, "type": "Butterworth, complex demodulation"},
        "excitation_lines_hz": lines,
        "static_offset": params.static_offset,
        "flagged_samples": flag_counter.flagged,  # among the decimated output samples after the warm-up
        "validity": {
            "min_amplitude_fraction": limits.min_amplitude_fraction,
            "max_sigma2_ratio": limits.max_sigma2_ratio,
            "max_offset_drift": limits.max_offset_drift,
            "free_air_levels": levels.as_dict(),
            "flags": flag_counter.as_dict(),
        },
        "summary_after_warmup_samples": warmup,
        "summary": {name: s.as_dict() for name, s in summaries.items()},
    }
    warnings.extend(flag_counter.warnings(limits))
    force_curves = curve_acc.tables() if curve_acc is not None else {}
    images = image_acc.images() if image_acc is not None else {}
    z_units = info.units("z_piezo") if z_mode else ""
    return ReepResult(results, tuple(warnings), images, geometry, force_curves, z_units)
