"""Thermal-noise spectrum tables (``--psd FILE.csv``): frequency and amplitude spectral density.

::

    frequency_hz,asd_m_per_sqrt_hz
    38.147,1.03296e-12
    ...

Comment lines starting with ``#`` are skipped.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import NamedTuple

import numpy as np

from afmtool.errors import InputError

__all__ = ["PsdTable", "read_psd_csv"]

_FREQUENCY_COLUMN = "frequency_hz"
_ASD_COLUMN = "asd_m_per_sqrt_hz"


class PsdTable(NamedTuple):
    """A spectrum read by :func:`read_psd_csv`: frequency (Hz) and ASD (m/√Hz)."""

    frequency_hz: np.ndarray
    asd_m_per_sqrt_hz: np.ndarray


def read_psd_csv(path: Path | str) -> PsdTable:
    """Read a ``--psd`` spectrum table: CSV with columns ``frequency_hz,asd_m_per_sqrt_hz``.

    Parameters
    ----------
    path : path-like
        The CSV file.  A header row names the columns (any order; other
        columns are ignored); lines starting with ``#`` and blank lines are
        skipped.

    Returns
    -------
    PsdTable
        ``(frequency_hz, asd_m_per_sqrt_hz)`` as float64 arrays.

    Raises
    ------
    InputError
        One line naming the file: missing file or columns, a row with the
        wrong number of fields, a non-numeric or non-finite value, a negative
        ASD or frequency, a frequency not strictly increasing, or no rows.
    """
    path = Path(path)
    try:
        with path.open(newline="", encoding="utf-8") as handle:
            return _parse_psd_rows(path, handle)
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a directory, not a CSV file") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a UTF-8 text file") from None
    except csv.Error as exc:
        raise InputError(f"{path}: not CSV ({exc})") from None


def _parse_psd_rows(path: Path, handle) -> PsdTable:
    rows = (
        (n, row) for n, row in enumerate(csv.reader(handle), start=1) if row and not row[0].lstrip().startswith("#")
    )
    header_line, header = next(rows, (0, None))
    if header is None:
        raise InputError(f"{path}: empty file (no header row {_FREQUENCY_COLUMN},{_ASD_COLUMN})")
    names = [name.strip() for name in header]
    missing = [c for c in (_FREQUENCY_COLUMN, _ASD_COLUMN) if c not in names]
    if missing:
        raise InputError(
            f"{path}: line {header_line}: missing column(s) {', '.join(missing)}; found {', '.join(names)}"
        )
    i_f, i_a = names.index(_FREQUENCY_COLUMN), names.index(_ASD_COLUMN)
    freq: list[float] = []
    asd: list[float] = []
    for line, row in rows:
        if len(row) != len(names):
            raise InputError(f"{path}: line {line} has {len(row)} fields, the header has {len(names)}")
        values = []
        for column, index in ((_FREQUENCY_COLUMN, i_f), (_ASD_COLUMN, i_a)):
            text = row[index].strip()
            try:
                value = float(text)
            except ValueError:
                raise InputError(f"{path}: line {line}: {column}={text!r} is not a number") from None
            if not math.isfinite(value) or value < 0:
                raise InputError(f"{path}: line {line}: {column}={text!r} must be a finite number >= 0")
            values.append(value)
        if freq and values[0] <= freq[-1]:
            raise InputError(
                f"{path}: line {line}: frequency_hz={values[0]!r} is not above the previous {freq[-1]!r} "
                "(frequencies must be strictly increasing)"
            )
        freq.append(values[0])
        asd.append(values[1])
    if not freq:
        raise InputError(f"{path}: no data rows after the header")
    return PsdTable(np.array(freq), np.array(asd))
