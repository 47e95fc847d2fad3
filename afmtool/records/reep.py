"""``reep``'s results: equivalent f0′ and Q′ every row, their summaries, and what each mode adds.

The stage (:class:`afmtool.analyses.reep.ReepStage`) builds :class:`ReepResults`
as the stream ends; the command (:mod:`afmtool.analyses.reep_outputs`) adds what
it reads back from the finished ``reep.h5``: the tracking error against
``/truth``, the interaction quantities, the force-curve extremes, the images'
means, a synthesised drive's share of the uncertainty.  ``theory compare``,
``theory fit``, ``overlay`` and ``kalman-bank --reep`` read it back from the
run's ``report.json`` (:meth:`ReepResults.from_json`).
"""

from __future__ import annotations

import enum
from collections.abc import Mapping

from afmtool.records.base import Item, Record, State, optional, record
from afmtool.records.common import FreeAirModelRecord, FreeAirRouteRecord, Moments, SeriesMoments, phase_state

__all__ = [
    "AntiAlias", "InputFilter", "ReepEstimatorRecord", "Settling", "LockInRecord", "LevelsSource",
    "FreeAirLevelsRecord", "FlagCounts", "Validity", "ReepSummary", "Segment", "ReepSegments", "CheckReference",
    "FreeAirCheck", "SyntheticDriveUncertainty", "TrackingError", "TruthTracking", "FreeReference",
    "InteractionSeriesUnits", "Interaction", "ForceCurveLeg", "ForceCurve", "ImageMean", "ReepResults",
]


# --------------------------------------------------------------------------- the estimator and its settling


@record
class AntiAlias(Record):
    """The anti-alias filter ahead of REEP's rate reduction.

    Attributes
    ----------
    type : str
        The filter (``root-raised-cosine``).
    rolloff : float
        Its roll-off factor (dimensionless).
    taps : int
        Its length (taps).
    """

    type: str
    rolloff: float
    taps: int


@record
class InputFilter(Record):
    """The FIR filter on the dither that makes the numerator exact for a continuous drive.

    Attributes
    ----------
    type : str
        What it is exact for.
    taps : int
        Its length (taps).
    """

    type: str
    taps: int


@record
class ReepEstimatorRecord(Record):
    """REEP's settings as they ran (:meth:`afmtool.estimators.reep_estimator.ReepEstimator.describe`).

    Attributes
    ----------
    window_us : float
        The forgetting window 1/(1 − λ) (µs).
    window_samples : float
        The window in capture samples.
    forgetting_factor : float
        λ per capture sample.
    reep_forgetting_factor : float
        λ per REEP sample (at REEP's own rate).
    rate_reduction : int
        Capture samples per REEP sample (D).
    reep_rate_hz : float
        REEP's rate (Hz).
    samples_per_period : float or None
        REEP samples per drive period.
    anti_alias : AntiAlias or None
        The anti-alias filter, None without a rate reduction.
    row_every_samples : int
        Capture samples per output row.
    row_rate_hz : float
        The rows' rate (Hz).
    row_every_s : float
        The rows' spacing (s).
    rows_per_window : float
        Output rows per forgetting window.
    input_filter : InputFilter or None
        The dither's FIR filter for a continuous drive, None without one.
    """

    window_us: float
    window_samples: float
    forgetting_factor: float
    reep_forgetting_factor: float
    rate_reduction: int
    reep_rate_hz: float
    samples_per_period: float | None
    anti_alias: AntiAlias | None
    row_every_samples: int
    row_rate_hz: float
    row_every_s: float
    rows_per_window: float
    input_filter: InputFilter | None


