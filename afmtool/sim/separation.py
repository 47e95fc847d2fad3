"""Separation programs l(t): the rest tip-sample separation over time, nm.

l is the distance from the undeflected tip (p = 0) down to the sample
surface, which sits at p = −l (see :mod:`afmtool.models.forces`).  A
program is a frozen dataclass that evaluates itself at any time
(``program(t_s)``), so the integrator can read it between samples.  Every
program also reports ``initial_hold_s``: how long l stays at its starting
value, which the simulator uses to mark an off-sample (free-air) segment.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple, Protocol

import numpy as np

from afmtool.errors import ConfigError

__all__ = [
    "SeparationProgram",
    "ConstantSeparation",
    "ForceCurve",
    "ForceCurveSamples",
    "SeparationSteps",
    "LineScan",
]


class SeparationProgram(Protocol):
    """l(t) in nm, evaluable at arbitrary times."""

    @property
    def initial_hold_s(self) -> float:
        """Time from 0 during which l keeps its initial value, s (may be inf)."""
        ...

    def __call__(self, t_s: np.ndarray) -> np.ndarray:
        """Separation l (nm) at times ``t_s`` (s)."""
        ...


def _check(name: str, value: float, *, exclusive: bool = False) -> None:
    ok = isinstance(value, (int, float)) and math.isfinite(value) and (value > 0 if exclusive else value >= 0)
    if not ok:
        raise ConfigError(f"{name}={value!r} must be a finite number {'>' if exclusive else '>='} 0")


@dataclass(frozen=True)
class ConstantSeparation:
    """l(t) = ``separation_nm`` for all t."""

    separation_nm: float

    def __post_init__(self) -> None:
        if not (isinstance(self.separation_nm, (int, float)) and math.isfinite(self.separation_nm)):
            raise ConfigError(f"separation_nm={self.separation_nm!r} must be a finite number")

    @property
    def initial_hold_s(self) -> float:
        return math.inf

    def __call__(self, t_s: np.ndarray) -> np.ndarray:
        return np.full(np.shape(t_s), float(self.separation_nm))


class ForceCurveSamples(NamedTuple):
    """A force-curve program sampled at given times."""

    separation_nm: np.ndarray
    #: piezo position relative to the start, nm: l(t) − l(0); negative while
    #: the sample is closer than at the start, 0 before and after the ramp.
    z_piezo_nm: np.ndarray
    #: int8: −1 approaching (l decreasing), +1 retracting (l increasing), 0 holding.
    direction: np.ndarray


@dataclass(frozen=True)
class ForceCurve:
    """Approach then retract: hold, ramp down, dwell, ramp up, hold.

    l = ``start_nm`` until ``free_air_s``; it then falls linearly to
    ``turn_nm`` over ``approach_s``, stays there for ``dwell_s``, rises
    linearly back to ``start_nm`` over ``retract_s`` and stays there.

    Parameters
    ----------
    start_nm : float
        Initial (and final) separation, nm.
    turn_nm : float
        Closest separation, nm (may be negative: the sample pressed past
        the undeflected tip position); must be below ``start_nm``.
    free_air_s, approach_s, dwell_s, retract_s : float
        Segment durations, s (approach and retract > 0).

    Notes
    -----
    The piezo signal is z_piezo(t) = l(t) − l(0): it increases with the
    separation (positive = sample moved away from the tip), so an
    approach drives it negative.
    """

    start_nm: float
    turn_nm: float
    free_air_s: float
    approach_s: float
    retract_s: float
    dwell_s: float = 0.0

    def __post_init__(self) -> None:
        for name in ("start_nm", "turn_nm"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value)):
                raise ConfigError(f"{name}={value!r} must be a finite number")
        if not self.turn_nm < self.start_nm:
            raise ConfigError(f"turn_nm={self.turn_nm!r} must be below start_nm={self.start_nm!r}")
        _check("free_air_s", self.free_air_s)
        _check("approach_s", self.approach_s, exclusive=True)
        _check("retract_s", self.retract_s, exclusive=True)
        _check("dwell_s", self.dwell_s)

    @property
    def initial_hold_s(self) -> float:
        return float(self.free_air_s)

    @property
    def end_s(self) -> float:
        """End of the retract ramp, s."""
        return self.free_air_s + self.approach_s + self.dwell_s + self.retract_s

    def __call__(self, t_s: np.ndarray) -> np.ndarray:
        t = np.asarray(t_s, dtype=np.float64)
        t1 = self.free_air_s + self.approach_s
        t2 = t1 + self.dwell_s
        times = np.array([self.free_air_s, t1, t2, self.end_s])
        levels = np.array([self.start_nm, self.turn_nm, self.turn_nm, self.start_nm], dtype=np.float64)
        return np.interp(t, times, levels)

    def z_piezo_nm(self, t_s: np.ndarray) -> np.ndarray:
        """Piezo position relative to the start, l(t) − l(0), nm."""
        return self(t_s) - self.start_nm

    def direction(self, t_s: np.ndarray) -> np.ndarray:
        """−1 on the approach ramp, +1 on the retract ramp, 0 elsewhere (int8)."""
        t = np.asarray(t_s, dtype=np.float64)
        t1 = self.free_air_s + self.approach_s
        t2 = t1 + self.dwell_s
        out = np.zeros(t.shape, dtype=np.int8)
        out[(t >= self.free_air_s) & (t < t1)] = -1
        out[(t >= t2) & (t < self.end_s)] = 1
        return out

    def sample(self, t_s: np.ndarray) -> ForceCurveSamples:
        """Separation, piezo position and ramp direction at ``t_s``."""
        separation = self(t_s)
        return ForceCurveSamples(separation, separation - self.start_nm, self.direction(t_s))


@dataclass(frozen=True)
class SeparationSteps:
    """Piecewise-constant l: ``levels_nm[k]`` during [start_s + k·dwell_s, start_s + (k+1)·dwell_s).

    The first level holds before ``start_s`` and the last one after the
    final step.
    """

    levels_nm: tuple[float, ...]
    dwell_s: float
    start_s: float = 0.0

    def __post_init__(self) -> None:
        if len(self.levels_nm) < 1:
            raise ConfigError("levels_nm needs at least one level")
        for k, value in enumerate(self.levels_nm):
            if not (isinstance(value, (int, float)) and math.isfinite(value)):
                raise ConfigError(f"levels_nm[{k}]={value!r} must be a finite number")
        _check("dwell_s", self.dwell_s, exclusive=True)
        _check("start_s", self.start_s)

    @property
    def initial_hold_s(self) -> float:
        return float(self.start_s + self.dwell_s) if len(self.levels_nm) > 1 else math.inf

    def __call__(self, t_s: np.ndarray) -> np.ndarray:
        t = np.asarray(t_s, dtype=np.float64)
        levels = np.asarray(self.levels_nm, dtype=np.float64)
        index = np.clip(np.floor((t - self.start_s) / self.dwell_s).astype(np.int64), 0, len(levels) - 1)
        return levels[index]


@dataclass(frozen=True, eq=False)
class LineScan:
    """One pass over a topography profile at constant speed.

    The tip position runs linearly from ``positions_m[0]`` (held before
    ``scan_start_s``) to ``positions_m[-1]`` (held after the scan) and
    l(t) = ``separation_nm`` − h(x(t)), with h linearly interpolated in
    the (``positions_m``, ``heights_nm``) profile: a raised feature brings
    the sample closer to the tip.

    Parameters
    ----------
    separation_nm : float
        Separation over height 0, nm.
    positions_m : array_like
        Strictly increasing positions along the line, m (≥ 2 points).
    heights_nm : array_like
        Topography height at each position, nm.
    scan_start_s, scan_duration_s : float
        When the scan starts and how long it takes, s.
    """

    separation_nm: float
    positions_m: np.ndarray
    heights_nm: np.ndarray
    scan_start_s: float
    scan_duration_s: float

    def __post_init__(self) -> None:
        positions = np.array(self.positions_m, dtype=np.float64)
        heights = np.array(self.heights_nm, dtype=np.float64)
        if positions.ndim != 1 or positions.shape != heights.shape or positions.size < 2:
            raise ConfigError(
                f"positions_m and heights_nm must be 1-D of equal length >= 2, got shapes "
                f"{positions.shape} and {heights.shape}"
            )
        if not (np.all(np.isfinite(positions)) and np.all(np.isfinite(heights))):
            raise ConfigError("positions_m and heights_nm must be finite")
        if not np.all(np.diff(positions) > 0):
            raise ConfigError("positions_m must be strictly increasing")
        if not (isinstance(self.separation_nm, (int, float)) and math.isfinite(self.separation_nm)):
            raise ConfigError(f"separation_nm={self.separation_nm!r} must be a finite number")
        _check("scan_start_s", self.scan_start_s)
        _check("scan_duration_s", self.scan_duration_s, exclusive=True)
        positions.flags.writeable = False
        heights.flags.writeable = False
        object.__setattr__(self, "positions_m", positions)
        object.__setattr__(self, "heights_nm", heights)

    @property
    def initial_hold_s(self) -> float:
        return float(self.scan_start_s)

    def position_m(self, t_s: np.ndarray) -> np.ndarray:
        """Tip position along the line at ``t_s``, m."""
        t = np.asarray(t_s, dtype=np.float64)
        frac = np.clip((t - self.scan_start_s) / self.scan_duration_s, 0.0, 1.0)
        return self.positions_m[0] + frac * (self.positions_m[-1] - self.positions_m[0])

    def height_nm(self, t_s: np.ndarray) -> np.ndarray:
        """Topography under the tip at ``t_s``, nm."""
        return np.interp(self.position_m(t_s), self.positions_m, self.heights_nm)

    def __call__(self, t_s: np.ndarray) -> np.ndarray:
        return self.separation_nm - self.height_nm(t_s)
