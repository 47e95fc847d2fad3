"""``overlay``'s results: several REEP runs side by side, each run's own numbers and their spread."""

from __future__ import annotations

import enum

from afmtool.records.base import Item, Record, record

__all__ = ["OverlayAxis", "CurveLeg", "OverlayRunRecord", "OverlayResults"]


class OverlayAxis(enum.Enum):
    """What the force-curve figures are drawn against (``--vs``)."""

    Z = "z"  # z_piezo
    SEPARATION = "separation"  # |z − z_c| from each run's contact point


class CurveLeg(enum.Enum):
    """A leg of a force curve."""

    APPROACH = "approach"
    RETRACT = "retract"


@record
class OverlayRunRecord(Record):
    """One run as the overlay read it.

    Attributes
    ----------
    label : str
        Its label in the figures.
    folder : str
        Its output folder.
    free_air_f0_hz : float or None
        Its free-air f0' (Hz): the free-air segment's mean, else its model's f0.
    free_air_q : float or None
        Its free-air Q'.
    largest_df0_hz : float or None
        The largest Δf0' on its approach (Hz).
    largest_df0_z : float or None
        Where it occurs, in the run's z units.
    smallest_q : float or None
        The smallest Q' on its approach.
    contact_z : float or None
        Its contact point z_c, where the approach amplitude first falls below 0.95 of free air (z units).
    force_curve_legs : tuple of CurveLeg
        The force-curve legs it has.
    time_rows : int
        Rows of its time series read (thinned).
    """

    label: str
    folder: str
    free_air_f0_hz: float | None
    free_air_q: float | None
    largest_df0_hz: float | None
    largest_df0_z: float | None
    smallest_q: float | None
    contact_z: float | None
    force_curve_legs: tuple[CurveLeg, ...]
    time_rows: int


@record
class OverlayResults(Record):
    """Several REEP runs overlaid: each run's numbers, and their spread across the runs.

    Attributes
    ----------
    runs : tuple of OverlayRunRecord
        The runs, in order.
    n_runs : int
        How many.
    vs : OverlayAxis
        The force-curve figures' x axis.
    x_units : str
        Its units (the runs' z units).
    contact_rule : str or None
        Against the separation: how each run's contact point was found.
    free_air_f0_hz_spread : float or None
        Largest less smallest free-air f0' across the runs (Hz).
    free_air_q_spread : float or None
        Largest less smallest free-air Q'.
    largest_df0_hz_spread : float or None
        Largest less smallest of the runs' largest Δf0' (Hz).
    first : OverlayRunRecord
        The first run.
    last : OverlayRunRecord
        The last run.
    """

    runs: tuple[OverlayRunRecord, ...]
    n_runs: int
    vs: OverlayAxis
    x_units: str
    contact_rule: str | None
    free_air_f0_hz_spread: float | None
    free_air_q_spread: float | None
    largest_df0_hz_spread: float | None
    first: OverlayRunRecord
    last: OverlayRunRecord

    HEADLINE = (
        Item("runs overlaid", "n_runs", "runs"),
        Item("free-air f0' spread across the runs", "free_air_f0_hz_spread", "Hz"),
        Item("free-air Q' spread across the runs", "free_air_q_spread", ""),
        Item("largest Δf0' on approach, first run", "first.largest_df0_hz", "Hz"),
        Item("largest Δf0' on approach, last run", "last.largest_df0_hz", "Hz"),
        Item("spread of the largest Δf0' across the runs", "largest_df0_hz_spread", "Hz"),
    )
