"""How long a recursion must run before its past no longer shows: the warm-up of a split capture.

A capture is processed in parallel by starting each chunk's recursions
from a fresh state W samples early (:mod:`afmtool.pipeline`).  W is the
number of samples after which the influence of the state at the start has
decayed by a factor ``residual``:

- exponential forgetting with factor λ weighs the start by λⁿ, so
  W = ⌈ln(residual)/ln λ⌉ (EW-RLS, eq. 3.39);
- a linear recursion (a filter, an observer's error) decays as rⁿ with r
  its largest pole radius, so W = ⌈ln(residual)/ln r⌉.

The default residual, 1e-13, leaves the split result within about 1e-12 of
the sequential one before amplification by the conversion to f0′ and Q′;
``tests/test_split.py`` checks 1e-9 end to end.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["DEFAULT_RESIDUAL", "forgetting_lead", "pole_lead", "sos_lead"]

#: The factor by which the start-up state must have decayed.
DEFAULT_RESIDUAL = 1e-13


def forgetting_lead(lam: float, residual: float = DEFAULT_RESIDUAL) -> int | None:
    """Samples until λⁿ < ``residual``; None for λ = 1 (a growing window never forgets)."""
    if not 0.0 < lam <= 1.0:
        raise ValueError(f"{lam=} must be in (0, 1]")
    if lam == 1.0:
        return None
    return math.ceil(math.log(residual) / math.log(lam))


def pole_lead(poles, residual: float = DEFAULT_RESIDUAL) -> int | None:
    """Samples until rⁿ < ``residual`` for the largest pole radius r; None if r >= 1 (no decay)."""
    radius = float(np.max(np.abs(np.asarray(poles)))) if np.size(poles) else 0.0
    if radius >= 1.0:
        return None
    if radius == 0.0:
        return 0
    return math.ceil(math.log(residual) / math.log(radius))


def sos_lead(sos: np.ndarray, residual: float = DEFAULT_RESIDUAL) -> int | None:
    """:func:`pole_lead` of second-order sections (rows [b0, b1, b2, 1, a1, a2]).

    A cascade's impulse response decays as its slowest pole's rⁿ times a
    polynomial in n for repeated poles; a factor 2 covers that for the
    low orders used here.
    """
    poles = np.concatenate([np.roots(row[3:]) for row in np.atleast_2d(sos)])
    lead = pole_lead(poles, residual)
    return None if lead is None else 2 * lead
