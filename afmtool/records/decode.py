"""``decode``'s results: the bits of an electrostatically actuated probe by the EKF innovation (ch. 7).

Both modes share the model, the tuning (ℓ0 and the noise levels) and the
EKF's figures; ``--mode bits`` adds the clock, the bits, the lock-in
baseline and, with ``/truth`` bits, the bit error rates; ``--mode step``
the response to a V_φ step (§7.7) instead.
"""

from __future__ import annotations

import enum

from afmtool.records.base import Item, Record, optional, record

__all__ = [
    "DecodeMode", "Rows", "ActuationSource", "L0Source", "MeasurementNoiseSource", "ProcessNoiseSource",
    "ModelSources", "DecodeModel", "L0Record", "NoiseRecord", "EkfRecord", "ClockRecord", "BitsRecord",
    "BaselineRecord", "Confusion", "BitScores", "BaselineBitScores", "TruthRecord", "Settling", "StepDetection",
    "StepRecord", "DecodeResults", "L0_SEARCH",
]


class DecodeMode(enum.Enum):
    """What the run decoded: a bit stream, or the response to a V_φ step."""

    BITS = "bits"
    STEP = "step"


class Rows(enum.Enum):
    """The density of ``decode.h5``'s rows (``--rows``)."""

    RESOLUTION = "resolution"  # the running mean once per actuation period
    PER_PERIOD = "per-period"  # and the innovation at every sample


class ActuationSource(enum.Enum):
    """Where the actuation frequency came from."""

    PARAMETER = "parameter"
    METADATA = "metadata"
    STRONGEST_LINE = "strongest line of V^2"


#: ``l0.source`` of a searched ℓ0.
L0_SEARCH = "innovation RMS minimum on the nominal segment (§7.4)"


class L0Source(enum.Enum):
    """How ℓ0 was set: given, or searched on the nominal segment."""

    PARAMETER = "parameter"
    SEARCH = L0_SEARCH


class MeasurementNoiseSource(enum.Enum):
    """Where the EKF's measurement noise came from."""

    PARAMETER = "parameter"
    PSD_FLOOR = "PSD floor of the nominal segment"


class ProcessNoiseSource(enum.Enum):
    """Where the EKF's process (force) noise came from."""

    PARAMETER = "parameter"
    MEAN_NIS = "mean NIS = 1 on the nominal segment"


@record
class ModelSources(Record):
    """Where each of the model's values came from: ``parameter``, ``--electrostatic FILE``, ``metadata``, or why none.

    Attributes
    ----------
    f0_hz : str
        Source of f0.
    q : str
        Source of Q.
    spring_constant_n_per_m : str
        Source of k.
    k_esf_f_m : str
        Source of K_esf.
    alpha_r : str
        Source of α_R (``unused (voltage channel)`` with a voltage channel).
    tip_height_nm : str
        Source of t_h (``none: ...`` when nothing gives it).
    l0_guess_nm : str
        Source of the ℓ0 guess (``none: ...`` when the default bracket is searched).
    """

    f0_hz: str
    q: str
    spring_constant_n_per_m: str
    k_esf_f_m: str
    alpha_r: str
    tip_height_nm: str
    l0_guess_nm: str


@record
class DecodeModel(Record):
    """The plant the EKF models (eq. 7.11), before ℓ0 is estimated.

    Attributes
    ----------
    f0_hz : float
        Resonant frequency (Hz).
    q : float
        Quality factor.
    spring_constant_n_per_m : float
        Spring constant k (N/m).
    k_esf_f_m : float
        Electrostatic force constant K_esf (F·m), F = −K_esf·V²/ℓ².
    alpha_r : float
        α_R of V = α_R·V_R − V_sub (eq. 6.3).
    tip_height_nm : float
        Tip height t_h (nm); 0 when nothing gives it.
    l0_guess_nm : float or None
        The ℓ0 guess that centres the search (nm); None when the default bracket is searched.
    sources : ModelSources
        Where each value came from.
    convention : str
        The force law's convention and the EKF's state.
    voltage : str
        The voltage the EKF is given: a channel's name, or ``alpha_r*v_r - v_sub``.
    """

    f0_hz: float
    q: float
    spring_constant_n_per_m: float
    k_esf_f_m: float
    alpha_r: float
    tip_height_nm: float
    l0_guess_nm: float | None
    sources: ModelSources
    convention: str
    voltage: str


