"""Where REEP's f0′ and Q′ can be trusted: the per-sample validity flags of ``afmtool reep``.

REEP fits a linear second-order model (eq. 3.40) in a window of 1/(1 − λ)
samples.  Three things make a fitted (b1, b0) meaningless, each a bit of the
``flag`` series in ``reep.h5`` (0 = valid):

* :data:`FLAG_NOT_UNDERDAMPED` (1): (b1, b0) outside the under-damped region
  0 < b0 < 1, |b1| < 2√b0, where eq. 3.48 has no (f0′, Q′) (NOTES.md);
* :data:`FLAG_LOW_AMPLITUDE` (2): the oscillation amplitude at the drive is
  below ``min_amplitude_fraction`` of the free amplitude.  The regressors
  then carry little but noise: the bias compensation subtracts σ²R⁻¹θ with
  R ≈ A²/2, so its error, and the estimate's variance, grow as (σ/A)²;
* :data:`FLAG_HIGH_SIGMA2` (4): σ̂² above ``max_sigma2_ratio`` times its
  free-air level.  σ̂² is the window's residual variance over (1 + θᵀθ)
  (eq. 3.39); far above the measurement noise it says the linear model does
  not describe the data (impacts on the repulsive wall, harmonics, a
  transient faster than the window).

The free-air levels come from the capture's own free-air segment, by the
same estimators (REEP with the same λ and regressors, and the lock-in):
medians after their start-up.  Flagged samples are NaN in the summaries,
force-curve tables and images of f0′ and Q′; ``reep.h5`` keeps the fitted
values and the flag.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

__all__ = [
    "FLAG_NOT_UNDERDAMPED",
    "FLAG_LOW_AMPLITUDE",
    "FLAG_HIGH_SIGMA2",
    "FLAG_REASONS",
    "FreeAirLevels",
    "ValidityLimits",
    "free_air_levels",
    "validity_flags",
    "FlagCounter",
]

FLAG_NOT_UNDERDAMPED = 1
FLAG_LOW_AMPLITUDE = 2
FLAG_HIGH_SIGMA2 = 4

#: Report keys and the warning text of each flag bit.
FLAG_REASONS = {
    FLAG_NOT_UNDERDAMPED: ("not_underdamped", "(b1, b0) outside the under-damped region of eq. 3.48"),
    FLAG_LOW_AMPLITUDE: ("low_amplitude", "amplitude below {min_amplitude_fraction:g} of the free amplitude"),
    FLAG_HIGH_SIGMA2: ("high_sigma2", "sigma^2 above {max_sigma2_ratio:g} times its free-air level"),
}


@dataclass(frozen=True)
class ValidityLimits:
    """Thresholds of the flags (module docstring).  0 switches a check off.

    Attributes
    ----------
    min_amplitude_fraction : float
        Lowest trusted amplitude, as a share of the free amplitude.
    max_sigma2_ratio : float
        Highest trusted σ̂², as a multiple of its free-air level.
    """

    min_amplitude_fraction: float
    max_sigma2_ratio: float


class FreeAirLevels(NamedTuple):
    """Free-air references of the flags.

    Attributes
    ----------
    amplitude : float or None
        Free amplitude at the drive, deflection units (None: unknown, the
        amplitude check is off).
    sigma2 : float or None
        REEP's σ̂² in free air, deflection units² (None: the σ² check is off).
    source : str
        Where they came from: ``"free-air segment"``, ``"metadata"`` or ``"none"``.
    """

    amplitude: float | None
    sigma2: float | None
    source: str

    def as_dict(self) -> dict:
        return {"amplitude": self.amplitude, "sigma2": self.sigma2, "source": self.source}


def free_air_levels(sigma2: np.ndarray, amplitude: np.ndarray, settled: int) -> FreeAirLevels:
    """Medians of REEP's σ̂² and the lock-in amplitude over a free-air segment, after ``settled`` samples.

    Parameters
    ----------
    sigma2, amplitude : numpy.ndarray
        σ̂²(n) (deflection units²) and amplitude (deflection units) over the segment.
    settled : int
        Leading samples to leave out (the start-up of both estimators).
    """
    s2 = sigma2[settled:]
    s2 = s2[np.isfinite(s2)]
    amp = amplitude[settled:]
    amp = amp[np.isfinite(amp)]
    return FreeAirLevels(
        float(np.median(amp)) if amp.size else None,
        float(np.median(s2)) if s2.size else None,
        "free-air segment",
    )


def validity_flags(
    underdamped: np.ndarray, amplitude: np.ndarray, sigma2: np.ndarray, levels: FreeAirLevels, limits: ValidityLimits
) -> np.ndarray:
    """The flag bits of every sample (uint8, 0 = f0′ and Q′ valid).

    Parameters
    ----------
    underdamped : numpy.ndarray of bool
        Whether (b1, b0) is in the under-damped region (the ``valid`` of
        :func:`afmtool.models.discretisation.resonance_from_denominator`).
    amplitude : numpy.ndarray
        Lock-in amplitude at the drive, deflection units.
    sigma2 : numpy.ndarray
        REEP's σ̂², deflection units² (NaN in the start-up: not flagged).
    levels : FreeAirLevels
    limits : ValidityLimits
    """
    flags = np.where(underdamped, 0, FLAG_NOT_UNDERDAMPED).astype(np.uint8)
    if levels.amplitude and limits.min_amplitude_fraction > 0:
        flags |= np.where(amplitude < limits.min_amplitude_fraction * levels.amplitude, FLAG_LOW_AMPLITUDE, 0).astype(
            np.uint8
        )
    if levels.sigma2 and limits.max_sigma2_ratio > 0:
        flags |= np.where(sigma2 > limits.max_sigma2_ratio * levels.sigma2, FLAG_HIGH_SIGMA2, 0).astype(np.uint8)
    return flags


@dataclass
class FlagCounter:
    """Counts of flagged samples, in all and by reason (a sample may have several)."""

    total: int = 0
    flagged: int = 0
    by_bit: dict = None

    def __post_init__(self) -> None:
        self.by_bit = {bit: 0 for bit in FLAG_REASONS}

    def add(self, flags: np.ndarray) -> None:
        self.total += int(flags.size)
        self.flagged += int(np.count_nonzero(flags))
        for bit in FLAG_REASONS:
            self.by_bit[bit] += int(np.count_nonzero(flags & bit))

    def as_dict(self) -> dict:
        return {
            "samples": self.total,
            "flagged": self.flagged,
            "fraction": self.flagged / self.total if self.total else 0.0,
            **{FLAG_REASONS[bit][0]: count for bit, count in self.by_bit.items()},
        }

    def warnings(self, limits: ValidityLimits) -> list[str]:
        """One warning per reason that flagged something, saying why and how many."""
        out = []
        for bit, count in self.by_bit.items():
            if count:
                reason = FLAG_REASONS[bit][1].format(
                    min_amplitude_fraction=limits.min_amplitude_fraction, max_sigma2_ratio=limits.max_sigma2_ratio
                )
                out.append(
                    f"{count} of {self.total} output samples ({count / self.total:.1%}) flagged: {reason}; "
                    "their f0' and Q' cannot be trusted and are NaN in the summary, force curves and images "
                    "(reep.h5 keeps them, with 'flag')"
                )
        return out
