"""The probe-loss detector for one capture, chosen by its predicted performance (issue 28).

:func:`design_detector` (re-exported as ``afmtool.estimators.reliability.design_detector``)
reads what the capture says (the free-air segment: model, noise, free
amplitude; a survey of the capture after it: the on-sample amplitude and
forcing, :func:`~afmtool.estimators.detectability.estimate_on_sample`) and
predicts, on a synthetic record of this capture's physics
(:mod:`afmtool.estimators.detectability`), how each kind of index would do:

* ``rms``: the thesis's innovation window RMS (ch. 2), one drive period;
* ``coherent``: the innovation demodulated at the drive over 1.5 periods;
* ``forcing``: the tip-sample force at the drive, a Kalman filter on the
  free-air model (:mod:`afmtool.estimators.forcing_observer`), its memory
  and thresholds chosen among candidates (:mod:`afmtool.estimators.forcing_design`).

The prediction models a single-tone drive: a dither with side lines (a
three-sine's) modulates the tapping at their beat, which neither the
synthetic record nor the forcing filter's one phasor represent, so such a
capture gets the thesis's index and no prediction.

``index="auto"`` takes the kind with the smallest predicted latency among
those meeting the precision and recall targets (else the most precise); an
explicit ``index`` designs that kind the same way, so explicit and auto
give the same detector whenever they name the same kind.  Settings that
belong to the thesis's observer narrow auto's choice: ``on``/``off``/
``index_level`` (in the RMS index's units) give the RMS index; ``gain``
kalman, ``decay_cycles`` or ``window_periods`` leave the forcing
detector out.  The prediction
(latency, return lag, precision, recall, the information limit, and
whether the capture is beyond the limit) goes into the report before any
sample is scored.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from afmtool.errors import ConfigError, InputError
from afmtool.estimators.detectability import (
    REFERENCE_EVENTS,
    LossEvents,
    OnSample,
    SwitchScores,
    estimate_on_sample,
    information_limit,
    measurement_noise,
    predicted_precision,
    score_switch,
    survey_events,
    synthetic_record,
)
from afmtool.records.probeloss import (
    AlternativeRecord,
    DetectabilityRecord,
    ForcingSource,
    GainDesign,
    IndexKind,
    IndexRecord,
    ObserverRecord,
    OnSampleRecord,
    PredictedOn,
    PredictionRecord,
    TargetsRecord,
)

__all__ = [
    "IndexKind",
    "DetectorOptions",
    "DesignInputs",
    "Prediction",
    "DetectorDesign",
    "design_detector",
    "RMS_WINDOW_PERIODS",
    "COHERENT_WINDOW_PERIODS",
]

#: Windows of the thesis's RMS index and of the coherent index when not given, drive periods.
RMS_WINDOW_PERIODS = 1.0
COHERENT_WINDOW_PERIODS = 1.5
#: The observer's error time constant of the rms and coherent indices when not given, drive periods.
DEFAULT_DECAY_CYCLES = 1.0
#: How the on-sample amplitude was found, for report.json.
_AMPLITUDE_SOURCES = {
    "setpoint": "set point",
    "estimated": "estimated from the capture: the mode of the amplitude below the free amplitude over the survey "
                 "(no set point given)",
    "estimated: the set point matches no stretch of the capture": "estimated from the capture: the mode of the "
    "amplitude below the free amplitude over the survey (the set point given matches no stretch of it)",
}
#: Memory of the filter that surveys the capture (on-sample forcing, survey events), drive periods.
SURVEY_MEMORY_PERIODS = 2.0


class DetectorOptions(NamedTuple):
    """The user's choices (``ProbeLossParams``); 0 means automatic."""

    index: str = "auto"
    gain: str = "decay"
    decay_cycles: float = 0.0
    process_noise: float = 0.0
    measurement_noise: float = 0.0
    window_periods: float = 0.0
    index_level: float = 0.0
    on: float = 0.0
    off: float = 0.0
    quantile: float = 0.999
    off_ratio: float = 2.0
    latency_periods: float = 0.0


