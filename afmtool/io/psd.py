"""Thermal-noise spectrum tables (``--psd FILE.csv``): a frequency column and a spectral density column.

The spectrum may be an amplitude (ASD) or a power (PSD) spectral density, of a
length (m, nm, pm, ...) or of a voltage (V, mV; converted with the InvOLS,
``--invols`` in nm/V), per √Hz or per Hz.  The columns are found by name and
units, the way the capture readers find theirs: a unit in brackets
(``ASD (nm/√Hz)``, ``PSD [V^2/Hz]``, ``frequency (kHz)``) or afmtool's own
names (``frequency_hz``, ``asd_m_per_sqrt_hz``, ``psd_nm2_per_hz``,
``asd_v_per_sqrt_hz``)::

    # averages: 1000
    frequency_hz,asd_m_per_sqrt_hz
    38.147,1.03296e-12
    ...

Whatever the input, the table comes out as frequency (Hz) and ASD (m/√Hz):
units are converted once, here.  Comment lines start with ``#``; a comment
``# averages: N`` (or ``n_averages``) records the number of averaged
periodograms, which the maximum-likelihood thermal fit uses.
"""

from __future__ import annotations

import csv
import math
import re
from pathlib import Path
from typing import NamedTuple

import numpy as np

from afmtool.errors import InputError

__all__ = ["PsdTable", "SpectrumUnit", "parse_spectrum_unit", "read_psd_csv"]

#: Names (lower case, units removed) of a frequency column, and the frequency units with their factor to Hz.
_FREQUENCY_NAMES = frozenset({"f", "freq", "frequency", "frequencies"})
_FREQUENCY_UNITS = {"hz": 1.0, "khz": 1e3, "mhz": 1e6}
#: afmtool's own column names: frequency_hz / frequency_khz, asd_<unit>_per_sqrt_hz, psd_<unit>2_per_hz.
_SNAKE_FREQUENCY = re.compile(r"^(?:f|freq|frequency)_(?P<unit>hz|khz|mhz)$")
_SNAKE_SPECTRUM = re.compile(r"^(?P<kind>asd|psd)_(?P<unit>[a-zµμ]+?)(?P<power>2?)_per_(?P<den>sqrt_hz|rt_?hz|hz)$")
#: Words that mark the spectral-density column when its name has no units.
_SPECTRUM_WORDS = ("asd", "psd", "spectral", "density", "spectrum", "noise", "amplitude", "power", "deflection")
_PER_ROOT_HZ = re.compile(r"^(?:√|sqrt\(?|rt)\s*hz\)?$|^hz\s*\^\s*\(?(?:0\.5|1/2)\)?$")
_NUMERATOR_POWER = re.compile(r"^(?P<base>.+?)\s*(?:\^\s*2|²|2)$")
_AVERAGES_KEYS = ("averages", "n_averages", "number of averages", "navg")
#: "name (unit)" or "name [unit]", the unit to the last bracket (it may hold its own: m/sqrt(Hz)).
_NAME_WITH_UNIT = re.compile(r"^(?P<name>[^(\[]*?)\s*[\(\[](?P<unit>.*)[\)\]]\s*$")


class SpectrumUnit(NamedTuple):
    """A spectral density's unit read: ASD or PSD, the numerator's kind and its power of ten to SI."""

    kind: str  # "asd" or "psd"
    quantity: str  # "length" or "voltage"
    exponent: int  # the numerator's base unit to m or V, a power of ten
    text: str  # as written, for the report


class PsdTable(NamedTuple):
    """A spectrum read by :func:`read_psd_csv`: frequency (Hz) and ASD (m/√Hz), and what the file held."""

    frequency_hz: np.ndarray
    asd_m_per_sqrt_hz: np.ndarray
    n_averages: int | None = None
    source_unit: str = "m/sqrt(Hz)"
    source_kind: str = "asd"
    columns: tuple[str, str] = ("frequency_hz", "asd_m_per_sqrt_hz")


