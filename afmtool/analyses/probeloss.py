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
from afmtool.analyses.freeair_route import resolve_free_air
from afmtool.analyses.freeair_source import FreeAirSegment
from afmtool.config.params import ProbeLossParams
from afmtool.errors import ConfigError, InputError
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
from afmtool.report.results import JsonResults

if TYPE_CHECKING:  # numba-backed modules load when the command runs
    from afmtool.estimators.observer import ObserverDesign
    from afmtool.estimators.reliability import FreeAirCalibration

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


@dataclass(frozen=True)
class ProbeLossSetup:
    """Everything fixed before the pass: model, observer, normalisation, thresholds, A_upper.

    Attributes
    ----------
    model : FreeAirModel
        The free-air model the observer runs on.
    model_source : str
        The free-air route: ``"f0-q"``, ``"model"`` (``--model``) or
        ``"segment"`` (ARX fit here); :mod:`afmtool.analyses.freeair_route`.
    design : ObserverDesign
        The observer.
    window_samples : int
        W of the index.
    drive_hz : float
        Drive (lock-in) frequency, Hz.
    period_samples : float
        fs/drive_hz.
    calibration : FreeAirCalibration
        Index level and thresholds.
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
        Set-up warnings (route fallbacks, a skipped baseline).
    drive_rad : float
        0 for the RMS index, ω_d·T (rad per sample) for the coherent index
        (:mod:`afmtool.estimators.reliability`).
    index_choice : dict
        Which index runs and why (:func:`_choose_index`), for report.json.
    """

    model: FreeAirModel
    model_source: str
    design: ObserverDesign
    window_samples: int
    drive_hz: float
    period_samples: float
    calibration: FreeAirCalibration
    amplitude_upper: float | None
    free_amplitude: float | None
    setpoint: float | None
    lowpass_hz: float
    decimate: int
    segment_s: tuple[float, float] | None
    route: dict = field(default_factory=dict)
    warnings: tuple[str, ...] = ()
    drive_rad: float = 0.0
    index_choice: dict = field(default_factory=dict)


@dataclass(frozen=True)
class ProbeLossResult(JsonResults):
    """What :func:`run_probeloss` found; the command turns it into files and a report."""

    results: dict
    warnings: tuple[str, ...]
    images: dict[str, np.ndarray] = field(default_factory=dict)
    geometry: ScanGeometry | None = None
    setup: ProbeLossSetup | None = None


# --------------------------------------------------------------------------- set-up


def _design(params: ProbeLossParams, model: FreeAirModel, fs: float, period_samples: float, decay_cycles: float):
    from afmtool.estimators.observer import ObserverDesign

    denominator, numerator = model.denominator_at(fs), model.numerator_at(fs)
    if params.gain == "kalman":
        return ObserverDesign.from_kalman(
            denominator, numerator, params.process_noise, params.measurement_noise, input_gain=model.gain
        )
    return ObserverDesign.from_decay(denominator, numerator, decay_cycles, period_samples)


def _calibrate(params: ProbeLossParams, design, window: int, segment: FreeAirSegment | None, drive_rad: float):
    """Index level and thresholds: from the segment, or given."""
    from afmtool.estimators.reliability import (
        FreeAirCalibration,
        ReliabilityState,
        calibrate_index,
        check_thresholds,
        reliability_update,
        settle_samples,
    )

    on = params.on or None
    off = params.off or None
    if segment is None:
        if not (params.index_level and on and off):
            raise ConfigError(
                "without a free-air segment (--free-air or metadata free_air) give --index-level, --on and --off"
            )
        thresholds = check_thresholds(on, off)
        return FreeAirCalibration(params.index_level, thresholds, 0, math.nan, math.nan, math.nan, params.quantile)
    # the detector itself with level 1 gives the un-normalised statistic (RMS or |X|) on the segment
    unit = ReliabilityState.initial(design, window, 1.0, (1.0, 2.0), drive_rad=drive_rad)
    statistic = reliability_update(unit, segment.data["deflection"], segment.data["dither"]).block.index
    skip = settle_samples(design, window)
    if statistic.size < skip + 16:
        raise InputError(
            f"free-air segment {segment.interval_s[0]:g}:{segment.interval_s[1]:g} s is shorter than the "
            f"observer's settling ({skip} samples) plus 16"
        )
    calibration = calibrate_index(
        statistic[skip:], on=on, off=off, quantile=params.quantile, off_ratio=params.off_ratio
    )
    if params.index_level:
        calibration = calibration._replace(level=params.index_level)
    return calibration