@record
class L0Record(Record):
    """The lever-sample separation ℓ0: given, or the innovation RMS minimum on the nominal segment (§7.4).

    Attributes
    ----------
    estimate_nm : float
        ℓ0 (nm).
    source : L0Source
        Given or searched.
    rms_at_minimum_nm : float or None
        Searched: the innovation RMS at the minimum (nm).
    bracket_nm : tuple of 2 float or None
        Searched: the bracket (nm), low first.
    grid_points : int or None
        Searched: points of the coarse grid.
    evaluations : int or None
        Searched: ℓ0 values evaluated (grid and golden section).
    unique_minimum : bool or None
        Searched: one interior minimum with a clear dip.
    process_noise_used_n_per_rthz : float or None
        Searched: the force-noise ASD the search ran with (N/√Hz).
    """

    estimate_nm: float
    source: L0Source
    rms_at_minimum_nm: float | None = optional()
    bracket_nm: tuple[float, float] | None = optional()
    grid_points: int | None = optional()
    evaluations: int | None = optional()
    unique_minimum: bool | None = optional()
    process_noise_used_n_per_rthz: float | None = optional()


@record
class NoiseRecord(Record):
    """The EKF's noise levels, each given or estimated on the nominal segment.

    Attributes
    ----------
    thermal_force_asd_n_per_rthz : float
        The thermal force-noise ASD at ``temperature_k`` (N/√Hz); 0 without a temperature.
    temperature_k : float
        Temperature (K).
    measurement_source : MeasurementNoiseSource
        Where the measurement noise came from.
    measurement_noise_nm : float
        Rms measurement noise per sample (nm).
    process_noise_n_per_rthz : float
        Force-noise ASD of the EKF (N/√Hz).
    process_source : ProcessNoiseSource
        Where the process noise came from.
    nominal_innovation_rms_nm : float or None
        With a nominal segment: the tuned EKF's innovation RMS on it (nm).
    nominal_mean_nis : float or None
        With a nominal segment: its mean normalised innovation squared.
    """

    thermal_force_asd_n_per_rthz: float
    temperature_k: float
    measurement_source: MeasurementNoiseSource
    measurement_noise_nm: float
    process_noise_n_per_rthz: float
    process_source: ProcessNoiseSource
    nominal_innovation_rms_nm: float | None = optional()
    nominal_mean_nis: float | None = optional()


@record
class EkfRecord(Record):
    """The EKF's rate, actuation and running mean.

    Attributes
    ----------
    sample_rate_hz : float
        The capture's sample rate (Hz).
    actuation_hz : float
        The actuation frequency (Hz).
    actuation_source : ActuationSource
        Where it came from.
    mean_window_samples : int
        The innovation's running-mean window (samples; one actuation period).
    bit_stream_innovation_rms_nm : float or None
        The innovation RMS over the bit stream (nm); None with no sample there.
    """

    sample_rate_hz: float
    actuation_hz: float
    actuation_source: ActuationSource
    mean_window_samples: int
    bit_stream_innovation_rms_nm: float | None


@record
class ClockRecord(Record):
    """The bit clock: acquired on the first ``clock_window_s`` of the bit stream, then tracked.

    Attributes
    ----------
    rate_hz : float
        The bit rate (bit/s).
    recovered : bool
        The rate came from the transitions (not given).
    period_samples : float
        The acquired bit period (samples).
    final_period_samples : float
        The tracked period at the end (samples).
    acquisition_transitions : int
        Transitions the acquisition used.
    line_strength : float
        How well the transitions sit on the clock's grid, 0 to 1.
    rms_jitter_samples : float
        Rms jitter of the transitions about the fitted grid (samples).
    bits_from_s : float
        Where the bit stream starts (s).
    """

    rate_hz: float
    recovered: bool
    period_samples: float
    final_period_samples: float
    acquisition_transitions: int
    line_strength: float
    rms_jitter_samples: float
    bits_from_s: float