def parse_spectrum_unit(text: str) -> SpectrumUnit:
    """Parse a spectral-density unit: ``m/√Hz``, ``nm/sqrt(Hz)``, ``pm/rtHz``, ``m^2/Hz``, ``V²/Hz`` ...

    Raises
    ------
    ValueError
        If the text is not a length or voltage per √Hz (ASD) or its square per Hz (PSD).
    """
    from afmtool.io.units import parse_unit

    unit = text.strip().replace(" ", "")
    if "/" not in unit:
        raise ValueError(f"{text!r} is not per Hz or per sqrt(Hz)")
    numerator, denominator = unit.split("/", 1)
    per_root = bool(_PER_ROOT_HZ.match(denominator.lower()))
    if not per_root and denominator.lower() != "hz":
        raise ValueError(f"{text!r}: the denominator must be Hz or sqrt(Hz)")
    squared = _NUMERATOR_POWER.match(numerator)
    base = squared.group("base") if squared else numerator
    power = 2 if squared else 1
    if (power, per_root) not in ((1, True), (2, False)):
        raise ValueError(f"{text!r} is neither an ASD (unit/sqrt(Hz)) nor a PSD (unit^2/Hz)")
    parsed = parse_unit(base)
    if parsed.kind not in ("length", "voltage"):
        raise ValueError(f"{text!r}: the spectrum must be of a length or a voltage, not a {parsed.kind}")
    return SpectrumUnit("asd" if per_root else "psd", parsed.kind, parsed.exponent, text.strip())


def _snake_unit(name: str) -> SpectrumUnit | None:
    """``asd_nm_per_sqrt_hz`` -> the ASD in nm/√Hz; ``psd_v2_per_hz`` -> the PSD in V²/Hz; else None."""
    match = _SNAKE_SPECTRUM.match(name.lower())
    if match is None:
        return None
    base = {"um": "um", "v": "V", "mv": "mV", "uv": "uV"}.get(match.group("unit"), match.group("unit"))
    per_root = match.group("den") != "hz"
    text = f"{base}{'^2' if match.group('power') else ''}/{'sqrt(Hz)' if per_root else 'Hz'}"
    try:
        unit = parse_spectrum_unit(text)
    except ValueError:
        return None
    return unit if unit.kind == match.group("kind") else None


def _split_unit(header: str) -> tuple[str, str]:
    """``"ASD (m/sqrt(Hz))"`` -> ``("ASD", "m/sqrt(Hz)")``; ``"frequency_hz"`` -> ``("frequency_hz", "")``."""
    match = _NAME_WITH_UNIT.match(header)
    if match and match.group("name").strip():
        return match.group("name").strip(), match.group("unit").strip()
    return header.strip(), ""


def _columns(path: Path, line: int, names: list[str]) -> tuple[int, float, int, SpectrumUnit]:
    """(frequency column, its factor to Hz, spectrum column, its unit), found by name and units."""
    frequency = spectrum = None
    for index, header in enumerate(names):
        name, unit = _split_unit(header)
        snake = _SNAKE_FREQUENCY.match(name.lower())
        if frequency is None and (snake or name.lower() in _FREQUENCY_NAMES or "freq" in name.lower()):
            factor = _FREQUENCY_UNITS.get((snake.group("unit") if snake else unit or "hz").lower())
            if factor is None:
                raise InputError(f"{path}: line {line}: frequency column {header!r} is in {unit!r}, not Hz, kHz or MHz")
            frequency = (index, factor)
        elif spectrum is None:
            parsed = _spectrum_column(path, line, header, name, unit)
            if parsed is not None:
                spectrum = (index, parsed)
    if frequency is None or spectrum is None:
        missing = "a frequency column (frequency_hz, 'frequency (kHz)')" if frequency is None else (
            "a spectral density column with its units (asd_m_per_sqrt_hz, 'PSD (nm^2/Hz)', 'ASD [V/sqrt(Hz)]')")
        raise InputError(f"{path}: line {line}: missing {missing}; found {', '.join(names)}")
    return frequency[0], frequency[1], spectrum[0], spectrum[1]


def _spectrum_column(path: Path, line: int, header: str, name: str, unit: str) -> SpectrumUnit | None:
    """The unit of a spectral-density column, None if ``header`` is not one; InputError for a bad unit."""
    snake = _snake_unit(name)
    if snake is not None:
        return snake
    looks_like = any(word in name.lower() for word in _SPECTRUM_WORDS) or "hz" in unit.lower()
    if not looks_like:
        return None
    if not unit:
        raise InputError(f"{path}: line {line}: column {header!r} has no units; write them in the header, "
                         "e.g. 'ASD (m/sqrt(Hz))' or 'PSD (nm^2/Hz)'")
    try:
        parsed = parse_spectrum_unit(unit)
    except ValueError as exc:
        raise InputError(f"{path}: line {line}: column {header!r}: {exc}") from None
    for kind in ("asd", "psd"):
        if kind in name.lower().split() and parsed.kind != kind:
            raise InputError(f"{path}: line {line}: column {header!r} is named {kind.upper()} but its unit "
                             f"{unit!r} is a{'n ASD' if parsed.kind == 'asd' else ' PSD'}")
    return parsed


