"""CSV captures: ``# key: value`` comment lines, a header row, numeric rows.

::

    # sample_rate_hz: 500000
    # units.deflection: nm
    # metadata: {"cantilever": {"f0_hz": 70000}}
    t,dither,deflection
    0,0.1,0.02
    ...

Also read, so that scope and DAQ exports need no editing:

- a time column named ``t``, ``time``, ``Time (s)``, ``Time [ms]`` and the
  like (its unit, s by default, may be s, ms, us/µs or ns); when present,
  sampling must be uniform, and it supplies the sample rate when no other
  source does;
- units in the header, ``deflection (nm)`` or ``deflection [nm]``, or in a
  second header row of unit names (``Second,Volt,Volt`` as some scopes
  write); a ``# units.NAME:`` line overrides both;
- comma, tab or semicolon separators (from the header row), quoted names;
- UTF-8 with or without a byte-order mark, Latin-1 (bytes that are not
  UTF-8 are read as Latin-1, so ``µm`` arrives either way), and CR, LF or
  CRLF line endings, mixed.

Files and standard input (``-``) are read line by line in blocks, so memory
stays bounded whatever the length.  So is the work on hostile input: a line
longer than :data:`MAX_LINE_CHARS` or a header of more than
:data:`MAX_COLUMNS` columns is refused (``info - < /dev/zero`` ends at
once), and the header is parsed in time linear in its columns.
"""

from __future__ import annotations

import codecs
import io
import json
import math
import re
import sys
import zipfile
import zlib
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import TextIO

import numpy as np

from afmtool.errors import InputError
from afmtool.io.capture import CaptureInfo, ChannelSpec, Chunk, ReaderBase
from afmtool.io.metadata import parse_metadata_json
from afmtool.io.preamble import preamble_metadata
from afmtool.io.unit_names import unit_symbol

__all__ = ["CsvReader", "CsvWriter", "STDIO", "MAX_LINE_CHARS", "MAX_COLUMNS", "split_unit"]

STDIO = "-"
TIME_COLUMN = "t"
#: Longest line read, in characters (a 40,000-column row of 17-digit numbers fits).
MAX_LINE_CHARS = 1 << 22
#: Most columns a header may have.
MAX_COLUMNS = 1 << 16
#: Most comment or blank lines before the header row.
MAX_PREAMBLE_LINES = 100_000
#: Values parsed per np.loadtxt call (bounds the temporary text held at once).
_BLOCK_VALUES = 1 << 21
# Uniform sampling means |t[n] - (t[0] + n/fs)| stays below this fraction of
# a sample period, plus the rounding of a 10-significant-digit time stamp.
_T_TOLERANCE_PERIODS = 0.1
_T_RELATIVE_DIGITS = 2e-9

#: Names (lower case, without units) of a time column.
TIME_NAMES = frozenset({"t", "time", "times", "time_s", "t_s", "timestamp_s", "second", "seconds"})
#: Units a time column may carry, as factors to seconds.
_TIME_UNITS = {"": 1.0, "s": 1.0, "sec": 1.0, "second": 1.0, "seconds": 1.0, "ms": 1e-3, "us": 1e-6,
               "\u00b5s": 1e-6, "\u03bcs": 1e-6, "ns": 1e-9}
_NAME_WITH_UNIT = re.compile(r"^(?P<name>.*?)\s*[\(\[](?P<unit>[^\)\]]*)[\)\]]\s*$")


def _latin1_fallback(error: UnicodeDecodeError) -> tuple[str, int]:
    """Decode the bytes that are not UTF-8 as Latin-1 (every byte is a Latin-1 character)."""
    return error.object[error.start : error.end].decode("latin-1"), error.end


codecs.register_error("afmtool-latin1", _latin1_fallback)


def _text_stream(binary) -> io.TextIOWrapper:
    # utf-8-sig drops a byte-order mark; newline=None reads CR, LF and CRLF alike.
    return io.TextIOWrapper(binary, encoding="utf-8-sig", errors="afmtool-latin1", newline=None)


def split_unit(header: str) -> tuple[str, str]:
    """``"deflection (nm)"`` -> ``("deflection", "nm")``; ``"CH1"`` -> ``("CH1", "")``."""
    match = _NAME_WITH_UNIT.match(header)
    if match and match.group("name").strip():
        return match.group("name").strip(), match.group("unit").strip()
    return header.strip(), ""


