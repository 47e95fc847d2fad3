"""``kalman-bank``'s results: REEP's on-sample model checked by a bank of Kalman filters (§3.4.2).

The bank's design (:class:`BankDesignRecord`), each filter's model and where its
innovation RMS is least (:class:`BankFilterRecord`), the adaptive observer that follows
REEP (:class:`AdaptiveRecord`) and the verdict (:class:`BankVerdictRecord`).  The
headline puts a free-air phase misfit above 30° first.
"""

from __future__ import annotations

import enum

from afmtool.records.base import Item, Record, State, optional, record
from afmtool.records.common import FreeAirModelRecord, FreeAirRouteRecord, free_air_model_items, phase_state

__all__ = [
    "Leg", "DesignMethod", "ReepCoefficients", "PerLeg", "BankReepRecord", "BankDesignRecord", "BankFilterRecord",
    "AdaptiveRecord", "BankVerdictRecord", "KalmanBankResults",
]


class Leg(enum.Enum):
    """A leg of the force curve."""

    APPROACH = "approach"
    RETRACT = "retract"


class DesignMethod(enum.Enum):
    """How the bank's design points were chosen."""

    AUTO = "auto"  # spread over the approach from the onset of the interaction
    AT_Z = "at-z"  # REEP's model at the z given (--at-z)
    MODELS = "models"  # the models given (--models), placed where REEP's model is nearest


class ReepCoefficients(enum.Enum):
    """Where the adaptive observer's model (REEP's b1, b0) came from, sample by sample."""

    HELD = "held per sample from the decimated series"  # a finished REEP run (--reep)
    INTERNAL = "every REEP sample, held between them"  # REEP run beside the bank


@record
class PerLeg(Record):
    """A number per force-curve leg; a leg the capture lacks is absent.

    Attributes
    ----------
    approach : float, optional
        On the approach (null when not finite).
    retract : float, optional
        On the retract (null when not finite).
    """

    # a plain float (NaN written as null) where the leg exists, None (absent) where it does not
    approach: float | None = optional()
    retract: float | None = optional()


@record
class BankReepRecord(Record):
    """The REEP whose model the bank checks.

    Attributes
    ----------
    source : str
        ``internal``, or the reep.h5 of the run given (``--reep``).
    forgetting_factor : float
        λ at the capture's rate.
    reep_forgetting_factor : float
        λ at REEP's own (reduced) rate.
    rate_reduction : int
        Capture samples per REEP sample.
    window_samples : float
        REEP's window 1/(1 − λ) (capture samples).
    coefficients : ReepCoefficients
        How its (b1, b0) reach the adaptive observer.
    """

    source: str
    forgetting_factor: float
    reep_forgetting_factor: float
    rate_reduction: int
    window_samples: float
    coefficients: ReepCoefficients


@record
class BankDesignRecord(Record):
    """How the bank was built.

    Attributes
    ----------
    method : DesignMethod
        How the design points were chosen.
    leg : Leg
        The leg the design points and the verdict refer to.
    n_filters : int
        Filters in the bank.
    gain : str
        The filters' gain.
    noise_ratio : float
        σ_w/σ_v, which sets the Kalman gains.
    f0_scale : float
        Multiplies every filter's f0 (1 unless a negative control).
    """

    method: DesignMethod
    leg: Leg
    n_filters: int
    gain: str
    noise_ratio: float
    f0_scale: float


@record
class BankFilterRecord(Record):
    """One filter of the bank: its model, its design point, and where its innovation RMS is least.

    Attributes
    ----------
    index : int
        Its number, from 1.
    f0_hz : float
        Its model's f0, after ``f0_scale`` (Hz).
    q : float
        Its model's Q.
    reep_f0_hz : float or None
        REEP's f0' at its design point (Hz); None for a model given (``--models``).
    source : DesignMethod
        How its design point was chosen.
    design_z : float
        Its design point (z_piezo units).
    design_bin : tuple of 2 float
        The z bin of its design point, lowest first (z_piezo units).
    model_distance_to_reep : float
        Distance between its model and REEP's at ``design_z`` (free-air half-widths).
    denominator : tuple of 2 float
        Its (b1, b0) of eq. 3.40.
    gain : tuple of 2 float
        Its predictor gain (L1, L2).
    error_pole_radius : float
        Mean radius of its error poles.
    min_z : PerLeg
        z of its least mean RMS on each leg (z_piezo units).
    min_bin_offset : int
        Bins from its design bin to its least RMS on the design leg.
    design_rms : float
        Its mean RMS in the design bin (deflection units).
    min_rms : float
        Its least mean RMS (deflection units).
    design_rms_excess : float
        design_rms / min_rms − 1.
    design_rms_over_adaptive : float
        design_rms over the adaptive observer's RMS there.
    pass_ : bool
        Its least RMS lies within the tolerance of its design bin.
    """

    index: int
    f0_hz: float
    q: float
    reep_f0_hz: float | None
    source: DesignMethod
    design_z: float
    design_bin: tuple[float, float]
    model_distance_to_reep: float
    denominator: tuple[float, float]
    gain: tuple[float, float]
    error_pole_radius: float
    min_z: PerLeg
    min_bin_offset: int
    design_rms: float
    min_rms: float
    design_rms_excess: float
    design_rms_over_adaptive: float
    pass_: bool


