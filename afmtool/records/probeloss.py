"""``probeloss``'s results: the detector designed for the capture, the loss it found, and its scores.

The index (:class:`IndexKind`) and its observer, the prediction made before the run
(:class:`DetectabilityRecord`), the amplitude-threshold baseline beside it, the loss
events, and, where the capture has them, the scan's images and the scores against
``/truth/contact``.  The headline puts the run's state first where it undermines the
scores (issue 28): the free-air phase misfit, a capture beyond the detection limit,
a switch in loss most of the time, event precision the time-weighted one contradicts.
"""

from __future__ import annotations

import enum

from afmtool.records.base import Item, Record, State, optional, record
from afmtool.records.common import FreeAirModelRecord, FreeAirRouteRecord, Route, phase_state

__all__ = [
    "IndexKind", "GainDesign", "PredictedOn", "ForcingSource", "ObserverRecord", "IndexRecord", "PredictionRecord",
    "AlternativeRecord", "TargetsRecord", "OnSampleRecord", "DetectabilityRecord", "AmplitudeBaselineRecord",
    "LossEventRecord", "LossPerLineRecord", "ScanRecord", "ScoreRecord", "IndexScoreRecord", "IndexFirstRecord",
    "TruthRecord", "ProbeLossResults", "MOSTLY_LOSS_FRACTION", "SCORE_AGREEMENT",
]

#: Above this loss fraction the run warns, and its headline shows the state, not the scores.
MOSTLY_LOSS_FRACTION = 0.5
#: Event and time-weighted precision farther apart than this disagree.
SCORE_AGREEMENT = 0.1


class IndexKind(enum.Enum):
    """The reliability index a detector thresholds."""

    RMS = "rms"  # the thesis's innovation window RMS (ch. 2)
    COHERENT = "coherent"  # the innovation demodulated at the drive
    FORCING = "forcing"  # the tip-sample force at the drive, a Kalman filter on the free-air model


class GainDesign(enum.Enum):
    """How the rms/coherent index's observer gain was designed (``--gain``)."""

    DECAY = "decay"  # error poles placed for a decay time
    KALMAN = "kalman"  # the steady-state Kalman gain


class PredictedOn(enum.Enum):
    """The loss events a predicted precision is for."""

    SURVEY = "survey"  # the events found in the survey of the capture
    REFERENCE = "reference"  # the reference set of events, when the survey finds none


class ForcingSource(enum.Enum):
    """Where the on-sample forcing came from."""

    SURVEY = "survey"  # the forcing over the survey's samples at the on-sample amplitude
    SETPOINT = "setpoint"  # a pure amplitude deficit at the set point


@record
class ObserverRecord(Record):
    """The free-air observer of the rms and coherent indices (eq. 2.10).

    Attributes
    ----------
    gain_design : GainDesign
        How its gain was designed.
    decay_cycles : float or None
        Its error time constant (drive periods), for a decay design.
    gain : tuple of 2 float
        The gain (L1, L2).
    error_pole_radius : float
        The largest error-pole radius.
    window_samples : int
        The index window W (samples).
    """

    gain_design: GainDesign
    decay_cycles: float | None
    gain: tuple[float, float]
    error_pole_radius: float
    window_samples: int


@record
class IndexRecord(Record):
    """Which index, why, its normalisation and its switching thresholds (index units).

    A field of one kind only is absent for the other kinds.

    Attributes
    ----------
    kind : IndexKind
        The index.
    reason : str
        Why this index.
    on : float
        Switch-on (loss) threshold, index units.
    off : float
        Switch-off threshold, index units.
    level : float
        The index's free-air level it is divided by (deflection units; for forcing, dither units).
    big : float, optional
        Forcing: the largest index threshold used in the design, index units.
    memory_periods : float, optional
        Forcing: the filter's memory (drive periods).
    on_sample_forcing : float, optional
        Forcing: the on-sample forcing at the drive, index units.
    units : str, optional
        Forcing: what the index units are.
    free_air_samples : int, optional
        rms/coherent: free-air samples the level was calibrated on (0 when given).
    free_air_median : float, optional
        rms/coherent: the index's median over the free-air segment (null without one).
    free_air_quantile : float, optional
        rms/coherent: its quantile there (null without a segment).
    free_air_max : float, optional
        rms/coherent: its maximum there (null without a segment).
    """

    kind: IndexKind
    reason: str
    on: float
    off: float
    level: float
    big: float | None = optional()
    memory_periods: float | None = optional()
    on_sample_forcing: float | None = optional()
    units: str | None = optional()
    free_air_samples: int | None = optional()
    # present (maybe null: not finite) for the rms and coherent indices, absent (None) for forcing
    free_air_median: float | None = optional()
    free_air_quantile: float | None = optional()
    free_air_max: float | None = optional()