def _to_asd_m(values: np.ndarray, unit: SpectrumUnit, invols_nm_per_v: float | None, path: Path) -> np.ndarray:
    """The column in m/√Hz: the square root of a PSD, scaled to m (through the InvOLS for a voltage)."""
    scale = 10.0**unit.exponent  # to m or to V
    if unit.quantity == "voltage":
        if not invols_nm_per_v:
            raise InputError(f"{path}: the spectrum is in {unit.text}, a voltage: give --invols (nm/V) to turn it "
                             "into a deflection")
        scale *= invols_nm_per_v * 1e-9
    asd = np.sqrt(values) if unit.kind == "psd" else values
    return asd * scale


def read_psd_csv(path: Path | str, invols_nm_per_v: float | None = None) -> PsdTable:
    """Read a ``--psd`` spectrum table (module docstring): frequency in Hz and ASD in m/√Hz.

    Parameters
    ----------
    path : path-like
        The CSV file (comma, tab or semicolon separated).  A header row names
        the columns (any order; other columns are ignored); lines starting with
        ``#`` and blank lines are skipped.
    invols_nm_per_v : float, optional
        Deflection sensitivity, nm/V, for a spectrum of a voltage.

    Returns
    -------
    PsdTable

    Raises
    ------
    InputError
        One line naming the file: missing file or columns, a unit that is not
        a spectral density, a voltage without InvOLS, a row with the wrong
        number of fields, a non-numeric or non-finite value, a negative
        density or frequency, a frequency not strictly increasing, or no rows.
    """
    path = Path(path)
    try:
        with path.open(newline="", encoding="utf-8-sig") as handle:
            return _parse_psd_rows(path, handle, invols_nm_per_v)
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a directory, not a CSV file") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a UTF-8 text file") from None
    except csv.Error as exc:
        raise InputError(f"{path}: not CSV ({exc})") from None


def _averages(comment: str) -> int | None:
    """N from a comment ``# averages: N`` (or ``=``), else None."""
    body = comment.lstrip("#").strip()
    for separator in (":", "="):
        if separator in body:
            key, value = (part.strip() for part in body.split(separator, 1))
            if key.lower() in _AVERAGES_KEYS:
                try:
                    number = float(value.split()[0])
                except (ValueError, IndexError):
                    return None
                return int(number) if number >= 1 and number == int(number) else None
    return None


def _parse_psd_rows(path: Path, handle, invols_nm_per_v: float | None) -> PsdTable:
    text_lines = handle.read().splitlines()
    averages = None
    body = []
    for number, text in enumerate(text_lines, start=1):
        if text.lstrip().startswith("#"):
            averages = _averages(text) or averages
        elif text.strip():
            body.append((number, text))
    if not body:
        raise InputError(f"{path}: empty file (no header row such as frequency_hz,asd_m_per_sqrt_hz)")
    header_line, header_text = body[0]
    delimiter = next((c for c in (",", "\t", ";") if c in header_text), ",")
    names = [name.strip() for name in next(csv.reader([header_text], delimiter=delimiter))]
    i_f, f_scale, i_s, unit = _columns(path, header_line, names)
    freq, values = _numbers(path, body[1:], delimiter, names, (i_f, i_s))
    asd = _to_asd_m(np.array(values), unit, invols_nm_per_v, path)
    return PsdTable(np.array(freq) * f_scale, asd, averages, unit.text, unit.kind, (names[i_f], names[i_s]))


def _numbers(path: Path, rows, delimiter: str, names: list[str], indices: tuple[int, int]):
    """The two columns as floats, checked row by row (finite, >= 0, frequencies strictly increasing)."""
    freq: list[float] = []
    values: list[float] = []
    for line, text in rows:
        row = next(csv.reader([text], delimiter=delimiter))
        if len(row) != len(names):
            raise InputError(f"{path}: line {line} has {len(row)} fields, the header has {len(names)}")
        pair = []
        for index in indices:
            field = row[index].strip()
            try:
                value = float(field)
            except ValueError:
                raise InputError(f"{path}: line {line}: {names[index]}={field!r} is not a number") from None
            if not math.isfinite(value) or value < 0:
                raise InputError(f"{path}: line {line}: {names[index]}={field!r} must be a finite number >= 0")
            pair.append(value)
        if freq and pair[0] <= freq[-1]:
            raise InputError(
                f"{path}: line {line}: {names[indices[0]]}={pair[0]!r} is not above the previous {freq[-1]!r} "
                "(frequencies must be strictly increasing)"
            )
        freq.append(pair[0])
        values.append(pair[1])
    if not freq:
        raise InputError(f"{path}: no data rows after the header")
    return freq, values
