"""Times and periods from parameters, turned into sample counts only when they are in range.

A parameter in seconds (a window, a warm-up, a free-air segment) or in drive
periods becomes a number of samples at the capture's rate.  ``round`` of an
infinite product raised ``OverflowError``, and a finite but absurd one
(``--free-air 0:1e300``, ``--decimate 99999999999999``) made loops, arrays
or integers no kernel can hold.  Every such conversion goes through here:
the product is checked to be finite and at most :data:`MAX_SAMPLES` before
it is converted, and the refusal names the parameter, its value and the
rate it met.
"""

from __future__ import annotations

import math

from afmtool.errors import ConfigError, InputError

__all__ = ["MAX_SAMPLES", "check_count", "sample_count", "interval_samples"]

#: More samples than any capture holds (2 MHz for 15 years); exact in float64 and within int64.
MAX_SAMPLES = 10**15


def sample_count(
    value: float, samples_per_unit: float, name: str, *, minimum: int = 0, ceil: bool = False, per: str = "s"
) -> int:
    """``max(minimum, round(value * samples_per_unit))`` (``ceil`` if asked), refused unless finite and in [0, MAX_SAMPLES].

    Parameters
    ----------
    value : float
        The parameter: seconds (``samples_per_unit`` is the sample rate, Hz)
        or drive periods (``samples_per_unit`` is samples per period).
    samples_per_unit : float
        Samples per unit of ``value``.
    name : str
        How the message names the parameter (``warmup_s``, ``--free-air``).
    minimum : int
        The fewest samples the caller can use: a shorter time gives this many.
    ceil : bool
        Round up instead of to the nearest.
    per : str
        The unit of ``value``, for the message (``s``, ``drive period``).

    Raises
    ------
    ConfigError
        The product is not finite, or outside ``[0, MAX_SAMPLES]``.
    """
    count = float(value) * float(samples_per_unit)
    if not (math.isfinite(count) and 0 <= count <= MAX_SAMPLES):
        raise ConfigError(
            f"{name}={value!r} is {count:.4g} samples (at {samples_per_unit:.6g} samples per {per}); "
            f"it must be between 0 and {MAX_SAMPLES:.0e} samples"
        )
    return max(minimum, math.ceil(count) if ceil else round(count))


def check_count(count: float, name: str, value: object) -> float:
    """``count`` (samples, not yet rounded) if finite and in [0, MAX_SAMPLES]; else ConfigError naming ``name=value``."""
    if not (math.isfinite(count) and 0 <= count <= MAX_SAMPLES):
        raise ConfigError(f"{name}={value!r} is {count:.4g} samples; it must be between 0 and {MAX_SAMPLES:.0e} samples")
    return count


def interval_samples(
    interval: tuple[float, float], sample_rate_hz: float, option: str, n_samples: int | None = None
) -> tuple[int, int]:
    """A START:END interval (s) as samples ``[start, end)``, refused past the capture's end.

    Raises
    ------
    ConfigError
        START or END is not finite or lies beyond :data:`MAX_SAMPLES`.
    InputError
        END lies past the capture's last sample (``n_samples``, when known).
    """
    start_s, end_s = interval
    text = f"{start_s:g}:{end_s:g}"
    start = sample_count(start_s, sample_rate_hz, f"{option} {text}: START")
    end = sample_count(end_s, sample_rate_hz, f"{option} {text}: END")
    if n_samples is not None and end > n_samples:
        raise InputError(
            f"{option} {text} s ends at sample {end:,}, past the capture's {n_samples:,} samples "
            f"({n_samples / sample_rate_hz:.6g} s at {sample_rate_hz:,.6g} Hz)"
        )
    return start, end
