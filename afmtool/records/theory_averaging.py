"""``theory averaging``'s results: averaging theory's force curve (eqs. 4.6-4.8), approach and retract."""

from __future__ import annotations

import enum
from collections.abc import Mapping

from afmtool.records.base import Item, Record, optional, record

__all__ = ["ForceSet", "AveragingForceRecord", "AveragingLegRecord", "QOverlayRecord", "AveragingResults"]


class ForceSet(enum.Enum):
    """The force a theory ran with: a thesis set (``models.forces.THESIS_FORCE_SETS``) or a custom ``--force``."""

    ATTRACTIVE = "attractive"
    ATTRACTIVE_REPULSIVE = "attractive-repulsive"
    REPULSIVE = "repulsive"
    REPULSIVE_Q38 = "repulsive-q38"
    CH4_DEFAULT = "ch4-default"
    CUSTOM = "custom"


@record
class AveragingForceRecord(Record):
    """The piecewise-linear force (eq. 4.1).

    Attributes
    ----------
    name : ForceSet
        The thesis set, or custom.
    spec : str
        Its parameters, as ``--force`` takes them (d in nm, ω² in 1/s², c in 1/s).
    """

    name: ForceSet
    spec: str


@record
class AveragingLegRecord(Record):
    """One leg of the theoretical force curve.

    Attributes
    ----------
    f0_e_range_hz : tuple of 2 float
        The effective resonance f0,e, lowest and highest (Hz).
    q_e_range : tuple of 2 float
        The effective quality factor Qe, lowest and highest.
    bistable_separation_nm : tuple of 2 float or None
        The separations with two stable amplitudes, from and to (nm); None where there are none.
    """

    f0_e_range_hz: tuple[float, float]
    q_e_range: tuple[float, float]
    bistable_separation_nm: tuple[float, float] | None


@record
class QOverlayRecord(Record):
    """One off-sample Q of ``--q``: its approach, at the same free amplitude.

    Attributes
    ----------
    drive_amplitude_nm : float
        The drive that gives the free amplitude at this Q (nm, as a static deflection).
    f0_e_change_hz : float
        The range of f0,e on approach (Hz).
    q_e_range : tuple of 2 float
        Qe on approach, lowest and highest.
    """

    drive_amplitude_nm: float
    f0_e_change_hz: float
    q_e_range: tuple[float, float]


@record
class AveragingResults(Record):
    """Averaging theory along a force curve: f0,e, Qe and the steady state on approach and retract.

    Attributes
    ----------
    drive_amplitude_nm : float
        The drive amplitude, as a static deflection (nm).
    drive_frequency_hz : float
        The drive frequency (Hz).
    force : AveragingForceRecord
        The force.
    approach : AveragingLegRecord
        The approach.
    retract : AveragingLegRecord
        The retract.
    q_overlay : Mapping of str to QOverlayRecord, optional
        With ``--q``: each off-sample Q's approach, keyed by the Q ("50", "200").
    """

    drive_amplitude_nm: float
    drive_frequency_hz: float
    force: AveragingForceRecord
    approach: AveragingLegRecord
    retract: AveragingLegRecord
    q_overlay: Mapping[str, QOverlayRecord] | None = optional()

    HEADLINE = (
        Item("f0e on approach, lowest", "approach.f0_e_range_hz.0", "Hz"),
        Item("f0e on approach, highest", "approach.f0_e_range_hz.1", "Hz"),
        Item("Qe on approach, lowest", "approach.q_e_range.0", ""),
        Item("bistable from separation", "approach.bistable_separation_nm.0", "nm"),
        Item("bistable up to separation", "approach.bistable_separation_nm.1", "nm"),
        Item("drive amplitude", "drive_amplitude_nm", "nm"),
    )
