"""``theory observer``'s results: ch. 5's observer-design maps and lines, and the recommended observer."""

from __future__ import annotations

from collections.abc import Mapping

from afmtool.records.base import Item, Record, inline, optional, record
from afmtool.records.common import DriveHold

__all__ = ["PlantRecord", "DirectionRecord", "ObserverDriveRecord", "NoiseRecord", "GainMapRecord", "MapsRecord",
           "LineRecord", "DiscreteObserverRecord", "RecommendationRecord", "ObserverResults"]

#: A range (lowest, highest) of the finite values, (None, None) when there are none.
Range = tuple[float | None, float | None]


@record
class PlantRecord(Record):
    """The free-air plant the observers are designed for.

    Attributes
    ----------
    f0_hz : float
        Resonant frequency (Hz).
    q : float
        Quality factor.
    gain : float
        DC gain, deflection units per drive unit.
    numerator_c1_c0 : tuple of 2 float
        (c1, c0) of the continuous numerator c1·s + c0 (c0 = gain·ω0², 1/s²).
    """

    f0_hz: float
    q: float
    gain: float
    numerator_c1_c0: tuple[float, float]


@record
class DirectionRecord(Record):
    """The force-curve direction: from the free-air model (s = 0) to the on-sample one (s = 1).

    Attributes
    ----------
    f0_free_hz : float
        Free-air f0 (Hz).
    q_free : float
        Free-air Q.
    f0_low_hz : float
        On-sample f0 at the lowest amplitude considered (Hz).
    q_low : float
        On-sample Q there.
    source : str
        Where the end came from.
    """

    f0_free_hz: float
    q_free: float
    f0_low_hz: float
    q_low: float
    source: str


@record
class ObserverDriveRecord(Record):
    """The drive.

    Attributes
    ----------
    frequency_hz : float
        Drive frequency (Hz).
    amplitude : float
        Drive amplitude, in the plant's drive units.
    free_amplitude : float
        Free-air deflection amplitude at the drive (nm).
    """

    frequency_hz: float
    amplitude: float
    free_amplitude: float


@record
class NoiseRecord(Record):
    """The process and measurement noise.

    Attributes
    ----------
    eta_psd_per_hz : float
        One-sided PSD of the process noise η, in drive units² per Hz.
    nu_psd_per_hz : float
        One-sided PSD of the measurement noise ν, in deflection units² per Hz.
    convention : str
        How a variance follows from the PSDs.
    """

    eta_psd_per_hz: float
    nu_psd_per_hz: float
    convention: str


@record
class GainMapRecord(Record):
    """One gain's map over the observer models (f_k, Q_k): the ranges of its metrics.

    Attributes
    ----------
    ae2_min_at : tuple of 2 float
        (f_k in Hz, Q_k) of the least A_e².
    ae2 : tuple of 2 float or None
        Range of A_e², the mismatch error's mean square.
    dae2_ds : tuple of 2 float or None
        Range of dA_e²/ds along the force-curve direction.
    snr_eta : tuple of 2 float or None
        Range of the sensitivity over the process noise.
    snr_nu : tuple of 2 float or None
        Range of the sensitivity over the measurement noise.
    peak_transient : tuple of 2 float or None
        Range of the peak error after a unit plant-state step.
    settling_cycles : tuple of 2 float or None
        Range of the settling time (drive periods).
    """

    ae2_min_at: tuple[float, float]
    ae2: Range
    dae2_ds: Range
    snr_eta: Range
    snr_nu: Range
    peak_transient: Range
    settling_cycles: Range


@record
class MapsRecord(Record):
    """The maps over observer models (f_k, Q_k), one per gain.

    Attributes
    ----------
    nominal : tuple of 2 float
        The plant (f0 in Hz, Q) the maps are centred on.
    f_k_hz_range : tuple of 2 float or None
        The observer f_k mapped, lowest and highest (Hz).
    q_k_range : tuple of 2 float or None
        The observer Q_k mapped, lowest and highest.
    per_gain : Mapping of str to GainMapRecord
        Each gain's map, keyed "<cycles>_cycles" ("4_cycles").
    """

    nominal: tuple[float, float]
    f_k_hz_range: Range
    q_k_range: Range
    per_gain: Mapping[str, GainMapRecord] = inline()


