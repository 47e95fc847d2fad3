"""``afmtool reep``: equivalent f0′ and Q′ every sample, beside amplitude and phase.

capture → chunks → BCEWRLS kernel (eq. 3.39, θ = [b1, b0], numerator fixed at
its free-air value, §3.3.3) → f0′, Q′ by eq. 3.48 → decimated series in
``reep.h5``, force-curve tables and scan images, and a summary for
``report.json``.  Every filter carries its state across chunks, so the
output does not depend on the chunk size.  Samples whose fit cannot be
trusted are flagged (:mod:`afmtool.estimators.reep_validity`) and left out of
everything but ``reep.h5``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

from afmtool.analyses.accumulators import ForceCurveAccumulator, ImageAccumulator, ScanGeometry
from afmtool.analyses.reep_timeseries import PLOTTED, SegmentMoments, Thinned, ThinnedRows
from afmtool.config.params import ReepParams
from afmtool.config.samples import sample_count
from afmtool.errors import InputError
from afmtool.estimators._common import check_resolvable
from afmtool.estimators.drive_lines import excitation_lines
from afmtool.estimators.moments import RunningMoments
from afmtool.estimators.reep_validity import (
    FlagCounter,
    FreeAirLevels,
    OffsetDrift,
    ValidityLimits,
    free_air_levels,
    reep_rows,
)
from afmtool.io.capture import CaptureReader, Chunk
from afmtool.io.metadata import DriveMetadata
from afmtool.io.results import ResultWriter
from afmtool.models.free_air import FreeAirModel
from afmtool.pipeline import Decimation, Head, Split, Warmup, run_stream
from afmtool.report.results import JsonResults

__all__ = ["SERIES_UNITS", "ReepKernels", "ReepResult", "ReepStage", "run_reep"]

#: Quantities kept per decimated sample, with their units ("" = dimensionless).
SERIES_UNITS = {
    "t": "s",
    "f0_hz": "Hz",
    "q": "",
    "f0_std_hz": "Hz",
    "q_std": "",
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


def _summary_dict(moments: RunningMoments) -> dict:
    """Count, mean, (population) std, min and max of the trusted rows after the warm-up."""
    if not moments.count:
        return {"count": 0, "mean": None, "std": None, "min": None, "max": None}
    return {"count": moments.count, "mean": moments.mean, "std": moments.std(), "min": moments.low, "max": moments.high}


@dataclass(frozen=True)
class ReepResult(JsonResults):
    """What ``run_reep`` found; the command turns it into files and a report."""

    results: dict
    warnings: tuple[str, ...]
    images: dict[str, np.ndarray] = field(default_factory=dict)
    geometry: ScanGeometry | None = None
    force_curves: dict = field(default_factory=dict)
    z_units: str = ""
    #: The rows of reep_time_series.png, gathered in the stream.
    plot_rows: Thinned | None = None


def _spectral_peak_hz(x: np.ndarray, sample_rate_hz: float) -> float:
    from afmtool.estimators.filters import welch_psd

    freqs, power = welch_psd(x, sample_rate_hz, min(len(x), 1 << 14))
    power[freqs < 1e3] = 0.0
    return float(freqs[int(np.argmax(power))])


class _Bandpass:
    """Causal Butterworth band-pass with carried state (output-only mode)."""

    def __init__(self, centre_hz: float, half_width_hz: float, sample_rate_hz: float) -> None:
        from scipy.signal import butter, sosfilt_zi

        self.design = (centre_hz, half_width_hz, sample_rate_hz)
        low = max(centre_hz - half_width_hz, 1.0)
        high = min(centre_hz + half_width_hz, 0.49 * sample_rate_hz)
        self.sos = butter(2, [low, high], btype="bandpass", fs=sample_rate_hz, output="sos")
        self.zi = sosfilt_zi(self.sos) * 0.0

    def __call__(self, x: np.ndarray) -> np.ndarray:
        from scipy.signal import sosfilt

        y, self.zi = sosfilt(self.sos, x, zi=self.zi)
        return y


@dataclass(frozen=True)
class ReepKernels:
    """REEP's recursions (BCEWRLS, the lock-in, the output-only band-pass) as a pure function of a chunk.

    The :class:`~afmtool.pipeline.ChunkKernels` of :class:`ReepStage`: on a
    worker, ``estimate`` runs them from their initial state over the lead
    (W samples, :func:`ReepKernels.lead_for`) and then over the chunk, and
    returns what :meth:`ReepStage.account` takes.
    """

    params: ReepParams
    numerator: tuple[float, float, float] | None
    lockin: object
    every: int
    bandpass: tuple[float, float, float] | None
    lead_samples: int
    drive_cycles_per_sample: float = 0.0

    @property
    def alignment(self) -> int:
        return self.every

    @staticmethod
    def lead_for(params: ReepParams, lockin, bandpass: _Bandpass | None) -> int | None:
        """W: the longest of the RLS forgetting and the filters' decay (:mod:`afmtool.estimators.split_lead`)."""
        from afmtool.estimators.split_lead import forgetting_lead, sos_lead

        leads = [forgetting_lead(params.lam), sos_lead(lockin.sos)]
        if bandpass is not None:
            leads.append(sos_lead(bandpass.sos))
        return None if any(lead is None for lead in leads) else max(leads)

    def estimate(self, lead: Chunk | None, chunk: Chunk):
        """``(ReepBlock, LockInBlock)`` of ``chunk``, from the initial states warmed on ``lead``."""
        from afmtool.estimators.rls import ReepState, reep_update

        params = self.params
        first = lead.start if lead is not None else chunk.start
        state = ReepState.initial(lam=params.lam, p0=params.p0, static_offset=params.static_offset)
        n_signals = 2 if params.use_input else 1
        lock_state = self.lockin.initial_state(n_signals, first)
        bandpass = _Bandpass(*self.bandpass) if self.bandpass is not None else None
        block = demod = None
        for part in (lead, chunk):
            if part is None:
                continue
            p, g = part.data["deflection"], part.data.get("dither")
            block, state = reep_update(
                state, bandpass(p) if bandpass is not None else p, g, self.numerator,
                bias_compensation=params.bias_compensation, use_input=params.use_input, keep_every=self.every,
                drive_cycles_per_sample=self.drive_cycles_per_sample,
            )
            if params.use_input:
                demod, lock_state = self.lockin.process_against(p, g, lock_state, self.every)
            else:
                (demod,), lock_state = self.lockin.process(p, lock_state, self.every)
        return block, demod


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
    warmup = Warmup.of_windows(params.warmup_windows, params.lam).samples
    return free_air_levels(block.sigma2, demod.amplitude, min(warmup, len(p) // 2))


def _metadata_levels(reader: CaptureReader) -> FreeAirLevels:
    """Without a free-air segment: the free amplitude from metadata (when the deflection is in nm)."""
    amplitude = reader.info.capture_metadata.drive.free_amplitude_nm
    if amplitude and reader.info.units("deflection") == "nm":
        return FreeAirLevels(float(amplitude), None, "metadata")
    return FreeAirLevels(None, None, "none")


class ReepStage:
    """REEP as a :mod:`afmtool.pipeline` stage: BCEWRLS and the lock-in over each chunk.

    ``free_air_prologue`` (the run's prologue, required) resolves the free-air model,
    reading its segment ahead; ``prepare`` fixes the drive, the lock-in,
    the decimation and the validity levels from the first chunk; ``step``
    returns the decimated columns of ``reep.h5`` and adds the trusted ones
    to the summaries, force curves and images; ``finish`` returns the
    :class:`ReepResult`.

    Parameters
    ----------
    reader : CaptureReader
        Needs ``deflection``, and ``dither`` unless ``params.use_input`` is off.
    params : ReepParams
        Effective parameters.
    model : FreeAirModel, optional
        A given free-air model; otherwise it is identified from the
        free-air segment (``params.free_air`` or the capture metadata).
    force_curves : bool, optional
        Bin the trusted values against z (with z_piezo); False still
        writes ``z`` with the columns, for a caller that bins them itself.
    """

    def __init__(self, reader: CaptureReader, params: ReepParams, *, model: FreeAirModel | None = None,
                 force_curves: bool = True) -> None:
        info = reader.info
        self.reader = reader
        self.params = params
        self.model = model
        self.fs = info.sample_rate_hz
        self.z_mode = params.vs == "z" or (params.vs == "auto" and "z_piezo" in info.channel_names)
        self.force_curves = force_curves
        #: Channels the stage reads.
        self.channels = (
            ["deflection"] + (["dither"] if params.use_input else []) + (["z_piezo"] if self.z_mode else [])
        )
        self.warnings: list[str] = []
        self.segment_s = None
        self.route = None
        self._segment = None
        self._resolved = False
        self.n_total = 0

    def free_air_prologue(self, chunks: Iterator[Chunk]) -> Iterator[Chunk]:
        """The free-air route, its segment read ahead (:func:`_resolve_model`); the stream handed on."""
        self.model, chunks, self.segment_s, resolved = _resolve_model(self.reader, self.params, self.model, chunks)
        self.route = resolved.report if resolved is not None else None
        self.warnings.extend(resolved.warnings if resolved is not None else ())
        self._segment = resolved.segment if resolved is not None else None
        self._resolved = True
        return chunks

    def prepare(self, head: Head) -> None:
        """Drive, lock-in, decimation, validity levels and accumulators, from the first chunk."""
        from afmtool.estimators.lockin import LockIn, default_lowpass_hz
        from afmtool.estimators.rls import ReepState

        if not self._resolved:
            raise RuntimeError("ReepStage runs with prologue=stage.free_air_prologue (the free-air route)")
        params, fs = self.params, self.fs
        check_resolvable("deflection", head.first.data["deflection"], "REEP's regression")
        drive = head.info.capture_metadata.drive
        self.drive_hz = _drive_frequency(params, drive, self.model, head.first.data["deflection"], fs)
        self.lowpass_hz = params.lockin_lowpass_hz or default_lowpass_hz(self.drive_hz, drive.sideband_offset_hz)
        self.decimation = Decimation(params.decimate or sample_count(1.0, fs / self.drive_hz, "the drive period", minimum=1, per="drive period"))
        self.numerator = self.model.numerator_at(fs) if (self.model is not None and params.use_input) else None
        self.lines = self._input_checks(head.first.data.get("dither"))
        self.bandpass = self._make_bandpass()
        self.state = ReepState.initial(lam=params.lam, p0=params.p0, static_offset=params.static_offset)
        self.lockin = LockIn(self.drive_hz, fs, self.lowpass_hz)
        self.lock_state = self.lockin.initial_state(2 if params.use_input else 1)
        self.warmup = Warmup.of_windows(params.warmup_windows, params.lam)
        self.limits = ValidityLimits(params.min_amplitude_fraction, params.max_sigma2_ratio, params.max_offset_drift)
        self.offset_drift = OffsetDrift(params.lam, self.decimation.every) if params.static_offset else None
        self.levels = self._free_air_levels()
        self.summaries = {name: RunningMoments() for name in ("f0_hz", "q", "amplitude", "phase_deg", "sigma2")}
        # in the stream, so that the command need not read reep.h5 back for them (0.7 s at 1e8 samples)
        self.segment_moments = SegmentMoments(self.warmup.samples / fs, self.segment_s)
        n_samples = head.info.n_samples
        self.plot_rows = ThinnedRows(PLOTTED, self.decimation.count(0, n_samples) if n_samples else None)
        self.flag_counter = FlagCounter()
        self.geometry = ScanGeometry.from_scan(head.info.capture_metadata.scan)
        # a raster capture with z also gets its height image: z_piezo per pixel, as recorded
        image_quantities = _IMAGE_QUANTITIES + (("z",) if self.z_mode else ())
        self.image_acc = ImageAccumulator(self.geometry, image_quantities) if self.geometry else None
        self.curve_acc = ForceCurveAccumulator(params.z_bin, _CURVE_QUANTITIES) if self.z_mode and self.force_curves else None
        self._side = head.side

    def _input_checks(self, first_dither: np.ndarray | None) -> list[float]:
        """The dither's lines near resonance, with warnings on too few lines and an unmodelled delay."""
        params, fs, model = self.params, self.fs, self.model
        lines: list[float] = []
        if params.use_input:
            lines = excitation_lines(first_dither, fs, model.f0_hz)
            if len(lines) < 3:
                self.warnings.append(
                    f"the dither has {len(lines)} spectral line(s) near resonance; REEP's free-air model needs "
                    "three to be persistently exciting for five parameters (thesis §3.3.2)"
                )
        if model is not None and params.use_input and model.delay_s > 1.5 / fs and (self.route or {}).get("route") != "f0-q":
            self.warnings.append(
                f"the free-air model has a drive delay of {model.delay_s * 1e6:.2f} us (> 1.5 samples) that the "
                "fixed numerator does not model; f0' and Q' may be biased"
            )
        return lines

    def _make_bandpass(self) -> _Bandpass | None:
        if not self.params.use_input and self.params.bandpass_half_width_hz > 0:
            return _Bandpass(self.drive_hz, self.params.bandpass_half_width_hz, self.fs)
        return None

    def _free_air_levels(self) -> FreeAirLevels:
        """σ̂² and amplitude in free air (segment, else metadata); a warning per check left without one."""
        if self._segment is not None:
            levels = _segment_levels(self._segment, self.params, self.numerator, self.lockin, self._make_bandpass)
        else:
            levels = _metadata_levels(self.reader)
        self._segment = None  # read once; not kept for the run
        for check, level, name in (
            (self.limits.min_amplitude_fraction, levels.amplitude, "free amplitude"),
            (self.limits.max_sigma2_ratio, levels.sigma2, "free-air sigma^2"),
        ):
            if check and level is None:
                self.warnings.append(f"no {name} known (no free-air segment): that validity check is off")
        return levels

    def _estimate(self, chunk: Chunk):
        """REEP on this thread, the lock-in on the side thread (both kernels release the GIL)."""
        from afmtool.estimators.rls import reep_update

        params, every = self.params, self.decimation.every
        p = chunk.data["deflection"]
        g = chunk.data.get("dither")
        if params.use_input:
            demodulating = self._side.submit(self.lockin.process_against, p, g, self.lock_state, every)
        else:
            demodulating = self._side.submit(self.lockin.process, p, self.lock_state, every)
        try:
            p_for_rls = self.bandpass(p) if self.bandpass is not None else p
            block, self.state = reep_update(
                self.state, p_for_rls, g, self.numerator, bias_compensation=params.bias_compensation,
                use_input=params.use_input, keep_every=every, drive_cycles_per_sample=self.drive_hz / self.fs,
            )
        finally:
            demodulated, self.lock_state = demodulating.result()
        return block, (demodulated if params.use_input else demodulated[0])

    def step(self, chunk: Chunk) -> dict[str, np.ndarray]:
        """The decimated columns of this chunk for ``reep.h5``; the trusted ones summarised."""
        return self.account(chunk, self._estimate(chunk))

    def kernels(self) -> ReepKernels | None:
        """The recursions as :class:`ReepKernels`, for a split run; None if one of them never forgets (λ = 1)."""
        lead = ReepKernels.lead_for(self.params, self.lockin, self.bandpass)
        if lead is None:
            return None
        bandpass = self.bandpass.design if self.bandpass is not None else None
        return ReepKernels(self.params, self.numerator, self.lockin, self.decimation.every, bandpass, lead,
                           self.drive_hz / self.fs)

    def account(self, chunk: Chunk, estimate) -> dict[str, np.ndarray]:
        """Everything after the kernels, in capture order: f0′, Q′, flags, columns, summaries."""
        block, demod = estimate
        # everything below runs on the kept samples only (Decimation)
        kept_index = self.decimation.kept_index(chunk.start, len(chunk))
        rows = reep_rows(
            block.b1, block.b0, block.c, block.sigma2, demod.amplitude, self.fs, self.levels, self.limits,
            self.offset_drift, block.covariance,
        )
        columns = {
            "t": kept_index / self.fs,
            "f0_hz": rows.f0_hz,
            "q": rows.q,
            "f0_std_hz": rows.f0_std_hz,
            "q_std": rows.q_std,
            "b1": block.b1,
            "b0": block.b0,
            "sigma2": block.sigma2,
            "amplitude": demod.amplitude,
            "phase_deg": np.degrees(demod.phase_rad),
        }
        if rows.offset is not None:
            columns["offset"] = rows.offset
        columns["flag"] = rows.flags
        if self.z_mode:
            columns["z"] = self.decimation.take(chunk.data["z_piezo"], chunk.start)
        self._account(columns, kept_index, rows.flags)
        self.n_total = chunk.start + len(chunk)
        return columns

    def _account(self, columns: dict[str, np.ndarray], kept_index: np.ndarray, flags: np.ndarray) -> None:
        """Summaries, flag counts, images and force curves, from the trusted values past the warm-up."""
        first_settled = self.warmup.first_settled(kept_index)
        self.flag_counter.add(flags[first_settled:])  # counted over what the summary covers
        # reep.h5 keeps the fitted values; everything else leaves out f0′ and Q′ where the fit is flagged
        for name, summary in self.summaries.items():
            summary.add(columns[name], flags if name in ("f0_hz", "q") else None, start=first_settled)
        self.segment_moments.add(columns["t"], columns["f0_hz"], columns["q"], flags, columns.get("f0_std_hz"))
        self.plot_rows.add(columns["t"], columns, flags)
        if self.image_acc is None and self.curve_acc is None:
            return
        trusted = dict(
            columns, f0_hz=np.where(flags == 0, columns["f0_hz"], np.nan), q=np.where(flags == 0, columns["q"], np.nan)
        )
        if self.image_acc is not None:
            self.image_acc.add(columns["t"], trusted)
        if self.curve_acc is not None:
            self.curve_acc.add(columns["z"], {k: self.warmup.mask(trusted[k], kept_index) for k in _CURVE_QUANTITIES})

    def finish(self) -> ReepResult:
        """The run's results, warnings, images and force-curve tables."""
        self.warnings.extend(self.flag_counter.warnings(self.limits))
        force_curves = self.curve_acc.tables() if self.curve_acc is not None else {}
        images = self.image_acc.images() if self.image_acc is not None else {}
        z_units = self.reader.info.units("z_piezo") if self.z_mode else ""
        results = self._results()
        check = _free_air_check(results["segments"].get("free_air"), self.model,
                                self.reader.info.capture_metadata.cantilever.f0_hz)
        if check is not None:
            results["free_air_check"] = check.as_dict()
            if not check.consistent:  # the run's premise is broken: first among the warnings
                self.warnings.insert(0, check.message())
        return ReepResult(results, tuple(self.warnings), images, self.geometry, force_curves, z_units,
                          self.plot_rows.result())

    def _results(self) -> dict:
        params, fs, model, n_total = self.params, self.fs, self.model, self.n_total
        window = 1.0 / (1.0 - params.lam)
        limits = self.limits
        return {
            "free_air_model": model.to_dict() if model is not None else None,
            "free_air_segment_s": list(self.segment_s) if self.segment_s else None,
            "free_air_route": self.route,
            "forgetting_factor": params.lam,
            "window_samples": window,
            "window_us": window / fs * 1e6,
            "bias_compensation": params.bias_compensation,
            "use_input": params.use_input,
            "n_samples": n_total,
            "duration_s": n_total / fs,
            "sample_rate_hz": fs,
            "decimate": self.decimation.every,
            "drive_frequency_hz": self.drive_hz,
            "lockin": {"lowpass_hz": self.lowpass_hz, "order": self.lockin.order,
                       "type": "Butterworth, complex demodulation"},
            "excitation_lines_hz": self.lines,
            "static_offset": params.static_offset,
            "flagged_samples": self.flag_counter.flagged,  # among the decimated output samples after the warm-up
            "validity": {
                "min_amplitude_fraction": limits.min_amplitude_fraction,
                "max_sigma2_ratio": limits.max_sigma2_ratio,
                "max_offset_drift": limits.max_offset_drift,
                "free_air_levels": self.levels.as_dict(),
                "flags": self.flag_counter.as_dict(),
            },
            "summary_after_warmup_samples": self.warmup.samples,
            "summary": {name: _summary_dict(s) for name, s in self.summaries.items()},
            "segments": self.segment_moments.as_dict(),
        }


def _free_air_check(segment: dict | None, model: FreeAirModel | None, metadata_f0_hz: float | None):
    """REEP's free-air f0′ against the model's f0 and the metadata's (:mod:`afmtool.estimators.free_air_consistency`)."""
    from afmtool.estimators.free_air_consistency import F0Reference, free_air_f0_check

    if segment is None or (segment["f0_hz"].get("count") or 0) < 10:  # too few rows for a scatter
        return None
    references = []
    if model is not None:
        references.append(F0Reference("model", float(model.f0_hz), float(model.f0_std_hz or 0.0)))
    if metadata_f0_hz and (model is None or metadata_f0_hz != model.f0_hz):
        references.append(F0Reference("metadata", float(metadata_f0_hz)))
    stats = segment["f0_hz"]
    # REEP's own per-row standard deviation of f0' where it has one, else the rows' spread over the segment
    std = segment.get("f0_row_std_hz") or stats.get("std") or 0.0
    return free_air_f0_check(float(stats["mean"]), float(std), references)


def _drive_frequency(params: ReepParams, drive: DriveMetadata, model: FreeAirModel | None, first_deflection, fs: float) -> float:
    """The lock-in's reference: the flag, the metadata, f0, else the first chunk's spectral peak (Hz)."""
    if params.drive_frequency_hz:
        drive_hz = params.drive_frequency_hz
    elif drive.frequency_hz is not None:
        drive_hz = drive.frequency_hz
    elif model is not None:
        drive_hz = model.f0_hz
    else:
        drive_hz = _spectral_peak_hz(first_deflection, fs)
    if not 0 < drive_hz < fs / 2:
        raise InputError(f"drive frequency {drive_hz:g} Hz is not below the Nyquist frequency {fs / 2:g} Hz")
    return drive_hz


def run_reep(
    reader: CaptureReader,
    params: ReepParams,
    writer: ResultWriter,
    *,
    model: FreeAirModel | None = None,
    progress: Callable[[int], None] | None = None,
    split: Split | None = None,
    on_stream_start: Callable[[], None] | None = None,
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
    progress : callable, optional
        Called with the capture samples done so far.
    split : Split, optional
        Run the kernels of several chunks at once (:class:`~afmtool.pipeline.Split`);
        the result equals the sequential one to 1e-9 (``tests/test_split.py``).
    on_stream_start : callable, optional
        Called once the free-air route is resolved and the stream begins (the command
        starts loading its plotting library then, so that it overlaps the kernels).
    """
    stage = ReepStage(reader, params, model=model)
    (result,) = run_stream(
        reader, [stage], writer, channels=stage.channels, chunk_samples=params.chunk_samples,
        progress=progress, prologue=stage.free_air_prologue, split=split, on_start=on_stream_start,
    )
    return result
