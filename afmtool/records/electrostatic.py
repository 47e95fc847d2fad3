"""``identify electrostatic``'s results: eq. 6.6 or 6.7 fitted before snap-in, and what the curve can determine.

``parameters`` and ``identifiability`` are also written, with the sensor and V_R,
to ``electrostatic.json`` (which ``decode --electrostatic`` reads).
"""

from __future__ import annotations

import enum
from collections.abc import Mapping

from afmtool.records.base import Item, Record, optional, record

__all__ = [
    "Sensor", "ThesisEquation", "ParameterStatus", "ParameterRecord", "ElectrostaticParameters",
    "NullDirectionRecord", "IdentifiabilityRecord", "RegionRecord", "ElectrostaticResults",
]


class Sensor(enum.Enum):
    """Which curve was fitted."""

    OPTICAL = "optical"  # the optical deflection p
    THERMAL = "thermal"  # the separation t_s from the thermal current through K_TP(t_s)


class ThesisEquation(enum.Enum):
    """The static balance fitted."""

    EQ_6_6 = "6.6"  # optical: k·p(ℓ0 + p)² = −K_esf·V²
    EQ_6_7 = "6.7"  # thermal: k(t_s + t_h − ℓ0)(t_s + t_h)² = −K_esf·V²


class ParameterStatus(enum.Enum):
    """How well the curve determines a parameter."""

    IDENTIFIED = "identified"
    FIXED = "fixed"  # given by the user (--spring-constant)
    POORLY_IDENTIFIABLE = "poorly identifiable"  # relative std above max_relative_std
    NOT_IDENTIFIABLE = "not identifiable"  # a structural null direction: no value


@record
class ParameterRecord(Record):
    """One parameter of the fit, in SI units.

    Attributes
    ----------
    value : float or None
        The estimate (SI units of its name); None when the curve cannot determine it.
    std : float or None
        Its standard deviation (same units); None with no value.
    relative_std : float or None
        |std/value|; None with no value or a zero one.
    status : ParameterStatus
        How well the curve determines it.
    note : str or None
        Why it is not identifiable, and what would make it so (k and K_esf only).
    """

    value: float | None
    std: float | None
    relative_std: float | None
    status: ParameterStatus
    note: str | None = optional()


@record
class ElectrostaticParameters(Record):
    """The parameters of eq. 6.6 (optical) or 6.7 (thermal), and the combination the curve always determines.

    Attributes
    ----------
    spring_constant_n_per_m : ParameterRecord
        The spring constant k (N/m): fixed when given, else not identifiable.
    l0_m : ParameterRecord
        The lever-sample separation ℓ0 at zero deflection (m).
    k_esf_f_m : ParameterRecord
        The electrostatic constant K_esf (F·m): from the given k, else not identifiable.
    alpha_r : ParameterRecord
        The share α_R of V_R on the lever surface.
    tip_height_m : ParameterRecord or None
        The tip height t_h (m), on the thermal route (eq. 6.7).
    k_esf_over_k_m3_per_v2 : ParameterRecord
        ρ = K_esf/k (m³/V²).
    """

    spring_constant_n_per_m: ParameterRecord
    l0_m: ParameterRecord
    k_esf_f_m: ParameterRecord
    alpha_r: ParameterRecord
    tip_height_m: ParameterRecord | None = optional()
    k_esf_over_k_m3_per_v2: ParameterRecord


@record
class NullDirectionRecord(Record):
    """A parameter combination the curve does not determine (a structural null direction).

    Attributes
    ----------
    parameters : tuple of str
        The parameters that take part.
    weights : tuple of float
        Their components of the unit singular vector, in relative units (δln θ).
    identifiable_combination : str or None
        For two parameters of equal weight, the combination the curve does determine ("b/a", "a*b").
    relative_singular_value : float
        Its singular value over the largest.
    """

    parameters: tuple[str, ...]
    weights: tuple[float, ...]
    identifiable_combination: str | None
    relative_singular_value: float