@record
class AdaptiveRecord(Record):
    """The adaptive observer, whose model follows REEP's sample by sample.

    Attributes
    ----------
    pole_radius : float
        Its error-pole radius (the bank's mean).
    error_time_constant_periods : float
        Its error time constant −1/ln r (drive periods).
    held_samples : int
        Samples with no valid REEP model, on which it kept its previous one.
    fraction_lowest : float
        Share of the kept samples after the warm-up where its RMS was the least.
    fraction_lowest_by_leg : PerLeg
        The same per leg, from the binned tables.
    fraction_lowest_within_bank_span : float
        The same between the outermost design points.
    samples_compared : int
        Kept samples after the warm-up.
    pass_ : bool
        ``fraction_lowest`` reaches the share required.
    """

    pole_radius: float
    error_time_constant_periods: float
    held_samples: int
    fraction_lowest: float
    fraction_lowest_by_leg: PerLeg
    fraction_lowest_within_bank_span: float
    samples_compared: int
    pass_: bool


@record
class BankVerdictRecord(Record):
    """The verdict: every filter and the adaptive observer pass.

    Attributes
    ----------
    pass_ : bool
        The verdict.
    tolerance : str
        What passing takes, in words.
    z_bin : float
        Bin width (z_piezo units).
    z_tolerance_bins : int
        Bins a filter's least RMS may lie from its design bin.
    rms_tolerance : float
        Or the share by which its design-bin RMS may exceed its least.
    adaptive_fraction_required : float
        The share of the time the adaptive observer must have the least RMS.
    reasons : tuple of str
        Each failure.
    """

    pass_: bool
    tolerance: str
    z_bin: float
    z_tolerance_bins: int
    rms_tolerance: float
    adaptive_fraction_required: float
    reasons: tuple[str, ...]


def _phase_state(results: KalmanBankResults, held: bool) -> State | None:
    """The free-air phase misfit, when it exceeds 30°."""
    return phase_state(results.free_air_route)


@record
class KalmanBankResults(Record):
    """REEP's on-sample model checked by a bank of steady-state Kalman filters and an adaptive observer.

    Attributes
    ----------
    free_air_model : FreeAirModelRecord
        The free-air model (every filter's numerator).
    free_air_segment_s : tuple of 2 float or None
        The free-air segment it came from (s).
    reep : BankReepRecord
        The REEP checked.
    n_samples : int
        Samples read.
    duration_s : float
        Their duration (s).
    sample_rate_hz : float
        The capture's sample rate (Hz).
    drive_frequency_hz : float
        The drive (Hz).
    decimate : int
        One output row in ``decimate`` capture samples.
    rows : str
        What set the rows' spacing (``resolution``, ``per-period``, ``decimate N``).
    row_every_samples : int
        Capture samples per row.
    row_rate_hz : float
        Rows per second of capture (Hz).
    rms_window_samples : int
        The innovation-RMS window W (samples).
    rms_window_periods : float
        W in drive periods.
    rms_binned_delay_samples : int
        How far back an RMS value is binned against z (samples).
    warmup_samples : int
        Samples left out of the statistics at the start.
    ramp_z_per_sample : float
        Mean |dz| per sample while z moves (z_piezo units).
    reep_window_z : float
        REEP's window measured in z along the ramp (z_piezo units).
    z_units : str
        The z_piezo units.
    envelope_beat : float
        How far the dither's side lines beat the free-air envelope, m = Σ_side A_i|G(f_i)| / (A_d|G(f_d)|)
        (dimensionless); above 0.03 the report warns that the verdict may fail on a right answer.
    design : BankDesignRecord
        How the bank was built.
    filters : tuple of BankFilterRecord
        The bank, in filter order.
    adaptive : AdaptiveRecord
        The adaptive observer.
    verdict : BankVerdictRecord
        The verdict.
    free_air_route : FreeAirRouteRecord or None
        How the free-air model was chosen; None when it came with ``--reep`` or ``--model``.
    """

    free_air_model: FreeAirModelRecord
    free_air_segment_s: tuple[float, float] | None
    reep: BankReepRecord
    n_samples: int
    duration_s: float
    sample_rate_hz: float
    drive_frequency_hz: float
    decimate: int
    rows: str
    row_every_samples: int
    row_rate_hz: float
    rms_window_samples: int
    rms_window_periods: float
    rms_binned_delay_samples: int
    warmup_samples: int
    ramp_z_per_sample: float
    reep_window_z: float
    z_units: str
    envelope_beat: float
    design: BankDesignRecord
    filters: tuple[BankFilterRecord, ...]
    adaptive: AdaptiveRecord
    verdict: BankVerdictRecord
    free_air_route: FreeAirRouteRecord | None

    HEADLINE = (
        Item("verdict: pass", "verdict.pass", "", text=True),
        Item("adaptive observer has the least RMS", "adaptive.fraction_lowest", "of time"),
        Item("filters in the bank", "design.n_filters", "filters"),
        *free_air_model_items(),
    )
    STATES = (_phase_state,)
