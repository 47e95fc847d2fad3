"""Optics11 Chiaro nanoindenter text exports (``.txt``, or the ``.zip`` holding one).

The export is Latin-1 text with CR, LF and CRLF line endings mixed: a
free-form header of ``key<TAB>value`` lines (date, device, software,
``k (N/m)``, tip radius, calibration factor, the load profile and its
fit), then a tab-separated table whose header starts with ``Time (s)``::

    Time (s)  Load (uN)  Indentation (nm)  Cantilever (nm)  Piezo (nm)  Auxiliary

The table is read by :class:`afmtool.io.csv.CsvReader` (so it streams and
its time column must be uniform); ``Cantilever`` (the raw cantilever
deflection) is named ``deflection`` and ``Piezo`` ``z_piezo``, other
columns keep their names, and units are the header's (``nm``, ``uN``).
The header's spring constant becomes ``cantilever.spring_constant_n_per_m``.
"""

from __future__ import annotations

import math
import zipfile
import zlib
from pathlib import Path

from afmtool.errors import InputError
from afmtool.io.capture import CaptureInfo
from afmtool.io.csv import MAX_PREAMBLE_LINES, TIME_NAMES, CsvReader, _text_stream, split_unit

__all__ = ["ChiaroReader"]

#: Chiaro column names with an afmtool channel name.
_CHANNELS = {"Cantilever": "deflection", "Piezo": "z_piezo"}

#: Most bytes of a .zip member read (the exports are a few MB).
_MAX_MEMBER_BYTES = 4 << 30


class ChiaroReader(CsvReader):
    """Read an Optics11 Chiaro text export, from the ``.txt`` or from the ``.zip`` it came in."""

    def __init__(self, path: Path, sample_rate_hz: float | None = None) -> None:
        self._zip = None
        self._preamble: dict[str, str] = {}
        path = Path(path)
        stream = None
        if path.suffix.lower() == ".zip":
            stream = self._open_member(path)
        try:
            super().__init__(path, sample_rate_hz, stream=stream)
        except BaseException:
            self._close_zip()
            raise

    def _open_member(self, path: Path):
        try:
            self._zip = zipfile.ZipFile(path)
            members = [m for m in self._zip.infolist() if m.filename.lower().endswith(".txt") and not m.is_dir()]
            if len(members) != 1:
                raise InputError(f"{path}: a Chiaro .zip holds one .txt export; this one holds {len(members)}")
            if members[0].file_size > _MAX_MEMBER_BYTES:
                raise InputError(f"{path}: {members[0].filename} is {members[0].file_size} bytes; too large")
            return _text_stream(self._zip.open(members[0]))
        except (zipfile.BadZipFile, zlib.error, EOFError, ValueError, NotImplementedError, RuntimeError) as exc:
            self._close_zip()
            raise InputError(f"{path}: not a readable ZIP archive ({str(exc).splitlines()[0][:200]})") from None
        except OSError as exc:
            self._close_zip()
            raise InputError(f"{path}: cannot read ({exc.strerror})") from None
        except BaseException:
            self._close_zip()
            raise

    def _read_header(self) -> tuple[list[str], dict]:
        for _ in range(MAX_PREAMBLE_LINES):
            line = self._next_line()
            if line is None:
                break
            stripped = line.strip()
            fields = [f.strip() for f in stripped.split("\t")]
            if len(fields) >= 2 and split_unit(fields[0])[0].lower() in TIME_NAMES:
                renamed = []
                for field in fields:
                    name, unit = split_unit(field)
                    name = _CHANNELS.get(name, name)
                    renamed.append(f"{name} ({unit})" if unit else name)
                return self._parse_header_row("\t".join(renamed), {}), {}
            self._remember(fields)
        raise InputError(f"{self._name}: no 'Time (s)' table header; not an Optics11 Chiaro export")

    def _remember(self, fields: list[str]) -> None:
        """Keep a header line: ``key<TAB>value`` pairs (``Date 12/05/2025 Time 11:20:38``) or ``key: value``."""
        if len(fields) == 1:
            key, sep, value = fields[0].partition(":")
            fields = [key, value] if sep else fields
        for key, value in zip(fields[::2], fields[1::2]):
            key = key.rstrip(":").strip()
            if key and key not in self._preamble:
                self._preamble[key] = value.strip()

    def _make_info(self, comments: dict, sample_rate_hz: float | None) -> CaptureInfo:
        info = super()._make_info(comments, sample_rate_hz)
        metadata = dict(info.metadata)
        instrument = {"vendor_format": "Optics11 Chiaro text export"}
        for key, target in (("Device", "model"), ("Software version", "software_version"), ("Date", "date"),
                            ("Time", "time"), ("Tip radius (um)", "tip_radius_um"), ("Calibration factor", "calibration_factor")):
            if self._preamble.get(key):
                instrument[target] = self._preamble[key]
        metadata["instrument"] = instrument
        try:
            k = float(self._preamble.get("k (N/m)", "nan"))
        except ValueError:
            k = math.nan
        if math.isfinite(k) and k > 0:
            metadata["cantilever"] = {"spring_constant_n_per_m": k}
        return CaptureInfo(info.source, "chiaro", info.sample_rate_hz, info.channels, None, metadata)

    def _close_zip(self) -> None:
        if self._zip is not None:
            self._zip.close()
            self._zip = None

    def close(self) -> None:
        super().close()
        self._close_zip()
