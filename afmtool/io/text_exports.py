"""Vendor text exports: a generic text table, AFM Workshop force curves and NT-MDT Nova exports.

**Generic text** (``.txt``, or a ``.csv`` with a preamble) is read by
:class:`afmtool.io.csv.CsvReader`, which takes a preamble of ``key: value``,
``key = value`` or ``key<TAB>value`` lines (and ``# key value`` comments), a
header whose column names carry their units (``Z-Sense (nm)``, ``T-B(V)``,
``Force [nN]``), comma, semicolon or tab delimiters and decimal commas.  Keys it
knows (spring constant, sensitivity, rates) become metadata
(:mod:`afmtool.io.preamble`).  Columns without units in such a file are in the
vendor's units, not afmtool's: ``--units`` must give them.

**AFM Workshop** force-curve CSVs (``Force-Distance Curve`` on the first line)
hold the extend and the retract side by side, one row per point::

    Extend Z-Sense(nm),Extend T-B(V),Retract Z-Sense(nm),Retract T-B(V)

They become one capture of two segments, ``extend`` then ``retract``, with
``Z-Sense`` as ``z_piezo`` (nm) and ``T-B`` (the photodiode's top-bottom signal)
as ``deflection`` (V).  ``Light Lever Gain, mV/nm`` gives the InvOLS (its
inverse) and ``Force Constant, nN/nm`` the spring constant.  The export records
no sample rate: give ``--sample-rate``.

**NT-MDT Nova** text exports (a ``.txt`` of three tab-separated columns with
decimal commas and no header) hold, per afmformats' documentation of the
format, the piezo height (nm) and the deflection signal (nA) on approach and on
retract at each height.  As afmformats does, the constant padding an export
puts at the start of each deflection column is cut, and the capture is the
approach (in time order, so the rows reversed) followed by the retract:
segments ``approach`` and ``retract``, channels ``z_piezo`` (nm) and
``deflection`` (nA).  No rate is recorded: give ``--sample-rate``.

The two vendor layouts are read whole (they are force curves of thousands of
points); files above :data:`MAX_TABLE_BYTES` are refused.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from afmtool.errors import InputError
from afmtool.io.capture import CaptureInfo, ChannelSpec, Chunk, ReaderBase, SegmentSpec
from afmtool.io.csv import CsvReader, _data_delimiter, _is_data_row
from afmtool.io.preamble import preamble_metadata
from afmtool.io.views import SEGMENTS_KEY, segments_metadata

__all__ = ["TextExportReader", "AfmWorkshopReader", "NtmdtReader", "sniff_text_export", "MAX_TABLE_BYTES"]

#: Largest vendor export read whole, bytes.
MAX_TABLE_BYTES = 256 << 20
#: Bytes read to recognise a text export.
_SNIFF_BYTES = 1 << 16


def sniff_text_export(path: Path, fmt: str) -> str:
    """``"chiaro"``, ``"afm-workshop"`` or ``"ntmdt"`` for those exports, else ``fmt`` (``"csv"`` or ``"text"``)."""
    try:
        with open(path, "rb") as handle:
            head = handle.read(_SNIFF_BYTES).decode("latin-1")
    except OSError:
        return fmt  # the reader says what is wrong
    lines = [line.strip() for line in head.replace("\r", "\n").split("\n") if line.strip()]
    if not lines:
        return fmt
    if lines[0].startswith("Force-Distance Curve") and any("Extend Z-Sense" in line for line in lines):
        return "afm-workshop"
    if fmt == "text":
        if any(line.startswith("Time (s)\t") for line in lines):
            return "chiaro"
        first = lines[0]
        if first.count("\t") == 2 and _is_data_row(first, _data_delimiter(first)):
            return "ntmdt"
    return fmt


class TextExportReader(CsvReader):
    """A text export (``.txt``): the generic table reader, reported as format ``text``."""

    format_name = "text"


class _TableReader(ReaderBase):
    """A vendor export read whole into named arrays, with segments read back to back."""

    def _load(self, path: Path, sample_rate_hz: float | None) -> tuple[CsvReader, dict[str, np.ndarray], float | None]:
        try:
            size = path.stat().st_size
        except OSError as exc:
            raise InputError(f"{path}: cannot read ({exc.strerror})") from None
        if size > MAX_TABLE_BYTES:
            raise InputError(f"{path}: {size:,} bytes; a {self.vendor} export is read whole, at most {MAX_TABLE_BYTES:,}")
        # the table's own rate is irrelevant here (the rows are re-ordered): 1 Hz while reading
        with CsvReader(path, 1.0) as table:
            parts = list(table.blocks(table.info.channel_names, 1 << 16))
            data = {name: np.concatenate([p.data[name] for p in parts]) if parts else np.empty(0)
                    for name in table.info.channel_names}
            stated = preamble_metadata(table._preamble, None).sample_rate_hz
        return table, data, sample_rate_hz if sample_rate_hz is not None else stated

    def _finish(self, path: Path, rate: float | None, channels: dict[str, tuple[str, np.ndarray]],
                segments: Sequence[tuple[str, int]], metadata: dict, fmt: str) -> None:
        if rate is None:
            raise InputError(f"{path}: no sample rate ({self.vendor} exports record none); give --sample-rate")
        if not (np.isfinite(rate) and rate > 0):
            raise InputError(f"{path}: sample rate {rate!r} must be a positive number")
        specs, start = [], 0
        for name, n in segments:
            specs.append(SegmentSpec(name, start, n, float(rate)))
            start += n
        metadata[SEGMENTS_KEY] = segments_metadata(specs)
        self._data = {name: values for name, (_, values) in channels.items()}
        spec = tuple(ChannelSpec(name, unit) for name, (unit, _) in channels.items())
        self.info = CaptureInfo(str(path), fmt, float(rate), spec, start, metadata, (), tuple(specs))

    def blocks(self, channels: Sequence[str], block_samples: int) -> Iterator[Chunk]:
        for start in range(0, self.info.n_samples, block_samples):
            yield Chunk(start, {name: self._data[name][start : start + block_samples] for name in channels})

    def truth(self) -> dict[str, np.ndarray]:
        return {}

    def close(self) -> None:
        self._data = {}


class AfmWorkshopReader(_TableReader):
    """An AFM Workshop force-curve CSV: extend then retract, ``z_piezo`` (nm) and ``deflection`` (V)."""

    vendor = "AFM Workshop"
    _NAMES = {"z-sense": "z_piezo", "t-b": "deflection"}

    def __init__(self, path: Path, sample_rate_hz: float | None = None) -> None:
        table, data, rate = self._load(Path(path), sample_rate_hz)
        sides: dict[str, dict[str, tuple[str, np.ndarray]]] = {"extend": {}, "retract": {}}
        for spec in table.info.channels:
            side, _, quantity = spec.name.partition(" ")
            if side.lower() not in sides or not quantity:
                raise InputError(f"{path}: column {spec.name!r} is neither Extend nor Retract; not an AFM Workshop curve")
            name = self._NAMES.get(quantity.strip().lower(), quantity.strip())
            sides[side.lower()][name] = (spec.units, data[spec.name])
        if not sides["extend"] or sides["extend"].keys() != sides["retract"].keys():
            raise InputError(f"{path}: extend columns {sorted(sides['extend'])} and retract columns "
                             f"{sorted(sides['retract'])} differ; not an AFM Workshop curve")
        n = len(next(iter(data.values())))
        channels = {name: (unit, np.concatenate([values, sides["retract"][name][1]]))
                    for name, (unit, values) in sides["extend"].items()}
        metadata = preamble_metadata(table._preamble, self.vendor).metadata
        self._finish(Path(path), rate, channels, (("extend", n), ("retract", n)), metadata, "afm-workshop")


def _crop_padding(height: np.ndarray, signal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cut the constant run an NT-MDT export pads a column with at its start, keeping its last value (as afmformats)."""
    changed = np.flatnonzero(signal != signal[0])
    if changed.size == 0:
        raise InputError("the deflection column is constant throughout (only export padding)")
    first = max(int(changed[0]) - 1, 0)
    return height[first:], signal[first:]