class DesignInputs(NamedTuple):
    """What the capture gives the design.

    Attributes
    ----------
    denominator, numerator
        The free-air model at the capture's rate.
    input_gain : float
        The model's DC gain (deflection per dither unit), for a Kalman observer.
    sample_rate_hz, drive_hz : float
    free_air : (deflection, dither) or None
        The free-air segment.
    survey : (deflection, dither, first sample) or None
        The capture after the free-air segment, read ahead.
    free_amplitude, free_spread : float or None
        A0 and its standard deviation over the free-air segment, deflection units.
    setpoint : float or None
        A_sp given (``--setpoint`` or metadata).
    lowpass_hz : float
        The lock-in's corner, Hz.
    lines_hz : tuple of float
        The dither's lines: the drive, then any side lines (for σ).
    """

    denominator: tuple[float, float]
    numerator: tuple[float, float, float]
    input_gain: float
    sample_rate_hz: float
    drive_hz: float
    free_air: tuple[np.ndarray, np.ndarray] | None
    survey: tuple[np.ndarray, np.ndarray, int] | None
    free_amplitude: float | None
    free_spread: float | None
    setpoint: float | None
    lowpass_hz: float
    lines_hz: tuple[float, ...] = ()

    @property
    def period(self) -> float:
        return self.sample_rate_hz / self.drive_hz

    @property
    def drive_rad(self) -> float:
        return 2.0 * math.pi * self.drive_hz / self.sample_rate_hz


class Prediction(NamedTuple):
    """A detector's predicted performance on this capture (before the run).

    Attributes
    ----------
    latency_periods, return_periods : float
        Median latency after the last contact, and median delay from the
        first contact back to the switch's release, drive periods.
    precision : float
        Time-weighted precision on ``events``.
    recall_5 : float
        Share of 5-period losses detected within them.
    false_fraction : float
        Share of on-sample time flagged away from the returns.
    events : str
        ``"survey"`` or ``"reference"``: the loss events ``precision`` is for.
    false_alarms_per_kperiod, false_returns_per_kperiod : float or None
        The forcing detector's expected false losses per 1000 drive periods on
        the sample and false returns per 1000 off it (Rice's formula:
        :func:`~afmtool.estimators.forcing_design.crossing_rate`); None for the
        rms and coherent indices (their rates are in ``false_fraction``).
    """

    latency_periods: float
    return_periods: float
    precision: float
    recall_5: float
    false_fraction: float
    events: str
    false_alarms_per_kperiod: float | None = None
    false_returns_per_kperiod: float | None = None

    @classmethod
    def of(cls, scores: SwitchScores, events: LossEvents, rates: tuple = (None, None)) -> Prediction:
        return cls(scores.latency_periods, scores.return_periods, predicted_precision(scores, events),
                   scores.recall_5, scores.false_fraction, events.source, *rates)

    def meets(self) -> bool:
        from afmtool.estimators.forcing_design import TARGET_PRECISION, TARGET_RECALL

        return self.precision >= TARGET_PRECISION and self.recall_5 >= TARGET_RECALL

    def record(self, kind: IndexKind | None = None) -> PredictionRecord:
        """The prediction for report.json; with ``kind``, as one of the alternatives considered."""
        values = {"latency_periods": self.latency_periods, "return_periods": self.return_periods,
                  "precision": self.precision, "recall_5_periods": self.recall_5,
                  "false_alarm_fraction": self.false_fraction, "precision_for": PredictedOn(self.events),
                  "false_alarms_per_1000_periods": self.false_alarms_per_kperiod,
                  "false_returns_per_1000_periods": self.false_returns_per_kperiod}
        return PredictionRecord(**values) if kind is None else AlternativeRecord(kind=kind, **values)


