"""``identify gamma``'s results: the sensing map Γ_IR,ts (thesis eq. 6.15), its feed-through and the uncorrected view.

The frequency responses themselves are in ``gamma.h5``; the results hold what a
reader quotes from them: the usable band, the DC sensitivity, the −3 dB bandwidth,
the roll-off, the same for the uncorrected ratio (eq. 6.16), how much the
feed-through inflates that ratio at the top of the band, and the fitted feed-through.
"""

from __future__ import annotations

import enum

from afmtool.records.base import Item, Record, record

__all__ = [
    "ResponseMethod", "GammaSamples", "GammaOperatingPoint", "GammaUnits", "SensingSummaryRecord",
    "FeedthroughRiseRecord", "FeedthroughFitRecord", "GammaResults",
]


class ResponseMethod(enum.Enum):
    """How a frequency response was estimated from a sweep."""

    H1 = "h1"  # a chirp or broadband drive: H1 = cross / auto spectrum over segments
    STEPPED = "stepped"  # stepped sines: a lock-in per segment


@record
class GammaSamples(Record):
    """Samples read from each sweep.

    Attributes
    ----------
    sweep : int
        Samples of the sweep near the sample.
    contact : int
        Samples of the sweep with the tip in contact.
    """

    sweep: int
    contact: int


@record
class GammaOperatingPoint(Record):
    """The sweeps' means: the operating point the responses hold at.

    Attributes
    ----------
    v_sub_mean_v : float
        Mean V_sub of the sweep near the sample (V).
    thermal_current_mean_ua : float
        Mean thermal current of that sweep (µA).
    deflection_mean_nm : float
        Mean deflection of that sweep (nm).
    contact_thermal_current_mean_ua : float
        Mean thermal current of the contact sweep (µA).
    """

    v_sub_mean_v: float
    thermal_current_mean_ua: float
    deflection_mean_nm: float
    contact_thermal_current_mean_ua: float


@record
class GammaUnits(Record):
    """The units of each response in ``gamma.h5`` and the FRF tables.

    Attributes
    ----------
    ir_v : str
        Γ_IR,V near the sample (``uA/V``).
    ts_v : str
        Γ_ts,V, the optical deflection (``nm/V``).
    feedthrough : str
        Γ_sp, the tip in contact (``uA/V``).
    ir_ts : str
        Γ_IR,ts of eq. 6.15 (``uA/nm``).
    ir_ts_uncorrected : str
        Γ_IR,V/Γ_ts,V of eq. 6.16 (``uA/nm``).
    """

    ir_v: str
    ts_v: str
    feedthrough: str
    ir_ts: str
    ir_ts_uncorrected: str


@record
class SensingSummaryRecord(Record):
    """The numbers that matter of a low-pass sensing map (§6.6.1).

    Attributes
    ----------
    dc_sensitivity_ua_per_nm : float
        Γ(0), signed (µA/nm): the real part of the DC extrapolation.
    bandwidth_hz : float
        Lowest frequency where |Γ| = |Γ(0)|/√2 (Hz); null where |Γ| never falls 3 dB.
    roll_off_db_per_decade : float
        Slope of 20·log10|Γ| against log10 f over the roll-off band (dB/decade); null without a bandwidth.
    roll_off_band_hz : tuple of 2 float
        The band of that fit (Hz).
    dc_band_hz : tuple of 2 float
        The band Γ(0) was extrapolated from (Hz).
    """

    dc_sensitivity_ua_per_nm: float
    bandwidth_hz: float
    roll_off_db_per_decade: float
    roll_off_band_hz: tuple[float, float]
    dc_band_hz: tuple[float, float]


@record
class FeedthroughRiseRecord(Record):
    """How much the feed-through inflates the uncorrected Γ (eq. 6.16) over the top third of a decade.

    Attributes
    ----------
    excess_db : float
        20·log10(|Γ_unc|/|Γ_IR,ts|) averaged over that band (dB; > 0: the false rise of Fig. 6.20).
    uncorrected_slope_db_per_decade : float
        Slope of the uncorrected magnitude over that band (dB/decade).
    corrected_slope_db_per_decade : float
        Slope of the corrected magnitude over that band (dB/decade).
    band_hz : tuple of 2 float
        The band (Hz).
    """

    excess_db: float
    uncorrected_slope_db_per_decade: float
    corrected_slope_db_per_decade: float
    band_hz: tuple[float, float]


