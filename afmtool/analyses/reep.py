"""``afmtool reep``: equivalent f0′ and Q′ every sample, beside amplitude and phase.

capture → chunks → :class:`~afmtool.estimators.reep_estimator.ReepEstimator`
(anti-alias filter and decimation to N–2N samples per period, BCEWRLS of
eq. 3.39 with θ = [b1, b0(, c)] and the numerator fixed at its free-air value,
§3.3.3, a window in time) → f0′, Q′ by eq. 3.48 with their standard
deviations → rows in ``reep.h5``, force-curve tables and scan images, and a
summary for ``report.json``.  Every filter carries its state across chunks,
so the output does not depend on the chunk size.  Rows whose fit is invalid
are flagged (:mod:`afmtool.estimators.reep_validity`) and left out of
everything but ``reep.h5``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

from afmtool.analyses.accumulators import ForceCurveAccumulator, ImageAccumulator, ScanGeometry
from afmtool.analyses.freeair_source import checked_drive_frequency
from afmtool.analyses.reep_timeseries import PLOTTED, SegmentMoments, Thinned, ThinnedRows
from afmtool.config.params import ReepParams
from afmtool.estimators._common import check_resolvable
from afmtool.estimators.drive_lines import excitation_lines
from afmtool.estimators.moments import RunningMoments
from afmtool.estimators.reep_estimator import ReepEstimator
from afmtool.estimators.reep_validity import (
    FlagCounter,
    FreeAirLevels,
    OffsetDrift,
    ValidityLimits,
    free_air_levels,
    reep_rows,
)
from afmtool.io.capture import CaptureInfo, CaptureReader, Chunk
from afmtool.io.results import ResultWriter
from afmtool.models.free_air import FreeAirModel
from afmtool.pipeline import Decimation, Head, Split, Warmup, run_stream
from afmtool.records.common import FreeAirRouteRecord, SeriesMoments
from afmtool.records.reep import (
    CheckReference,
    FlagCounts,
    FreeAirCheck,
    FreeAirLevelsRecord,
    LevelsSource,
    LockInRecord,
    ReepResults,
    ReepSegments,
    ReepSummary,
    Segment,
    Settling,
    Validity,
)

__all__ = ["SERIES_UNITS", "ReepKernels", "ReepResult", "ReepStage", "build_reep_estimator", "run_reep"]

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
#: Chunks read ahead while the kernels run (issue 33): one 1 Mi-sample chunk is read in a few
#: ms, far less than the kernels take, so a second only held 16 MB more at the same speed.
_READ_AHEAD = 1


def _series_moments(moments: RunningMoments) -> SeriesMoments:
    """Count, mean, (population) std, min and max of the trusted rows after the warm-up (NaN without one)."""
    if not moments.count:
        return SeriesMoments(count=0, mean=math.nan, std=None, min=math.nan, max=math.nan)
    return SeriesMoments(count=moments.count, mean=moments.mean, std=moments.std(), min=moments.low,
                         max=moments.high)


@dataclass(frozen=True)
class ReepResult:
    """What ``run_reep`` found; the command turns it into files and a report."""

    results: ReepResults
    warnings: tuple[str, ...]
    images: dict[str, np.ndarray] = field(default_factory=dict)
    geometry: ScanGeometry | None = None
    force_curves: dict = field(default_factory=dict)
    z_units: str = ""
    #: The rows of reep_time_series.png, gathered in the stream.
    plot_rows: Thinned | None = None

    def to_json(self) -> dict:
        """``results`` as report.json holds them."""
        return self.results.to_json()


def _spectral_peak_hz(x: np.ndarray, sample_rate_hz: float) -> float:
    from afmtool.estimators.filters import welch_psd

    freqs, power = welch_psd(x, sample_rate_hz, min(len(x), 1 << 14))
    power[freqs < 1e3] = 0.0
    return float(freqs[int(np.argmax(power))])


@dataclass(frozen=True)
class ReepKernels:
    """REEP's recursions (the :class:`ReepEstimator` and the lock-in) as a pure function of a chunk.

    The :class:`~afmtool.pipeline.ChunkKernels` of :class:`ReepStage`: on a
    worker, ``estimate`` runs them from their initial state over the lead
    (W samples, :func:`ReepKernels.lead_for`) and then over the chunk, and
    returns what :meth:`ReepStage.account` takes.
    """

    estimator: ReepEstimator
    lockin: object
    lead_samples: int

    @property
    def alignment(self) -> int:
        return self.estimator.row_every

    @staticmethod
    def lead_for(estimator: ReepEstimator, lockin) -> int | None:
        """W: the longest of the estimator's forgetting and filters and the lock-in's decay (:mod:`afmtool.estimators.split_lead`)."""
        from afmtool.estimators.split_lead import sos_lead

        leads = [estimator.lead_samples(), sos_lead(lockin.sos)]
        return None if any(lead is None for lead in leads) else max(leads)

    def estimate(self, lead: Chunk | None, chunk: Chunk):
        """``(ReepBlock, LockInBlock)`` of ``chunk``, from the initial states warmed on ``lead``."""
        estimator = self.estimator
        first = lead.start if lead is not None else chunk.start
        state = estimator.initial(first)
        lock_state = self.lockin.initial_state(2 if estimator.use_input else 1, first)
        block = demod = None
        for part in (lead, chunk):
            if part is None:
                continue
            p, g = part.data["deflection"], part.data.get("dither")
            block, state = estimator.run(state, p, g)
            if estimator.use_input:
                demod, lock_state = self.lockin.process_against(p, g, lock_state, estimator.row_every)
            else:
                (demod,), lock_state = self.lockin.process(p, lock_state, estimator.row_every)
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


def _segment_levels(segment, estimator: ReepEstimator, lockin, warmup_samples: int) -> FreeAirLevels:
    """σ̂² and amplitude in free air, by the run's own estimator and lock-in over the free-air segment."""
    p = segment.data["deflection"]
    g = segment.data.get("dither") if estimator.use_input else None
    rows = estimator.with_rows(estimator.factor)
    block = rows.run(rows.initial(), p, g).block
    if estimator.use_input:
        demod, _ = lockin.process_against(p, g, lockin.initial_state(2), estimator.factor)
    else:
        demod = lockin.process(p, lockin.initial_state(1), estimator.factor)[0][0]
    return free_air_levels(block.sigma2, demod.amplitude, min(warmup_samples, len(p) // 2) // estimator.factor)


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
        self._route_name: str | None = None
        self._segment = None
        self._resolved = False
        self.n_total = 0

    def free_air_prologue(self, chunks: Iterator[Chunk]) -> Iterator[Chunk]:
        """The free-air route, its segment read ahead (:func:`_resolve_model`); the stream handed on."""
        self.model, chunks, self.segment_s, resolved = _resolve_model(self.reader, self.params, self.model, chunks)
        self.route = resolved.report if resolved is not None else None
        self._route_name = resolved.route if resolved is not None else None
        self.warnings.extend(resolved.warnings if resolved is not None else ())
        self._segment = resolved.segment if resolved is not None else None
        self._resolved = True
        return chunks

    def prepare(self, head: Head) -> None:
        """Drive, the estimator, lock-in, rows, validity levels and accumulators, from the first chunk."""
        from afmtool.estimators.lockin import LockIn, default_lowpass_hz

        if not self._resolved:
            raise RuntimeError("ReepStage runs with prologue=stage.free_air_prologue (the free-air route)")
        params, fs = self.params, self.fs
        check_resolvable("deflection", head.first.data["deflection"], "REEP's regression")
        drive = head.info.capture_metadata.drive
        self.drive_hz = _drive_frequency(params, head.info, self.model, head.first.data["deflection"])
        self.lowpass_hz = params.lockin_lowpass_hz or default_lowpass_hz(self.drive_hz, drive.sideband_offset_hz)
        self.estimator = self._build_estimator()
        self.decimation = Decimation(self.estimator.row_every)
        self.lines = self._input_checks(head.first.data.get("dither"))
        self.state = self.estimator.initial()
        self.lockin = LockIn(self.drive_hz, fs, self.lowpass_hz)
        self.lock_state = self.lockin.initial_state(2 if params.use_input else 1)
        self.warmup = Warmup.of_windows(params.warmup_windows, self.estimator.capture_lam)
        self.limits = ValidityLimits(params.min_amplitude_fraction, params.max_offset_drift)
        reep_rows_per_row = self.estimator.row_every // self.estimator.factor
        self.offset_drift = OffsetDrift(self.estimator.lam, reep_rows_per_row) if params.static_offset else None
        self.levels = self._free_air_levels()
        self.settling = _settling(self.estimator, self.model, head, self.geometry_of(head))
        self.summaries = {name: RunningMoments() for name in ("f0_hz", "q", "amplitude", "phase_deg", "sigma2")}
        # in the stream, so that the command need not read reep.h5 back for them (0.7 s at 1e8 samples)
        self.segment_moments = SegmentMoments(self.warmup.samples / fs, self.segment_s)
        n_samples = head.info.n_samples
        self.plot_rows = ThinnedRows(PLOTTED, self.decimation.count(0, n_samples) if n_samples else None)
        self.flag_counter = FlagCounter()
        self.geometry = self.geometry_of(head)
        # a raster capture with z also gets its height image: z_piezo per pixel, as recorded
        image_quantities = _IMAGE_QUANTITIES + (("z",) if self.z_mode else ())
        self.image_acc = ImageAccumulator(self.geometry, image_quantities) if self.geometry else None
        self.curve_acc = ForceCurveAccumulator(params.z_bin, _CURVE_QUANTITIES) if self.z_mode and self.force_curves else None
        self._side = head.side

    @staticmethod
    def geometry_of(head: Head) -> ScanGeometry | None:
        return ScanGeometry.from_scan(head.info.capture_metadata.scan)

    def _build_estimator(self) -> ReepEstimator:
        """The one :class:`ReepEstimator` of this run (:func:`build_reep_estimator`)."""
        return build_reep_estimator(self.params, self.model, self.fs, self.drive_hz, self.route, self._segment)

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
        if model is not None and params.use_input and model.delay_s > 1.5 / fs and self._route_name != "f0-q":
            self.warnings.append(
                f"the free-air model has a drive delay of {model.delay_s * 1e6:.2f} us (> 1.5 samples) that the "
                "fixed numerator does not model; f0' and Q' may be biased"
            )
        return lines

    def _free_air_levels(self) -> FreeAirLevels:
        """σ̂² and amplitude in free air (segment, else metadata); a warning when the amplitude floor has none."""
        if self._segment is not None:
            levels = _segment_levels(self._segment, self.estimator, self.lockin, self.warmup.samples)
        else:
            levels = _metadata_levels(self.reader)
        self._segment = None  # read once; not kept for the run
        if self.limits.min_amplitude_fraction and levels.amplitude is None:
            self.warnings.append("no free amplitude known (no free-air segment): the amplitude floor is off")
        return levels

    def _estimate(self, chunk: Chunk):
        """REEP on this thread, the lock-in on the side thread (both kernels release the GIL)."""
        params, every = self.params, self.decimation.every
        p = chunk.data["deflection"]
        g = chunk.data.get("dither")
        if params.use_input:
            demodulating = self._side.submit(self.lockin.process_against, p, g, self.lock_state, every)
        else:
            demodulating = self._side.submit(self.lockin.process, p, self.lock_state, every)
        try:
            block, self.state = self.estimator.run(self.state, p, g)
        finally:
            demodulated, self.lock_state = demodulating.result()
        return block, (demodulated if params.use_input else demodulated[0])

    def step(self, chunk: Chunk) -> dict[str, np.ndarray]:
        """The decimated columns of this chunk for ``reep.h5``; the trusted ones summarised."""
        return self.account(chunk, self._estimate(chunk))

    def kernels(self) -> ReepKernels | None:
        """The recursions as :class:`ReepKernels`, for a split run; None if one of them never forgets (λ = 1)."""
        lead = ReepKernels.lead_for(self.estimator, self.lockin)
        if lead is None:
            return None
        return ReepKernels(self.estimator, self.lockin, lead)

    def account(self, chunk: Chunk, estimate) -> dict[str, np.ndarray]:
        """Everything after the kernels, in capture order: f0′, Q′, flags, columns, summaries."""
        block, demod = estimate
        # everything below runs on the kept samples only (Decimation)
        kept_index = self.decimation.kept_index(chunk.start, len(chunk))
        rows = reep_rows(
            block.b1, block.b0, block.c, block.sigma2, demod.amplitude, self.estimator.rate_hz, self.levels,
            self.limits, self.offset_drift, block.covariance, self.warmup.first_settled(kept_index), self.levels.sigma2,
            output_only=not self.estimator.use_input,
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
        segments = self.segment_moments.record()
        check = _free_air_check(segments.free_air, self.model, self.reader.info.capture_metadata.cantilever.f0_hz)
        if check is not None and not check.consistent:  # the run's premise is broken: first among the warnings
            self.warnings.insert(0, check.message())
        results = self._results(segments, _check_record(check) if check is not None else None)
        return ReepResult(results, tuple(self.warnings), images, self.geometry, force_curves, z_units,
                          self.plot_rows.result())

    def _results(self, segments: ReepSegments, check: FreeAirCheck | None) -> ReepResults:
        params, fs, model, n_total = self.params, self.fs, self.model, self.n_total
        estimator = self.estimator.describe()
        return ReepResults(
            free_air_model=model.record() if model is not None else None,
            free_air_segment_s=tuple(self.segment_s) if self.segment_s else None,
            # the route's report, as freeair_route writes it for report.json
            free_air_route=FreeAirRouteRecord.from_json(self.route) if self.route is not None else None,
            forgetting_factor=estimator.forgetting_factor,
            window_samples=estimator.window_samples,
            window_us=estimator.window_us,
            estimator=estimator,
            settling=self.settling,
            bias_compensation=params.bias_compensation,
            use_input=params.use_input,
            # without the dither the AR(2) fit sees no input: its damping is the loop's, not the cantilever's
            q_identifiable=params.use_input,
            n_samples=n_total,
            duration_s=n_total / fs,
            sample_rate_hz=fs,
            decimate=self.decimation.every,
            row_rate_hz=estimator.row_rate_hz,
            # what set the rows' density: --decimate N, else --rows (issue 33)
            rows=f"decimate {params.decimate}" if params.decimate else params.rows,
            row_every_samples=estimator.row_every_samples,
            drive_frequency_hz=self.drive_hz,
            lockin=LockInRecord(lowpass_hz=self.lowpass_hz, order=self.lockin.order,
                                type="Butterworth, complex demodulation"),
            excitation_lines_hz=tuple(self.lines),
            static_offset=params.static_offset,
            flagged_samples=self.flag_counter.flagged,  # among the decimated output samples after the warm-up
            validity=self._validity(),
            summary_after_warmup_samples=self.warmup.samples,
            summary=ReepSummary(**{name: _series_moments(s) for name, s in self.summaries.items()}),
            segments=segments,
            free_air_check=check,
        )

    def _validity(self) -> Validity:
        """The validity checks' limits, the free-air levels, the flags counted and, if most rows are flagged, why."""
        limits, levels, counter = self.limits, self.levels, self.flag_counter
        mostly = counter.mostly_flagged(limits)
        return Validity(
            min_amplitude_fraction=limits.min_amplitude_fraction,
            max_offset_drift=limits.max_offset_drift,
            free_air_levels=FreeAirLevelsRecord(amplitude=levels.amplitude, sigma2=levels.sigma2,
                                                source=LevelsSource(levels.source)),
            flags=FlagCounts(**counter.as_dict()),
            mostly_flagged=str(mostly) if mostly is not None else None,
        )


def _free_air_check(segment: Segment | None, model: FreeAirModel | None, metadata_f0_hz: float | None):
    """REEP's free-air f0′ against the model's f0 and the metadata's (:mod:`afmtool.estimators.free_air_consistency`)."""
    from afmtool.estimators.free_air_consistency import F0Reference, free_air_f0_check

    if segment is None or segment.f0_hz.count < 10:  # too few rows for a scatter
        return None
    references = []
    if model is not None:
        references.append(F0Reference("model", float(model.f0_hz), float(model.f0_std_hz or 0.0)))
    if metadata_f0_hz and (model is None or metadata_f0_hz != model.f0_hz):
        references.append(F0Reference("metadata", float(metadata_f0_hz)))
    stats = segment.f0_hz
    # REEP's own per-row standard deviation of f0' where it has one, else the rows' spread over the segment
    std = segment.f0_row_std_hz or stats.std or 0.0
    return free_air_f0_check(float(stats.mean), float(std), references)


def _check_record(check) -> FreeAirCheck:
    """The report's copy of a :class:`~afmtool.estimators.free_air_consistency.FreeAirF0Check`."""
    from afmtool.estimators.free_air_consistency import MAX_DEVIATION_STD

    return FreeAirCheck(
        f0_hz=check.f0_hz, f0_std_hz=check.f0_std_hz, reference=CheckReference(check.reference.name),
        reference_f0_hz=check.reference.f0_hz, reference_std_hz=check.reference.std_hz,
        deviation_hz=check.deviation_hz, deviation_std=check.deviation_std, max_deviation_std=MAX_DEVIATION_STD,
        consistent=check.consistent,
    )


def build_reep_estimator(params: ReepParams, model: FreeAirModel | None, sample_rate_hz: float, drive_hz: float,
                         route: dict | None, segment) -> ReepEstimator:
    """REEP for a run from its parameters, its free-air model and route, and the drive: what every REEP runs.

    ``reep``'s stage and kalman-bank's pass 2 (``--models``, no pass 1) build it here.
    The ``segment`` route's ARX fit is redone at REEP's rate on the same free-air segment
    (:meth:`ReepEstimator.build`).
    """
    with_model = model is not None and params.use_input
    arrays = None
    route_name = (route or {}).get("route")
    continuous = with_model and (route or {}).get("drive_hold") == "continuous"
    numerator = model.numerator_at(sample_rate_hz) if with_model else None
    denominator = model.denominator_at(sample_rate_hz) if with_model else None
    lines_model = None
    if with_model and segment is not None and route_name == "segment":
        arrays = (segment.data["deflection"], segment.data["dither"])
        if continuous:
            lines_model = _continuous_from_lines(arrays, model, sample_rate_hz, drive_hz)
    if lines_model is not None:  # the segment's lines give a continuous model: REEP runs on it as on f0-q's
        numerator, denominator, arrays = (*lines_model, None)
    return ReepEstimator.build(
        params, sample_rate_hz=sample_rate_hz, resonance_hz=model.f0_hz if model is not None else drive_hz,
        drive_hz=drive_hz, numerator=numerator, denominator=denominator,
        bandpass_half_width_hz=params.bandpass_half_width_hz, segment=arrays,
        # a continuous model (f0, Q, gain, delay) has a numerator exact across the band (ReepEstimator)
        continuous_drive=continuous and (route_name == "f0-q" or lines_model is not None),
    )


def _continuous_from_lines(segment, model: FreeAirModel, fs: float, drive_hz: float):
    """(numerator, denominator) at fs of κ·G·e^{−jωτ} fitted to the segment's drive lines, or None (< 3 lines).

    The segment's ARX fit has three numerator taps, exact for a zero-order
    hold but not across the side lines of a continuous drive, and REEP's
    free-air mean follows the model's poles nearly one for one: at Q 20–38
    Q′ read 0.01–0.03 % high on noise-free reference captures.  The lines'
    own responses (least squares at every line, as the ``f0-q`` route
    measures its drive) fitted by the continuous G carry no such error.
    """
    from afmtool.analyses.freeair_route import line_responses
    from afmtool.estimators.drive_lines import excitation_lines
    from afmtool.models.discretisation import discrete_denominator, fit_continuous_lines, line_numerator

    deflection, dither = segment
    lines = excitation_lines(dither, fs, model.f0_hz)
    if len(lines) < 3:
        return None
    lines = [drive_hz] + [_refined_line(dither, fs, f) for f in sorted(lines, key=lambda f: abs(f - drive_hz))[1:]]
    fit = fit_continuous_lines(lines, line_responses(deflection, dither, fs, lines), model.f0_hz, model.q)
    if fit is None or fit.f0_hz >= fs / 2:
        return None
    unit = line_numerator(fit.f0_hz, fit.q, fs, match_hz=drive_hz, delay_s=fit.delay_s)
    return tuple(fit.gain * a for a in unit), tuple(float(b) for b in discrete_denominator(fit.f0_hz, fit.q, fs))


def _refined_line(dither: np.ndarray, fs: float, frequency_hz: float) -> float:
    """A line's frequency to a small share of a periodogram bin: the peak of the windowed Fourier sum near it."""
    n = min(len(dither), 1 << 16)
    x = np.asarray(dither[:n], dtype=np.float64)
    x = (x - x.mean()) * np.hanning(n + 1)[:-1]
    t = np.arange(n) / fs
    best = frequency_hz
    for half_width in (fs / n, fs / n / 20):  # one bin, then a twentieth of one
        grid = best + np.linspace(-half_width, half_width, 41)
        power = np.abs(np.exp(-2j * np.pi * np.outer(grid, t)) @ x)
        best = float(grid[int(np.argmax(power))])
    return best


def _drive_frequency(params: ReepParams, info: CaptureInfo, model: FreeAirModel | None, first_deflection) -> float:
    """The lock-in's reference: the flag, the metadata, f0, else the first chunk's spectral peak (Hz)."""
    drive = info.capture_metadata.drive
    if params.drive_frequency_hz:
        drive_hz = params.drive_frequency_hz
    elif drive.frequency_hz is not None:
        drive_hz = drive.frequency_hz
    elif model is not None:
        drive_hz = model.f0_hz
    else:
        drive_hz = _spectral_peak_hz(first_deflection, info.sample_rate_hz)
    return checked_drive_frequency(drive_hz, info)


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
        progress=progress, prologue=stage.free_air_prologue, read_ahead=_READ_AHEAD, split=split,
        on_start=on_stream_start,
    )
    return result


#: The longest step-response simulation run (capture samples): 2**24 holds 15 windows of 0.5 s at 2 MHz, in
#: 270 MB; a window of λ = 1 − 1e-12 (1e12 samples) asked for 55 TiB (a MemoryError, an internal error).
_MOST_SETTLING_SAMPLES = 1 << 24


def _settling(estimator: ReepEstimator, model: FreeAirModel | None, head: Head,
              geometry: ScanGeometry | None) -> Settling:
    """The window, the measured 10–90 % settling of f0′ and Q′, and for a scan the distance the tip covers meanwhile."""
    from afmtool.estimators.reep_estimator import settling_samples, step_settling

    window_us = estimator.window_s * 1e6
    dither = head.first.data.get("dither")
    if model is None or not estimator.use_input or dither is None:
        return Settling(window_us=window_us, f0_settling_10_90_s=None, q_settling_10_90_s=None,
                        note="no step response without the recorded dither and a free-air model")
    fs = estimator.sample_rate_hz
    simulated = settling_samples(estimator)
    if simulated > _MOST_SETTLING_SAMPLES:
        return Settling(window_us=window_us, f0_settling_10_90_s=None, q_settling_10_90_s=None,
                        note=f"no step response: REEP's window of {estimator.window_s:.3g} s needs {simulated:.3g} "
                        f"samples simulated (at most {_MOST_SETTLING_SAMPLES:.3g})")
    step = step_settling(estimator, model.numerator_at(fs), model.denominator_at(fs), dither)
    out = Settling(window_us=window_us, f0_settling_10_90_s=step.f0_s, q_settling_10_90_s=step.q_s,
                   f0_step_hz=step.f0_step_hz, q_step=step.q_step,
                   method="noise-free free-air model, f0 stepped down by half a linewidth and Q by 10 %")
    if geometry is not None and step.f0_s is not None:
        # the tip crosses the scan once per line period, twice with trace and retrace
        speed = geometry.scan_size_m * geometry.line_rate_hz * (2.0 if geometry.trace_retrace else 1.0)
        out = out.replace(scan_speed_m_per_s=speed, spatial_resolution_m=speed * step.f0_s,
                          spatial_resolution_pixels=speed * step.f0_s / (geometry.scan_size_m / geometry.pixels_per_line))
    return out
