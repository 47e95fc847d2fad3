"""``identify freeair``'s results: the free-air model by one route, and on the thermal route the spring constant.

The model (``free_air.json``) is there on every route; the rest depends on
the route: the segment's interval (``segment``), the sweep's method and hold
with, for the whole-record fit, its band and noise (``sweep``), or the
thermal spectrum, its maximum-likelihood fit and the spring constant by
equipartition and, given the lever's length and width, by Sader
(``thermal``).
"""

from __future__ import annotations

import enum

from afmtool.records.base import Item, Record, optional, record
from afmtool.records.common import DriveHold, FreeAirModelRecord, free_air_model_items

__all__ = [
    "FreeAirRoute", "SweepMethod", "AveragesFrom", "Detection", "Fluid", "Weighting", "ThermalSpectrumRecord",
    "ValueSpread", "ThermalVariantRecord", "ThermalFitRecord", "ThermalSpringConstant", "SaderSpringConstant",
    "SpringConstantParameters", "SpringConstants", "FreeAirResults",
]


class FreeAirRoute(enum.Enum):
    """How the free-air model was identified."""

    SEGMENT = "segment"  # the ARX fit on the capture's free-air segment
    SWEEP = "sweep"  # a frequency sweep of the drive
    THERMAL = "thermal"  # a thermal-noise spectrum (--psd) or time record (--thermal)


class SweepMethod(enum.Enum):
    """The sweep route's method."""

    RECORD = "record"  # the whole-record fit, any sweep rate
    H1 = "h1"  # Welch cross spectra
    STEPPED = "stepped"  # lock-in sums per stepped sine


class AveragesFrom(enum.Enum):
    """Where the number of averaged periodograms of a ``--psd`` table came from."""

    GIVEN = "--averages"
    FILE = "the file"
    ESTIMATED = "estimated from the scatter"


class Detection(enum.Enum):
    """How the spectrum's deflection was measured (``--detection``)."""

    OPTICAL_LEVER = "optical-lever"
    DISPLACEMENT = "displacement"


class Fluid(enum.Enum):
    """The fluid around the cantilever (Sader)."""

    AIR = "air"
    WATER = "water"


class Weighting(enum.Enum):
    """How a refit of the thermal spectrum weighted its bins."""

    MAXIMUM_LIKELIHOOD = "maximum likelihood"
    LINEAR = "linear least squares"


@record
class ThermalSpectrumRecord(Record):
    """The thermal spectrum fitted: a ``--psd`` table read, or the Welch spectrum of a ``--thermal`` record.

    Attributes
    ----------
    columns : tuple of str or None
        ``--psd``: the table's columns used (frequency, spectrum).
    spectrum : str or None
        ``--psd``: what the table held (ASD or PSD, and its units).
    n_averages_from : AveragesFrom or None
        ``--psd``: where the number of averaged periodograms came from.
    invols_nm_per_v : float or None
        ``--psd`` of a spectrum in V: the InvOLS it was scaled by (nm/V).
    method : str or None
        ``--thermal``: how the spectrum was computed.
    nperseg : int or None
        ``--thermal``: samples per Welch segment.
    segments : int or None
        ``--thermal``: segments averaged.
    resolution_hz : float or None
        ``--thermal``: the spectrum's resolution (Hz).
    n_averages_effective : float or None
        ``--thermal``: the effective number of averages of the overlapped segments.
    """

    columns: tuple[str, ...] | None = optional()
    spectrum: str | None = optional()
    n_averages_from: AveragesFrom | None = optional()
    invols_nm_per_v: float | None = optional()
    method: str | None = optional()
    nperseg: int | None = optional()
    segments: int | None = optional()
    resolution_hz: float | None = optional()
    n_averages_effective: float | None = optional()


@record
class ValueSpread(Record):
    """A fitted value with its statistical and systematic uncertainty, in the quantity's units (f0 in Hz).

    Attributes
    ----------
    value : float
        The maximum-likelihood value.
    std : float
        Its statistical standard deviation.
    systematic : float
        Its systematic uncertainty: the spread over bands and weightings where it exceeds the statistical one, else 0.
    spread : float
        The spread over the refits in other bands and weightings.
    """

    value: float
    std: float
    systematic: float
    spread: float