@record
class Settling(Record):
    """REEP's window and the 10–90 % settling of f0′ and Q′ to a step, simulated on the free-air model.

    Attributes
    ----------
    window_us : float
        The forgetting window (µs).
    f0_settling_10_90_s : float or None
        10–90 % settling time of f0′ (s); None where not simulated or not settled.
    q_settling_10_90_s : float or None
        10–90 % settling time of Q′ (s).
    note : str, optional
        Why there is no step response (no dither or model, or a window too long to simulate).
    f0_step_hz : float, optional
        The step of f0 simulated (Hz).
    q_step : float, optional
        The step of Q simulated (dimensionless).
    method : str, optional
        How the step response was simulated.
    scan_speed_m_per_s : float, optional
        On a scan: the tip's speed over the sample (m/s).
    spatial_resolution_m : float, optional
        On a scan: the distance the tip covers while f0′ settles (m).
    spatial_resolution_pixels : float, optional
        That distance in image pixels.
    """

    window_us: float
    f0_settling_10_90_s: float | None
    q_settling_10_90_s: float | None
    note: str | None = optional()
    f0_step_hz: float | None = optional()
    q_step: float | None = optional()
    method: str | None = optional()
    scan_speed_m_per_s: float | None = optional()
    spatial_resolution_m: float | None = optional()
    spatial_resolution_pixels: float | None = optional()


@record
class LockInRecord(Record):
    """The lock-in that gives the amplitude and phase beside f0′ and Q′.

    Attributes
    ----------
    lowpass_hz : float
        Its low-pass cut-off (Hz).
    order : int
        The low-pass filter's order.
    type : str
        The filter and demodulation.
    """

    lowpass_hz: float
    order: int
    type: str


# --------------------------------------------------------------------------- validity


class LevelsSource(enum.Enum):
    """Where the free-air levels of σ̂² and the amplitude came from."""

    SEGMENT = "free-air segment"
    METADATA = "metadata"
    NONE = "none"


@record
class FreeAirLevelsRecord(Record):
    """σ̂² and the amplitude in free air, the references of the validity checks.

    Attributes
    ----------
    amplitude : float or None
        The free amplitude (deflection units); None where unknown.
    sigma2 : float or None
        REEP's σ̂² in free air (deflection units²); None where unknown.
    source : LevelsSource
        Where they came from.
    """

    amplitude: float | None
    sigma2: float | None
    source: LevelsSource


@record
class FlagCounts(Record):
    """Rows flagged after the warm-up, by reason (a row may have several).

    Attributes
    ----------
    samples : int
        Output rows after the warm-up.
    flagged : int
        Those flagged.
    fraction : float
        The share flagged (dimensionless).
    not_underdamped : int
        Rows whose (b1, b0) lie outside the under-damped region of eq. 3.48.
    low_amplitude : int
        Rows below the amplitude floor.
    not_converged : int
        Rows before the estimator converged.
    offset_drift : int
        Rows whose static offset drifted beyond its limit.
    """

    samples: int
    flagged: int
    fraction: float
    not_underdamped: int
    low_amplitude: int
    not_converged: int
    offset_drift: int


@record
class Validity(Record):
    """The validity checks of REEP's rows and what they found.

    Attributes
    ----------
    min_amplitude_fraction : float
        The amplitude floor, a share of the free amplitude (dimensionless).
    max_offset_drift : float
        The static offset's drift limit, a share of the oscillation's power A²/2 (dimensionless).
    free_air_levels : FreeAirLevelsRecord
        The free-air references.
    flags : FlagCounts
        Rows flagged, by reason.
    mostly_flagged : str or None
        When more than half the rows are flagged: why (the commonest reason); else None.
    """

    min_amplitude_fraction: float
    max_offset_drift: float
    free_air_levels: FreeAirLevelsRecord
    flags: FlagCounts
    mostly_flagged: str | None


# --------------------------------------------------------------------------- summaries


@record
class ReepSummary(Record):
    """Each series over the trusted rows after the warm-up.

    Attributes
    ----------
    f0_hz : SeriesMoments
        f0′ (Hz), unflagged rows.
    q : SeriesMoments
        Q′ (dimensionless), unflagged rows.
    amplitude : SeriesMoments
        The lock-in amplitude (deflection units).
    phase_deg : SeriesMoments
        The lock-in phase (degrees).
    sigma2 : SeriesMoments
        REEP's σ̂² (deflection units²).
    """

    f0_hz: SeriesMoments
    q: SeriesMoments
    amplitude: SeriesMoments
    phase_deg: SeriesMoments
    sigma2: SeriesMoments


