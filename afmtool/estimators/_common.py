"""Shared helpers of the estimator kernels: compile options and input checks."""

from __future__ import annotations

import math

import numpy as np

from afmtool.errors import ConfigError, InputError

__all__ = ["JIT_OPTIONS", "as_signal", "check_numerator"]

#: Compile options of every kernel in the tree, kept in one constant (a test
#: checks that every ``@njit`` uses it, and only it).
#:
#: * ``cache``: compiled kernels are kept on disk, so a command starts in
#:   a fraction of a second after the first run.
#: * ``nogil``: kernels release the GIL, so the read-ahead and side-kernel
#:   threads of the streaming commands run beside them.
#: * ``error_model="numpy"``: a division by zero gives inf or NaN, as IEEE 754
#:   and numpy say, instead of raising ZeroDivisionError from inside a
#:   kernel; the wrappers validate their arguments, and a NaN sample must
#:   flow through a recursion the way it does through the plain-Python
#:   references.
#: * No ``fastmath``: NaN and inf must propagate, and ``contract``/``reassoc``
#:   would make the numba results differ from the plain-Python references.
#:
#: Never change it at run time: the on-disk cache is keyed on these options.
JIT_OPTIONS = {"cache": True, "nogil": True, "error_model": "numpy"}


def as_signal(name: str, x) -> np.ndarray:
    """A 1-D float64 C-contiguous view or copy of ``x``; the input is never modified."""
    try:
        a = np.ascontiguousarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a 1-D array of numbers") from None
    if a.ndim != 1:
        raise InputError(f"{name} must be 1-D, got shape {a.shape}")
    return a


def check_numerator(numerator) -> tuple[float, float, float]:
    try:
        a2, a1, a0 = (float(v) for v in numerator)
    except (TypeError, ValueError):
        raise ConfigError(f"numerator={numerator!r} must be three numbers (a2, a1, a0)") from None
    if not all(map(math.isfinite, (a2, a1, a0))):
        raise ConfigError(f"numerator={numerator!r} must be finite")
    return a2, a1, a0