@dataclass(frozen=True, eq=False)
class DetectorDesign:
    """A designed probe-loss detector: which index, its parameters, and what it is predicted to do.

    Attributes
    ----------
    kind : IndexKind
    observer : ObserverDesign or None
        The free-air observer of the rms and coherent indices.
    window_samples : int
        Their window W.
    calibration : FreeAirCalibration or None
        Their level and thresholds.
    forcing : ForcingDetector or None
        The forcing detector.
    prediction : Prediction or None
        None when nothing could be predicted (no on-sample stretch, no free air).
    on_sample : OnSample or None
        The survey's on-sample amplitude and forcing.
    information_limit_periods : float or None
        The latency no detector beats (:func:`~afmtool.estimators.detectability.information_limit`).
    reason : str
        Why this kind, in a sentence.
    alternatives : tuple
        ``(kind, Prediction)`` of the kinds considered.
    memory_periods : float or None
        The forcing filter's memory, drive periods.
    decay_cycles : float
        The observer's error time constant (rms, coherent), drive periods.
    """

    kind: IndexKind
    observer: object = None
    window_samples: int = 1
    calibration: object = None
    forcing: object = None
    prediction: Prediction | None = None
    on_sample: OnSample | None = None
    information_limit_periods: float | None = None
    reason: str = ""
    alternatives: tuple = ()
    memory_periods: float | None = None
    decay_cycles: float = DEFAULT_DECAY_CYCLES
    drive_rad: float = 0.0

    @property
    def beyond_limit(self) -> bool:
        """The prediction (with its uncertainty) misses a target; False without a prediction."""
        from afmtool.estimators.forcing_design import LATENCY_UNCERTAINTY, TARGET_LATENCY

        p = self.prediction
        return p is not None and not (p.latency_periods * (1.0 + LATENCY_UNCERTAINTY) <= TARGET_LATENCY and p.meets())

    def initial_state(self, samples_seen: int = 0):
        """The detector's state before sample ``samples_seen`` of the stream."""
        if self.kind is IndexKind.FORCING:
            from afmtool.estimators.forcing_observer import ForcingState

            return ForcingState.initial(self.forcing, samples_seen=samples_seen)
        from afmtool.estimators.reliability import ReliabilityState

        calibration = self.calibration
        return ReliabilityState.initial(
            self.observer, self.window_samples, float(calibration.level), calibration.thresholds,
            drive_rad=self.drive_rad if self.kind is IndexKind.COHERENT else 0.0, samples_seen=samples_seen,
        )

    def update(self, state, deflection, dither, *, keep_every: int = 1):
        """One chunk: ``ReliabilityStep`` (switch, index, first decisive sample; next state)."""
        if self.kind is IndexKind.FORCING:
            from afmtool.estimators.forcing_observer import forcing_update

            return forcing_update(state, deflection, dither, keep_every=keep_every)
        from afmtool.estimators.reliability import reliability_update

        return reliability_update(state, deflection, dither, keep_every=keep_every)

    def lead_samples(self, residual: float) -> int:
        """Samples the detector needs to forget its start (a split run's lead)."""
        if self.kind is IndexKind.FORCING:
            from afmtool.estimators.forcing_observer import closed_loop_radius

            radius = closed_loop_radius(self.forcing.model, self.forcing.gain)
            return 0 if radius == 0 else math.ceil(math.log(residual) / math.log(radius))
        from afmtool.estimators.reliability import settle_samples

        return settle_samples(self.observer, self.window_samples, residual)

    def index_thresholds(self) -> tuple[float, float]:
        """(on, off) in index units, for figures."""
        if self.kind is IndexKind.FORCING:
            return self.forcing.on / self.forcing.scale, self.forcing.off / self.forcing.scale
        return tuple(self.calibration.thresholds)

    def observer_record(self, gain_design: str) -> ObserverRecord | None:
        """The rms/coherent index's observer, for report.json (None for the forcing index)."""
        if self.observer is None:
            return None
        design = GainDesign(gain_design)
        return ObserverRecord(gain_design=design,
                              decay_cycles=self.decay_cycles if design is GainDesign.DECAY else None,
                              gain=tuple(self.observer.gain),
                              error_pole_radius=float(np.max(np.abs(self.observer.error_poles))),
                              window_samples=self.window_samples)

    def index_record(self) -> IndexRecord:
        """Which index, why, its normalisation and thresholds (index units), for report.json."""
        on, off = self.index_thresholds()
        if self.kind is IndexKind.FORCING:
            forcing = self.forcing
            return IndexRecord(
                kind=self.kind, reason=self.reason, on=on, off=off, level=forcing.scale,
                big=forcing.big / forcing.scale, memory_periods=self.memory_periods,
                on_sample_forcing=abs(self.on_sample.forcing) / forcing.scale if self.on_sample else None,
                units="the free-air standard deviation of the projected forcing (dither units: level)")
        calibration = self.calibration
        # NaN without a free-air segment: written as null
        return IndexRecord(kind=self.kind, reason=self.reason, on=on, off=off, level=calibration.level,
                           free_air_samples=calibration.samples, free_air_median=float(calibration.index_median),
                           free_air_quantile=float(calibration.index_quantile),
                           free_air_max=float(calibration.index_max))

    def detectability_record(self) -> DetectabilityRecord:
        """The prediction made before the run, for report.json (issue 28, item 2)."""
        from afmtool.estimators.forcing_design import TARGET_LATENCY, TARGET_PRECISION, TARGET_RECALL

        on = self.on_sample
        return DetectabilityRecord(
            predicted=self.prediction.record() if self.prediction is not None else None,
            information_limit_periods=self.information_limit_periods,
            beyond_limit=self.beyond_limit,
            statement=self.statement() or None,
            targets=TargetsRecord(latency_periods=TARGET_LATENCY, precision=TARGET_PRECISION, recall=TARGET_RECALL),
            on_sample=None if on is None else OnSampleRecord(
                free_amplitude=on.free_amplitude, amplitude=on.amplitude,
                amplitude_source=_AMPLITUDE_SOURCES.get(on.amplitude_source, on.amplitude_source),
                forcing_source=ForcingSource(on.forcing_source), periods_on_sample=on.periods_on_sample,
            ),
            alternatives=tuple(prediction.record(IndexKind(kind)) for kind, prediction in self.alternatives),
        )

    def statement(self) -> str:
        """The headline sentence when the capture is beyond the limit, else ''."""
        p = self.prediction
        if p is None or not self.beyond_limit:
            return ""
        from afmtool.estimators.forcing_design import TARGET_LATENCY, TARGET_PRECISION

        limit = self.information_limit_periods
        bound = f"; information limit {limit:.1f} periods" if limit is not None and math.isfinite(limit) else ""
        if p.precision >= TARGET_PRECISION:
            return (f"beyond the detection limit: no detector is predicted to meet the targets within "
                    f"{TARGET_LATENCY:g} drive periods on this capture; predicted latency {p.latency_periods:.1f} "
                    f"periods (±15 %) at precision {p.precision:.2f}{bound}")
        return (f"beyond the detection limit: precision {TARGET_PRECISION:g} is out of reach on this capture; "
                f"predicted latency {p.latency_periods:.1f} periods at precision {p.precision:.2f}{bound}")


