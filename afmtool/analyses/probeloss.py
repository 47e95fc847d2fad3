"""``afmtool probeloss``: reliability index, switching signal and amplitude baseline (ch. 2).

capture → chunks → free-air observer (eq. 2.10, :mod:`afmtool.estimators.observer`)
→ innovation window RMS / free-air level = reliability index → hysteresis
switching signal (1 = probe loss, index low) → events; beside it the
lock-in amplitude and the amplitude-threshold baseline (loss while
A > A_upper, Ando et al., thesis §2.2) → events; decimated series in
``probeloss.h5``, probe-loss mask and index images with scan geometry, and,
when the capture carries ``/truth/contact``, per-event scores of both
detectors.  Every filter carries its state across chunks, so the output does
not depend on the chunk size, and everything is causal (sample n uses
samples up to n), as on the instrument.

Before the pass, the free-air segment (``--free-air`` or metadata) gives the
free-air model (unless ``--model``), the free-air innovation RMS the index is
divided by, the automatic switching thresholds and the free amplitude A0.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from afmtool.analyses.accumulators import ImageAccumulator, ScanGeometry
from afmtool.analyses.freeair_route import drive_lines, resolve_free_air, route_record
from afmtool.analyses.freeair_source import FreeAirSegment
from afmtool.config.params import ProbeLossParams
from afmtool.estimators.probeloss_events import (
    Events,
    RunState,
    overlapping_lead,
    runs_finish,
    runs_update,
    score_events,
    truth_loss_events,
)
from afmtool.io.capture import CaptureReader, Chunk
from afmtool.models.free_air import FreeAirModel
from afmtool.pipeline import Decimation, Head, Split, run_stream
from afmtool.records.common import Route
from afmtool.records.probeloss import (
    MOSTLY_LOSS_FRACTION,
    AmplitudeBaselineRecord,
    IndexFirstRecord,
    IndexScoreRecord,
    LossEventRecord,
    LossPerLineRecord,
    ProbeLossResults,
    ScanRecord,
    ScoreRecord,
    TruthRecord,
)

if TYPE_CHECKING:  # numba-backed modules load when the command runs
    from afmtool.estimators.reliability import DetectorDesign, DetectorOptions

__all__ = [
    "SERIES_UNITS",
    "ProbeLossKernels",
    "ProbeLossResult",
    "ProbeLossSetup",
    "ProbeLossStage",
    "prepare_probeloss",
    "run_probeloss",
]

#: Decimated series written per kept sample ("" = dimensionless; amplitude in input units).
SERIES_UNITS = {"t": "s", "index": "", "switch": "", "amplitude": "deflection units", "amplitude_switch": ""}
_IMAGE_QUANTITIES = ("loss", "index")
#: Chunks read ahead while the kernels run (issue 33): one 1 Mi-sample chunk is read in a few
#: ms, far less than the kernels take, so a second only held 16 MB more at the same speed.
_READ_AHEAD = 1


@dataclass(frozen=True)
class ProbeLossSetup:
    """Everything fixed before the pass: model, detector (with its prediction), A_upper.

    Attributes
    ----------
    model : FreeAirModel
        The free-air model the observer runs on.
    model_source : str
        The free-air route: ``"f0-q"``, ``"model"`` (``--model``) or
        ``"segment"`` (ARX fit here); :mod:`afmtool.analyses.freeair_route`.
    detector : DetectorDesign
        The index, its parameters and its predicted performance
        (:func:`~afmtool.estimators.reliability.design_detector`).
    drive_hz : float
        Drive (lock-in) frequency, Hz.
    period_samples : float
        fs/drive_hz.
    amplitude_upper : float or None
        A_upper, deflection units; None when neither it nor a set point is
        known (the amplitude baseline is then skipped).
    free_amplitude : float or None
        A0 on the free-air segment, deflection units.
    setpoint : float or None
        A_sp used for the automatic A_upper.
    lowpass_hz : float
        Lock-in corner, Hz.
    decimate : int
        One output sample in ``decimate``.
    segment_s : tuple of 2 floats or None
        The free-air segment, s.
    route : dict
        How the model was chosen and the drive's hold, for report.json.
    warnings : tuple of str
        Set-up warnings (route fallbacks, a skipped baseline, a capture beyond the limit).
    """

    model: FreeAirModel
    model_source: str
    detector: DetectorDesign
    drive_hz: float
    period_samples: float
    amplitude_upper: float | None
    free_amplitude: float | None
    setpoint: float | None
    lowpass_hz: float
    decimate: int
    segment_s: tuple[float, float] | None
    route: dict = field(default_factory=dict)
    warnings: tuple[str, ...] = ()


@dataclass(frozen=True)
class ProbeLossResult:
    """What :func:`run_probeloss` found; the command turns it into files and a report.

    Attributes
    ----------
    results : ProbeLossResults
        The ``results`` of report.json.
    warnings : tuple of str
    images : dict of str to ndarray
        The probe-loss mask and index images (``"loss/trace"`` ...), with scan geometry.
    geometry : ScanGeometry or None
    setup : ProbeLossSetup or None
    """

    results: ProbeLossResults
    warnings: tuple[str, ...]
    images: dict[str, np.ndarray] = field(default_factory=dict)
    geometry: ScanGeometry | None = None
    setup: ProbeLossSetup | None = None

    def to_json(self) -> dict:
        """``results`` as report.json holds them."""
        return self.results.to_json()


# --------------------------------------------------------------------------- set-up

#: Samples after the free-air segment read ahead as the survey (on-sample amplitude and forcing, loss events).
SURVEY_SAMPLES = 1 << 20


def _free_amplitude(segment: FreeAirSegment | None, drive_hz: float, fs: float,
                    lowpass_hz: float) -> tuple[float | None, float | None]:
    """Mean and standard deviation of the lock-in amplitude over the free-air segment after the low-pass settles."""
    from afmtool.estimators.lockin import LockIn

    if segment is None:
        return None, None
    lockin = LockIn(drive_hz, fs, lowpass_hz)
    blocks, _ = lockin.process(segment.data["deflection"], lockin.initial_state(1))
    amplitude = blocks[0].amplitude
    skip = min(amplitude.size // 2, math.ceil(5.0 * fs / lowpass_hz))
    return float(np.mean(amplitude[skip:])), float(np.std(amplitude[skip:]))


def _setpoint(params: ProbeLossParams, reader: CaptureReader) -> float | None:
    """A_sp from ``--setpoint`` or metadata ``controller.setpoint_nm``, deflection units; None if neither."""
    value = params.setpoint or reader.info.capture_metadata.controller.setpoint_nm
    return None if value is None else float(value)


def _amplitude_upper(params: ProbeLossParams, reader: CaptureReader, free_amplitude: float | None):
    if params.amplitude_upper:
        return params.amplitude_upper, None
    setpoint = _setpoint(params, reader)
    if setpoint is None or free_amplitude is None:
        # the baseline is only a comparison: without A_upper the index still runs
        return None, None
    # A_upper = A_sp + fraction·(A0 − A_sp)
    return setpoint + params.upper_fraction * (free_amplitude - setpoint), setpoint


def _options(params: ProbeLossParams) -> DetectorOptions:
    from afmtool.estimators.reliability import DetectorOptions

    return DetectorOptions(
        index=params.index, gain=params.gain, decay_cycles=params.decay_cycles, process_noise=params.process_noise,
        measurement_noise=params.measurement_noise, window_periods=params.window_periods,
        index_level=params.index_level, on=params.on, off=params.off, quantile=params.quantile,
        off_ratio=params.off_ratio, latency_periods=params.latency_periods,
    )


def _read_survey(reader: CaptureReader, chunks: Iterator[Chunk], segment: FreeAirSegment | None):
    """The capture after the free-air segment, up to ``SURVEY_SAMPLES``, read ahead: ((y, g, first) or None, chunks).

    None for a stream of unknown length (stdin): reading ahead would hold back the first rows of a live
    capture; the detector is then designed from the set point, if one is given.
    """
    if segment is None or reader.info.n_samples is None:
        return None, chunks
    from afmtool.pipeline import read_ahead

    first = segment.start_sample + len(segment.data["deflection"])
    data, chunks = read_ahead(chunks, ("deflection", "dither"), first, first + SURVEY_SAMPLES)
    if data["deflection"].size < 16:
        return None, chunks
    return (data["deflection"], data["dither"], first), chunks


def _design_detector(params: ProbeLossParams, reader: CaptureReader, model: FreeAirModel, drive_hz: float,
                     segment: FreeAirSegment | None, survey, lowpass_hz: float, free: tuple) -> DetectorDesign:
    from afmtool.estimators.reliability import DesignInputs, design_detector

    fs = reader.info.sample_rate_hz
    lines = drive_lines(reader.info.capture_metadata, segment, fs, drive_hz)
    inputs = DesignInputs(
        tuple(model.denominator_at(fs)), tuple(model.numerator_at(fs)), model.gain, fs, drive_hz,
        (segment.data["deflection"], segment.data["dither"]) if segment is not None else None, survey,
        free[0], free[1], _setpoint(params, reader), lowpass_hz, lines,
    )
    return design_detector(inputs, _options(params))


def _setup_warnings(route_warnings, upper, detector: DetectorDesign, setpoint: float | None) -> list[str]:
    warnings = list(route_warnings)
    statement = detector.statement()
    if statement:  # the run's premise: first
        warnings.insert(0, statement)
    on = detector.on_sample
    if on is not None and setpoint and on.amplitude_source.startswith("estimated"):
        warnings.append(f"the set point {setpoint:g} matches no stretch of the capture; the detector is designed for "
                        f"the amplitude it taps at, {on.amplitude:.3g} (the mode below the free amplitude)")
    if upper is None:
        warnings.append(
            "amplitude baseline skipped: it needs --amplitude-upper, or a free-air segment and the set point "
            "(--setpoint or metadata controller.setpoint_nm) for the automatic A_upper"
        )
    return warnings


def prepare_probeloss(
    reader: CaptureReader, params: ProbeLossParams, chunks: Iterator[Chunk], model: FreeAirModel | None
) -> tuple[ProbeLossSetup, Iterator[Chunk]]:
    """Read the free-air segment and the survey ahead; fix the model, the detector (predicted) and A_upper."""
    from afmtool.estimators.lockin import default_lowpass_hz

    fs = reader.info.sample_rate_hz
    route, chunks = resolve_free_air(
        reader, chunks, given=model, free_air=params.free_air, f0_hz=params.f0_hz, q=params.q,
        drive_hold=params.drive_hold, drive_frequency_hz=params.drive_frequency_hz,
    )
    model, source, segment, drive_hz = route.model, route.route, route.segment, route.drive_hz
    period = fs / drive_hz
    sideband_offset_hz = reader.info.capture_metadata.drive.sideband_offset_hz
    lowpass_hz = params.lockin_lowpass_hz or default_lowpass_hz(drive_hz, sideband_offset_hz)
    free = _free_amplitude(segment, drive_hz, fs, lowpass_hz)
    upper, setpoint = _amplitude_upper(params, reader, free[0])
    survey, chunks = _read_survey(reader, chunks, segment)
    detector = _design_detector(params, reader, model, drive_hz, segment, survey, lowpass_hz, free)
    setup = ProbeLossSetup(
        model, source, detector, drive_hz, period, upper, free[0], setpoint, lowpass_hz,
        _row_every(params, detector, period), segment.interval_s if segment is not None else None, route.report,
        tuple(_setup_warnings(route.warnings, upper, detector, _setpoint(params, reader))),
    )
    return setup, chunks


def _row_every(params: ProbeLossParams, detector, period: float) -> int:
    """Capture samples per row: ``--decimate``, else one per drive period or one per index window (issue 33).

    The index at sample n is a statistic of its window (the RMS or coherent
    index's W samples, the forcing filter's memory), so rows one window apart
    tile the capture and hold all it resolves; the events come from every
    sample's switch, whatever the rows.
    """
    if params.decimate:
        return params.decimate
    if params.rows == "per-period":
        return max(1, round(period))
    if detector.memory_periods:
        return max(1, round(detector.memory_periods * period))
    return max(1, int(detector.window_samples))


# --------------------------------------------------------------------------- pass


@dataclass(frozen=True)
class ProbeLossKernels:
    """The detector and the lock-in, as a pure function of a chunk.

    The :class:`~afmtool.pipeline.ChunkKernels` of :class:`ProbeLossStage`:
    ``estimate`` runs both from their initial state over the lead and the
    chunk.  The detector's filter forgets its start with its poles (and a
    window RMS after one window: :meth:`~afmtool.estimators.reliability.DetectorDesign.lead_samples`),
    the lock-in with its low-pass's poles.  The switch, whose hysteresis
    remembers its state for as long as its statistics stay between the
    thresholds, is put right by :meth:`ProbeLossStage.account` from the
    chunk's first decisive sample.
    """

    detector: DetectorDesign
    every: int
    lockin: object
    lead_samples: int

    @property
    def alignment(self) -> int:
        return self.every

    def estimate(self, lead: Chunk | None, chunk: Chunk):
        """``(ReliabilityBlock, amplitude)`` of ``chunk`` from the initial states warmed on ``lead``."""
        first = lead.start if lead is not None else chunk.start
        design = self.detector
        detector = design.initial_state(first)
        lock_state = self.lockin.initial_state(1, first)
        block = amplitude = None
        for part in (lead, chunk):
            if part is not None:
                p = part.data["deflection"]
                block, detector = design.update(detector, p, part.data["dither"], keep_every=self.every)
                (demodulated,), lock_state = self.lockin.process(p, lock_state, self.every)
                amplitude = demodulated.amplitude
        return block, amplitude


class ProbeLossStage:
    """The streaming pass as a :mod:`afmtool.pipeline` stage: detectors, events, counts, images.

    ``free_air_prologue`` (the run's prologue, required) reads the free-air segment
    ahead and fixes the setup (:func:`prepare_probeloss`).  Per chunk the
    lock-in runs on the side thread while the observer kernel runs in the
    caller's (both numba kernels release the GIL); each keeps its own
    carried state, so the result does not depend on the threads.
    """

    def __init__(self, reader: CaptureReader, params: ProbeLossParams, model: FreeAirModel | None = None) -> None:
        self.reader = reader
        self.params = params
        self.model = model
        self.fs = reader.info.sample_rate_hz
        self.geometry = ScanGeometry.from_scan(reader.info.capture_metadata.scan)
        self.setup: ProbeLossSetup | None = None

    def free_air_prologue(self, chunks: Iterator[Chunk]) -> Iterator[Chunk]:
        """Fix the setup from the free-air segment, read ahead; hand the whole stream on."""
        self.setup, chunks = prepare_probeloss(self.reader, self.params, chunks, self.model)
        return chunks

    def prepare(self, head: Head) -> None:
        """Detectors and counters at their initial state."""
        from afmtool.estimators.lockin import LockIn

        setup = self.setup
        if setup is None:
            raise RuntimeError("ProbeLossStage runs with prologue=stage.free_air_prologue (the free-air setup)")
        self.side = head.side
        self.decimation = Decimation(setup.decimate)
        self.detector = setup.detector.initial_state()
        self.lockin = LockIn(setup.drive_hz, self.fs, setup.lowpass_hz)
        self.lock_state = self.lockin.initial_state(1)
        self.amp_switch = 0
        self.switch_state = 0
        self.kept_seen = 0
        self.index_runs = RunState()
        self.amp_runs = RunState()
        self.index_events: list[Events] = []
        self.amp_events: list[Events] = []
        self.n_samples = 0
        self.images = ImageAccumulator(self.geometry, _IMAGE_QUANTITIES) if self.geometry else None

    def step(self, chunk: Chunk) -> dict[str, np.ndarray]:
        """The index, switch and amplitude baseline at the kept samples of this chunk."""
        setup = self.setup
        p = chunk.data["deflection"]
        # the amplitude at the kept samples (Decimation), beside the observer
        demodulating = self.side.submit(self.lockin.process, p, self.lock_state, setup.decimate)
        try:
            step = setup.detector.update(self.detector, p, chunk.data["dither"], keep_every=setup.decimate)
        finally:
            demodulated, self.lock_state = demodulating.result()
        self.detector = step.state
        return self.account(chunk, (step.block, demodulated[0].amplitude))

    def kernels(self) -> ProbeLossKernels | None:
        """The detector and the lock-in as :class:`ProbeLossKernels`, for a split run."""
        from afmtool.estimators.split_lead import DEFAULT_RESIDUAL, sos_lead

        setup = self.setup
        lockin_lead = sos_lead(self.lockin.sos)
        if lockin_lead is None:
            return None
        lead = max(setup.detector.lead_samples(DEFAULT_RESIDUAL), lockin_lead)
        return ProbeLossKernels(setup.detector, setup.decimate, self.lockin, lead)

    def account(self, chunk: Chunk, estimate) -> dict[str, np.ndarray]:
        """Everything after the kernels, in capture order: the switch's true state, events, baseline, images."""
        from afmtool.estimators.reliability import hysteresis_update

        setup = self.setup
        block, amplitude = estimate
        switch = block.switch
        # a chunk's kernels may have started from a guessed switch state: up to the first
        # sample that sets the switch whatever its state, it holds the state it came in with
        switch[:block.first_decisive if block.first_decisive >= 0 else len(switch)] = self.switch_state
        if len(switch):
            self.switch_state = int(switch[-1])
        runs = runs_update(self.index_runs, switch, chunk.start)
        self.index_runs = runs.state
        self.index_events.append(runs.events)
        # a skipped baseline (no A_upper) never switches
        upper = setup.amplitude_upper if setup.amplitude_upper is not None else float(np.finfo(np.float64).max)
        amp = hysteresis_update(self.amp_switch, amplitude, upper, upper, loss_when="above")
        self.amp_switch = amp.state
        amp_runs = runs_update(self.amp_runs, amp.switch, self.kept_seen)
        self.amp_runs = amp_runs.state
        self.amp_events.append(amp_runs.events)
        kept = self.decimation.kept_index(chunk.start, len(switch))
        self.kept_seen += amplitude.size
        self.n_samples = chunk.start + len(switch)
        columns = {
            "t": kept / self.fs,
            "index": block.index,
            "switch": self.decimation.take(switch, chunk.start),
            "amplitude": amplitude,
            "amplitude_switch": amp.switch,
        }
        if self.images is not None:
            self.images.add(columns["t"], {"loss": columns["switch"].astype(np.float64), "index": columns["index"]})
        return columns

    def finish(self) -> tuple[Events, Events]:
        """The loss events of the index and of the amplitude baseline, in capture samples."""
        index_events = Events.concatenate([*self.index_events, runs_finish(self.index_runs, self.n_samples)])
        # amplitude runs are counted in kept samples (Decimation.index_of_kept maps them to capture samples)
        amp_runs = Events.concatenate([*self.amp_events, runs_finish(self.amp_runs, self.kept_seen)])
        start = self.decimation.index_of_kept(amp_runs.start)
        end = np.minimum(self.decimation.index_of_kept(amp_runs.end), self.n_samples)
        return index_events, Events(start, end)


# --------------------------------------------------------------------------- report


def _event_list(index_events: Events, lead: np.ndarray, fs: float, limit: int) -> tuple[LossEventRecord, ...]:
    out = []
    for k in range(min(len(index_events), limit)):
        start, end = int(index_events.start[k]), int(index_events.end[k])
        out.append(LossEventRecord(
            start_s=start / fs,
            end_s=end / fs,
            duration_s=(end - start) / fs,
            amplitude_lead_s=None if math.isnan(lead[k]) else float(lead[k]) / fs,
        ))
    return tuple(out)


def _median(values: np.ndarray) -> float | None:
    values = values[np.isfinite(values)]
    return float(np.median(values)) if values.size else None


def _score_record(score, period: float, kind: type[ScoreRecord] = ScoreRecord, **more) -> ScoreRecord:
    latency = score.latency_samples / period
    return kind(
        truth_events=score.truth_events,
        detected_events=score.detected_events,
        recall=score.recall,
        precision=score.precision,
        median_latency_periods=_median(latency),
        p90_latency_periods=float(np.percentile(latency, 90)) if latency.size else None,
        carried_over=score.carried_over,
        **more,
    )


def _event_mask(events: Events, n: int) -> np.ndarray:
    """Boolean mask of the samples inside ``events`` (sorted, disjoint [start, end))."""
    edges = np.zeros(n + 1, dtype=np.int64)
    np.add.at(edges, np.minimum(events.start, n), 1)
    np.add.at(edges, np.minimum(events.end, n), -1)
    return np.cumsum(edges[:-1]) > 0


def _truth_record(reader: CaptureReader, params: ProbeLossParams, setup: ProbeLossSetup,
                  index_events: Events, amp_events: Events) -> TruthRecord | None:
    if "contact" not in reader.info.truth_names:
        return None
    contact = reader.truth()["contact"]
    period = setup.period_samples
    truth = truth_loss_events(contact, period, params.truth_gap_periods)
    minimum = params.min_event_periods * period
    index_score = score_events(index_events, truth, minimum)
    amp_score = score_events(amp_events, truth, minimum)
    flagged = _event_mask(index_events, len(contact))
    off_sample = _event_mask(truth.stretches, len(contact))
    t_index, t_amp = index_score.detection_samples, amp_score.detection_samples
    both = (t_index >= 0) & (t_amp >= 0)
    index_only = (t_index >= 0) & (t_amp < 0)
    amplitude_only = (t_index < 0) & (t_amp >= 0)
    first = both & (t_index < t_amp)
    lead = (t_amp - t_index)[both] / period
    stretch_samples = int(np.sum(truth.stretches.duration))
    return TruthRecord(
        loss_fraction=stretch_samples / len(contact) if len(contact) else None,
        gap_periods=params.truth_gap_periods,
        min_event_periods=params.min_event_periods,
        index=_score_record(
            index_score, period, IndexScoreRecord,
            # share of flagged time that is truly off the sample, and of on-sample time flagged
            time_precision=float(np.mean(off_sample[flagged])) if flagged.any() else None,
            on_sample_flagged_fraction=float(np.mean(flagged[~off_sample])) if (~off_sample).any() else None,
        ),
        amplitude=_score_record(amp_score, period) if setup.amplitude_upper is not None else None,
        index_first=IndexFirstRecord(
            events=int(index_score.truth_events),
            both_detected=int(both.sum()),
            index_first=int(first.sum()),
            index_only=int(index_only.sum()),
            amplitude_only=int(amplitude_only.sum()),
            fraction_of_both=float(first.sum() / both.sum()) if both.any() else None,
            median_lead_periods=_median(lead),
        ),
    )


def _scan_record(result_images: dict, geometry: ScanGeometry, median_lead_s: float | None) -> ScanRecord:
    per_line = {}
    for key, image in result_images.items():
        quantity, direction = key.split("/")
        if quantity == "loss":
            with np.errstate(invalid="ignore"):
                rows = [float(np.nanmean(row)) if np.isfinite(row).any() else None for row in image]
            per_line[direction] = tuple(rows)
    loss_images = [img for key, img in result_images.items() if key.startswith("loss/")]
    stacked = np.concatenate([img.ravel() for img in loss_images])
    finite = stacked[np.isfinite(stacked)]
    velocity = geometry.scan_size_m * geometry.line_rate_hz * (2.0 if geometry.trace_retrace else 1.0)
    return ScanRecord(
        loss_fraction_scan=float(finite.mean()) if finite.size else None,
        loss_fraction_per_line=LossPerLineRecord(trace=per_line["trace"], retrace=per_line.get("retrace")),
        tip_velocity_m_per_s=velocity,
        median_amplitude_lead_m=None if median_lead_s is None else median_lead_s * velocity,
    )


def _amplitude_baseline(setup: ProbeLossSetup, amp_events: Events, n_samples: int) -> AmplitudeBaselineRecord:
    """The baseline's threshold and what it found (nothing when it was skipped: no A_upper)."""
    skipped = setup.amplitude_upper is None
    return AmplitudeBaselineRecord(
        upper=setup.amplitude_upper,
        free_amplitude=setup.free_amplitude,
        setpoint=setup.setpoint,
        lockin_lowpass_hz=setup.lowpass_hz,
        skipped=skipped,
        loss_fraction=None if skipped else float(np.sum(amp_events.duration)) / n_samples,
        events_total=None if skipped else len(amp_events),
    )


def _mostly_loss_warning(loss_fraction: float, truth: TruthRecord | None) -> list[str]:
    """A warning when the switch read loss most of the time, or flagged most of the on-sample time (truth).

    A run never flags most of the on-sample time silently (issue 28): either
    the tip was off the sample that long, or the index has no contrast on
    the sample (results.detectability says what was predicted).
    """
    warnings = []
    if loss_fraction > MOSTLY_LOSS_FRACTION:
        warnings.append(
            f"the switch reads probe loss {100 * loss_fraction:.0f} % of the time: either the tip was off the sample "
            "that long, or the index has no contrast on the sample; see results.detectability (the predicted "
            "latency and precision) and the index figure, and try --index forcing or a longer --latency-periods"
        )
    flagged = truth.index.on_sample_flagged_fraction if truth is not None else None
    if flagged is not None and flagged > MOSTLY_LOSS_FRACTION:
        warnings.append(f"the switch flags {100 * flagged:.0f} % of the on-sample time (against /truth)")
    return warnings


def _results(params: ProbeLossParams, stage: ProbeLossStage, index_events: Events, amp_events: Events,
             images: dict, truth: TruthRecord | None) -> ProbeLossResults:
    """The model, the detector (observer, index, prediction), the baseline and the events, for report.json."""
    setup, detector, n, fs = stage.setup, stage.setup.detector, stage.n_samples, stage.fs
    lead = overlapping_lead(index_events, amp_events)
    median_lead = _median(lead / fs)
    return ProbeLossResults(
        free_air_model=setup.model.record(),
        free_air_model_source=Route(setup.model_source),
        free_air_route=route_record(setup.route),
        free_air_segment_s=setup.segment_s or None,
        drive_frequency_hz=setup.drive_hz,
        decimate=setup.decimate,
        # the series' density and what set it (issue 33)
        rows=f"decimate {params.decimate}" if params.decimate else params.rows,
        row_every_samples=setup.decimate,
        row_rate_hz=setup.drive_hz * setup.period_samples / setup.decimate,
        observer=detector.observer_record(params.gain),
        index=detector.index_record(),
        detectability=detector.detectability_record(),
        amplitude_baseline=_amplitude_baseline(setup, amp_events, n),
        n_samples=n,
        duration_s=n / fs,
        sample_rate_hz=fs,
        loss_fraction=float(np.sum(index_events.duration)) / n,
        events_total=len(index_events),
        events_listed=min(len(index_events), params.max_events),
        median_amplitude_lead_s=median_lead,
        events=_event_list(index_events, lead, fs, params.max_events),
        scan=_scan_record(images, stage.geometry, median_lead) if stage.geometry is not None else None,
        truth=truth,
    )


def run_probeloss(
    reader: CaptureReader,
    params: ProbeLossParams,
    writer,
    *,
    model: FreeAirModel | None = None,
    progress: Callable[[int], None] | None = None,
    split: Split | None = None,
    on_stream_start: Callable[[], None] | None = None,
) -> ProbeLossResult:
    """Reliability index, switching signal and amplitude baseline over a whole capture, streaming.

    Parameters
    ----------
    reader : CaptureReader
        Needs ``deflection`` and ``dither``.
    params : ProbeLossParams
        Effective parameters.
    writer : ResultWriter or RowWriter
        Receives ``t``, ``index``, ``switch``, ``amplitude``,
        ``amplitude_switch`` at the kept samples.
    model : FreeAirModel, optional
        A given free-air model; otherwise identified from the free-air segment.
    split : Split, optional
        Run the kernels of several chunks at once (:class:`~afmtool.pipeline.Split`).
    on_stream_start : callable, optional
        Called as the stream starts (:func:`~afmtool.pipeline.run_stream`'s ``on_start``).

    Returns
    -------
    ProbeLossResult
    """
    fs = reader.info.sample_rate_hz
    state = ProbeLossStage(reader, params, model)
    ((index_events, amp_events),) = run_stream(
        reader, [state], writer, channels=("deflection", "dither"), chunk_samples=params.chunk_samples,
        progress=progress, prologue=state.free_air_prologue, read_ahead=_READ_AHEAD, split=split,
        on_start=on_stream_start,
    )
    setup = state.setup
    warnings: list[str] = list(setup.warnings)
    if setup.model_source != "f0-q" and setup.model.delay_s > 1.5 / fs:
        warnings.append(
            f"the free-air model has a drive delay of {setup.model.delay_s * 1e6:.2f} us (> 1.5 samples) that the "
            "observer does not model; the free-air index level absorbs it, the contrast on the sample drops"
        )
    images = state.images.images() if state.images is not None else {}
    truth = _truth_record(reader, params, setup, index_events, amp_events)
    results = _results(params, state, index_events, amp_events, images, truth)
    warnings.extend(_mostly_loss_warning(results.loss_fraction, truth))
    return ProbeLossResult(results, tuple(warnings), images, state.geometry, setup)
