"""How afmtool writes a number for a reader: one rule for the terminal, report.json and the HTML page.

With a standard deviation the deviation keeps two significant digits and
the value is rounded to the same decimal (``80318.4 ± 1.3``, ``79700 ± 1300``); where both
are below 1e-3 or from 1e6 up they share a power of ten
(``(1.24318 ± 0.00021)e-06``).  Without one, a value keeps four
significant digits, and never loses a digit left of the decimal point
(``0.4151``, ``80318``, ``2.192``).  Integers and text are shown as they
are, booleans as yes/no, a missing or non-finite number as a dash.

This module imports nothing heavy: ``afmtool --help`` and the end-of-run
headline use it.
"""

from __future__ import annotations

import math

__all__ = ["DIGITS_WITHOUT_STD", "format_measurement", "format_value", "format_with_units"]

#: Significant digits of a number that comes without an uncertainty.
DIGITS_WITHOUT_STD = 4


def _plain(value: float) -> str:
    """``value`` to :data:`DIGITS_WITHOUT_STD` significant digits (exponent outside [1e-3, 1e6))."""
    if value == 0:
        return "0"
    magnitude = abs(value)
    if 1e-3 <= magnitude < 1e6:
        decimals = max(0, DIGITS_WITHOUT_STD - 1 - int(math.floor(math.log10(magnitude))))
        text = f"{value:.{decimals}f}"
        # rounding can carry into a new digit (9.9996 -> 10.000): one decimal too many then
        if decimals and len(text.lstrip("-").replace(".", "").lstrip("0")) > DIGITS_WITHOUT_STD:
            text = f"{value:.{decimals - 1}f}"
        return text
    return f"{value:.{DIGITS_WITHOUT_STD - 1}e}"


def format_value(value) -> str:
    """A value without an uncertainty, by the rule above."""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if value is None:
        return "—"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return _plain(value) if math.isfinite(value) else "—"
    return str(value)


def format_measurement(value, std=None) -> str:
    """``value ± std`` (or ``value`` alone) by the rule above, without units."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return format_value(value)
    usable = isinstance(std, (int, float)) and not isinstance(std, bool) and math.isfinite(std) and std > 0
    if not usable or not math.isfinite(value):
        return format_value(value)
    exponent = 0
    magnitude = max(abs(value), std)
    if magnitude < 1e-3 or magnitude >= 1e6:  # a shared power of ten: (1.24318 ± 0.00021)e-06
        exponent = int(math.floor(math.log10(magnitude)))
        value, std = value / 10.0**exponent, std / 10.0**exponent
    decimals = 1 - int(math.floor(math.log10(std)))
    if decimals >= 0:
        text = f"{value:.{decimals}f} ± {std:.{decimals}f}"
    else:  # a deviation of 100 or more: both rounded to its second digit (79700 ± 1300)
        text = f"{round(value, decimals):.0f} ± {round(std, decimals):.0f}"
    return f"({text})e{exponent:+03d}" if exponent else text


def format_with_units(value, std=None, units: str = "") -> str:
    """``format_measurement`` followed by the units, if any: ``80318.4 ± 1.3 Hz``."""
    number = format_measurement(value, std)
    return f"{number} {units}" if units and number != "—" else number
