"""Running count, mean, spread and range of a stream of values, one numba pass per block.

The streaming commands summarise tens of millions of output rows (REEP
keeps one row per drive period).  The state is shifted sums,

    n,  K,  S1 = Σ (x − K),  S2 = Σ (x − K)²,  min,  max,

with K the first value added: then mean = K + S1/n and
Σ (x − mean)² = S2 − S1²/n, and the sums stay of the size of the spread
rather than of x² (f0′ ≈ 3e5 Hz with a spread of 1 Hz would lose the
variance to rounding in Σ x²).  A row is added where it is finite and, if
flags are given, its flag is 0.  The result does not depend on how the
stream is cut into blocks.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from afmtool.jit import JIT_OPTIONS

__all__ = ["RunningMoments"]

_NO_FLAGS = np.zeros(0, dtype=np.uint8)


@njit(**JIT_OPTIONS)
def _moments_kernel(x, flags, start, stop, state):
    """Adds the finite x[start:stop] whose flag is 0 (no flags: all) to state = [n, K, S1, S2, min, max]."""
    n, shift, s1, s2, low, high = state[0], state[1], state[2], state[3], state[4], state[5]
    use_flags = flags.shape[0] > 0
    for i in range(start, stop):
        v = x[i]
        if (use_flags and flags[i] != 0) or not math.isfinite(v):
            continue
        if n == 0.0:
            shift = v
        d = v - shift
        n += 1.0
        s1 += d
        s2 += d * d
        low = min(low, v)
        high = max(high, v)
    state[0], state[1], state[2], state[3], state[4], state[5] = n, shift, s1, s2, low, high


class RunningMoments:
    """Count, mean, standard deviation, minimum and maximum of the values added so far."""

    def __init__(self) -> None:
        self._state = np.array([0.0, 0.0, 0.0, 0.0, math.inf, -math.inf])

    def add(self, values: np.ndarray, flags: np.ndarray | None = None, start: int = 0, stop: int | None = None) -> None:
        """Adds ``values[start:stop]`` where finite and (with ``flags``, uint8) the flag is 0."""
        x = np.ascontiguousarray(values, dtype=np.float64)
        stop = x.shape[0] if stop is None else min(int(stop), x.shape[0])
        mask = _NO_FLAGS if flags is None else np.ascontiguousarray(flags, dtype=np.uint8)
        if flags is not None and mask.shape[0] != x.shape[0]:
            raise ValueError(f"flags has {mask.shape[0]} rows, values {x.shape[0]}")
        if stop > start:
            _moments_kernel(x, mask, int(start), stop, self._state)

    @property
    def count(self) -> int:
        return int(self._state[0])

    @property
    def mean(self) -> float:
        n, shift, s1 = self._state[0], self._state[1], self._state[2]
        return float(shift + s1 / n) if n else math.nan

    def sum_of_squares(self) -> float:
        """Σ (x − mean)² over the values added."""
        n, s1, s2 = self._state[0], self._state[2], self._state[3]
        return float(max(s2 - s1 * s1 / n, 0.0)) if n else math.nan

    def std(self, ddof: int = 0) -> float | None:
        """√(Σ (x − mean)² / (n − ddof)); None with n ≤ ddof."""
        n = self.count
        return math.sqrt(self.sum_of_squares() / (n - ddof)) if n > ddof else None

    @property
    def low(self) -> float:
        return float(self._state[4])

    @property
    def high(self) -> float:
        return float(self._state[5])