@record
class PredictionRecord(Record):
    """A detector's predicted performance on this capture, before the run.

    Attributes
    ----------
    latency_periods : float
        Median latency after the last contact (drive periods).
    return_periods : float
        Median delay from the first contact back to the switch's release (drive periods).
    precision : float
        Time-weighted precision on the events ``precision_for``.
    recall_5_periods : float
        Share of 5-period losses detected within them.
    false_alarm_fraction : float
        Share of on-sample time flagged away from the returns.
    precision_for : PredictedOn
        The loss events the precision is for.
    false_alarms_per_1000_periods : float or None
        Forcing: expected false losses per 1000 drive periods on the sample.
    false_returns_per_1000_periods : float or None
        Forcing: expected false returns per 1000 drive periods off it.
    """

    latency_periods: float
    return_periods: float
    precision: float
    recall_5_periods: float
    false_alarm_fraction: float
    precision_for: PredictedOn
    false_alarms_per_1000_periods: float | None
    false_returns_per_1000_periods: float | None


@record
class AlternativeRecord(PredictionRecord):
    """A kind of index considered, with its prediction (the fields of :class:`PredictionRecord`, and:).

    Attributes
    ----------
    kind : IndexKind
        The index.
    """

    kind: IndexKind


@record
class TargetsRecord(Record):
    """What a detector must meet.

    Attributes
    ----------
    latency_periods : float
        The latency (drive periods).
    precision : float
        The time-weighted precision.
    recall : float
        The recall of 5-period losses.
    """

    latency_periods: float
    precision: float
    recall: float


@record
class OnSampleRecord(Record):
    """What the survey after the free-air segment says tapping looks like.

    Attributes
    ----------
    free_amplitude : float
        A0 on the free-air segment (deflection units).
    amplitude : float
        The on-sample amplitude A_sp (deflection units).
    amplitude_source : str
        How A_sp was found.
    forcing_source : ForcingSource
        Where the on-sample forcing came from.
    periods_on_sample : float
        Survey drive periods at A_sp.
    """

    free_amplitude: float
    amplitude: float
    amplitude_source: str
    forcing_source: ForcingSource
    periods_on_sample: float


@record
class DetectabilityRecord(Record):
    """The prediction made before any sample was scored (issue 28, item 2).

    Attributes
    ----------
    predicted : PredictionRecord or None
        The chosen detector's prediction; None when nothing could be predicted.
    information_limit_periods : float or None
        The latency no detector beats (drive periods).
    beyond_limit : bool
        The prediction, with its uncertainty, misses a target.
    statement : str or None
        The headline sentence when beyond the limit.
    targets : TargetsRecord
        The targets.
    on_sample : OnSampleRecord or None
        The survey's on-sample amplitude and forcing.
    alternatives : tuple of AlternativeRecord
        The kinds considered, with their predictions.
    """

    predicted: PredictionRecord | None
    information_limit_periods: float | None
    beyond_limit: bool
    statement: str | None
    targets: TargetsRecord
    on_sample: OnSampleRecord | None
    alternatives: tuple[AlternativeRecord, ...]


@record
class AmplitudeBaselineRecord(Record):
    """The amplitude-threshold baseline: loss while A > A_upper (Ando et al., thesis §2.2).

    Attributes
    ----------
    upper : float or None
        A_upper (deflection units); None when it could not be set.
    free_amplitude : float or None
        A0 on the free-air segment (deflection units).
    setpoint : float or None
        A_sp the automatic A_upper used (deflection units).
    lockin_lowpass_hz : float
        The lock-in's corner (Hz).
    skipped : bool
        No A_upper: the baseline did not run.
    loss_fraction : float or None
        Share of the time it read loss.
    events_total : int or None
        Its loss events.
    """

    upper: float | None
    free_amplitude: float | None
    setpoint: float | None
    lockin_lowpass_hz: float
    skipped: bool
    loss_fraction: float | None
    events_total: int | None