@record
class Segment(Record):
    """f0′ and Q′ over one time segment (:class:`afmtool.analyses.reep_timeseries.SegmentMoments`).

    Attributes
    ----------
    t_s : tuple of 2 float
        Its start and end (s).
    f0_hz : Moments
        f0′ (Hz) over its unflagged rows; std is the rows' sample spread.
    q : Moments
        Q′ (dimensionless) over its unflagged rows.
    f0_row_std_hz : float, optional
        The mean of REEP's own per-row standard deviation of f0′ (Hz).
    """

    t_s: tuple[float, float]
    f0_hz: Moments
    q: Moments
    f0_row_std_hz: float | None = optional()


@record
class ReepSegments(Record):
    """f0′ and Q′ per time segment: in and after the free-air segment, or after the warm-up without one.

    Attributes
    ----------
    free_air : Segment, optional
        Inside the free-air segment, after the warm-up.
    after_free_air : Segment, optional
        From one warm-up after the free-air segment's end.
    settled : Segment, optional
        Without a free-air segment: every row after the warm-up.
    """

    free_air: Segment | None = optional()
    after_free_air: Segment | None = optional()
    settled: Segment | None = optional()


class CheckReference(enum.Enum):
    """What REEP's free-air f0′ was held against."""

    MODEL = "model"
    METADATA = "metadata"


@record
class FreeAirCheck(Record):
    """REEP's free-air f0′ against the lever's f0 (:mod:`afmtool.estimators.free_air_consistency`).

    Attributes
    ----------
    f0_hz : float
        The mean free-air f0′ (Hz).
    f0_std_hz : float
        Its standard deviation per row (Hz).
    reference : CheckReference
        The f0 it was held against (the farthest of those known).
    reference_f0_hz : float
        That f0 (Hz).
    reference_std_hz : float
        Its standard deviation (Hz).
    deviation_hz : float
        f0′ less the reference (Hz).
    deviation_std : float
        The deviation in standard deviations.
    max_deviation_std : float
        The most standard deviations that are consistent.
    consistent : bool
        Within that many.
    """

    f0_hz: float
    f0_std_hz: float
    reference: CheckReference
    reference_f0_hz: float
    reference_std_hz: float
    deviation_hz: float
    deviation_std: float
    max_deviation_std: float
    consistent: bool


# --------------------------------------------------------------------------- what the command adds


@record
class SyntheticDriveUncertainty(Record):
    """A synthesised drive's phase uncertainty, added to reep.h5's ``f0_std_hz`` and ``q_std`` (eq. D.3).

    Attributes
    ----------
    main_line_phase_std_deg : float
        σ_φ of the drive's main line (degrees).
    added_to : tuple of str
        The series widened (none when σ_φ is 0).
    formula : str
        The shares added in quadrature.
    largest_f0_std_added_hz : float, optional
        The largest share added to f0′'s std (Hz).
    largest_q_std_added : float, optional
        The largest share added to Q′'s std (dimensionless).
    """

    main_line_phase_std_deg: float
    added_to: tuple[str, ...]
    formula: str
    largest_f0_std_added_hz: float | None = optional()
    largest_q_std_added: float | None = optional()


@record
class TrackingError(Record):
    """|estimate − truth| over the rows after the warm-up.

    Attributes
    ----------
    median_abs : float or None
        Its median, in ``units``; None without a finite row.
    p95_abs : float or None
        Its 95th percentile, in ``units``.
    units : str
        Units (``Hz``, or ``""`` for Q′).
    """

    median_abs: float | None
    p95_abs: float | None
    units: str


@record
class TruthTracking(Record):
    """f0′ and Q′ against the capture's ``/truth`` (a simulated capture).

    Attributes
    ----------
    f0_hz : TrackingError
        |f0′ − f0| (Hz).
    q : TrackingError
        |Q′ − Q| (dimensionless).
    after_s : float
        Rows from this time on were compared (s).
    rows_compared : int
        Rows compared.
    row_step : int
        Every ``row_step``-th row was taken for the percentiles.
    """

    f0_hz: TrackingError
    q: TrackingError
    after_s: float
    rows_compared: int
    row_step: int


class FreeReference(enum.Enum):
    """The free-air f0, Q the interaction quantities are taken against."""

    SEGMENT = "REEP's median over the settled free-air segment"
    MODEL = "the free-air model"