# ----------------------------------------------------------------------------------- rms and coherent


def _observer(options: DetectorOptions, inputs: DesignInputs, cycles: float):
    from afmtool.estimators.observer import ObserverDesign

    if options.gain == "kalman":
        return ObserverDesign.from_kalman(inputs.denominator, inputs.numerator, options.process_noise,
                                          options.measurement_noise, input_gain=inputs.input_gain)
    return ObserverDesign.from_decay(inputs.denominator, inputs.numerator, cycles, inputs.period)


def _calibrate(options: DetectorOptions, design, window: int, free_air, drive_rad: float):
    """Index level and thresholds of an rms/coherent index: from the free-air segment, or given."""
    from afmtool.estimators.reliability import (
        FreeAirCalibration,
        ReliabilityState,
        calibrate_index,
        check_thresholds,
        reliability_update,
        settle_samples,
    )

    on, off = options.on or None, options.off or None
    if free_air is None:
        if not (options.index_level and on and off):
            raise ConfigError(
                "without a free-air segment (--free-air or metadata free_air) give --index-level, --on and --off"
            )
        return FreeAirCalibration(options.index_level, check_thresholds(on, off), 0, math.nan, math.nan, math.nan,
                                  options.quantile)
    # the detector itself with level 1 gives the un-normalised statistic (RMS or |X|) on the segment
    unit = ReliabilityState.initial(design, window, 1.0, (1.0, 2.0), drive_rad=drive_rad)
    statistic = reliability_update(unit, *free_air).block.index
    skip = settle_samples(design, window)
    if statistic.size < skip + 16:
        raise InputError(f"the free-air segment is shorter than the observer's settling ({skip} samples) plus 16")
    calibration = calibrate_index(statistic[skip:], on=on, off=off, quantile=options.quantile,
                                  off_ratio=options.off_ratio)
    return calibration._replace(level=options.index_level) if options.index_level else calibration