@record
class BitsRecord(Record):
    """The decided bits and the two classes of the decoder's cell values.

    Attributes
    ----------
    count : int
        Bits decoded.
    ones : int
        Of them ones.
    incomplete_cells : int
        Cells with no sample to integrate (their bits are 0).
    detector : str
        How a cell's value is formed.
    threshold_nm : float
        The two-class threshold (nm).
    centres_nm : tuple of 2 float
        The low and high class centres (nm).
    std_nm : tuple of 2 float
        The low and high class standard deviations (nm).
    separation : float
        Half the distance of the centres over the pooled standard deviation.
    estimated_ber_gaussian : float
        The BER two Gaussian classes would give.
    """

    count: int
    ones: int
    incomplete_cells: int
    detector: str
    threshold_nm: float
    centres_nm: tuple[float, float]
    std_nm: tuple[float, float]
    separation: float
    estimated_ber_gaussian: float


@record
class BaselineRecord(Record):
    """The lock-in amplitude baseline, integrated over the decoder's cells.

    Attributes
    ----------
    method : str
        What the baseline is.
    lockin_lowpass_hz : float
        The lock-in's low-pass corner (Hz).
    lockin_order : int
        Its order.
    amplitude_kept_every : int
        The amplitude is kept one sample in this many, held in between.
    alignment_delay_samples : int
        Samples the innovation mean is delayed by against the amplitude (negative: the amplitude is).
    threshold_nm : float
        The two-class threshold of the amplitudes (nm).
    separation : float
        Their two classes' separation.
    estimated_ber_gaussian : float
        The BER two Gaussian classes would give.
    """

    method: str
    lockin_lowpass_hz: float
    lockin_order: int
    amplitude_kept_every: int
    alignment_delay_samples: int
    threshold_nm: float
    separation: float
    estimated_ber_gaussian: float


@record
class Confusion(Record):
    """Decided bits against the truth's (absent when no bit was compared).

    Attributes
    ----------
    truth0_decoded0 : int or None
        Truth 0, decided 0.
    truth0_decoded1 : int or None
        Truth 0, decided 1.
    truth1_decoded0 : int or None
        Truth 1, decided 0.
    truth1_decoded1 : int or None
        Truth 1, decided 1.
    """

    truth0_decoded0: int | None = optional()
    truth0_decoded1: int | None = optional()
    truth1_decoded0: int | None = optional()
    truth1_decoded1: int | None = optional()


@record
class BitScores(Record):
    """One decoder's bits against ``/truth``, at the latency with the fewest errors.

    Attributes
    ----------
    ber : float
        Bit error rate (null when no bit was compared).
    ber_upper_95 : float or None
        Its one-sided 95 % upper bound; None when no bit was compared.
    errors : int
        Bit errors.
    compared : int
        Bits compared.
    latency_s : float
        The latency chosen (s).
    confusion : Confusion
        The counts by truth and decision.
    """

    ber: float
    ber_upper_95: float | None
    errors: int
    compared: int
    latency_s: float
    confusion: Confusion


@record
class BaselineBitScores(BitScores):
    """The baseline's bits against ``/truth``; its polarity is free (the fields of :class:`BitScores`, and:).

    Attributes
    ----------
    inverted : bool
        The baseline's bits were compared inverted.
    """

    inverted: bool


@record
class TruthRecord(Record):
    """The decoder and the baseline against ``/truth`` bits, and ℓ0 against the truth's.

    Attributes
    ----------
    l0_nm : float or None
        The truth's ℓ0 (nm), when it has one.
    l0_error_percent : float or None
        ℓ0's error against it (%).
    decoder : BitScores
        The EKF decoder.
    baseline : BaselineBitScores
        The lock-in baseline.
    alignment : str
        How each decoder's latency was chosen.
    baseline_to_decoder_ber_ratio : float or None
        The baseline's BER over the decoder's (with no decoder error, over its 95 % bound); when both compared bits.
    ratio_is_lower_bound : bool or None
        The ratio is a lower bound (the decoder made no error).
    """

    l0_nm: float | None = optional()
    l0_error_percent: float | None = optional()
    decoder: BitScores
    baseline: BaselineBitScores
    alignment: str
    baseline_to_decoder_ber_ratio: float | None = optional()
    ratio_is_lower_bound: bool | None = optional()


@record
class Settling(Record):
    """How a signal settles after the V_φ step.

    Attributes
    ----------
    settling_s : float
        Settling time (s).
    settling_periods : float
        The same in actuation periods.
    transient_peak_nm : float
        The peak of the transient's one-period rms envelope (nm).
    """

    settling_s: float
    settling_periods: float
    transient_peak_nm: float