@record
class LossEventRecord(Record):
    """One loss event of the index.

    Attributes
    ----------
    start_s : float
        Its start (s).
    end_s : float
        Its end (s).
    duration_s : float
        Its length (s).
    amplitude_lead_s : float or None
        How much earlier the index switched than the amplitude baseline (s); None without an overlapping one.
    """

    start_s: float
    end_s: float
    duration_s: float
    amplitude_lead_s: float | None


@record
class LossPerLineRecord(Record):
    """The probe-loss fraction of each scan line, first line first.

    Attributes
    ----------
    trace : tuple of float or None
        Trace lines; None for a line with no sample.
    retrace : tuple of float or None, optional
        Retrace lines, where the scan has them.
    """

    trace: tuple[float | None, ...]
    retrace: tuple[float | None, ...] | None = optional()


@record
class ScanRecord(Record):
    """The probe-loss images' summary (a capture with scan geometry).

    Attributes
    ----------
    loss_fraction_scan : float or None
        Mean probe-loss fraction over the image pixels.
    loss_fraction_per_line : LossPerLineRecord
        Per line.
    tip_velocity_m_per_s : float
        The tip's speed over the sample (m/s).
    median_amplitude_lead_m : float or None
        The index's median lead over the amplitude baseline as a distance travelled (m).
    """

    loss_fraction_scan: float | None
    loss_fraction_per_line: LossPerLineRecord
    tip_velocity_m_per_s: float
    median_amplitude_lead_m: float | None


@record
class ScoreRecord(Record):
    """Per-event scores of a detector against ``/truth/contact``.

    Attributes
    ----------
    truth_events : int
        Truth loss onsets at least the minimum length.
    detected_events : int
        Detected events at least the minimum length.
    recall : float or None
        Share of truth events detected.
    precision : float or None
        Share of detected events that are true.
    median_latency_periods : float or None
        Median detection latency (drive periods).
    p90_latency_periods : float or None
        Its 90th percentile (drive periods).
    carried_over : int
        Onsets recalled by a detection begun before the tip was back on the sample.
    """

    truth_events: int
    detected_events: int
    recall: float | None
    precision: float | None
    median_latency_periods: float | None
    p90_latency_periods: float | None
    carried_over: int


@record
class IndexScoreRecord(ScoreRecord):
    """The index's per-event scores (the fields of :class:`ScoreRecord`), and its time-weighted ones.

    Attributes
    ----------
    time_precision : float or None
        Share of the flagged time truly off the sample.
    on_sample_flagged_fraction : float or None
        Share of the on-sample time flagged.
    """

    time_precision: float | None
    on_sample_flagged_fraction: float | None


@record
class IndexFirstRecord(Record):
    """Which detector saw each truth loss first.

    Attributes
    ----------
    events : int
        Truth events scored.
    both_detected : int
        Events both detectors detected.
    index_first : int
        ... of which the index first.
    index_only : int
        Events only the index detected.
    amplitude_only : int
        Events only the amplitude baseline detected.
    fraction_of_both : float or None
        index_first / both_detected.
    median_lead_periods : float or None
        The index's median lead where both detected (drive periods).
    """

    events: int
    both_detected: int
    index_first: int
    index_only: int
    amplitude_only: int
    fraction_of_both: float | None
    median_lead_periods: float | None


@record
class TruthRecord(Record):
    """Scores against ``/truth/contact``.

    Attributes
    ----------
    loss_fraction : float or None
        Share of the time truly off the sample.
    gap_periods : float
        Contact gaps shorter than this are bridged (drive periods).
    min_event_periods : float
        Events shorter than this are not scored (drive periods).
    index : IndexScoreRecord
        The index's scores.
    amplitude : ScoreRecord or None
        The amplitude baseline's; None when it was skipped.
    index_first : IndexFirstRecord
        Which saw each loss first.
    """

    loss_fraction: float | None
    gap_periods: float
    min_event_periods: float
    index: IndexScoreRecord
    amplitude: ScoreRecord | None
    index_first: IndexFirstRecord


def _phase_state(results: ProbeLossResults, held: bool) -> State | None:
    """The free-air phase misfit, when it exceeds 30°."""
    return phase_state(results.free_air_route)


def _detectability_state(results: ProbeLossResults, held: bool) -> State | None:
    """A capture predicted beyond the detection limit."""
    if not results.detectability.beyond_limit:
        return None
    return State(results.detectability.statement or "beyond the detection limit", "detectability.beyond_limit",
                 hides_scores=False)


