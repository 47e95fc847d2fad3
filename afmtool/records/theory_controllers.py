"""``theory controllers``'s results: ch. 2's three z-controller gains on the grating, per line rate, and the verdict."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

from afmtool.records.base import Item, Record, record

__all__ = ["ControllerRowRecord", "Ch2RowRecord", "GainRecord", "GainsRecord", "CriteriaRecord", "ControllersResults"]


@record
class ControllerRowRecord(Record):
    """One controller at one line rate, over the scan after the engage.

    Attributes
    ----------
    loss_area : float
        Probe-loss area: share of scan time in truth probe loss (§2.2's parachuting), 0-1.
    lift_off_area : float
        Share of scan time in truth loss on a surface that did not fall away, 0-1.
    peak_force_n : float
        Largest repulsive tip-sample force over the scan (N).
    p999_force_n : float
        99.9th percentile of the per-sample force extremes (N).
    detected_loss : float
        Share of scan samples the in-loop switching signal read loss, 0-1.
    """

    loss_area: float
    lift_off_area: float
    peak_force_n: float
    p999_force_n: float
    detected_loss: float


@record
class Ch2RowRecord(Record):
    """The three controllers at one line rate, and the two ratios of the acceptance test.

    Attributes
    ----------
    line_rate_hz : float
        The line rate (Hz).
    low : ControllerRowRecord
        The low gain.
    high : ControllerRowRecord
        The high gain.
    switching : ControllerRowRecord
        The switching gain.
    loss_ratio_switching_to_high : float
        Switching probe-loss area over the high gain's (null for infinite: the high gain has none).
    force_ratio_switching_to_low : float
        Switching peak force over the low gain's.
    """

    line_rate_hz: float
    low: ControllerRowRecord
    high: ControllerRowRecord
    switching: ControllerRowRecord
    loss_ratio_switching_to_high: float
    force_ratio_switching_to_low: float


@record
class GainRecord(Record):
    """One PI gain pair of the z-controller.

    Attributes
    ----------
    ki_per_s : float
        Integral gain (1/s).
    kp : float
        Proportional gain.
    """

    ki_per_s: float
    kp: float


@record
class GainsRecord(Record):
    """The low and high gain pairs (the switching controller switches between them).

    Attributes
    ----------
    low : GainRecord
        The low gain.
    high : GainRecord
        The high gain.
    """

    low: GainRecord
    high: GainRecord


@record
class CriteriaRecord(Record):
    """The thesis's claims (§2.5) at one line rate.

    Attributes
    ----------
    high_below_low : bool
        The high gain loses less than the low gain.
    high_least_loss : bool
        The high gain has the least probe-loss area of the three.
    switching_loss_within : bool
        Switching probe-loss area within the tolerance times the high gain's.
    switching_force_within : bool
        Switching peak force within the tolerance times the low gain's.
    """

    high_below_low: bool
    high_least_loss: bool
    switching_loss_within: bool
    switching_force_within: bool

    def holds(self) -> bool:
        """Every claim holds."""
        return all(getattr(self, f.name) for f in dataclasses.fields(self))


@record
class ControllersResults(Record):
    """Low, high and switching z-controller gains on the grating (ch. 2), per line rate.

    Attributes
    ----------
    line_rates_hz : tuple of float
        The line rates simulated (Hz).
    gains : GainsRecord
        The controllers' gains.
    table : tuple of Ch2RowRecord
        One row per line rate.
    criteria : Mapping of str to CriteriaRecord
        The claims at each line rate, keyed by the rate in Hz ("8", "12.5").
    tolerance : float
        The acceptance tolerance on the two ratios.
    pass_ : bool
        Every claim holds at three line rates or more (all, for fewer rates).
    """

    line_rates_hz: tuple[float, ...]
    gains: GainsRecord
    table: tuple[Ch2RowRecord, ...]
    criteria: Mapping[str, CriteriaRecord]
    tolerance: float
    pass_: bool

    HEADLINE = (
        Item("verdict: pass", "pass", "", text=True),
        Item("probe-loss area, low gain", "table.0.low.loss_area", "of the image"),
        Item("probe-loss area, high gain", "table.0.high.loss_area", "of the image"),
        Item("probe-loss area, switching gain", "table.0.switching.loss_area", "of the image"),
        Item("peak force, switching gain", "table.0.switching.peak_force_n", "N"),
        Item("at line rate", "table.0.line_rate_hz", "Hz"),
    )