@record
class ThermalVariantRecord(Record):
    """One refit of the thermal spectrum, for the systematic spread.

    Attributes
    ----------
    band_hz : tuple of 2 float
        Its band (Hz), low first.
    weighting : Weighting
        How it weighted the bins.
    f0_hz : float
        Its f0 (Hz).
    q : float
        Its Q.
    mean_square_m2 : float
        Its mean-square displacement of the mode (m²).
    """

    band_hz: tuple[float, float]
    weighting: Weighting
    f0_hz: float
    q: float
    mean_square_m2: float


@record
class ThermalFitRecord(Record):
    """The maximum-likelihood fit of the thermal spectrum: its goodness of fit and its spread.

    Attributes
    ----------
    estimator : str
        The estimator.
    n_averages : float
        M, the Gamma shape of the bins (periodograms averaged).
    n_averages_estimated : bool
        M was estimated from the spectrum's scatter.
    deviance : float
        The deviance D of the fit.
    dof : int
        Its degrees of freedom.
    p_value : float or None
        The probability of a deviance at least D; None when M was estimated.
    dispersion : float
        Pearson's statistic over the degrees of freedom.
    bin_correlation : float
        How correlated neighbouring bins are (1: independent).
    f0_hz : ValueSpread
        f0 (Hz).
    q : ValueSpread
        Q.
    variants : tuple of ThermalVariantRecord
        The refits in half and double the band and with the linear weighting.
    """

    estimator: str
    n_averages: float
    n_averages_estimated: bool
    deviance: float
    dof: int
    p_value: float | None
    dispersion: float
    bin_correlation: float
    f0_hz: ValueSpread
    q: ValueSpread
    variants: tuple[ThermalVariantRecord, ...]


@record
class ThermalSpringConstant(Record):
    """The spring constant by equipartition of mode 1, corrected for the detection (Butt & Jaschke).

    Attributes
    ----------
    method : str
        The method.
    detection : Detection
        How the deflection was measured.
    factor : float
        The correction factor for the detection.
    factor_source : str
        Where the factor comes from.
    temperature_k : float or None
        Temperature (K).
    value_n_per_m : float or None
        k (N/m).
    std_n_per_m : float or None
        Its statistical standard deviation (N/m).
    systematic_n_per_m : float or None
        Its systematic uncertainty (N/m).
    """

    method: str
    detection: Detection
    factor: float
    factor_source: str
    temperature_k: float | None
    value_n_per_m: float | None
    std_n_per_m: float | None
    systematic_n_per_m: float | None


@record
class SaderSpringConstant(Record):
    """The spring constant by Sader's method from the plan-view length and width, f0 and Q in the fluid.

    Attributes
    ----------
    method : str
        The method.
    value_n_per_m : float
        k (N/m).
    std_n_per_m : float
        Its standard deviation, f0's and Q's systematic spread included (N/m).
    length_um : float
        The cantilever's length L (µm).
    width_um : float
        Its width b (µm).
    fluid : Fluid
        The fluid.
    fluid_density_kg_per_m3 : float
        Its density (kg/m³).
    fluid_viscosity_pa_s : float
        Its viscosity (Pa·s).
    reynolds : float
        The Reynolds number at f0.
    gamma_imag : float
        The imaginary part of the hydrodynamic function there.
    """

    method: str
    value_n_per_m: float
    std_n_per_m: float
    length_um: float
    width_um: float
    fluid: Fluid
    fluid_density_kg_per_m3: float
    fluid_viscosity_pa_s: float
    reynolds: float
    gamma_imag: float


@record
class SpringConstantParameters(Record):
    """The ``[identify.spring_constant]`` parameters of the run.

    Attributes
    ----------
    detection : Detection
        How the spectrum's deflection was measured.
    length_um : float
        Sader: the plan-view length L (µm); 0 for no Sader value.
    width_um : float
        Sader: the plan-view width b (µm); 0 for no Sader value.
    fluid : Fluid
        Sader: the fluid.
    fluid_density_kg_per_m3 : float
        Sader: its density (kg/m³); 0 for the fluid's at 25 °C.
    fluid_viscosity_pa_s : float
        Sader: its viscosity (Pa·s); 0 for the fluid's at 25 °C.
    """

    detection: Detection
    length_um: float
    width_um: float
    fluid: Fluid
    fluid_density_kg_per_m3: float
    fluid_viscosity_pa_s: float