def _mostly_loss_state(results: ProbeLossResults, held: bool) -> State | None:
    """The switch reading loss more than half the time."""
    loss = results.loss_fraction
    if loss is None or not loss > MOSTLY_LOSS_FRACTION:
        return None
    return State(f"the switch reads probe loss {100 * loss:.0f} % of the time: off the sample that long, or the "
                 "index has no contrast on the sample; scores are not shown", "loss_fraction")


def _scores_disagree_state(results: ProbeLossResults, held: bool) -> State | None:
    """Event precision vs /truth against the time-weighted one (asked only while the scores still stand)."""
    index = results.truth.index if results.truth is not None else None
    if held or index is None or index.precision is None or index.time_precision is None:
        return None
    event, timed = index.precision, index.time_precision
    if not abs(event - timed) > SCORE_AGREEMENT:
        return None
    return State(f"event precision {event:.2f} disagrees with the time-weighted precision {timed:.2f}: event "
                 "precision and recall are not shown", "truth.index.time_precision")


@record
class ProbeLossResults(Record):
    """Reliability index, switching signal and amplitude baseline over a capture (thesis ch. 2).

    Attributes
    ----------
    free_air_model : FreeAirModelRecord
        The free-air model the observer ran on.
    free_air_model_source : Route
        Where it came from.
    free_air_route : FreeAirRouteRecord
        How it was chosen, and the drive's hold.
    free_air_segment_s : tuple of 2 float or None
        The free-air segment (s).
    drive_frequency_hz : float
        The drive (lock-in) frequency (Hz).
    decimate : int
        One output row in ``decimate`` capture samples.
    rows : str
        What set the rows' spacing (``resolution``, ``per-period``, ``decimate N``).
    row_every_samples : int
        Capture samples per row.
    row_rate_hz : float
        Rows per second of capture (Hz).
    observer : ObserverRecord or None
        The rms/coherent index's observer; None for the forcing index.
    index : IndexRecord
        The index and its thresholds.
    detectability : DetectabilityRecord
        The prediction made before the run.
    amplitude_baseline : AmplitudeBaselineRecord
        The amplitude-threshold baseline.
    n_samples : int
        Samples read.
    duration_s : float
        Their duration (s).
    sample_rate_hz : float
        The capture's sample rate (Hz).
    loss_fraction : float
        Share of the time the index's switch read loss.
    events_total : int
        The index's loss events.
    events_listed : int
        Those listed in ``events`` (at most ``max_events``).
    median_amplitude_lead_s : float or None
        The index's median lead over the amplitude baseline (s).
    events : tuple of LossEventRecord
        The index's loss events, first first.
    scan : ScanRecord, optional
        A capture with scan geometry: the images' summary.
    truth : TruthRecord, optional
        A capture with ``/truth/contact``: the scores.
    """

    free_air_model: FreeAirModelRecord
    free_air_model_source: Route
    free_air_route: FreeAirRouteRecord
    free_air_segment_s: tuple[float, float] | None
    drive_frequency_hz: float
    decimate: int
    rows: str
    row_every_samples: int
    row_rate_hz: float
    observer: ObserverRecord | None
    index: IndexRecord
    detectability: DetectabilityRecord
    amplitude_baseline: AmplitudeBaselineRecord
    n_samples: int
    duration_s: float
    sample_rate_hz: float
    loss_fraction: float
    events_total: int
    events_listed: int
    median_amplitude_lead_s: float | None
    events: tuple[LossEventRecord, ...]
    scan: ScanRecord | None = optional()
    truth: TruthRecord | None = optional()

    HEADLINE = (
        Item("probe-loss fraction (index)", "loss_fraction", "of time"),
        Item("probe-loss fraction (truth)", "truth.loss_fraction", "of time"),
        Item("precision (index)", "truth.index.precision", "", scores=True),
        Item("recall (index)", "truth.index.recall", "", scores=True),
        Item("median latency (index)", "truth.index.median_latency_periods", "drive periods", scores=True),
        Item("probe-loss fraction (amplitude baseline)", "amplitude_baseline.loss_fraction", "of time"),
        Item("precision (amplitude baseline)", "truth.amplitude.precision", ""),
        Item("recall (amplitude baseline)", "truth.amplitude.recall", ""),
        Item("loss events (index)", "events_total", "events"),
    )
    STATES = (
        _phase_state,
        _detectability_state,
        _mostly_loss_state,
        _scores_disagree_state,
    )