@record
class FeedthroughFitRecord(Record):
    """Γ_sp ≈ (b1·s + b0)/(s + a0) fitted where the contact sweep is coherent (Fig. 6.18).

    Attributes
    ----------
    capacitance_pf : float
        The capacitive slope b1/a0 below the pole as a coupling capacitance C_c (pF).
    pole_hz : float
        a0/2π (Hz).
    numerator_ua_per_v : tuple of 2 float
        (b1, b0), µA/V with s in rad/s.
    denominator : tuple of 2 float
        (1, a0), s in rad/s.
    rms_residual_ua_per_v : float
        RMS residual of the fit (µA/V).
    band_hz : tuple of 2 float
        The coherent band fitted (Hz).
    form : str
        The fitted form, in words.
    """

    capacitance_pf: float
    pole_hz: float
    numerator_ua_per_v: tuple[float, float]
    denominator: tuple[float, float]
    rms_residual_ua_per_v: float
    band_hz: tuple[float, float]
    form: str


@record
class GammaResults(Record):
    """Γ_IR,ts with the feed-through removed (eq. 6.15), summarised over its usable band.

    Attributes
    ----------
    method : ResponseMethod
        How the responses were estimated.
    nperseg : int or None
        H1 segment length (samples); None for stepped sines.
    frequency_resolution_hz : float or None
        The H1 bin spacing (Hz); None for stepped sines.
    n_frequencies : int
        Frequencies of the responses.
    samples : GammaSamples
        Samples read from each sweep.
    operating_point : GammaOperatingPoint
        The sweeps' means.
    units : GammaUnits
        The units of each response.
    min_coherence : float
        The coherence the usable band needs of Γ_IR,V and Γ_ts,V.
    usable_band_hz : tuple of 2 float
        The usable band (Hz).
    usable_bins : int
        Usable frequencies.
    dc_sensitivity_ua_per_nm : float
        DC sensitivity Γ_IR,ts(0), signed (µA/nm).
    bandwidth_hz : float
        −3 dB bandwidth of Γ_IR,ts (Hz); null where it never falls 3 dB.
    roll_off_db_per_decade : float
        Roll-off of |Γ_IR,ts| above the bandwidth (dB/decade).
    roll_off_band_hz : tuple of 2 float
        The band of the roll-off fit (Hz).
    dc_band_hz : tuple of 2 float
        The band Γ_IR,ts(0) was extrapolated from (Hz).
    uncorrected : SensingSummaryRecord or None
        The same for the uncorrected ratio (eq. 6.16); None where it has no summary.
    feedthrough_rise : FeedthroughRiseRecord
        How much the feed-through inflates the uncorrected ratio at the top of the band.
    feedthrough_fit : FeedthroughFitRecord or None
        The fitted feed-through; None where the contact sweep is too little coherent to fit.
    """

    method: ResponseMethod
    nperseg: int | None
    frequency_resolution_hz: float | None
    n_frequencies: int
    samples: GammaSamples
    operating_point: GammaOperatingPoint
    units: GammaUnits
    min_coherence: float
    usable_band_hz: tuple[float, float]
    usable_bins: int
    dc_sensitivity_ua_per_nm: float
    bandwidth_hz: float
    roll_off_db_per_decade: float
    roll_off_band_hz: tuple[float, float]
    dc_band_hz: tuple[float, float]
    uncorrected: SensingSummaryRecord | None
    feedthrough_rise: FeedthroughRiseRecord
    feedthrough_fit: FeedthroughFitRecord | None

    HEADLINE = (
        Item("DC sensitivity Γ_IR,ts", "dc_sensitivity_ua_per_nm", "µA/nm"),
        Item("−3 dB bandwidth", "bandwidth_hz", "Hz"),
        Item("roll-off", "roll_off_db_per_decade", "dB/decade"),
        Item("feed-through capacitance", "feedthrough_fit.capacitance_pf", "pF"),
    )
