"""The parameters a text export writes above its table, mapped into capture metadata.

Vendor exports (AFM Workshop, NT-MDT, scope and DAQ software) start with
``key: value`` lines, often with the unit in the key (``Force Constant, nN/nm:
1.0``, ``Sample rate (kHz) = 500``).  Where a key names something afmtool uses,
its value is converted once, here, into the metadata's units:

===============================================  ==============================================
key (any case; the unit after a comma or in ())   metadata
===============================================  ==============================================
spring constant, force constant, k               cantilever.spring_constant_n_per_m (N/m, nN/nm, pN/nm, mN/m)
sensitivity, deflection sensitivity, invols      cantilever.deflection_sensitivity_nm_per_v (nm/V, m/V, um/V, nm/mV)
light lever gain (mV/nm, V/nm, V/m)              cantilever.deflection_sensitivity_nm_per_v, as its inverse
resonance frequency, f0, free resonance          cantilever.f0_hz (Hz, kHz, MHz)
q, quality factor, q factor                      cantilever.q
drive frequency                                  drive.frequency_hz (Hz, kHz, MHz)
sample rate, sampling rate, sampling frequency   the sample rate (Hz, kHz, MHz)
sample interval, sampling interval, time step    the sample rate, as its inverse (s, ms, us, ns)
===============================================  ==============================================

Every key and value is also kept, bounded, under ``instrument.header``.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from typing import NamedTuple

__all__ = ["PreambleMetadata", "preamble_metadata", "split_key_unit"]

#: Most preamble entries copied into ``instrument.header``.
MAX_HEADER_ENTRIES = 200

_KEY_UNIT = re.compile(r"^(?P<name>.*?)\s*(?:,\s*(?P<comma>[^,]+)|[\(\[](?P<bracket>[^\)\]]*)[\)\]])\s*$")

# name -> (metadata path or "rate"/"interval", {unit: factor to the metadata's unit}); "" is a bare number
_FREQUENCY = {"": 1.0, "hz": 1.0, "khz": 1e3, "mhz": 1e6}
_RULES = {
    **dict.fromkeys(("spring constant", "force constant", "k", "spring_constant", "spring constant k",
                     "cantilever spring constant", "spring_constant_n_per_m"),
                    ("cantilever.spring_constant_n_per_m", {"": 1.0, "n/m": 1.0, "nn/nm": 1.0, "pn/nm": 1e-3,
                                                             "mn/m": 1e-3})),
    **dict.fromkeys(("sensitivity", "deflection sensitivity", "invols", "inverse optical lever sensitivity",
                     "deflection_sensitivity_nm_per_v"),
                    ("cantilever.deflection_sensitivity_nm_per_v", {"": 1.0, "nm/v": 1.0, "m/v": 1e9, "um/v": 1e3,
                                                                     "µm/v": 1e3, "nm/mv": 1e3})),
    "light lever gain": ("gain", {"mv/nm": 1e-3, "v/nm": 1.0, "v/m": 1e-9}),  # V per nm; the InvOLS is its inverse
    **dict.fromkeys(("resonance frequency", "f0", "free resonance", "resonant frequency"), ("cantilever.f0_hz", _FREQUENCY)),
    **dict.fromkeys(("q", "quality factor", "q factor"), ("cantilever.q", {"": 1.0})),
    **dict.fromkeys(("drive frequency",), ("drive.frequency_hz", _FREQUENCY)),
    **dict.fromkeys(("sample rate", "sampling rate", "sampling frequency", "sample_rate_hz", "sample frequency",
                     "acquisition rate"), ("rate", _FREQUENCY)),
    **dict.fromkeys(("sample interval", "sampling interval", "time step", "dt", "sample period"),
                    ("interval", {"": 1.0, "s": 1.0, "ms": 1e-3, "us": 1e-6, "µs": 1e-6, "ns": 1e-9})),
}


class PreambleMetadata(NamedTuple):
    """What a preamble gives: metadata (typed keys set), and the sample rate (Hz) if it states one."""

    metadata: dict
    sample_rate_hz: float | None


def split_key_unit(key: str) -> tuple[str, str]:
    """``"Force Constant, nN/nm"`` -> ``("force constant", "nn/nm")``; ``"Rate (kHz)"`` -> ``("rate", "khz")``."""
    match = _KEY_UNIT.match(key.strip())
    if match and match.group("name").strip():
        unit = match.group("comma") or match.group("bracket") or ""
        return match.group("name").strip().lower(), unit.strip().lower()
    return key.strip().lower(), ""


def _number(text: str) -> float | None:
    try:
        value = float(text.strip().replace(",", ".") if text.count(",") == 1 and "." not in text else text.strip())
    except ValueError:
        return None
    return value if math.isfinite(value) and value > 0 else None


def preamble_metadata(preamble: Mapping[str, str], vendor_format: str | None) -> PreambleMetadata:
    """Map a preamble's known keys into metadata (see the module's table).

    With ``vendor_format``, the preamble is also kept as text under ``instrument.header``;
    without, only what maps is returned (comment lines of an afmtool CSV).
    """
    metadata: dict = {}
    rate = None
    for key, text in preamble.items():
        name, unit = split_key_unit(key)
        rule = _RULES.get(name)
        value = _number(text) if rule is not None else None
        if value is None or unit not in rule[1]:
            continue
        target, factor = rule[0], rule[1][unit] * value
        if target == "rate":
            rate = rate or factor
        elif target == "interval":
            rate = rate or 1.0 / factor
        elif target == "gain":
            metadata.setdefault("cantilever", {}).setdefault("deflection_sensitivity_nm_per_v", 1.0 / factor)
        else:
            family, field = target.split(".")
            metadata.setdefault(family, {}).setdefault(field, factor)
    if vendor_format is not None:
        metadata["instrument"] = {"vendor_format": vendor_format}
        header = dict(list(preamble.items())[:MAX_HEADER_ENTRIES])
        if header:
            metadata["instrument"]["header"] = header
    return PreambleMetadata(metadata, rate)