def _thesis_design(kind: IndexKind, options: DetectorOptions, inputs: DesignInputs) -> DetectorDesign:
    """The rms or coherent index, as given or by default (module docstring)."""
    from afmtool.estimators.reliability import index_window

    cycles = options.decay_cycles or DEFAULT_DECAY_CYCLES
    periods = options.window_periods or (COHERENT_WINDOW_PERIODS if kind is IndexKind.COHERENT else
                                         RMS_WINDOW_PERIODS)
    observer = _observer(options, inputs, cycles)
    window = index_window(inputs.sample_rate_hz, inputs.drive_hz, periods)
    drive_rad = inputs.drive_rad if kind is IndexKind.COHERENT else 0.0
    calibration = _calibrate(options, observer, window, inputs.free_air, drive_rad)
    return DetectorDesign(kind, observer, window, calibration, decay_cycles=cycles, drive_rad=drive_rad)


def _thesis_scores(design: DetectorDesign, record, inputs: DesignInputs) -> SwitchScores:
    """An rms/coherent design run over the synthetic record, its noise scaled to the capture's level."""
    from afmtool.estimators.reliability import (
        ReliabilityState,
        calibrate_index,
        reliability_update,
        settle_samples,
    )

    zeros = np.zeros(record.signal.size)
    drive_rad = design.drive_rad
    skip = settle_samples(design.observer, design.window_samples)
    # the level this index reads on the synthetic noise alone, against the capture's
    unit = ReliabilityState.initial(design.observer, design.window_samples, 1.0, (1.0, 2.0), drive_rad=drive_rad)
    noise_level = calibrate_index(reliability_update(unit, record.noise, zeros).block.index[skip:]).level
    y = record.signal + record.noise * (design.calibration.level / noise_level)
    state = design.initial_state()
    switch = reliability_update(state, y, zeros).block.switch
    return score_switch(switch, record.contact, record.period_samples, record.first_scored)


# ----------------------------------------------------------------------------------- survey and forcing


class _Survey(NamedTuple):
    on_sample: OnSample | None
    model: object  # ForcingModel
    sigma: float
    steady: np.ndarray | None
    skip: int