@record
class SpringConstants(Record):
    """The spring constant by each method.

    Attributes
    ----------
    thermal : ThermalSpringConstant
        By equipartition.
    sader : SaderSpringConstant or None
        By Sader's method; None without the lever's length and width.
    parameters : SpringConstantParameters
        The parameters they ran with.
    """

    thermal: ThermalSpringConstant
    sader: SaderSpringConstant | None
    parameters: SpringConstantParameters


@record
class FreeAirResults(Record):
    """The free-air model by the segment, sweep or thermal route.

    Attributes
    ----------
    free_air_model : FreeAirModelRecord
        The model (``free_air.json``).
    route : FreeAirRoute
        The route.
    segment_s : tuple of 2 float or None
        Segment route: the free-air segment (s).
    segment_samples : int or None
        Segment route: its samples.
    sweep_method : SweepMethod or None
        Sweep route: the method.
    samples : int or None
        Sweep route: samples read.
    drive_hold : DriveHold or None
        Sweep route: the hold of the model fitted.
    drive_hold_reason : str or None
        Sweep route: why that hold.
    spectrum : ThermalSpectrumRecord or None
        Thermal route: the spectrum fitted.
    fit : ThermalFitRecord or None
        Thermal route: the maximum-likelihood fit.
    floor_asd_m_per_sqrt_hz : float or None
        Thermal route: the white floor of the spectrum (m/√Hz).
    peak_asd_m_per_sqrt_hz : float or None
        Thermal route: the ASD at the peak above the floor (m/√Hz).
    band_hz : tuple of 2 float or None
        Sweep route (record fit) and thermal route: the band fitted (Hz), low first.
    n_bins : int or None
        Sweep route (record fit) and thermal route: frequency bins fitted.
    transient_order : int or None
        Sweep route (record fit): the order of the transient removed.
    delay_std_s : float or None
        Sweep route (record fit): the drive delay's standard deviation (s).
    noise_std : float or None
        Sweep route (record fit): the deflection noise's standard deviation, in deflection units.
    drive_edges_s : tuple of float or None
        Sweep route (record fit): the drive's switches found (s).
    rms_log_residual : float or None
        Thermal route: rms residual of the fit in log ASD.
    spring_constant_n_per_m : float or None
        Thermal route: k by equipartition before the detection's correction (N/m).
    spring_constant_note : str or None
        Thermal route: what that k assumes.
    temperature_k : float or None
        Thermal route: temperature (K).
    spring_constant : SpringConstants or None
        Thermal route: the spring constant by each method.
    """

    free_air_model: FreeAirModelRecord
    route: FreeAirRoute
    segment_s: tuple[float, float] | None = optional()
    segment_samples: int | None = optional()
    sweep_method: SweepMethod | None = optional()
    samples: int | None = optional()
    drive_hold: DriveHold | None = optional()
    drive_hold_reason: str | None = optional()
    spectrum: ThermalSpectrumRecord | None = optional()
    fit: ThermalFitRecord | None = optional()
    floor_asd_m_per_sqrt_hz: float | None = optional()
    peak_asd_m_per_sqrt_hz: float | None = optional()
    band_hz: tuple[float, float] | None = optional()
    n_bins: int | None = optional()
    transient_order: int | None = optional()
    delay_std_s: float | None = optional()
    noise_std: float | None = optional()
    drive_edges_s: tuple[float, ...] | None = optional()
    rms_log_residual: float | None = optional()
    spring_constant_n_per_m: float | None = optional()
    spring_constant_note: str | None = optional()
    temperature_k: float | None = optional()
    spring_constant: SpringConstants | None = optional()

    HEADLINE = (
        *free_air_model_items(),
        Item("gain", "free_air_model.gain", "", "free_air_model.gain_std"),
        Item("k (thermal, equipartition)", "spring_constant.thermal.value_n_per_m", "N/m",
             "spring_constant.thermal.std_n_per_m"),
        Item("k (Sader)", "spring_constant.sader.value_n_per_m", "N/m", "spring_constant.sader.std_n_per_m"),
    )