def _delimiter(header_line: str) -> str:
    for candidate in (",", "\t", ";"):
        if candidate in header_line:
            return candidate
    return ","


def _data_delimiter(line: str) -> str:
    """The delimiter of a row of numbers: tab or semicolon when present (their numbers may use decimal commas)."""
    for candidate in ("\t", ";"):
        if candidate in line:
            return candidate
    return ","


def _fields(line: str, delimiter: str) -> list[str]:
    return [c.strip().strip('"').strip() for c in line.split(delimiter)]


def _is_number(text: str, delimiter: str = ",") -> bool:
    """Whether ``text`` is a number (with a decimal comma where the delimiter is not a comma)."""
    if delimiter != ",":
        text = text.replace(",", ".")
    try:
        float(text)
    except ValueError:
        return False
    return True


def _is_data_row(line: str, delimiter: str) -> bool:
    return all(_is_number(field, delimiter) for field in _fields(line, delimiter))


def _parse_comment(line: str, header: dict) -> None:
    """``# key: value``, ``# key = value`` or ``# key value`` (the value is the last word)."""
    body = line.lstrip("#").strip()
    pair = _preamble_pair(body, words=True, max_chars=None)  # a metadata JSON is as long as its line
    if pair is not None:
        header[pair[0]] = pair[1]


#: Most preamble keys kept from a text export.
MAX_PREAMBLE_KEYS = 1000
#: Longest preamble value kept, characters.
_MAX_VALUE_CHARS = 1000


def _preamble_pair(line: str, *, words: bool = False, max_chars: int | None = _MAX_VALUE_CHARS) -> tuple[str, str] | None:
    """A preamble line as ``(key, value)``: ``key: value``, ``key = value``, ``key<TAB>value`` (the first separator
    in the line); else None.  With ``words``, also ``key value`` (a comment's key and its last word).
    """
    at = [(line.find(sep), sep) for sep in (":", "=", "\t") if line.find(sep) > 0]
    if at:
        _, separator = min(at)
        key, _, value = line.partition(separator)
        if key.strip():
            return key.strip(), value.strip()[:max_chars]
    if words:
        key, _, value = line.rpartition(" ")
        if key.strip() and value:
            return key.strip(), value[:max_chars]
    return None


