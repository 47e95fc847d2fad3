"""Does REEP's free-air f0′ agree with the lever's f0? (issue 28, item 4)

In the free-air segment the tip feels no force, so REEP's f0′ must read the
free-air model's f0 within its own scatter.  A free-air f0′ far from it says
that the run's premise is broken (the drive far off resonance, where a
three-sine's lines barely excite the resonance; a wrong f0/Q; an
unmodelled drive path), and then every f0′ on the sample is offset alike:
the headline shows this before any f0′ (:mod:`afmtool.report.headline`).

The deviation is counted in standard deviations of a single f0′ row::

    n_std = |mean(f0′) − f0_ref| / √(s_f0′² + s_ref²)

with s_f0′ REEP's own standard deviation of a row (the mean over the
segment of the per-row ``f0_std_hz``; the rows' scatter where there is none)
and s_ref the reference's stated uncertainty (an ARX fit's ``f0_std_hz``; 0
for metadata or flags).  References: the model REEP runs on, and the
capture metadata's ``cantilever.f0_hz`` when it differs from the model's.
Above ``MAX_DEVIATION_STD`` (5) the check fails.
"""

from __future__ import annotations

import math
from typing import NamedTuple

__all__ = ["MAX_DEVIATION_STD", "F0Reference", "FreeAirF0Check", "free_air_f0_check"]

#: A free-air f0′ farther than this many standard deviations from a reference f0 fails the check.
MAX_DEVIATION_STD = 5.0


class F0Reference(NamedTuple):
    """One f0 the free-air f0′ is held against.

    Attributes
    ----------
    name : str
        ``"model"`` (the free-air model REEP runs on) or ``"metadata"``.
    f0_hz, std_hz : float
        The reference and its standard deviation (0 if none is stated), Hz.
    """

    name: str
    f0_hz: float
    std_hz: float = 0.0


class FreeAirF0Check(NamedTuple):
    """The free-air f0′ against its references (module docstring).

    Attributes
    ----------
    f0_hz, f0_std_hz : float
        Mean and standard deviation of the free-air f0′ rows, Hz.
    reference : F0Reference
        The reference it deviates from most.
    deviation_hz : float
        mean f0′ − reference f0, Hz.
    deviation_std : float
        |deviation| over the combined standard deviation.
    """

    f0_hz: float
    f0_std_hz: float
    reference: F0Reference
    deviation_hz: float
    deviation_std: float

    @property
    def consistent(self) -> bool:
        return self.deviation_std <= MAX_DEVIATION_STD

    def message(self) -> str:
        """One sentence for the warnings and the headline."""
        where = "the lever's f0 in the capture metadata" if self.reference.name == "metadata" else "the free-air model's f0"
        return (f"REEP's free-air f0' {self.f0_hz:.1f} ± {self.f0_std_hz:.1f} Hz is {self.deviation_std:.0f} std "
                f"({self.deviation_hz:+.1f} Hz) from {where}, {self.reference.f0_hz:.1f} Hz: the drive may be far off "
                "resonance, or the model (f0/Q, drive path) wrong; every f0' on the sample is offset alike")

    def as_dict(self) -> dict:
        return {"f0_hz": self.f0_hz, "f0_std_hz": self.f0_std_hz, "reference": self.reference.name,
                "reference_f0_hz": self.reference.f0_hz, "reference_std_hz": self.reference.std_hz,
                "deviation_hz": self.deviation_hz, "deviation_std": self.deviation_std,
                "max_deviation_std": MAX_DEVIATION_STD, "consistent": self.consistent}


def free_air_f0_check(f0_mean_hz: float, f0_std_hz: float, references: list[F0Reference]) -> FreeAirF0Check | None:
    """The free-air f0′ (mean, row std) against ``references``; None when nothing can be compared.

    Parameters
    ----------
    f0_mean_hz, f0_std_hz : float
        Mean and standard deviation of the trusted free-air f0′ rows, Hz.
    references : list of F0Reference
        The f0 values to hold it against (module docstring).
    """
    if not (math.isfinite(f0_mean_hz) and math.isfinite(f0_std_hz)) or not references:
        return None
    worst = None
    for reference in references:
        deviation = f0_mean_hz - reference.f0_hz
        scale = math.hypot(f0_std_hz, reference.std_hz)
        n_std = abs(deviation) / scale if scale > 0 else (0.0 if deviation == 0 else math.inf)
        if worst is None or n_std > worst.deviation_std:
            worst = FreeAirF0Check(f0_mean_hz, f0_std_hz, reference, deviation, n_std)
    return worst