@record
class StepDetection(Record):
    """When the innovation's running mean leaves its pre-step scatter.

    Attributes
    ----------
    pre_step_mean_nm : float
        Its mean before the step (nm).
    pre_step_std_nm : float
        Its standard deviation before the step (nm).
    peak_deviation_nm : float
        Its largest deviation after the step (nm).
    threshold_nm : float
        The deviation that counts as detected (nm).
    delay_s : float or None
        The detection delay after the step (s); None when never detected.
    delay_periods : float or None
        The same in actuation periods.
    """

    pre_step_mean_nm: float
    pre_step_std_nm: float
    peak_deviation_nm: float
    threshold_nm: float
    delay_s: float | None
    delay_periods: float | None


@record
class StepRecord(Record):
    """The response to the V_φ step (§7.7): settling times and the detection delay.

    Attributes
    ----------
    time_s : float
        The step's time (s).
    lever_time_constant_s : float
        The lever's 2Q/ω0 (s).
    lever_time_constant_periods : float
        The same in actuation periods.
    deflection : Settling
        The deflection's settling.
    amplitude : Settling
        The lock-in amplitude's settling.
    innovation : Settling
        The EKF innovation's settling.
    innovation_mean : StepDetection
        The innovation running mean's detection delay.
    window_s : tuple of 2 float
        The signals kept around the step (s), start first.
    settling : str
        How a settling time is defined.
    """

    time_s: float
    lever_time_constant_s: float
    lever_time_constant_periods: float
    deflection: Settling
    amplitude: Settling
    innovation: Settling
    innovation_mean: StepDetection
    window_s: tuple[float, float]
    settling: str


@record
class DecodeResults(Record):
    """The bits (or the V_φ step response) of an electrostatically actuated probe by the EKF innovation.

    Attributes
    ----------
    model : DecodeModel
        The plant the EKF models.
    nominal_segment_s : tuple of 2 float or None
        The nominal (bit-free) segment (s); None without one.
    l0 : L0Record
        ℓ0, given or searched.
    noise : NoiseRecord
        The EKF's noise levels.
    ekf : EkfRecord
        Its rate, actuation and running mean.
    rows : Rows
        The density of ``decode.h5``'s rows.
    row_every_samples : int
        Samples per row of ``innovation_mean``.
    row_rate_hz : float
        Rows per second (Hz).
    innovation_every_sample : bool
        ``decode.h5`` holds the innovation at every sample.
    n_samples : int
        Samples decoded.
    duration_s : float
        Their duration (s).
    mode : DecodeMode
        Bits or step.
    step : StepRecord or None
        Step mode: the response to the V_φ step.
    clock : ClockRecord or None
        Bits mode: the bit clock.
    bits : BitsRecord or None
        Bits mode: the decided bits.
    baseline : BaselineRecord or None
        Bits mode: the lock-in amplitude baseline.
    truth : TruthRecord or None
        Bits mode with ``/truth`` bits: the bit error rates.
    """

    model: DecodeModel
    nominal_segment_s: tuple[float, float] | None
    l0: L0Record
    noise: NoiseRecord
    ekf: EkfRecord
    rows: Rows
    row_every_samples: int
    row_rate_hz: float
    innovation_every_sample: bool
    n_samples: int
    duration_s: float
    mode: DecodeMode
    step: StepRecord | None = optional()
    clock: ClockRecord | None = optional()
    bits: BitsRecord | None = optional()
    baseline: BaselineRecord | None = optional()
    truth: TruthRecord | None = optional()

    HEADLINE = (
        Item("BER (EKF decoder)", "truth.decoder.ber", ""),
        Item("BER 95 % upper bound (EKF decoder)", "truth.decoder.ber_upper_95", ""),
        Item("BER (lock-in baseline)", "truth.baseline.ber", ""),
        Item("BER estimated from the bit clusters", "bits.estimated_ber_gaussian", ""),
        Item("bits decoded", "bits.count", "bits"),
        Item("bit rate", "clock.rate_hz", "bit/s"),
        Item("ℓ0", "l0.estimate_nm", "nm"),
        # --mode step: the response to a V_phi step (§7.7)
        Item("innovation settling after the V_phi step", "step.innovation.settling_periods", "actuation periods"),
        Item("amplitude settling after the V_phi step", "step.amplitude.settling_periods", "actuation periods"),
        Item("deflection settling after the V_phi step", "step.deflection.settling_periods", "actuation periods"),
        Item("running mean of the innovation: detection delay", "step.innovation_mean.delay_periods",
             "actuation periods"),
    )