@record
class InteractionSeriesUnits(Record):
    """The units of each ``/interaction`` series in reep.h5.

    Attributes
    ----------
    k_e_n_per_m : str
        The effective spring constant k_e (N/m).
    force_gradient_n_per_m : str
        The force gradient k_e − k (N/m).
    damping_n_s_per_m : str
        The effective damping c_e (N·s/m).
    damping_ts_n_s_per_m : str
        The tip–sample damping c_ts (N·s/m).
    phi_c_n : str
        The conservative force Φ_c (N).
    phi_d_n : str
        The dissipative force Φ_d (N).
    energy_per_cycle_ev : str
        The energy dissipated per cycle (eV).
    power_w : str
        The power dissipated (W).
    virial_j : str
        The virial (J).
    """

    k_e_n_per_m: str
    force_gradient_n_per_m: str
    damping_n_s_per_m: str
    damping_ts_n_s_per_m: str
    phi_c_n: str
    phi_d_n: str
    energy_per_cycle_ev: str
    power_w: str
    virial_j: str


@record
class Interaction(Record):
    """The tip–sample interaction per row, written to reep.h5's ``/interaction`` (or why not).

    Attributes
    ----------
    written : bool
        The series were written.
    reason : str, optional
        Why not (no spring constant, an amplitude not in a length, no free-air reference).
    spring_constant_n_per_m : float, optional
        The spring constant k used (N/m).
    spring_constant_source : str, optional
        Where k came from.
    free_f0_hz : float, optional
        The free-air f0 the quantities are taken against (Hz).
    free_q : float, optional
        The free-air Q (dimensionless).
    free_reference : FreeReference, optional
        Where that f0 and Q came from.
    series : InteractionSeriesUnits, optional
        The series written, with their units.
    """

    written: bool
    reason: str | None = optional()
    spring_constant_n_per_m: float | None = optional()
    spring_constant_source: str | None = optional()
    free_f0_hz: float | None = optional()
    free_q: float | None = optional()
    free_reference: FreeReference | None = optional()
    series: InteractionSeriesUnits | None = optional()


@record
class ForceCurveLeg(Record):
    """One leg of a force curve, binned against z: ranges, sensitivities and the extremes.

    Numbers a leg may lack are NaN (null) when the mode gives them but no bin is finite.

    Attributes
    ----------
    bins : int
        z bins with rows.
    z_range : tuple of 2 float
        The lowest and highest bin's z (``z_units``).
    z_units : str
        The capture's z units.
    f0_hz_range : tuple of 2 float
        The lowest and highest bin mean of f0′ (Hz).
    q_range : tuple of 2 float
        The lowest and highest bin mean of Q′ (dimensionless).
    max_abs_df0_dz : float or None
        The largest |df0′/dz| (Hz per z unit); None for one bin.
    max_abs_dq_dz : float or None
        The largest |dQ′/dz| (per z unit).
    max_abs_da_dz : float or None
        The largest |dA/dz| (deflection units per z unit).
    largest_df0_hz : float, optional
        The bin mean of f0′ farthest from the free-air f0′, less it (Hz); where a free-air f0′ is known.
    largest_df0_z : float, optional
        Where it occurs (``z_units``).
    smallest_q : float or None
        The lowest bin mean of Q′ (dimensionless).
    smallest_q_z : float or None
        Where it occurs (``z_units``).
    largest_energy_per_cycle_ev : float, optional
        With the interaction series: the largest energy dissipated per cycle (eV).
    largest_energy_per_cycle_z : float, optional
        Where it occurs (``z_units``).
    largest_force_gradient_n_per_m : float, optional
        With the interaction series: the force gradient of largest magnitude (N/m).
    largest_force_gradient_z : float, optional
        Where it occurs (``z_units``).
    """

    bins: int
    z_range: tuple[float, float]
    z_units: str
    f0_hz_range: tuple[float, float]
    q_range: tuple[float, float]
    max_abs_df0_dz: float | None
    max_abs_dq_dz: float | None
    max_abs_da_dz: float | None
    largest_df0_hz: float | None = optional()
    largest_df0_z: float | None = optional()
    smallest_q: float | None
    smallest_q_z: float | None
    largest_energy_per_cycle_ev: float | None = optional()
    largest_energy_per_cycle_z: float | None = optional()
    largest_force_gradient_n_per_m: float | None = optional()
    largest_force_gradient_z: float | None = optional()