@record
class LineRecord(Record):
    """One observer model and gain along the force-curve direction.

    Attributes
    ----------
    observer : tuple of 2 float
        The observer model (f_k in Hz, Q_k).
    cycles : float
        The gain: drive periods per 1/e of the error.
    ae2_min_at_s : float
        The s of the least A_e² (0 free air, 1 on-sample).
    ae2_range : tuple of 2 float or None
        Range of A_e².
    dae2_ds_range : tuple of 2 float or None
        Range of dA_e²/ds.
    snr_nu_range : tuple of 2 float or None
        Range of the sensitivity over the measurement noise.
    peak_transient_range : tuple of 2 float or None
        Range of the peak error after a unit plant-state step.
    """

    observer: tuple[float, float]
    cycles: float
    ae2_min_at_s: float
    ae2_range: Range
    dae2_ds_range: Range
    snr_nu_range: Range
    peak_transient_range: Range


@record
class DiscreteObserverRecord(Record):
    """The recommended observer, discretised (eq. 3.40).

    Attributes
    ----------
    sample_rate_hz : float
        The rate it runs at (Hz).
    drive_hold : DriveHold
        How the drive reaches the plant (the numerator's discretisation).
    numerator : tuple of 3 float
        (a2, a1, a0).
    denominator : tuple of 2 float
        (b1, b0).
    gain : tuple of 2 float
        The predictor gain (l1, l2).
    """

    sample_rate_hz: float
    drive_hold: DriveHold
    numerator: tuple[float, float, float]
    denominator: tuple[float, float]
    gain: tuple[float, float]


@record
class RecommendationRecord(Record):
    """The observer model and gain of greatest |dA_e²/ds| among those that settle in time.

    Attributes
    ----------
    f_k_hz : float
        The observer's f_k (Hz).
    q_k : float
        The observer's Q_k.
    cycles : float
        The gain: drive periods per 1/e of the error.
    dae2_ds : float
        dA_e²/ds at the nominal plant.
    ae2 : float
        A_e² at the nominal plant.
    snr_eta : float
        Sensitivity over the process noise.
    snr_nu : float
        Sensitivity over the measurement noise.
    peak_transient : float
        Peak error after a unit plant-state step.
    settling_cycles : float
        Settling time (drive periods).
    feasible : int
        Candidates that settle within max_cycles.
    candidates : int
        Candidates examined.
    at_grid_edge : bool
        The pick lies on the edge of the map: the optimum may lie beyond it.
    max_cycles : float
        The settling limit (drive periods).
    criterion : str
        What was maximised, subject to what.
    discrete : DiscreteObserverRecord
        The pick, discretised.
    """

    f_k_hz: float
    q_k: float
    cycles: float
    dae2_ds: float
    ae2: float
    snr_eta: float
    snr_nu: float
    peak_transient: float
    settling_cycles: float
    feasible: int
    candidates: int
    at_grid_edge: bool
    max_cycles: float
    criterion: str
    discrete: DiscreteObserverRecord


@record
class ObserverResults(Record):
    """Observer design (ch. 5): maps over observer models per gain, lines along the force curve, a recommendation.

    Attributes
    ----------
    plant : PlantRecord
        The free-air plant.
    direction : DirectionRecord
        The force-curve direction.
    drive : ObserverDriveRecord
        The drive.
    noise : NoiseRecord
        The noise.
    cycles : tuple of float
        The gains: drive periods per 1/e of the error.
    maps : MapsRecord
        The maps over observer models.
    lines : tuple of LineRecord
        Each observer model and gain along the direction.
    recommendation : RecommendationRecord, optional
        With --recommend: the pick.
    """

    plant: PlantRecord
    direction: DirectionRecord
    drive: ObserverDriveRecord
    noise: NoiseRecord
    cycles: tuple[float, ...]
    maps: MapsRecord
    lines: tuple[LineRecord, ...]
    recommendation: RecommendationRecord | None = optional()

    HEADLINE = (
        Item("recommended observer f_k", "recommendation.f_k_hz", "Hz"),
        Item("recommended observer Q_k", "recommendation.q_k", ""),
        Item("recommended window", "recommendation.cycles", "drive periods"),
        Item("observer f_k range mapped, lowest", "maps.f_k_hz_range.0", "Hz"),
        Item("observer f_k range mapped, highest", "maps.f_k_hz_range.1", "Hz"),
        Item("plant f0 (free air)", "plant.f0_hz", "Hz"),
        Item("plant Q (free air)", "plant.q", ""),
    )
