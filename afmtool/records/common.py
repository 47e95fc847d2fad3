"""Records that several commands' results share: moments of a series, the free-air model and its route.

The free-air model's record (:class:`FreeAirModelRecord`) is the report's copy of
:class:`afmtool.models.free_air.FreeAirModel` (``models/`` sits above this floor, so the
record mirrors its fields; ``FreeAirModel.record()`` and ``.from_record()`` convert).
"""

from __future__ import annotations

import enum

from afmtool.records.base import Item, Record, State, optional, record

__all__ = ["Moments", "SeriesMoments", "FreeAirModelRecord", "free_air_model_items", "Route", "DriveHold",
           "DriveHoldOption", "FreeAirRouteRecord", "phase_state", "PHASE_MISFIT_DEG"]


@record
class Moments(Record):
    """Count, mean and standard deviation of the finite, unflagged values of a series.

    Attributes
    ----------
    count : int
        Values counted.
    mean : float
        Their mean, in the series' units.
    std : float or None
        Their standard deviation (population), None for fewer than two values.
    """

    count: int
    mean: float
    std: float | None


@record
class SeriesMoments(Record):
    """:class:`Moments` with the extremes.

    Attributes
    ----------
    count : int
        Values counted.
    mean : float
        Their mean, in the series' units.
    std : float or None
        Their standard deviation (population), None for fewer than two values.
    min : float
        The smallest value.
    max : float
        The largest value.
    """

    count: int
    mean: float
    std: float | None
    min: float
    max: float


@record
class FreeAirModelRecord(Record):
    """The free-air model G(s) = gain·ω0²/(s² + (ω0/Q)s + ω0²) an analysis ran on (``free_air.json``'s fields).

    Attributes
    ----------
    f0_hz : float
        Resonant frequency (Hz).
    q : float
        Quality factor.
    gain : float
        DC gain, deflection units per dither unit (nm/V).
    f0_std_hz : float or None
        Standard deviation of f0 (Hz).
    q_std : float or None
        Standard deviation of Q.
    gain_std : float or None
        Standard deviation of the gain.
    source : str
        Where it came from: ``segment``, ``sweep``, ``thermal``, ``given``, ``f0-q:<from>``.
    sample_rate_hz : float or None
        The rate the discrete coefficients are for (Hz).
    numerator : tuple of 3 float or None
        (a2, a1, a0) of eq. 3.40.
    denominator : tuple of 2 float or None
        (b1, b0) of eq. 3.40.
    delay_s : float
        Pure delay of the drive path (s).
    spring_constant_n_per_m : float or None
        The spring constant k (N/m), where the route measured it.
    spring_constant_std_n_per_m : float or None
        Its standard deviation (N/m).
    spring_constant_source : str or None
        How k was obtained.
    """

    f0_hz: float
    q: float
    gain: float
    f0_std_hz: float | None
    q_std: float | None
    gain_std: float | None
    source: str
    sample_rate_hz: float | None
    numerator: tuple[float, float, float] | None
    denominator: tuple[float, float] | None
    delay_s: float
    spring_constant_n_per_m: float | None = optional()
    spring_constant_std_n_per_m: float | None = optional()
    spring_constant_source: str | None = optional()


def free_air_model_items(prefix: str = "free_air_model") -> tuple[Item, ...]:
    """The headline items of a :class:`FreeAirModelRecord` at ``prefix``: f0 and Q with their std."""
    return (
        Item("f0 (free air)", f"{prefix}.f0_hz", "Hz", f"{prefix}.f0_std_hz"),
        Item("Q (free air)", f"{prefix}.q", "", f"{prefix}.q_std"),
    )


class Route(enum.Enum):
    """Where the free-air model came from (:mod:`afmtool.analyses.freeair_route`)."""

    SEGMENT = "segment"  # the ARX fit on the capture's free-air segment
    MODEL = "model"  # given (--model)
    F0_Q = "f0-q"  # the lever's f0 and Q, the gain and delay fitted at the drive


class DriveHold(enum.Enum):
    """How the drive reached the cantilever between samples (:mod:`afmtool.models.discretisation`)."""

    CONTINUOUS = "continuous"
    ZOH = "zoh"


class DriveHoldOption(enum.Enum):
    """``--drive-hold`` as given."""

    AUTO = "auto"
    CONTINUOUS = "continuous"
    ZOH = "zoh"


@record
class FreeAirRouteRecord(Record):
    """How the free-air model was chosen, and the drive's hold.

    Attributes
    ----------
    route : Route
        Where the model came from.
    f0_q_from : str or None
        On the f0-q route, where f0 and Q came from (``metadata``, ``flags``).
    drive_hold : DriveHold
        The hold the model assumes.
    drive_hold_option : DriveHoldOption
        ``--drive-hold`` as given.
    drive_hold_reason : str
        Why that hold.
    measured_excess_phase_deg : float or None
        The free-air phase at the drive, less the continuous model's (degrees).
    zoh_excess_phase_deg : float or None
        What a zero-order hold would give (degrees).
    fitted_gain : float or None
        On the f0-q route: the gain fitted at the drive.
    fitted_delay_s : float or None
        On the f0-q route: the drive-path delay fitted at the drive (s).
    phase_misfit_deg : float or None
        The measured phase less the chosen hold's (degrees), where the model was discretised here.
    phase_explained_deg : tuple of 2 float or None
        The phase range a hold and up to one sample of delay explain (degrees).
    """

    route: Route
    f0_q_from: str | None
    drive_hold: DriveHold
    drive_hold_option: DriveHoldOption
    drive_hold_reason: str
    measured_excess_phase_deg: float | None = optional()
    zoh_excess_phase_deg: float | None = optional()
    fitted_gain: float | None = optional()
    fitted_delay_s: float | None = optional()
    phase_misfit_deg: float | None = optional()
    phase_explained_deg: tuple[float, float] | None = optional()


#: Above this free-air phase misfit (degrees) a headline shows the misfit, not the scores.
PHASE_MISFIT_DEG = 30.0


def phase_state(route: FreeAirRouteRecord | None) -> State | None:
    """The free-air phase misfit, when it exceeds 30°: a state rule of the commands that run on the model."""
    misfit = None if route is None else route.phase_misfit_deg
    if misfit is None or abs(misfit) <= PHASE_MISFIT_DEG:
        return None
    return State(f"the free-air model misses the capture's phase at the drive by {misfit:+.0f} deg (> 30): "
                 "scores against it are not shown", "free_air_route.phase_misfit_deg")