@record
class ForceCurve(Record):
    """A force curve's legs (with ``z_piezo``).

    Attributes
    ----------
    approach : ForceCurveLeg, optional
        The approach (z towards the sample).
    retract : ForceCurveLeg, optional
        The retract.
    """

    approach: ForceCurveLeg | None = optional()
    retract: ForceCurveLeg | None = optional()


@record
class ImageMean(Record):
    """One scan image's mean.

    Attributes
    ----------
    mean : float or None
        The mean of its finite pixels, in the quantity's units; None without one.
    """

    mean: float | None


# --------------------------------------------------------------------------- the root


def _phase(results: ReepResults, held: bool) -> State | None:
    """The free-air phase misfit, when it exceeds 30°."""
    return phase_state(results.free_air_route)


def _free_air_check(results: ReepResults, held: bool) -> State | None:
    """A free-air f0′ far (in its std) from the lever's or the model's f0."""
    check = results.free_air_check
    if check is None or check.consistent:
        return None
    reference = "the lever" if check.reference is CheckReference.METADATA else "the model"
    return State(f"REEP's free-air f0' {check.f0_hz:.1f} Hz is {check.deviation_std:.0f} std from "
                 f"{reference}'s f0 {check.reference_f0_hz:.1f} Hz: the drive may be far off resonance or the model "
                 "wrong", "free_air_check.deviation_std", hides_scores=False)


def _mostly_flagged(results: ReepResults, held: bool) -> State | None:
    """More than half of the rows flagged, with the commonest reason (the run's first warning)."""
    text = results.validity.mostly_flagged
    if not text:
        return None
    return State(f"{text}: the numbers below are from the remaining rows", "validity.flags.fraction",
                 hides_scores=False)


def _q_identifiable(results: ReepResults, held: bool) -> State | None:
    """Without the dither the damping is the loop's: Q′ is not identifiable (no Q′ item is shown)."""
    if results.q_identifiable:
        return None
    return State("Q' is not identifiable without the dither (output-only: the damping is the loop's, not the "
                 "cantilever's); f0' is the frequency the motion oscillates at", "q_identifiable", hides_scores=False)


def _segment_items() -> tuple[Item, ...]:
    labels = {"free_air": "in the free-air segment", "after_free_air": "after the free-air segment",
              "settled": "after the warm-up"}
    items = []
    for segment, label in labels.items():
        items.append(Item(f"f0' {label}", f"segments.{segment}.f0_hz.mean", "Hz", f"segments.{segment}.f0_hz.std"))
        items.append(Item(f"Q' {label}", f"segments.{segment}.q.mean", "", f"segments.{segment}.q.std",
                          needs="q_identifiable"))
    return tuple(items)


def _force_curve_items() -> tuple[Item, ...]:
    """On a force curve: the approach's extremes and where they occur (z in the capture's z units)."""
    leg = "force_curve.approach"
    z_units = f"@{leg}.z_units"
    return (
        Item("largest Δf0' on approach", f"{leg}.largest_df0_hz", "Hz", at=f"{leg}.largest_df0_z", at_units=z_units),
        Item("smallest Q' on approach", f"{leg}.smallest_q", "", at=f"{leg}.smallest_q_z", at_units=z_units,
             needs="q_identifiable"),
        Item("largest energy dissipated per cycle", f"{leg}.largest_energy_per_cycle_ev", "eV",
             at=f"{leg}.largest_energy_per_cycle_z", at_units=z_units, needs="q_identifiable"),
        Item("largest force gradient", f"{leg}.largest_force_gradient_n_per_m", "N/m",
             at=f"{leg}.largest_force_gradient_z", at_units=z_units),
    )


