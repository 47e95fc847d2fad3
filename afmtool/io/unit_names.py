"""Instruments' long unit names and the symbols afmtool writes for them.

This renames, it never converts: ``"Volts"`` becomes ``"V"``, and a value in
``"mV"`` stays in mV.  Converting to afmtool's internal units happens once,
where a capture is opened for an analysis.
"""

from __future__ import annotations

__all__ = ["UNIT_SYMBOLS", "unit_symbol"]

#: Long unit names (as NI DAQmx, scopes and LabOne write them) and their symbols.
UNIT_SYMBOLS = {
    "volt": "V",
    "volts": "V",
    "amp": "A",
    "amps": "A",
    "ampere": "A",
    "amperes": "A",
    "meter": "m",
    "meters": "m",
    "metre": "m",
    "metres": "m",
    "second": "s",
    "seconds": "s",
    "newton": "N",
    "newtons": "N",
    "hertz": "Hz",
    "degree": "deg",
    "degrees": "deg",
    "deg c": "degC",
}


def unit_symbol(name: str) -> str:
    """The symbol for a long unit name (case-insensitive), else ``name`` stripped."""
    name = name.strip()
    return UNIT_SYMBOLS.get(name.lower(), name)
