"""``theory compare``'s results: a REEP run beside averaging theory along its force curve, binned, with a verdict.

A number a mode may lack is a plain ``float`` field declared :func:`optional`: absent in the
modes without it, and where it is present but unknown (not finite) it is NaN, written as null.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping

from afmtool.records.base import Item, Record, optional, record
from afmtool.records.theory_fit import FitModel

__all__ = ["SeparationSource", "ContactMethod", "BinLeg", "CompareForceRecord", "SeparationRecord", "BeatRecord",
           "FreeAirReferenceRecord", "WorstBinRecord", "TheoryComparisonRecord", "TheoryCompareResults"]


class SeparationSource(enum.Enum):
    """Where the separation of each REEP row came from."""

    TRUTH = "truth"  # the capture's /truth/separation_nm
    Z_PIEZO = "z-piezo"  # z_piezo from a contact point
    FIT = "fit"  # z_piezo from the contact point ``theory fit`` found


class ContactMethod(enum.Enum):
    """How the contact point was placed."""

    GIVEN = "given"  # --contact-z
    ALIGNED = "aligned on the approach amplitude"
    FITTED = "fitted by theory fit"


class BinLeg(enum.Enum):
    """The leg of a separation bin."""

    APPROACH = "approach"
    RETRACT = "retract"


@record
class CompareForceRecord(Record):
    """The force compared with, and where it came from.

    Attributes
    ----------
    source : str
        A thesis set's name, "custom", "metadata" (or the capture's own name of its force) or "fit".
    spec : str, optional
        Its parameters as ``--force`` takes them; not for a fitted force.
    fit : str, optional
        For a fitted force: the fit.json it was read from.
    model : FitModel, optional
        For a fitted force: the model the fit kept.
    d_nm : float, optional
        For a fitted force: d (nm).
    omega_a2 : float, optional
        For a fitted force: ω_a² (1/s²).
    omega_b2 : float, optional
        For a fitted force: ω_b² (1/s²).
    c_a : float, optional
        For a fitted force: c_a (1/s).
    c_b : float, optional
        For a fitted force: c_b (1/s).
    """

    source: str
    spec: str | None = optional()
    fit: str | None = optional()
    model: FitModel | None = optional()
    d_nm: float | None = optional()
    omega_a2: float | None = optional()
    omega_b2: float | None = optional()
    c_a: float | None = optional()
    c_b: float | None = optional()


@record
class SeparationRecord(Record):
    """Where the separation axis came from.

    Attributes
    ----------
    source : SeparationSource
        Truth, z_piezo or the fit.
    z_units : str, optional
        From z: its units.
    nm_per_unit : float, optional
        From z: the z scale s (nm per z unit).
    contact_z : float, optional
        From z: the contact point z_c (z units).
    contact_method : ContactMethod, optional
        From z: how z_c was placed.
    amplitude_rms_residual_nm : float, optional
        From z_piezo: the RMS residual of the amplitude alignment (nm); null when z_c was given.
    contact_z_std : float, optional
        From z_piezo: the standard error of z_c (z units); null where unknown.
    separation_std_nm : float, optional
        From z: the separation's uncertainty σ_l (nm).
    """

    source: SeparationSource
    z_units: str | None = optional()
    nm_per_unit: float | None = optional()
    contact_z: float | None = optional()
    contact_method: ContactMethod | None = optional()
    amplitude_rms_residual_nm: float | None = optional()
    contact_z_std: float | None = optional()
    separation_std_nm: float | None = optional()


@record
class BeatRecord(Record):
    """The drive's envelope beat m and where its lines came from.

    Attributes
    ----------
    modulation : float
        m = Σ_side B_i|G(f_i)| / (A|G(f)|).
    lines : tuple of (float, float)
        The drive's lines: (frequency in Hz, amplitude in V).
    lines_from : str
        Where the lines came from ("unknown" when they are not known).
    """

    modulation: float
    lines: tuple[tuple[float, float], ...]
    lines_from: str


@record
class FreeAirReferenceRecord(Record):
    """The free-air f0' and Q' the shifts are taken from.

    Attributes
    ----------
    f0_hz : float
        Free-air f0' (Hz).
    q : float
        Free-air Q'.
    source : str
        Where they came from.
    """

    f0_hz: float
    q: float
    source: str


@record
class WorstBinRecord(Record):
    """One of the well-conditioned bins with the largest |z|.

    Attributes
    ----------
    leg : BinLeg
        Approach or retract.
    separation_nm : float
        The bin's centre (nm).
    f0_shift_reep_hz : float
        REEP's f0' shift from free air (Hz).
    f0_shift_theory_hz : float
        The theory's f0,e shift (Hz).
    f0_z : float
        Their difference over its uncertainty (eq. C.1).
    q_shift_reep : float
        REEP's Q' shift from free air.
    q_shift_theory : float
        The theory's Qe shift.
    q_z : float
        Their difference over its uncertainty.
    """

    leg: BinLeg
    separation_nm: float
    f0_shift_reep_hz: float
    f0_shift_theory_hz: float
    f0_z: float
    q_shift_reep: float
    q_shift_theory: float
    q_z: float


@record
class TheoryComparisonRecord(Record):
    """The comparison's numbers and verdict in words, as the comparison (:mod:`afmtool.analyses.theory`) gives them.

    Attributes
    ----------
    verdict : str
        The verdict in words: "agree: ...", "disagree: ..." or "inconclusive: ...".
    compared_rows : int
        REEP rows compared.
    bins : int
        Separation bins.
    bins_compared : int
        Bins in the verdict.
    bins_ill_conditioned : int
        Bins left out of it.
    ill_conditioned_reasons : Mapping of str to int
        Bins left out, by why.
    excluded_near_jumps : int
        Rows left out near a branch jump.
    outlier_share : float
        Share of z values beyond ±3 (null when inconclusive).
    max_outlier_share : float
        The largest share allowed.
    chi2_per_dof : float
        Σz²/ν (null when inconclusive).
    chi2_limit_per_dof : float
        Its limit, χ²_ν(0.999)/ν (null when inconclusive).
    tolerance : float
        The theory's relative tolerance τ.
    f0_theory_change_hz : float
        The largest theory f0,e shift in the compared bins (Hz).
    q_theory_change : float
        The largest theory Qe shift in the compared bins.
    free_air_reference : FreeAirReferenceRecord
        The free-air reference of the shifts.
    uncertainty_source : str
        Where REEP's uncertainties came from.
    beat_modulation : float
        The envelope beat m the theory's uncertainty includes.
    worst_bins : tuple of WorstBinRecord
        Up to three bins with the largest |z|, worst first.
    """

    verdict: str
    compared_rows: int
    bins: int
    bins_compared: int
    bins_ill_conditioned: int
    ill_conditioned_reasons: Mapping[str, int]
    excluded_near_jumps: int
    outlier_share: float
    max_outlier_share: float
    chi2_per_dof: float
    chi2_limit_per_dof: float
    tolerance: float
    f0_theory_change_hz: float
    q_theory_change: float
    free_air_reference: FreeAirReferenceRecord
    uncertainty_source: str
    beat_modulation: float
    worst_bins: tuple[WorstBinRecord, ...]


@record
class TheoryCompareResults(TheoryComparisonRecord):
    """REEP against averaging theory (eqs. 4.9-4.10) in separation bins, with a verdict (§3.4.3).

    Attributes
    ----------
    force_set : str
        The force compared with: a thesis set's name, "custom", "metadata" (or the capture's name of it) or "fit".
    force : CompareForceRecord
        The force's parameters and where they came from.
    free_amplitude_nm : float
        The free-air amplitude A0 the theory is evaluated for (nm).
    separation : SeparationRecord
        Where the separation axis came from.
    beat : BeatRecord
        The drive's envelope beat.
    pass_ : bool
        The verdict: REEP and the theory agree.
    """

    force_set: str
    force: CompareForceRecord
    free_amplitude_nm: float
    separation: SeparationRecord
    beat: BeatRecord
    pass_: bool

    HEADLINE = (
        Item("verdict", "verdict", "", text=True),
        Item("χ² per degree of freedom", "chi2_per_dof", ""),
        Item("χ² limit per degree of freedom", "chi2_limit_per_dof", ""),
        Item("outlier share of the bins", "outlier_share", ""),
        Item("bins compared", "bins_compared", "bins"),
        Item("bins left out (ill-conditioned)", "bins_ill_conditioned", "bins"),
        Item("worst bin: (f0' − f0e) shift", "worst_bins.0.f0_z", "σ", at="worst_bins.0.separation_nm",
             at_label="separation", at_units="nm"),
        Item("worst bin: (Q' − Qe) shift", "worst_bins.0.q_z", "σ", at="worst_bins.0.separation_nm",
             at_label="separation", at_units="nm"),
        Item("second worst bin: (f0' − f0e) shift", "worst_bins.1.f0_z", "σ", at="worst_bins.1.separation_nm",
             at_label="separation", at_units="nm"),
    )