class NtmdtReader(_TableReader):
    """An NT-MDT Nova text export: approach then retract, ``z_piezo`` (nm) and ``deflection`` (nA)."""

    vendor = "NT-MDT Nova"

    def __init__(self, path: Path, sample_rate_hz: float | None = None) -> None:
        path = Path(path)
        table, data, rate = self._load(path, sample_rate_hz)
        if len(data) != 3:
            raise InputError(f"{path}: {len(data)} columns; an NT-MDT Nova export has 3 (height, approach, retract)")
        height, approach, retract = (data[f"column{i}"] for i in (1, 2, 3))
        if len(height) == 0:
            raise InputError(f"{path}: no rows")
        try:
            z_approach, d_approach = _crop_padding(height, approach)
            z_retract, d_retract = _crop_padding(height, retract)
        except InputError as exc:
            raise InputError(f"{path}: {exc}") from None
        channels = {
            "z_piezo": ("nm", np.concatenate([z_approach[::-1], z_retract])),  # the approach in time order
            "deflection": ("nA", np.concatenate([d_approach[::-1], d_retract])),
        }
        metadata = {"instrument": {"vendor_format": self.vendor}}
        segments = (("approach", len(z_approach)), ("retract", len(z_retract)))
        self._finish(path, rate, channels, segments, metadata, "ntmdt")
