"""Argument checks shared by the spectral estimators and fits (frequency responses, stepped sine, fits).

Split out of :mod:`afmtool.estimators.frequency_response` (issue 29, item 6).
"""

from __future__ import annotations

import math
import numbers

import numpy as np

from afmtool.errors import ConfigError, InputError

__all__ = ["is_real", "check_positive", "check_int", "checked_signal", "signal_pair", "frozen", "window_array", "segmentation"]


def is_real(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


def check_positive(name: str, value) -> float:
    if not (is_real(value) and math.isfinite(value) and value > 0):
        raise ConfigError(f"{name}={value!r} must be a finite number > 0")
    return float(value)


def check_int(name: str, value, minimum: int) -> int:
    if not (isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_)) and value >= minimum):
        raise ConfigError(f"{name}={value!r} must be an integer >= {minimum}")
    return int(value)


def checked_signal(name: str, values) -> np.ndarray:
    """A 1-D finite float64 copy of ``values`` (the caller's array is not touched)."""
    try:
        arr = np.array(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a 1-D array of numbers") from None
    if arr.ndim != 1:
        raise InputError(f"{name} must be 1-D, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        bad = int(np.flatnonzero(~np.isfinite(arr))[0])
        raise InputError(f"{name} has a non-finite value at index {bad} ({arr[bad]!r})")
    return arr


def signal_pair(x, y) -> tuple[np.ndarray, np.ndarray]:
    xa, ya = checked_signal("x", x), checked_signal("y", y)
    if xa.shape != ya.shape:
        raise InputError(f"x and y must have the same length, got {xa.size} and {ya.size}")
    return xa, ya


def frozen(arr: np.ndarray) -> np.ndarray:
    arr = np.ascontiguousarray(arr)
    arr.setflags(write=False)
    return arr


def window_array(window, nperseg: int) -> np.ndarray:
    if isinstance(window, str) or isinstance(window, tuple):
        import scipy.signal

        try:
            return scipy.signal.get_window(window, nperseg)
        except ValueError as exc:
            raise ConfigError(f"window={window!r} is not a scipy.signal window ({exc})") from None
    win = np.asarray(window, dtype=np.float64)
    if win.shape != (nperseg,) or not np.all(np.isfinite(win)):
        raise ConfigError(f"window must be a window name or {nperseg=} finite values, got shape {win.shape}")
    return win


def segmentation(nperseg, noverlap, detrend) -> tuple[int, int]:
    nperseg = check_int("nperseg", nperseg, 2)
    noverlap = nperseg // 2 if noverlap is None else check_int("noverlap", noverlap, 0)
    if noverlap >= nperseg:
        raise ConfigError(f"{noverlap=} must be < {nperseg=}")
    if not (detrend is False or (isinstance(detrend, str) and detrend in ("constant", "linear"))):
        raise ConfigError(f"detrend={detrend!r} must be 'constant', 'linear' or False")
    return nperseg, noverlap
