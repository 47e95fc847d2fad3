"""Channel units, parsed once where a capture is opened, and converted to afmtool's internal units.

Every analysis assumes lengths in nm, voltages in V, currents in µA and
times in s (µA, not A: the canonical current of the thermal-sensor analyses,
:data:`afmtool.analyses.gamma.CANONICAL_UNITS`, whose results are in µA/nm).  :class:`UnitsReader` wraps any reader: it parses each channel's units
(from the file, or from ``--units NAME=UNIT``), refuses a unit it cannot parse
or one of the wrong kind for a canonical channel (a deflection in A), turns a
deflection or z-piezo recorded in V into nm through the InvOLS (``--invols``,
metadata ``cantilever.deflection_sensitivity_nm_per_v``) or the z sensitivity
(``--z-sensitivity``), and scales the chunks as they stream.  A channel
already in its internal unit, or one without units (assumed internal, as
before), is passed through untouched, so the common case costs nothing.

A small table (SI prefixes × a few base units) is enough; pint would cost
0.3 s of start-up for the same answer.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import NamedTuple

from afmtool.errors import ConfigError, InputError
from afmtool.io.capture import CaptureInfo, CaptureReader, ChannelSpec, Chunk, ReaderBase

__all__ = [
    "INTERNAL_UNITS",
    "CHANNEL_KINDS",
    "ParsedUnit",
    "parse_unit",
    "Calibration",
    "ChannelConversion",
    "plan_conversions",
    "UnitsReader",
    "calibration_record",
]

#: The unit each kind of quantity is converted to.
INTERNAL_UNITS: Mapping[str, str] = MappingProxyType(
    {"length": "nm", "voltage": "V", "current": "uA", "time": "s", "frequency": "Hz"}
)
#: The kinds a canonical channel may be recorded in ("voltage" for deflection and
#: z_piezo only through a sensitivity).
CHANNEL_KINDS: Mapping[str, tuple[str, ...]] = MappingProxyType(
    {
        "deflection": ("length", "voltage"),
        "z_piezo": ("length", "voltage"),
        "dither": ("voltage",),
        "v_sub": ("voltage",),
        "v_r": ("voltage",),
        "thermal_current": ("current",),
    }
)

#: SI prefixes as powers of ten (factors are built as 10.0**n, so "m" → "nm" is exactly 1e9).
_PREFIXES = {
    "": 0, "Y": 24, "Z": 21, "E": 18, "P": 15, "T": 12, "G": 9, "M": 6, "k": 3, "h": 2, "da": 1,
    "d": -1, "c": -2, "m": -3, "u": -6, "µ": -6, "μ": -6, "n": -9, "p": -12, "f": -15, "a": -18,
    "z": -21, "y": -24,
}
#: Base symbols that take a prefix, and their kind.
_BASES = {"m": "length", "V": "voltage", "A": "current", "s": "time", "Hz": "frequency", "N": "force", "W": "power"}
#: Whole words and symbols that take no prefix: kind and power of ten to the kind's SI unit.
_WORDS = {
    "metre": ("length", 0), "meter": ("length", 0), "metres": ("length", 0), "meters": ("length", 0),
    "Å": ("length", -10), "angstrom": ("length", -10),
    "volt": ("voltage", 0), "volts": ("voltage", 0),
    "ampere": ("current", 0), "amp": ("current", 0), "amps": ("current", 0),
    "sec": ("time", 0), "seconds": ("time", 0),
    "": ("none", 0), "1": ("dimensionless", 0), "a.u.": ("dimensionless", 0), "au": ("dimensionless", 0),
    "arb": ("dimensionless", 0), "counts": ("dimensionless", 0), "%": ("dimensionless", -2),
    "deg": ("angle", 0), "rad": ("angle", 0), "dB": ("level", 0), "K": ("temperature", 0),
    "degC": ("temperature", 0), "°C": ("temperature", 0),
}
#: Power of ten of each kind's internal unit to SI (nm = 1e-9 m, µA = 1e-6 A).
_INTERNAL_EXPONENT = {"length": -9, "voltage": 0, "current": -6, "time": 0, "frequency": 0}


class ParsedUnit(NamedTuple):
    """A unit string read: its kind (``"length"``, ``"voltage"``...) and its power of ten to SI."""

    kind: str
    exponent: int

    @property
    def si_factor(self) -> float:
        return 10.0**self.exponent


def parse_unit(text: str) -> ParsedUnit:
    """Parse a unit string such as ``"nm"``, ``"µm"``, ``"mV"``, ``"uA"`` or ``"m"``.

    Raises
    ------
    ValueError
        If the text is not a known unit (the caller names the channel).
    """
    unit = text.strip()
    if unit in _WORDS:
        return ParsedUnit(*_WORDS[unit])
    if len(unit) > 3 and unit.lower() in _WORDS:  # "Volts", "METERS"; never for symbols ("mV" is not "MV")
        return ParsedUnit(*_WORDS[unit.lower()])
    for base, kind in _BASES.items():
        if unit.endswith(base) and unit[: -len(base)] in _PREFIXES:
            return ParsedUnit(kind, _PREFIXES[unit[: -len(base)]])
    raise ValueError(f"unknown unit {text!r}")


@dataclass(frozen=True)
class Calibration:
    """How the user asked a capture's channels to be read.

    Attributes
    ----------
    units : mapping of str to str
        ``--units NAME=UNIT``: overrides the file's units of those channels.
    invols_nm_per_v : float or None
        ``--invols``: deflection sensitivity, nm of deflection per V of detector signal.
    z_sensitivity_nm_per_v : float or None
        ``--z-sensitivity``: nm of z-piezo travel per V of its sensor signal.
    raw_deflection : bool
        Leave a deflection in V as it is (``identify invols`` measures the InvOLS itself).
    """

    units: Mapping[str, str] = field(default_factory=dict)
    invols_nm_per_v: float | None = None
    z_sensitivity_nm_per_v: float | None = None
    raw_deflection: bool = False

    def __post_init__(self) -> None:
        for name, value in (("--invols", self.invols_nm_per_v), ("--z-sensitivity", self.z_sensitivity_nm_per_v)):
            if value is not None and not (math.isfinite(value) and value > 0):
                raise ConfigError(f"{name} {value!r} must be a finite number > 0 (nm/V)")
        for name, unit in self.units.items():
            try:
                parse_unit(unit)
            except ValueError:
                raise ConfigError(f"--units {name}={unit}: unknown unit {unit!r}") from None
        object.__setattr__(self, "units", MappingProxyType(dict(self.units)))


class ChannelConversion(NamedTuple):
    """How one channel is brought to its internal unit: ``internal = factor * recorded``."""

    recorded_units: str
    internal_units: str
    factor: float
    via: str  # "" (unit prefix only), "invols", "z_sensitivity", "assumed" (no units), "override", "unparsed"


def _sensitivity(name: str, info: CaptureInfo, calibration: Calibration) -> tuple[float, str, str]:
    """nm/V for a deflection or z-piezo in V, where it came from, and the way out if it is missing."""
    if name == "deflection":
        if calibration.invols_nm_per_v is not None:
            return calibration.invols_nm_per_v, "invols (--invols)", ""
        invols = info.capture_metadata.cantilever.deflection_sensitivity_nm_per_v
        if invols is not None:
            return invols, "invols (metadata)", ""
        return math.nan, "", "give --invols NM_PER_V or metadata cantilever.deflection_sensitivity_nm_per_v"
    if calibration.z_sensitivity_nm_per_v is not None:
        return calibration.z_sensitivity_nm_per_v, "z_sensitivity (--z-sensitivity)", ""
    return math.nan, "", "give --z-sensitivity NM_PER_V"


def _conversion(name: str, units: str, info: CaptureInfo, calibration: Calibration) -> ChannelConversion:
    where = f"{info.source}: channel {name!r}"
    allowed = CHANNEL_KINDS.get(name)
    try:
        kind, exponent = parse_unit(units)
    except ValueError:
        if allowed is None and name not in calibration.units:
            # a channel no analysis reads by its canonical name ("Vrms", "counts/s"...): kept as recorded,
            # so that one odd column does not stop an analysis of the others
            return ChannelConversion(units, units, 1.0, "unparsed")
        raise InputError(f"{where} has units {units!r}, which afmtool cannot parse; give --units {name}=UNIT") from None
    if kind == "none":
        return ChannelConversion("", "", 1.0, "assumed")
    if allowed is not None and kind not in allowed:
        raise InputError(f"{where} has units {units!r} ({kind}); a {name} must be in {' or '.join(allowed)} units")
    if allowed is not None and kind == "voltage" and name in ("deflection", "z_piezo"):
        if calibration.raw_deflection and name == "deflection":
            return ChannelConversion(units, "V", 10.0**exponent, "")
        nm_per_v, via, missing = _sensitivity(name, info, calibration)
        if missing:
            raise InputError(f"{where} is in {units!r}; to convert it to nm {missing}")
        return ChannelConversion(units, "nm", 10.0**exponent * nm_per_v, via)
    if kind not in _INTERNAL_EXPONENT:
        return ChannelConversion(units, units, 1.0, "")
    return ChannelConversion(units, INTERNAL_UNITS[kind], 10.0 ** (exponent - _INTERNAL_EXPONENT[kind]), "")


def _check_unit_names(info: CaptureInfo, calibration: Calibration) -> None:
    for name in calibration.units:
        if name not in info.channel_names:
            have = ", ".join(info.channel_names) or "none"
            raise InputError(f"{info.source}: --units names no channel {name!r} (has: {have})")


def _check_units_given(info: CaptureInfo, calibration: Calibration, convert: bool) -> None:
    """A capture whose file gives no units (a headerless text export) needs ``--units``.

    Refused when no channel has units from either source; for an analysis (``convert``), also when a
    canonical channel, which it reads in afmtool's units, has none.
    """
    if info.units_declared:
        return
    missing = [c.name for c in info.channels if not c.units and c.name not in calibration.units]
    if len(missing) == len(info.channels) or (convert and any(name in CHANNEL_KINDS for name in missing)):
        names = [n for n in missing if n in CHANNEL_KINDS] if len(missing) < len(info.channels) else missing
        raise InputError(
            f"{info.source}: columns {', '.join(names[:8])} have no units in the file; give them with "
            f"--units {names[0]}=UNIT (e.g. nm, V)"
        )


def plan_conversions(info: CaptureInfo, calibration: Calibration) -> dict[str, ChannelConversion]:
    """Each channel's conversion to its internal unit.

    A channel that is not canonical and whose unit cannot be parsed is kept
    as recorded (``via="unparsed"``); an analysis that reads it by another
    name checks it itself.

    Raises
    ------
    InputError
        A unit of a canonical channel that cannot be parsed, one of the wrong kind for a canonical
        channel, a deflection (z-piezo) in V without an InvOLS (z
        sensitivity), or ``--units`` naming a channel the capture lacks.
    """
    _check_unit_names(info, calibration)
    plan = {}
    for spec in info.channels:
        units = calibration.units.get(spec.name, spec.units)
        conversion = _conversion(spec.name, units, info, calibration)
        if spec.name in calibration.units and conversion.via in ("", "assumed"):
            conversion = conversion._replace(via="override")
        plan[spec.name] = conversion
    return plan


class UnitsReader(ReaderBase):
    """A reader whose channels come out in afmtool's internal units (nm, V, µA, s).

    Parameters
    ----------
    reader : CaptureReader
        The opened capture; closed with this one.
    calibration : Calibration
        ``--units``, ``--invols``, ``--z-sensitivity``.
    convert : bool
        False: only apply ``--units`` (``info``, ``convert`` keep the file's own scale).
    """

    def __init__(self, reader: CaptureReader, calibration: Calibration, *, convert: bool = True) -> None:
        self._reader = reader
        self.calibration = calibration
        source_info = reader.info
        _check_unit_names(source_info, calibration)
        _check_units_given(source_info, calibration, convert)
        overridden = tuple(ChannelSpec(c.name, calibration.units.get(c.name, c.units)) for c in source_info.channels)
        source_info = replace(source_info, channels=overridden)
        if convert:
            self.conversions = plan_conversions(source_info, calibration)
            channels = tuple(
                ChannelSpec(c.name, self.conversions[c.name].internal_units or c.units) for c in source_info.channels
            )
            self._factors = {name: c.factor for name, c in self.conversions.items() if c.factor != 1.0}
        else:
            self.conversions = {}
            channels = overridden
            self._factors = {}
        self.info = replace(source_info, channels=channels)

    def blocks(self, channels: Sequence[str], block_samples: int) -> Iterator[Chunk]:
        factors = {name: self._factors[name] for name in channels if name in self._factors}
        for chunk in self._reader.blocks(channels, block_samples):
            if factors:
                data = dict(chunk.data)
                for name, factor in factors.items():
                    data[name] = data[name] * factor
                chunk = Chunk(chunk.start, data)
            yield chunk

    def ranges(self):
        """The source's ranges, scaled as :meth:`blocks` scales them (:mod:`afmtool.io.ranges`)."""
        from afmtool.io.ranges import ScaledRanges, range_source

        source = range_source(self._reader)
        return None if source is None else ScaledRanges(source, dict(self._factors))

    def truth(self):
        return self._reader.truth()

    def close(self) -> None:
        self._reader.close()


def calibration_record(reader: CaptureReader) -> dict:
    """What the report records of how a capture's units were read: empty when nothing was converted.

    ``{"unit_conversions": {channel: {recorded_units, internal_units, factor, via}},
    "calibration": {...}}`` for the channels whose samples were scaled or
    whose units were given on the command line, and the sensitivities used.
    """
    conversions = getattr(reader, "conversions", {})
    changed = {
        name: {"recorded_units": c.recorded_units, "internal_units": c.internal_units, "factor": c.factor, "via": c.via}
        for name, c in conversions.items()
        if c.factor != 1.0 or c.via not in ("", "assumed")
    }
    record: dict = {}
    if changed:
        record["unit_conversions"] = changed
    calibration = getattr(reader, "calibration", None)
    if calibration is not None:
        used = {}
        if calibration.invols_nm_per_v is not None:
            used["invols_nm_per_v"] = calibration.invols_nm_per_v
        if calibration.z_sensitivity_nm_per_v is not None:
            used["z_sensitivity_nm_per_v"] = calibration.z_sensitivity_nm_per_v
        for c in conversions.values():
            if c.via == "invols (metadata)":
                used.setdefault("invols_nm_per_v", c.factor / parse_unit(c.recorded_units).si_factor)
        if used:
            record["calibration"] = used
    drive = getattr(reader, "drive_record", None)
    if drive:
        record["synthetic_drive"] = drive
    return record