def _free_amplitude(segment: FreeAirSegment | None, drive_hz: float, fs: float, lowpass_hz: float) -> float | None:
    """Mean lock-in amplitude over the free-air segment after the low-pass settles."""
    from afmtool.estimators.lockin import LockIn

    if segment is None:
        return None
    lockin = LockIn(drive_hz, fs, lowpass_hz)
    blocks, _ = lockin.process(segment.data["deflection"], lockin.initial_state(1))
    amplitude = blocks[0].amplitude
    skip = min(amplitude.size // 2, math.ceil(5.0 * fs / lowpass_hz))
    return float(np.mean(amplitude[skip:]))


#: The observer's error time constant when ``decay_cycles = 0`` (auto), drive periods.
DEFAULT_DECAY_CYCLES = 1.0
#: Auto: the shortest time constant it may choose, drive periods, and the on-sample RMS index it aims
#: at, as a multiple of the off threshold (the index reads 1.3-1.6x its prediction; tests/test_probeloss_reference.py).
AUTO_MIN_DECAY_CYCLES = 0.5
AUTO_TARGET_OFF_RATIO = 1.5
#: Window of the coherent index when ``index = "auto"`` chooses it, drive periods: at one period
#: its Rayleigh tail (0.999 quantile 2.6) leaves it no better than the RMS index (reliability docstring).
AUTO_COHERENT_WINDOW_PERIODS = 1.5


def _setpoint(params: ProbeLossParams, reader: CaptureReader) -> float | None:
    """A_sp from ``--setpoint`` or metadata ``controller.setpoint_nm``, deflection units; None if neither."""
    value = params.setpoint or reader.info.capture_metadata.controller.setpoint_nm
    return None if value is None else float(value)


def _choose_index(params: ProbeLossParams, q: float, design, period: float, rms_calibration, free_amplitude,
                  setpoint) -> dict:
    """Which index runs, and why (``results.index.choice``).

    ``auto`` keeps the thesis's RMS index unless the amplitude the sample takes
    away is known (A0 from the free-air segment, A_sp from the set point) and
    the RMS index it predicts on the sample
    (:func:`~afmtool.estimators.reliability.predicted_rms_index`) stays below
    the off threshold: the switch would then never leave loss on the sample,
    and the coherent index, linear in the contrast, runs instead.
    """
    from afmtool.estimators.reliability import predicted_rms_index

    if params.index == "rms":
        return {"kind": "rms", "reason": "--index"}
    if free_amplitude is None or setpoint is None or not 0 < setpoint < free_amplitude:
        return {"kind": "rms", "reason": "the thesis's index; A0 or A_sp unknown, so its on-sample contrast cannot be predicted"}
    radius = float(np.max(np.abs(design.error_poles)))
    predicted = predicted_rms_index(free_amplitude - setpoint, q, rms_calibration.level, radius, period)
    off = rms_calibration.thresholds.off
    record = {"predicted_rms_index_on_sample": predicted, "rms_off_threshold": off}
    if predicted >= off:
        return {"kind": "rms", "reason": f"the RMS index is predicted to read {predicted:.2f} on the sample, above its "
                                         f"off threshold {off:.2f}", **record}
    return {"kind": "coherent", "reason": f"the RMS index is predicted to read only {predicted:.2f} on the sample, "
                                          f"below its off threshold {off:.2f} (high Q x noise / amplitude change)",
            **record}


def _amplitude_upper(params: ProbeLossParams, reader: CaptureReader, free_amplitude: float | None):
    if params.amplitude_upper:
        return params.amplitude_upper, None
    setpoint = _setpoint(params, reader)
    if setpoint is None or free_amplitude is None:
        # the baseline is only a comparison: without A_upper the index still runs
        return None, None
    # A_upper = A_sp + fraction·(A0 − A_sp)
    return setpoint + params.upper_fraction * (free_amplitude - setpoint), setpoint


def _auto_decay_cycles(params: ProbeLossParams, choice: dict, cycles: float) -> float | None:
    """A shorter observer memory where the RMS index has contrast to spare (``decay_cycles = 0``), else None.

    The index falls to ``on`` after the tip leaves in about τ_obs·ln(index/on):
    at Q 100 with 0.03 nm of noise it reads 12 on the sample and takes 3.2
    drive periods.  The contrast C grows as τ_obs (:func:`~afmtool.estimators.reliability.predicted_rms_index`),
    so τ_obs is cut in proportion until the predicted index is
    ``AUTO_TARGET_OFF_RATIO`` × off, down to ``AUTO_MIN_DECAY_CYCLES``.
    """
    predicted = choice.get("predicted_rms_index_on_sample")
    if params.decay_cycles or params.gain != "decay" or choice["kind"] != "rms" or predicted is None:
        return None
    target = AUTO_TARGET_OFF_RATIO * choice["rms_off_threshold"]
    if predicted <= target:
        return None
    # index = √(1 + C²/2) with C ∝ τ_obs: scale τ_obs by C(target)/C(predicted)
    shorter = cycles * math.sqrt((target * target - 1.0) / (predicted * predicted - 1.0))
    return max(AUTO_MIN_DECAY_CYCLES, shorter)


def _detector(params: ProbeLossParams, model: FreeAirModel, fs: float, drive_hz: float,
              segment: FreeAirSegment | None, free_amplitude: float | None, setpoint: float | None):
    """The observer, index window, calibration, demodulation angle and index choice, as ``params`` ask."""
    from afmtool.estimators.reliability import index_window

    period = fs / drive_hz
    coherent_rad = 2.0 * math.pi * drive_hz / fs
    cycles = params.decay_cycles or DEFAULT_DECAY_CYCLES
    design = _design(params, model, fs, period, cycles)
    window = index_window(fs, drive_hz, params.window_periods)
    if params.index == "coherent":  # nothing to choose: one calibration, of the coherent index
        calibration = _calibrate(params, design, window, segment, coherent_rad)
        return design, window, calibration, coherent_rad, {"kind": "coherent", "reason": "--index"}
    calibration = _calibrate(params, design, window, segment, 0.0)
    choice = _choose_index(params, model.q, design, period, calibration, free_amplitude, setpoint)
    shorter = _auto_decay_cycles(params, choice, cycles)
    if shorter is not None:
        choice = {**choice, "decay_cycles": shorter, "decay_cycles_reason":
                  f"the RMS index has contrast to spare ({choice['predicted_rms_index_on_sample']:.1f} predicted on the "
                  f"sample); a shorter observer memory reads loss sooner"}
        design = _design(params, model, fs, period, shorter)
        calibration = _calibrate(params, design, window, segment, 0.0)
    if choice["kind"] != "coherent":
        return design, window, calibration, 0.0, choice
    window = index_window(fs, drive_hz, AUTO_COHERENT_WINDOW_PERIODS)
    calibration = _calibrate(params, design, window, segment, coherent_rad)
    return design, window, calibration, coherent_rad, choice


def prepare_probeloss(
    reader: CaptureReader, params: ProbeLossParams, chunks: Iterator[Chunk], model: FreeAirModel | None
) -> tuple[ProbeLossSetup, Iterator[Chunk]]:
    """Read the free-air segment ahead and fix the model, observer, index level, thresholds and A_upper."""
    from afmtool.estimators.lockin import default_lowpass_hz

    fs = reader.info.sample_rate_hz
    route, chunks = resolve_free_air(
        reader, chunks, given=model, free_air=params.free_air, f0_hz=params.f0_hz, q=params.q,
        drive_hold=params.drive_hold, drive_frequency_hz=params.drive_frequency_hz,
    )
    model, source, segment, drive_hz = route.model, route.route, route.segment, route.drive_hz
    interval = segment.interval_s if segment is not None else None
    period = fs / drive_hz
    sideband_offset_hz = reader.info.capture_metadata.drive.sideband_offset_hz
    lowpass_hz = params.lockin_lowpass_hz or default_lowpass_hz(drive_hz, sideband_offset_hz)
    free_amplitude = _free_amplitude(segment, drive_hz, fs, lowpass_hz)
    upper, setpoint = _amplitude_upper(params, reader, free_amplitude)
    design, window, calibration, drive_rad, index = _detector(
        params, model, fs, drive_hz, segment, free_amplitude, _setpoint(params, reader)
    )
    warnings = list(route.warnings)
    if upper is None:
        warnings.append(
            "amplitude baseline skipped: it needs --amplitude-upper, or a free-air segment and the set point "
            "(--setpoint or metadata controller.setpoint_nm) for the automatic A_upper"
        )
    decimate = params.decimate or max(1, round(period))
    setup = ProbeLossSetup(
        model, source, design, window, drive_hz, period, calibration, upper, free_amplitude, setpoint,
        lowpass_hz, decimate, interval, route.report, tuple(warnings), drive_rad, index,
    )
    return setup, chunks


# --------------------------------------------------------------------------- pass


@dataclass(frozen=True)
class ProbeLossKernels:
    """The free-air observer with its index, and the lock-in, as a pure function of a chunk.

    The :class:`~afmtool.pipeline.ChunkKernels` of :class:`ProbeLossStage`:
    ``estimate`` runs both from their initial state over the lead and the
    chunk.  The observer's error forgets its start with its poles and the
    window RMS after one window (:func:`~afmtool.estimators.reliability.settle_samples`),
    the lock-in with its low-pass's poles.  The switch, whose hysteresis
    remembers its state for as long as the index stays between the
    thresholds, is put right by :meth:`ProbeLossStage.account` from the
    chunk's first decisive sample.
    """

    design: ObserverDesign
    window_samples: int
    level: float
    thresholds: tuple[float, float]
    every: int
    lockin: object
    lead_samples: int
    drive_rad: float = 0.0

    @property
    def alignment(self) -> int:
        return self.every

    def estimate(self, lead: Chunk | None, chunk: Chunk):
        """``(ReliabilityBlock, amplitude)`` of ``chunk`` from the initial states warmed on ``lead``."""
        from afmtool.estimators.reliability import ReliabilityState, reliability_update

        first = lead.start if lead is not None else chunk.start
        detector = ReliabilityState.initial(self.design, self.window_samples, self.level, self.thresholds,
                                            drive_rad=self.drive_rad, samples_seen=first)
        lock_state = self.lockin.initial_state(1, first)
        block = amplitude = None
        for part in (lead, chunk):
            if part is not None:
                p = part.data["deflection"]
                block, detector = reliability_update(detector, p, part.data["dither"], keep_every=self.every)
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
        from afmtool.estimators.reliability import ReliabilityState

        setup = self.setup
        if setup is None:
            raise RuntimeError("ProbeLossStage runs with prologue=stage.free_air_prologue (the free-air setup)")
        self.side = head.side
        self.decimation = Decimation(setup.decimate)
        self.detector = ReliabilityState.initial(
            setup.design, setup.window_samples, float(setup.calibration.level), setup.calibration.thresholds,
            drive_rad=setup.drive_rad,
        )
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
        from afmtool.estimators.reliability import reliability_update

        setup = self.setup
        p = chunk.data["deflection"]
        # the amplitude at the kept samples (Decimation), beside the observer
        demodulating = self.side.submit(self.lockin.process, p, self.lock_state, setup.decimate)
        try:
            step = reliability_update(self.detector, p, chunk.data["dither"], keep_every=setup.decimate)
        finally:
            demodulated, self.lock_state = demodulating.result()
        self.detector = step.state
        return self.account(chunk, (step.block, demodulated[0].amplitude))

    def kernels(self) -> ProbeLossKernels | None:
        """The observer and the lock-in as :class:`ProbeLossKernels`, for a split run."""
        from afmtool.estimators.reliability import settle_samples
        from afmtool.estimators.split_lead import DEFAULT_RESIDUAL, sos_lead

        setup = self.setup
        lockin_lead = sos_lead(self.lockin.sos)
        if lockin_lead is None:
            return None
        lead = max(settle_samples(setup.design, setup.window_samples, DEFAULT_RESIDUAL), lockin_lead)
        return ProbeLossKernels(setup.design, setup.window_samples, float(setup.calibration.level),
                                tuple(setup.calibration.thresholds), setup.decimate, self.lockin, lead, setup.drive_rad)

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


def _event_list(index_events: Events, lead: np.ndarray, fs: float, limit: int) -> list[dict]:
    out = []
    for k in range(min(len(index_events), limit)):
        start, end = int(index_events.start[k]), int(index_events.end[k])
        out.append({
            "start_s": start / fs,
            "end_s": end / fs,
            "duration_s": (end - start) / fs,
            "amplitude_lead_s": None if math.isnan(lead[k]) else float(lead[k]) / fs,
        })
    return out


def _median(values: np.ndarray) -> float | None:
    values = values[np.isfinite(values)]
    return float(np.median(values)) if values.size else None


def _score_dict(score, period: float) -> dict:
    latency = score.latency_samples / period
    return {
        "truth_events": score.truth_events,
        "detected_events": score.detected_events,
        "recall": score.recall,
        "precision": score.precision,
        "median_latency_periods": _median(latency),
        "p90_latency_periods": float(np.percentile(latency, 90)) if latency.size else None,
        "carried_over": score.carried_over,
    }


def _event_mask(events: Events, n: int) -> np.ndarray:
    """Boolean mask of the samples inside ``events`` (sorted, disjoint [start, end))."""
    edges = np.zeros(n + 1, dtype=np.int64)
    np.add.at(edges, np.minimum(events.start, n), 1)
    np.add.at(edges, np.minimum(events.end, n), -1)
    return np.cumsum(edges[:-1]) > 0


def _truth_results(reader: CaptureReader, params: ProbeLossParams, setup: ProbeLossSetup,
                   index_events: Events, amp_events: Events) -> dict | None:
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
    return {
        "loss_fraction": stretch_samples / len(contact) if len(contact) else None,
        "gap_periods": params.truth_gap_periods,
        "min_event_periods": params.min_event_periods,
        "index": {
            **_score_dict(index_score, period),
            # share of flagged time that is truly off the sample, and of on-sample time flagged
            "time_precision": float(np.mean(off_sample[flagged])) if flagged.any() else None,
            "on_sample_flagged_fraction": float(np.mean(flagged[~off_sample])) if (~off_sample).any() else None,
        },
        "amplitude": _score_dict(amp_score, period) if setup.amplitude_upper is not None else None,
        "index_first": {
            "events": int(index_score.truth_events),
            "both_detected": int(both.sum()),
            "index_first": int(first.sum()),
            "index_only": int(index_only.sum()),
            "amplitude_only": int(amplitude_only.sum()),
            "fraction_of_both": float(first.sum() / both.sum()) if both.any() else None,
            "median_lead_periods": _median(lead),
        },
    }


def _image_results(result_images: dict, geometry: ScanGeometry) -> dict:
    per_line = {}
    for key, image in result_images.items():
        quantity, direction = key.split("/")
        if quantity == "loss":
            with np.errstate(invalid="ignore"):
                rows = [float(np.nanmean(row)) if np.isfinite(row).any() else None for row in image]
            per_line[direction] = rows
    loss_images = [img for key, img in result_images.items() if key.startswith("loss/")]
    stacked = np.concatenate([img.ravel() for img in loss_images])
    finite = stacked[np.isfinite(stacked)]
    return {
        "loss_fraction_scan": float(finite.mean()) if finite.size else None,
        "loss_fraction_per_line": per_line,
        "tip_velocity_m_per_s": geometry.scan_size_m * geometry.line_rate_hz * (2.0 if geometry.trace_retrace else 1.0),
    }


def _finite_or_none(value: float) -> float | None:
    return None if math.isnan(value) else float(value)


def _setup_results(setup: ProbeLossSetup, params: ProbeLossParams) -> dict:
    """The model, observer, index normalisation and baseline threshold, for report.json."""
    calibration = setup.calibration
    return {
        "free_air_model": setup.model.to_dict(),
        "free_air_model_source": setup.model_source,
        "free_air_route": setup.route,
        "free_air_segment_s": list(setup.segment_s) if setup.segment_s else None,
        "drive_frequency_hz": setup.drive_hz,
        "decimate": setup.decimate,
        "observer": {
            "gain_design": params.gain,
            "decay_cycles": (setup.index_choice.get("decay_cycles", params.decay_cycles or DEFAULT_DECAY_CYCLES)
                             if params.gain == "decay" else None),
            "gain": list(setup.design.gain),
            "error_pole_radius": float(np.max(np.abs(setup.design.error_poles))),
            "window_samples": setup.window_samples,
        },
        "index": {
            "kind": "coherent" if setup.drive_rad else "rms",
            "choice": setup.index_choice,
            "level": calibration.level,
            "on": calibration.thresholds.on,
            "off": calibration.thresholds.off,
            "free_air_samples": calibration.samples,
            "free_air_median": _finite_or_none(calibration.index_median),
            "free_air_quantile": _finite_or_none(calibration.index_quantile),
            "free_air_max": _finite_or_none(calibration.index_max),
        },
        "amplitude_baseline": {
            "upper": setup.amplitude_upper,
            "free_amplitude": setup.free_amplitude,
            "setpoint": setup.setpoint,
            "lockin_lowpass_hz": setup.lowpass_hz,
        },
    }


#: A loss fraction above this gets :func:`_mostly_loss_warning`.
MOSTLY_LOSS_FRACTION = 0.5


def _mostly_loss_warning(loss_fraction: float) -> list[str]:
    """A warning when the switch read loss most of the time: off the sample, or an index without contrast.

    On the sample the index rises by about ΔA·π·c/(Q·σ) (module docstring of
    :mod:`afmtool.estimators.reliability`): at high Q and noise it can stay below
    the off threshold, and the switch then never leaves the loss it entered in
    free air (issue 14: 91-96 % of on-sample time flagged at Q 300-400, 0.1 nm).
    """
    if not loss_fraction > MOSTLY_LOSS_FRACTION:
        return []
    return [f"the switch reads probe loss {100 * loss_fraction:.0f} % of the time: either the tip was off the sample "
            "that long, or the index does not rise above its off threshold on the sample (its contrast falls as "
            "Q x noise / amplitude change grows); check the index figure, and try the coherent index "
            "(--index coherent --window-periods 1.5, or give --setpoint and --index auto chooses it where it "
            "is needed), a longer observer memory (--decay-cycles) or --kalman"]


def _event_results(index_events: Events, amp_events: Events, lead: np.ndarray, n_samples: int, fs: float,
                   limit: int) -> dict:
    """Loss fraction, the index events and their lead over the amplitude baseline."""
    return {
        "loss_fraction": float(np.sum(index_events.duration)) / n_samples,
        "events_total": len(index_events),
        "events_listed": min(len(index_events), limit),
        "median_amplitude_lead_s": _median(lead / fs),
        "events": _event_list(index_events, lead, fs, limit),
    }


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
    info = reader.info
    fs = info.sample_rate_hz
    state = ProbeLossStage(reader, params, model)
    ((index_events, amp_events),) = run_stream(
        reader, [state], writer, channels=("deflection", "dither"), chunk_samples=params.chunk_samples,
        progress=progress, prologue=state.free_air_prologue, split=split, on_start=on_stream_start,
    )
    setup, geometry = state.setup, state.geometry
    lead = overlapping_lead(index_events, amp_events)
    warnings: list[str] = list(setup.warnings)
    if setup.model_source != "f0-q" and setup.model.delay_s > 1.5 / fs:
        warnings.append(
            f"the free-air model has a drive delay of {setup.model.delay_s * 1e6:.2f} us (> 1.5 samples) that the "
            "observer does not model; the free-air index level absorbs it, the contrast on the sample drops"
        )
    results = {
        **_setup_results(setup, params),
        "n_samples": state.n_samples,
        "duration_s": state.n_samples / fs,
        "sample_rate_hz": fs,
        **_event_results(index_events, amp_events, lead, state.n_samples, fs, params.max_events),
    }
    warnings.extend(_mostly_loss_warning(results["loss_fraction"]))
    skipped = setup.amplitude_upper is None
    results["amplitude_baseline"]["skipped"] = skipped
    results["amplitude_baseline"]["loss_fraction"] = None if skipped else float(np.sum(amp_events.duration)) / state.n_samples
    results["amplitude_baseline"]["events_total"] = None if skipped else len(amp_events)
    images = state.images.images() if state.images is not None else {}
    if geometry is not None:
        results["scan"] = _image_results(images, geometry)
        median_lead = results["median_amplitude_lead_s"]
        results["scan"]["median_amplitude_lead_m"] = (
            None if median_lead is None else median_lead * results["scan"]["tip_velocity_m_per_s"]
        )
    truth = _truth_results(reader, params, setup, index_events, amp_events)
    if truth is not None:
        results["truth"] = truth
    return ProbeLossResult(results, tuple(warnings), images, geometry, setup)