@record
class ReepResults(Record):
    """What ``afmtool reep`` found: f0′ and Q′ by REEP (§3.3), their summaries and the run's settings.

    Attributes
    ----------
    free_air_model : FreeAirModelRecord or None
        The free-air model REEP ran beside (as its route refined it); None output-only without one.
    free_air_segment_s : tuple of 2 float or None
        The free-air segment it was identified from (s).
    free_air_route : FreeAirRouteRecord or None
        How the model was chosen, and the drive's hold; None output-only.
    forgetting_factor : float
        λ per capture sample.
    window_samples : float
        The forgetting window 1/(1 − λ) (capture samples).
    window_us : float
        The forgetting window (µs).
    estimator : ReepEstimatorRecord
        REEP's settings as they ran.
    settling : Settling
        The window and the simulated settling of f0′ and Q′.
    bias_compensation : bool
        The noise bias of the regression was compensated (BCEWRLS).
    use_input : bool
        The recorded dither was used (False: output-only).
    q_identifiable : bool
        Q′ is the cantilever's (with the dither); without it the damping is the loop's.
    n_samples : int
        Capture samples read.
    duration_s : float
        Their duration (s).
    sample_rate_hz : float
        The capture's rate (Hz).
    decimate : int
        Capture samples per output row.
    row_rate_hz : float
        The output rows' rate (Hz).
    rows : str
        What set the rows' density: ``resolution``, ``per-period`` or ``decimate N``.
    row_every_samples : int
        Capture samples per output row.
    drive_frequency_hz : float
        The lock-in's reference, the drive (Hz).
    lockin : LockInRecord
        The lock-in.
    excitation_lines_hz : tuple of float
        The dither's spectral lines near resonance (Hz).
    static_offset : bool
        A static offset was estimated beside b1, b0.
    flagged_samples : int
        Output rows flagged after the warm-up.
    validity : Validity
        The validity checks of the rows.
    summary_after_warmup_samples : int
        The warm-up the summaries leave out (capture samples).
    summary : ReepSummary
        Each series over the trusted rows after the warm-up.
    segments : ReepSegments
        f0′ and Q′ per time segment.
    free_air_check : FreeAirCheck, optional
        The free-air f0′ against the lever's f0 (with ten or more free-air rows).
    synthetic_drive_uncertainty : SyntheticDriveUncertainty, optional
        With a synthesised drive: its share of the rows' uncertainty.
    truth_tracking : TruthTracking, optional
        With ``/truth`` f0 and Q: the tracking error.
    interaction : Interaction, optional
        The interaction series (every run of the command; not the stage's own result).
    force_curve : ForceCurve, optional
        With ``z_piezo``: the force curve's legs.
    images : mapping of str to ImageMean, optional
        On a raster scan: each image (``<quantity>/trace``, ``<quantity>/retrace``) and its mean.
    """

    free_air_model: FreeAirModelRecord | None
    free_air_segment_s: tuple[float, float] | None
    free_air_route: FreeAirRouteRecord | None
    forgetting_factor: float
    window_samples: float
    window_us: float
    estimator: ReepEstimatorRecord
    settling: Settling
    bias_compensation: bool
    use_input: bool
    q_identifiable: bool
    n_samples: int
    duration_s: float
    sample_rate_hz: float
    decimate: int
    row_rate_hz: float
    rows: str
    row_every_samples: int
    drive_frequency_hz: float
    lockin: LockInRecord
    excitation_lines_hz: tuple[float, ...]
    static_offset: bool
    flagged_samples: int
    validity: Validity
    summary_after_warmup_samples: int
    summary: ReepSummary
    segments: ReepSegments
    free_air_check: FreeAirCheck | None = optional()
    synthetic_drive_uncertainty: SyntheticDriveUncertainty | None = optional()
    truth_tracking: TruthTracking | None = optional()
    interaction: Interaction | None = optional()
    force_curve: ForceCurve | None = optional()
    images: Mapping[str, ImageMean] | None = optional()

    HEADLINE = (
        *_segment_items(),
        *_force_curve_items(),
        Item("|f0' − f0| median vs truth", "truth_tracking.f0_hz.median_abs", "Hz"),
        Item("|f0' − f0| 95th percentile vs truth", "truth_tracking.f0_hz.p95_abs", "Hz"),
        Item("|Q' − Q| median vs truth", "truth_tracking.q.median_abs", "", needs="q_identifiable"),
        Item("|Q' − Q| 95th percentile vs truth", "truth_tracking.q.p95_abs", "", needs="q_identifiable"),
        Item("flagged output samples", "flagged_samples", "samples"),
    )
    #: The run's state first (issue 28): the phase misfit, the free-air f0′ check, most rows flagged, no Q′.
    STATES = (_phase, _free_air_check, _mostly_flagged, _q_identifiable)