@record
class IdentifiabilityRecord(Record):
    """The SVD of the fit's relative Jacobian: which parameter combinations the curve determines.

    Attributes
    ----------
    method : str
        How the analysis was made, in words.
    parameters : tuple of str
        The parameters, in the order of the directions' components.
    singular_values : tuple of float
        Descending, in noise units per unit relative change.
    condition_number : float or None
        Largest over smallest singular value; None with an exact null direction.
    directions : tuple of tuple of float
        The right singular vectors, one per singular value.
    non_identifiable : tuple of NullDirectionRecord
        The structural null directions.
    fixed_in_fit : tuple of str
        Parameters held fixed in the fit (one per null direction, and k when given).
    poorly_identifiable : tuple of str
        Parameters determined worse than max_relative_std.
    """

    method: str
    parameters: tuple[str, ...]
    singular_values: tuple[float, ...]
    condition_number: float | None
    directions: tuple[tuple[float, ...], ...]
    non_identifiable: tuple[NullDirectionRecord, ...]
    fixed_in_fit: tuple[str, ...]
    poorly_identifiable: tuple[str, ...]


@record
class RegionRecord(Record):
    """The part of the approach fitted: before snap-in, less a margin.

    Attributes
    ----------
    v_sub_range_v : tuple of 2 float
        V_sub at its first and last sample (V).
    points : int
        Finite samples fitted.
    snap_in_v_sub_v : float
        V_sub at the snap-in (V); null without one.
    snap_in_jump_nm : float
        The jump of the curve at the snap-in (nm); 0 without one, null where the curve leaves its
        calibration there (thermal).
    margin_fraction : float
        The share of the V_sub range before snap-in left out.
    """

    v_sub_range_v: tuple[float, float]
    points: int
    snap_in_v_sub_v: float
    snap_in_jump_nm: float
    margin_fraction: float


@record
class ElectrostaticResults(Record):
    """Electrostatic parameters from a quasi-static approach curve before snap-in (thesis eqs. 6.6, 6.7).

    Attributes
    ----------
    sensor : Sensor
        Which curve was fitted.
    thesis_equation : ThesisEquation
        The balance fitted.
    v_r_v : float
        The sensor voltage V_R (V).
    region : RegionRecord
        The part of the approach fitted.
    parameters : ElectrostaticParameters
        The parameters, with their standing.
    identifiability : IdentifiabilityRecord
        What the curve can determine.
    correlation : mapping of str to mapping of str to float
        Correlation between each pair of fitted parameters, by their names (those fitted depend on the run).
    rms_residual_nm : float
        RMS residual of the fit (nm).
    residual_lag1_autocorrelation : float
        Lag-1 autocorrelation of the residuals in V_sub order (near 0: fits to the noise; near 1: a misfit).
    """

    sensor: Sensor
    thesis_equation: ThesisEquation
    v_r_v: float
    region: RegionRecord
    parameters: ElectrostaticParameters
    identifiability: IdentifiabilityRecord
    correlation: Mapping[str, Mapping[str, float]]
    rms_residual_nm: float
    residual_lag1_autocorrelation: float

    HEADLINE = (
        Item("ℓ0", "parameters.l0_m.value", "m", "parameters.l0_m.std"),
        Item("K_esf/k", "parameters.k_esf_over_k_m3_per_v2.value", "m³/V²", "parameters.k_esf_over_k_m3_per_v2.std"),
        Item("α_R", "parameters.alpha_r.value", "", "parameters.alpha_r.std"),
        Item("t_h", "parameters.tip_height_m.value", "m", "parameters.tip_height_m.std"),
        Item("K_esf", "parameters.k_esf_f_m.value", "F·m", "parameters.k_esf_f_m.std"),
        Item("RMS residual", "rms_residual_nm", "nm"),
    )