class CsvReader(ReaderBase):
    """Read a CSV capture from a file or from standard input (``"-"``)."""

    def __init__(self, path: Path | str, sample_rate_hz: float | None = None, *, stream: TextIO | None = None) -> None:
        self._name = "<stdin>" if str(path) == STDIO else str(path)
        if stream is not None:
            self._stream = stream
        elif str(path) == STDIO:
            self._stream = _text_stream(sys.stdin.buffer)
        else:
            try:
                self._stream = _text_stream(open(path, "rb"))  # noqa: SIM115 - the reader owns the file and closes it in close()
            except FileNotFoundError:
                raise InputError(f"{path}: no such file") from None
            except OSError as exc:
                raise InputError(f"{path}: cannot open ({exc.strerror})") from None
        self._line_no = 0
        self._pushed_back: str | None = None
        self._preamble: dict[str, str] = {}
        self._headerless = False
        self._decimal_comma = False
        try:
            self._columns, comments = self._read_header()
            self._rows_per_read = max(1, _BLOCK_VALUES // len(self._columns))
            self._pending_rows = self._first_rows()
            self.info = self._make_info(comments, sample_rate_hz)
        except BaseException:
            self.close()
            raise

    def _next_line(self) -> str | None:
        """The next line, or None at the end; a line longer than MAX_LINE_CHARS is refused."""
        if self._pushed_back is not None:
            line, self._pushed_back = self._pushed_back, None
            self._line_no += 1
            return line
        try:
            line = self._stream.readline(MAX_LINE_CHARS + 1)
        except (OSError, ValueError, EOFError, zlib.error, zipfile.BadZipFile) as exc:  # a file, stdin or a zip member
            raise InputError(f"{self._name}: cannot read ({_short(exc)})") from None
        if not line:
            return None
        self._line_no += 1
        if self._line_no == 1:
            line = line.lstrip("\ufeff")  # a byte-order mark that reached us as text (a stream given decoded)
        if len(line) > MAX_LINE_CHARS:
            raise InputError(f"{self._name}: line {self._line_no} is longer than {MAX_LINE_CHARS} characters")
        return line

    def _read_header(self) -> tuple[list[str], dict]:
        """Comments, a preamble, the header (and a row of unit names), up to the first row of numbers.

        The header is the last line before the first data row that splits into as many fields;
        the lines before it are the preamble (``key: value``, ``key = value``, ``key<TAB>value``).
        A file whose first non-comment line is numbers has no header: its columns are
        ``column1``, ``column2``... and their units unknown.
        """
        comments: dict[str, str] = {}
        recent: list[str] = []  # the last lines that were neither blank, comments nor numbers
        for _ in range(MAX_PREAMBLE_LINES):
            line = self._next_line()
            if line is None:
                break
            stripped = line.strip()
            if not stripped:
                continue
            if stripped.startswith("#"):
                _parse_comment(stripped, comments)
                continue
            delimiter = _data_delimiter(stripped)
            if _is_data_row(stripped, delimiter):
                self._pushed_back, self._line_no = line, self._line_no - 1
                return self._header_before(recent, stripped, delimiter, comments), comments
            if len(recent) == 2:
                self._remember_preamble(recent.pop(0))
            recent.append(stripped)
        else:
            raise InputError(f"{self._name}: no data row in the first {MAX_PREAMBLE_LINES} lines")
        if recent:  # a header and no rows
            for line in recent[:-1]:
                self._remember_preamble(line)
            return self._parse_header_row(recent[-1], comments), comments
        raise InputError(f"{self._name}: empty file (no header row)")

    def _header_before(self, recent: list[str], data_row: str, delimiter: str, comments: dict) -> list[str]:
        """The columns named by the header line(s) just before the first data row (see :meth:`_read_header`)."""
        width = len(data_row.split(delimiter))
        split = [_fields(line, delimiter) for line in recent]
        if split and len(split[-1]) == width:
            units_row = None
            if len(split) == 2 and len(split[0]) == width and not any(_is_number(f, delimiter) for f in split[1] if f):
                units_row = split.pop()  # a row of unit names under the header (scope CSVs)
                recent = recent[:1]
            for line in recent[:-1]:
                self._remember_preamble(line)
            return self._set_columns(split[-1], delimiter, comments, units_row)
        for line in recent:
            self._remember_preamble(line)
        self._headerless = True
        return self._set_columns([f"column{i + 1}" for i in range(width)], delimiter, comments, None)

    def _remember_preamble(self, line: str) -> None:
        """Keep a preamble line's ``key: value`` (or ``key = value``, ``key<TAB>value``), bounded."""
        if len(self._preamble) < MAX_PREAMBLE_KEYS:
            parsed = _preamble_pair(line)
            if parsed is not None:
                self._preamble.setdefault(parsed[0], parsed[1])

    def _parse_header_row(self, stripped: str, comments: dict) -> list[str]:
        """A header line on its own (its delimiter from itself), and a row of unit names under it, if any."""
        columns = self._set_columns(_fields(stripped, _delimiter(stripped)), _delimiter(stripped), comments, None)
        self._read_units_row(columns)
        return columns

    def _set_columns(self, fields: list[str], delimiter: str, comments: dict, units_row: list[str] | None) -> list[str]:
        self._delimiter = delimiter
        self._decimal_comma = delimiter != ","
        if len(fields) > MAX_COLUMNS:
            raise InputError(f"{self._name}: line {self._line_no}: {len(fields)} columns; at most {MAX_COLUMNS}")
        named = [split_unit(f) for f in fields]
        columns = [name for name, _ in named]
        if any(not c for c in columns) or len(set(columns)) != len(columns):
            raise InputError(f"{self._name}: line {self._line_no}: header needs distinct non-empty names")
        self._header_units = {name: unit for name, unit in named}
        for name, unit in zip(columns, units_row or ()):
            self._header_units[name] = self._header_units[name] or unit
        self._time = next((c for c in columns if c.lower() in TIME_NAMES), None)
        self._t_scale, self._t_relative = 1.0, _T_RELATIVE_DIGITS
        if self._time is not None:
            unit = self._header_units[self._time]
            if unit not in _TIME_UNITS:
                raise InputError(f"{self._name}: time column {self._time!r} has unit {unit!r}; expected s, ms, us or ns")
            self._t_scale = _TIME_UNITS[unit]
        if len(columns) == 1 and self._time is not None:
            raise InputError(f"{self._name}: the capture has no channels besides {self._time}")
        self._index = {name: i for i, name in enumerate(columns)}
        return columns

    def _read_units_row(self, columns: list[str]) -> None:
        """A second header row of unit names (no field a number) fills units the header lacks."""
        line = self._next_line()
        if line is None:
            return
        fields = _fields(line.strip(), self._delimiter)
        if line.strip() and not line.lstrip().startswith("#") and len(fields) == len(columns):
            if not any(_is_number(f, self._delimiter) for f in fields if f):
                for name, unit in zip(columns, fields):
                    self._header_units[name] = self._header_units[name] or unit
                return
        self._pushed_back = line
        self._line_no -= 1

    def _first_rows(self) -> np.ndarray:
        """Read a first block so the sample rate can come from the time column."""
        return self._read_rows(min(4096, self._rows_per_read))

    #: The format name this reader reports.
    format_name = "csv"

    def _make_info(self, comments: dict, sample_rate_hz: float | None) -> CaptureInfo:
        # '# key value' comments and a vendor preamble both give what they can (a rate, k, the InvOLS)
        comment_keys = {k: v for k, v in comments.items() if k not in ("metadata", "sample_rate_hz") and not k.startswith("units.")}
        mapped = preamble_metadata({**comment_keys, **self._preamble}, "text export" if self._preamble else None)
        metadata, sample_rate_hz = mapped.metadata, sample_rate_hz or mapped.sample_rate_hz
        if "metadata" in comments:
            metadata = {**metadata, **parse_metadata_json(comments["metadata"], self._name)}
        if sample_rate_hz is None and "sample_rate_hz" in comments:
            try:
                sample_rate_hz = float(comments["sample_rate_hz"])
            except ValueError:
                raise InputError(f"{self._name}: sample_rate_hz {comments['sample_rate_hz']!r} is not a number") from None
        has_t = self._time is not None
        if sample_rate_hz is None and has_t and len(self._pending_rows) >= 2:
            t = self._pending_rows[:, self._index[self._time]] * self._t_scale
            sample_rate_hz = (len(t) - 1) / (t[-1] - t[0]) if t[-1] != t[0] else float("nan")
            if np.isfinite(sample_rate_hz):
                # Decimal time stamps make (n-1)/span 500000.00000000006 for 500 kHz; 12 significant
                # digits undo that and move the rate by < 1e-12, far inside the uniformity check.
                sample_rate_hz = float(f"{sample_rate_hz:.12g}")
        if sample_rate_hz is None:
            raise InputError(f"{self._name}: no sample rate; add '# sample_rate_hz: ...', a t column, or give --sample-rate")
        if not np.isfinite(sample_rate_hz) or sample_rate_hz <= 0:
            raise InputError(f"{self._name}: sample rate {sample_rate_hz!r} must be a positive number")
        self._t0 = 0.0
        if has_t and len(self._pending_rows):
            self._t0 = float(self._pending_rows[0, self._index[self._time]]) * self._t_scale
        channels = tuple(
            ChannelSpec(name, comments.get(f"units.{name}", unit_symbol(self._header_units.get(name, ""))))
            for name in self._columns
            if name != self._time
        )
        if self.format_name == "text" and not len(self._pending_rows):
            raise InputError(f"{self._name}: no rows of numbers; not a table afmtool reads")
        # a vendor export's columns without units are in the vendor's units, not afmtool's: --units must say
        declared = not self._headerless and not (self._preamble and any(not c.units for c in channels))
        return CaptureInfo(self._name, self.format_name, float(sample_rate_hz), channels, None, metadata,
                           units_declared=declared)

    def _read_rows(self, n_rows: int) -> np.ndarray:
        parts = []
        while n_rows > 0:
            rows = self._read_row_batch(min(n_rows, self._rows_per_read))
            if rows is None:
                break
            parts.append(rows)
            n_rows -= len(rows)
        if not parts:
            return np.empty((0, len(self._columns)))
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    def _read_row_batch(self, n_rows: int) -> np.ndarray | None:
        """Up to ``n_rows`` data rows (comment and blank lines skipped), or None at the end."""
        first_line = self._line_no + 1
        lines = []
        while len(lines) < n_rows:
            line = self._next_line()
            if line is None:
                break
            if line.strip() and not line.lstrip().startswith("#"):
                if not line.endswith("\n"):
                    raise InputError(
                        f"{self._name}: line {self._line_no} ends without a line end, as a file cut short does (its last "
                        "value may have lost digits); end the file with a newline if it is complete"
                    )
                lines.append(line)
        if not lines:
            return None
        if self._decimal_comma:
            lines = [line.replace(",", ".") for line in lines]
        try:
            rows = np.loadtxt(lines, delimiter=self._delimiter, dtype=np.float64, ndmin=2)
        except ValueError as exc:
            raise InputError(f"{self._name}: near line {first_line}: {_short(exc)}") from None
        if rows.shape[1] != len(self._columns):
            raise InputError(
                f"{self._name}: near line {first_line}: rows have {rows.shape[1]} columns, header has {len(self._columns)}"
            )
        return rows

    def _check_time(self, t: np.ndarray, start: int) -> None:
        fs = self.info.sample_rate_hz
        t = t * self._t_scale
        expected = self._t0 + (start + np.arange(len(t))) / fs
        tolerance = _T_TOLERANCE_PERIODS / fs + self._t_relative * np.abs(expected)
        bad = np.flatnonzero(~(np.abs(t - expected) <= tolerance))
        if bad.size:
            i = int(bad[0])
            raise InputError(
                f"{self._name}: non-uniform sampling: t={t[i]!r} at sample {start + i}, expected {expected[i]:.10g}"
            )

    def blocks(self, channels: Sequence[str], block_samples: int) -> Iterator[Chunk]:
        index = {name: self._index[name] for name in channels}
        t_index = self._index[self._time] if self._time is not None else None
        start = 0
        pending, self._pending_rows = self._pending_rows, np.empty((0, len(self._columns)))
        while True:
            need = block_samples - len(pending)
            rows = np.concatenate([pending, self._read_rows(need)]) if need > 0 else pending
            rows, pending = rows[:block_samples], rows[block_samples:]
            if len(rows) == 0:
                return
            if t_index is not None:
                self._check_time(rows[:, t_index], start)
            yield Chunk(start, {name: np.ascontiguousarray(rows[:, i]) for name, i in index.items()})
            start += len(rows)

    def truth(self) -> dict[str, np.ndarray]:
        return {}

    def close(self) -> None:
        stream = getattr(self, "_stream", None)
        if stream is not None and stream is not sys.stdin:
            try:
                if isinstance(stream, io.TextIOWrapper) and stream.buffer is getattr(sys.stdin, "buffer", None):
                    stream.detach()  # leave the process's stdin open
                else:
                    stream.close()
            except (OSError, ValueError):
                pass


def _short(exc: Exception) -> str:
    return str(exc).strip().splitlines()[0]


class CsvWriter:
    """Write a CSV capture to a text stream, with a ``t`` column in seconds."""

    def __init__(
        self,
        stream: TextIO,
        sample_rate_hz: float,
        channels: Sequence[ChannelSpec],
        metadata: Mapping | None = None,
    ) -> None:
        self._stream = stream
        self._fs = float(sample_rate_hz)
        self._names = [c.name for c in channels]
        self._written = 0
        stream.write(f"# sample_rate_hz: {self._fs!r}\n")
        for spec in channels:
            if spec.units:
                stream.write(f"# units.{spec.name}: {spec.units}\n")
        if metadata:
            stream.write(f"# metadata: {json.dumps(dict(metadata))}\n")
        stream.write(",".join([TIME_COLUMN, *self._names]) + "\n")

    def write(self, data: Mapping[str, np.ndarray]) -> None:
        n = len(data[self._names[0]])
        t = (self._written + np.arange(n)) / self._fs
        if n and not math.isfinite(t[-1]):
            raise InputError(f"sample {self._written + n - 1:,} at {self._fs!r} Hz: its time overflows the t column")
        # repr-exact float64 round trip: 17 significant digits
        table = np.column_stack([t, *(np.asarray(data[name], dtype=np.float64) for name in self._names)])
        np.savetxt(self._stream, table, delimiter=",", fmt="%.17g")
        self._written += n

    def write_truth(self, truth: Mapping[str, np.ndarray]) -> None:
        """CSV carries no ground truth; the HDF5 layout does."""

    def close(self) -> None:
        self._stream.flush()
