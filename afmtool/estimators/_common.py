"""Shared helpers of the estimator kernels: input checks (the compile options are :data:`afmtool.jit.JIT_OPTIONS`)."""

from __future__ import annotations

import math

import numpy as np

from afmtool.errors import ConfigError, InputError

__all__ = ["as_signal", "check_numerator"]

def as_signal(name: str, x) -> np.ndarray:
    """A 1-D float64 C-contiguous view or copy of ``x``; the input is never modified."""
    try:
        a = np.ascontiguousarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a 1-D array of numbers") from None
    if a.ndim != 1:
        raise InputError(f"{name} must be 1-D, got shape {a.shape}")
    return a


#: A channel whose RMS is below this cannot be regressed on: its squares (about 1e-300) come
#: within a few digits of the smallest normal double, 2.2e-308, and sums of products of
#: such values lose their digits or underflow to zero (a singular regression).
RESOLVABLE_RMS = 1e-150


def channel_rms(values: np.ndarray) -> float:
    """RMS of finite ``values``, computed without squaring them (so tiny values do not underflow)."""
    a = np.asarray(values, dtype=np.float64)
    if a.size == 0:
        return 0.0
    peak = float(np.max(np.abs(a)))
    if not (peak > 0 and math.isfinite(peak)):
        return peak
    scaled = a / peak
    return peak * math.sqrt(float(np.mean(scaled * scaled)))


def check_resolvable(name: str, values: np.ndarray, what: str) -> float:
    """Refuse a channel too small for ``what`` (a regression) to resolve; return its RMS.

    Raises
    ------
    InputError
        Its RMS is below :data:`RESOLVABLE_RMS` (or it is all zeros): named
        with its scale, the cause, and the way out (its units).
    """
    rms = channel_rms(values)
    if rms == 0:
        raise InputError(f"{name} is all zeros; {what} needs a signal")
    if not rms >= RESOLVABLE_RMS:
        raise InputError(
            f"{name}: RMS {rms:.3g} (in the units afmtool works in) is below {RESOLVABLE_RMS:g}: its squares underflow "
            f"double precision, so {what} is singular; check the channel's units (--units {name}=UNIT)"
        )
    return rms


def check_numerator(numerator) -> tuple[float, float, float]:
    try:
        a2, a1, a0 = (float(v) for v in numerator)
    except (TypeError, ValueError):
        raise ConfigError(f"numerator={numerator!r} must be three numbers (a2, a1, a0)") from None
    if not all(map(math.isfinite, (a2, a1, a0))):
        raise ConfigError(f"numerator={numerator!r} must be finite")
    return a2, a1, a0
