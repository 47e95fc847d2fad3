"""``identify invols``'s results: the contact slope of one leg and the InvOLS it gives."""

from __future__ import annotations

import enum

from afmtool.records.base import Item, Record, optional, record

__all__ = ["Leg", "InvolsResults"]


class Leg(enum.Enum):
    """The part of the force curve fitted."""

    APPROACH = "approach"
    RETRACT = "retract"
    ALL = "all"


@record
class InvolsResults(Record):
    """The InvOLS from the contact part of a force curve.

    Attributes
    ----------
    leg : Leg
        The leg fitted.
    points : int
        Samples in that leg.
    contact_z_nm : float
        The contact point z (nm).
    contact_side : str
        Which side of the contact point is in contact.
    fitted_points : int
        Samples in the contact fit.
    fitted_z_range_nm : tuple of float
        The z range of the contact fit (nm), lowest first.
    contact_slope : float
        The contact slope, deflection per nm of z.
    contact_slope_std : float
        Its standard deviation.
    contact_slope_units : str
        Its units (``V/nm``, ``nm/nm``).
    rms_residual : float
        RMS residual of the contact fit, in deflection units.
    capture_invols_nm_per_v : float or None
        The capture's own InvOLS (metadata), nm/V.
    note : str
        When 1/|slope| is the InvOLS.
    invols_nm_per_v : float or None
        InvOLS = 1/|slope| (nm/V), for a deflection recorded in V.
    invols_std_nm_per_v : float or None
        Its standard deviation (nm/V).
    implied_invols_nm_per_v : float or None
        For a deflection already in nm: the capture's InvOLS over |slope| (nm/V).
    implied_invols_std_nm_per_v : float or None
        Its standard deviation (nm/V).
    """

    leg: Leg
    points: int
    contact_z_nm: float
    contact_side: str
    fitted_points: int
    fitted_z_range_nm: tuple[float, float]
    contact_slope: float
    contact_slope_std: float
    contact_slope_units: str
    rms_residual: float
    capture_invols_nm_per_v: float | None
    note: str
    invols_nm_per_v: float | None = optional()
    invols_std_nm_per_v: float | None = optional()
    implied_invols_nm_per_v: float | None = optional()
    implied_invols_std_nm_per_v: float | None = optional()

    HEADLINE = (
        Item("InvOLS (contact slope)", "invols_nm_per_v", "nm/V", "invols_std_nm_per_v"),
        Item("InvOLS implied by the contact slope", "implied_invols_nm_per_v", "nm/V", "implied_invols_std_nm_per_v"),
        Item("InvOLS of the capture (metadata)", "capture_invols_nm_per_v", "nm/V"),
        Item("contact slope", "contact_slope", "@contact_slope_units", "contact_slope_std"),
        Item("contact point z", "contact_z_nm", "nm"),
    )