def _survey(inputs: DesignInputs) -> _Survey:
    """σ, the forcing model, and the on-sample amplitude and forcing from the survey."""
    from afmtool.estimators.forcing_design import reference_gain
    from afmtool.estimators.forcing_observer import closed_loop_radius, forcing_model, forcing_phasors
    from afmtool.estimators.lockin import LockIn

    fs, period = inputs.sample_rate_hz, inputs.period
    deflection, dither = inputs.free_air
    sigma = measurement_noise(deflection, fs, inputs.lines_hz or (inputs.drive_hz,))
    model = forcing_model(inputs.denominator, inputs.numerator, inputs.drive_rad)
    gain = reference_gain(model, sigma, period, SURVEY_MEMORY_PERIODS)
    skip = min(deflection.size // 2, math.ceil(math.log(1e-6) / math.log(closed_loop_radius(model, gain))))
    reference = complex(np.mean(forcing_phasors(model, gain, deflection, dither)[skip:]))
    if inputs.free_amplitude is None:
        return _Survey(None, model, sigma, None, skip)
    if inputs.survey is None:  # a stream read live: the set point alone, if given, says what tapping does
        empty = np.zeros(0)
        on_sample = estimate_on_sample(empty, empty.astype(complex), inputs.free_amplitude, inputs.free_spread or 0.0,
                                       reference, 1.0, setpoint=inputs.setpoint,
                                       drive_phasor=_drive_phasor(dither, inputs.drive_rad))
        return _Survey(on_sample, model, sigma, None, skip)
    y, g, first = inputs.survey
    every = max(1, round(period))
    lockin = LockIn(inputs.drive_hz, fs, inputs.lowpass_hz)
    (block,), _ = lockin.process(y, lockin.initial_state(1, first), every)
    phasors = forcing_phasors(model, gain, y, g, keep_every=every, first=first)
    drive_phasor = _drive_phasor(dither, inputs.drive_rad)
    on_sample = estimate_on_sample(block.amplitude, phasors, inputs.free_amplitude, inputs.free_spread or 0.0,
                                   reference, period / every, setpoint=inputs.setpoint, drive_phasor=drive_phasor)
    steady = None
    if on_sample is not None and on_sample.forcing_source == "survey":
        band = max(0.02 * inputs.free_amplitude, 3.0 * (inputs.free_spread or 0.0))
        steady = _rows_to_samples(np.abs(block.amplitude - on_sample.amplitude) < band, every, y.size)
    return _Survey(on_sample, model, sigma, steady, skip)


def _rows_to_samples(rows: np.ndarray, every: int, n: int) -> np.ndarray:
    """A mask over decimated rows as a mask over samples (each kept row stands for the ``every`` before it)."""
    mask = np.repeat(rows, every)[:n]
    return np.concatenate([mask, np.zeros(n - mask.size, dtype=bool)])


def _drive_phasor(dither: np.ndarray, drive_rad: float) -> complex:
    """U: the dither's line at the drive, Re(U e^{jω n}) (least squares, n from the segment's start)."""
    n = np.arange(dither.size)
    basis = np.column_stack([np.ones(dither.size), np.cos(drive_rad * n), np.sin(drive_rad * n)])
    coef, *_ = np.linalg.lstsq(basis, np.asarray(dither, dtype=np.float64), rcond=None)
    return complex(coef[1], -coef[2])


def _loss_events(candidate, survey: _Survey, inputs: DesignInputs) -> LossEvents:
    """The survey's loss events, found by ``candidate``; the reference events when it finds none."""
    from afmtool.estimators.forcing_observer import ForcingState, forcing_update
    from afmtool.estimators.probeloss_events import Events, RunState, runs_finish, runs_update

    if inputs.survey is None:
        return REFERENCE_EVENTS
    y, g, first = inputs.survey
    switch = forcing_update(ForcingState.initial(candidate.detector, samples_seen=first), y, g).block.switch
    runs = runs_update(RunState(), switch, 0)
    events = Events.concatenate([runs.events, runs_finish(runs.state, y.size)])
    found = survey_events((events.start, events.end), y.size, inputs.period, candidate.latency,
                          candidate.scores.return_periods)
    return found if found is not None else REFERENCE_EVENTS


def _forcing_design(options: DetectorOptions, inputs: DesignInputs, survey: _Survey, record):
    """The forcing detector (module docstring) and the loss events its precision is predicted on."""
    from afmtool.estimators.forcing_design import choose_candidate, forcing_candidates, provisional_candidate

    on_sample = survey.on_sample
    survey_data = inputs.survey if survey.steady is not None else None
    candidates = forcing_candidates(survey.model, survey.sigma, on_sample.forcing, inputs.period, inputs.free_air,
                                    record, survey=survey_data, steady=survey.steady, skip=survey.skip)
    provisional = provisional_candidate(candidates)
    if provisional is None:
        return None, REFERENCE_EVENTS
    events = _loss_events(provisional, survey, inputs)
    chosen = choose_candidate(candidates, options.latency_periods, events)
    rates = (chosen.false_alarms_per_kperiod, chosen.false_returns_per_kperiod)
    design = DetectorDesign(IndexKind.FORCING, forcing=chosen.detector, memory_periods=chosen.memory_periods,
                            prediction=Prediction.of(chosen.scores, events, rates), on_sample=on_sample)
    return design, events


# ----------------------------------------------------------------------------------- the choice


#: Auto's order of preference among designs predicted equally fast (within the prediction's uncertainty):
#: the thesis's index reads all of the innovation, so it is the least hurt by what the synthetic record
#: leaves out (tapping that rings after a return, grazing contacts, a three-sine's beat).
_PREFERENCE = (IndexKind.RMS, IndexKind.COHERENT, IndexKind.FORCING)


def _pick(designs: list[DetectorDesign], latency_periods: float) -> DetectorDesign:
    """Auto: the smallest predicted latency among those meeting the targets, else the most precise.

    Designs within ``LATENCY_UNCERTAINTY`` of the smallest latency count as
    equally fast and are ranked by ``_PREFERENCE``.
    """
    from afmtool.estimators.forcing_design import LATENCY_UNCERTAINTY

    if latency_periods:
        within = [d for d in designs if d.prediction.latency_periods <= latency_periods]
        if within:
            return max(within, key=lambda d: d.prediction.precision)
    meeting = [d for d in designs if d.prediction.meets()]
    if meeting:
        fastest = min(d.prediction.latency_periods for d in meeting)
        tied = [d for d in meeting if d.prediction.latency_periods <= fastest * (1.0 + LATENCY_UNCERTAINTY)]
        return min(tied, key=lambda d: _PREFERENCE.index(d.kind))
    return max(designs, key=lambda d: (d.prediction.precision, -d.prediction.latency_periods))


def design_detector(inputs: DesignInputs, options: DetectorOptions | None = None) -> DetectorDesign:
    """The probe-loss detector for this capture (module docstring).

    Parameters
    ----------
    inputs : DesignInputs
        The model, the free-air segment, the survey, A0 and the set point.
    options : DetectorOptions
        ``index`` ("auto", "rms", "coherent", "forcing"), ``latency_periods``
        (0: the fastest meeting the targets) and the rms/coherent settings.

    Returns
    -------
    DetectorDesign
        With its prediction, the survey's on-sample estimate, the
        information limit and the alternatives considered.

    Raises
    ------
    ConfigError
        ``index="forcing"`` on a capture without a free-air segment or an
        on-sample stretch (and no set point): it has nothing to design from.
    """
    import dataclasses

    options = options or DetectorOptions()
    if options.index not in ("auto", *(k.value for k in IndexKind)):
        raise ConfigError(f"index={options.index!r} must be auto, rms, coherent or forcing")
    wanted = None if options.index == "auto" else IndexKind(options.index)
    if wanted is None and (options.on or options.off or options.index_level):
        # thresholds or a level in the thesis's index units: the thesis's index is the one meant
        return dataclasses.replace(_thesis_design(IndexKind.RMS, options, inputs),
                                   reason="--on/--off/--index-level given: the thesis's index they are set for")
    observer_given = options.gain == "kalman" or options.decay_cycles or options.window_periods
    thesis = {kind: _thesis_design(kind, options, inputs)
              for kind in (IndexKind.RMS, IndexKind.COHERENT) if wanted in (None, kind)}
    single_tone = len(inputs.lines_hz) <= 1
    survey = _survey(inputs) if inputs.free_air is not None and single_tone else None
    if survey is None or survey.on_sample is None:
        if wanted is IndexKind.FORCING:
            raise ConfigError("--index forcing needs a single-tone drive, a free-air segment and an on-sample stretch "
                              "in the capture (or --setpoint)")
        design = thesis[wanted or IndexKind.RMS]
        why = ("--index" if wanted else
               "the thesis's index: the prediction models a single-tone drive, and this dither has side lines" if
               not single_tone else "the thesis's index: no stretch below the free amplitude was found after the "
               "free-air segment, so no detector's performance can be predicted")
        return dataclasses.replace(design, reason=why)
    on_sample = survey.on_sample
    record = synthetic_record(inputs.denominator, inputs.numerator, on_sample.forcing, inputs.period, survey.sigma)
    limit = information_limit(inputs.denominator, inputs.numerator, on_sample.forcing, inputs.period, survey.sigma)
    designs, events = [], REFERENCE_EVENTS
    # observer settings (--gain kalman, --decay-cycles, --window-periods) are the rms/coherent indices'
    if wanted is IndexKind.FORCING or (wanted is None and not observer_given):
        forcing, events = _forcing_design(options, inputs, survey, record)
        if forcing is not None:
            designs.append(forcing)
        elif wanted is IndexKind.FORCING:
            raise ConfigError("--index forcing: the on-sample forcing is within the noise of every candidate filter; "
                              "use --index rms or coherent")
    for design in thesis.values():
        scores = _thesis_scores(design, record, inputs)
        designs.append(dataclasses.replace(design, prediction=Prediction.of(scores, events)))
    chosen = designs[0] if wanted else _pick(designs, options.latency_periods)
    alternatives = tuple((d.kind.value, d.prediction) for d in designs)
    reason = ("--index" if wanted else f"the smallest predicted latency meeting the targets among "
              f"{', '.join(d.kind.value for d in designs)}" if chosen.prediction.meets() else
              "the most precise predicted (none meets the targets)")
    return dataclasses.replace(chosen, on_sample=on_sample, information_limit_periods=limit, reason=reason,
                               alternatives=alternatives)
