"""``theory fit``'s results (``fit.json``): the piecewise-linear force fitted to REEP's approach (ch. 4)."""

from __future__ import annotations

import enum

from afmtool.records.base import Item, Record, record

__all__ = ["ParameterStatus", "FitModel", "FitParameterName", "FitParameterRecord", "FitParametersRecord",
           "WallTestRecord", "OnsetRecord", "FitResidualsRecord", "TheoryFitResults"]

#: An interval (low, high); None for a side the profile leaves open.
Interval = tuple[float | None, float | None]


class ParameterStatus(enum.Enum):
    """What the curve says of a parameter (:mod:`afmtool.analyses.theory_fit`)."""

    IDENTIFIED = "identified"  # a closed 2σ interval, std within max_relative_std of the value
    POORLY_IDENTIFIABLE = "poorly identifiable"  # closed, but wider
    NOT_IDENTIFIABLE = "not identifiable"  # open on a side, not probed, or only in the onset


class FitModel(enum.Enum):
    """The model the curve supports."""

    ATTRACTIVE = "attractive"  # ω_a², c_a and the contact point; ω_b² = c_b = 0, d fixed
    WALL = "wall"  # every parameter, the repulsive wall too


class FitParameterName(enum.Enum):
    """A fitted parameter, by its name in ``parameters``."""

    D_NM = "d_nm"
    OMEGA_A2 = "omega_a2"
    OMEGA_B2 = "omega_b2"
    C_A = "c_a"
    C_B = "c_b"
    CONTACT_Z = "contact_z"


@record
class FitParameterRecord(Record):
    """One parameter: its value, 2σ interval, std and standing.

    Attributes
    ----------
    value : float
        The fitted value, in ``units``.
    std : float or None
        Its standard deviation (statistical and systematic), None for an open interval.
    units : str
        Its units (``nm``, ``1/s^2``, ``1/s``, ``z units``).
    interval_2sigma : tuple of 2 float or None
        The 2σ profile-likelihood interval, widened by the systematic part; None for an open side.
    systematic : float or None
        The systematic part of the std (the refits with every shift scaled by 1 ± τ).
    fitted : bool
        Fitted (False: held by the model).
    status : ParameterStatus
        Identified, poorly identifiable or not identifiable.
    reason : str
        Why that status.
    """

    value: float
    std: float | None
    units: str
    interval_2sigma: Interval
    systematic: float | None
    fitted: bool
    status: ParameterStatus
    reason: str


@record
class FitParametersRecord(Record):
    """The force's parameters (eq. 4.1) and the contact point.

    Attributes
    ----------
    d_nm : FitParameterRecord
        The attraction's range d (nm).
    omega_a2 : FitParameterRecord
        The attraction's stiffness per mass ω_a² (1/s²).
    omega_b2 : FitParameterRecord
        The repulsive wall's stiffness per mass ω_b² (1/s²).
    c_a : FitParameterRecord
        The attraction's damping per mass c_a (1/s).
    c_b : FitParameterRecord
        The wall's damping per mass c_b (1/s).
    contact_z : FitParameterRecord
        The contact point z_c, in z units.
    """

    d_nm: FitParameterRecord
    omega_a2: FitParameterRecord
    omega_b2: FitParameterRecord
    c_a: FitParameterRecord
    c_b: FitParameterRecord
    contact_z: FitParameterRecord


@record
class WallTestRecord(Record):
    """The test that keeps the wall model.

    Attributes
    ----------
    statistic : float
        The χ² drop of the wall model, in units of c.
    threshold : float
        χ²₃ at 0.99: the drop that keeps the wall.
    meaning : str
        What the statistic is.
    """

    statistic: float
    threshold: float
    meaning: str


@record
class OnsetRecord(Record):
    """The onset d + s·z_c, which the curve always pins.

    Attributes
    ----------
    value : float
        The onset (nm).
    std : float or None
        Its standard deviation (nm).
    interval_2sigma : tuple of 2 float or None
        Its 2σ interval (nm).
    """

    value: float
    std: float | None
    interval_2sigma: Interval


@record
class FitResidualsRecord(Record):
    """RMS residuals of the fitted rows.

    Attributes
    ----------
    f0_hz : float
        Of f0' (Hz).
    q : float
        Of Q'.
    amplitude_nm : float
        Of the amplitude (nm).
    """

    f0_hz: float
    q: float
    amplitude_nm: float


@record
class TheoryFitResults(Record):
    """The piecewise-linear force fitted to a measured approach; ``fit.json`` holds the same.

    Attributes
    ----------
    parameters : FitParametersRecord
        Each parameter.
    model : FitModel
        The model the curve supports.
    wall_test : WallTestRecord
        The test that chose it.
    uncertainty : str
        How the intervals were found.
    chi2_scale : float
        c = max(1, χ²/ν)·τ_int, the scale of the profile's rise.
    separation_offset_nm : float
        −s·z_c: the separation at z = 0 less d's share (nm).
    onset_d_plus_s_contact_z_nm : OnsetRecord
        The onset d + s·z_c (nm).
    repulsive_share : float
        Share of the fitted rows on the repulsive wall.
    nm_per_unit : float
        The z scale s (nm per z unit).
    identified : tuple of FitParameterName
        The parameters identified.
    not_identified : tuple of FitParameterName
        The others.
    rms_residual : FitResidualsRecord
        RMS residuals.
    fitted_samples : int
        Rows fitted.
    free_amplitude_nm : float
        The free-air amplitude (nm).
    beat_modulation : float
        The drive's envelope beat m.
    """

    parameters: FitParametersRecord
    model: FitModel
    wall_test: WallTestRecord
    uncertainty: str
    chi2_scale: float
    separation_offset_nm: float
    onset_d_plus_s_contact_z_nm: OnsetRecord
    repulsive_share: float
    nm_per_unit: float
    identified: tuple[FitParameterName, ...]
    not_identified: tuple[FitParameterName, ...]
    rms_residual: FitResidualsRecord
    fitted_samples: int
    free_amplitude_nm: float
    beat_modulation: float

    HEADLINE = (
        *(Item(label, f"parameters.{name}.value", units, f"parameters.{name}.std", note=f"parameters.{name}.status")
          for name, label, units in (("d_nm", "d", "nm"), ("omega_a2", "ω_a²", "1/s²"), ("omega_b2", "ω_b²", "1/s²"),
                                     ("c_a", "c_a", "1/s"), ("c_b", "c_b", "1/s"),
                                     ("contact_z", "contact point z_c", "@parameters.contact_z.units"))),
        Item("onset d + s·z_c", "onset_d_plus_s_contact_z_nm.value", "nm", "onset_d_plus_s_contact_z_nm.std"),
        Item("RMS residual of f0'", "rms_residual.f0_hz", "Hz"),
    )
