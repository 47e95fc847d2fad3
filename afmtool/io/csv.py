"""CSV captures: ``# key: value`` comment lines, a header row, numeric rows.

::

    # sample_rate_hz: 500000
    # units.deflection: nm
    # metadata: {"cantilever": {"f0_hz": 70000}}
    t,dither,deflection
    0,0.1,0.02
    ...

The time column ``t`` (s) is optional; when present, sampling must be
uniform.  Files and standard input (``-``) are read line by line in blocks,
so memory stays bounded whatever the length.
"""

from __future__ import annotations

import io
import itertools
import json
import sys
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import TextIO

import numpy as np

from afmtool.errors import InputError
from afmtool.io.capture import ReaderBase, CaptureInfo, ChannelSpec, Chunk
from afmtool.io.metadata import parse_metadata_json

__all__ = ["CsvReader", "CsvWriter", "STDIO"]

STDIO = "-"
TIME_COLUMN = "t"
# Uniform sampling means |t[n] - (t[0] + n/fs)| stays below this fraction of
# a sample period, plus the rounding of a 10-significant-digit time stamp.
_T_TOLERANCE_PERIODS = 0.1
_T_RELATIVE_DIGITS = 2e-9


def _parse_comment(line: str, header: dict) -> None:
    body = line.lstrip("#").strip()
    if not body or ":" not in body:
        return
    key, value = (part.strip() for part in body.split(":", 1))
    header[key] = value


class CsvReader(ReaderBase):
    """Read a CSV capture from a file or from standard input (``"-"``)."""

    def __init__(self, path: Path | str, sample_rate_hz: float | None = None, *, stream: TextIO | None = None) -> None:
        self._name = "<stdin>" if str(path) == STDIO else str(path)
        if stream is not None:
            self._stream = stream
        elif str(path) == STDIO:
            self._stream = io.TextIOWrapper(sys.stdin.buffer, encoding="utf-8", errors="replace")
        else:
            try:
                self._stream = open(path, encoding="utf-8", errors="replace", newline="")  # noqa: SIM115
            except FileNotFoundError:
                raise InputError(f"{path}: no such file") from None
            except OSError as exc:
                raise InputError(f"{path}: cannot open ({exc.strerror})") from None
        self._line_no = 0
        try:
            self._columns, comments = self._read_header()
            self._pending_rows = self._first_rows()
            self.info = self._make_info(comments, sample_rate_hz)
        except BaseException:
            self.close()
            raise

    def _read_header(self) -> tuple[list[str], dict]:
        comments: dict[str, str] = {}
        for line in self._stream:
            self._line_no += 1
            stripped = line.strip()
            if not stripped:
                continue
            if stripped.startswith("#"):
                _parse_comment(stripped, comments)
                continue
            columns = [c.strip() for c in stripped.split(",")]
            if any(not c for c in columns) or len(set(columns)) != len(columns):
                raise InputError(f"{self._name}: line {self._line_no}: header needs distinct non-empty names")
            if columns == [TIME_COLUMN]:
                raise InputError(f"{self._name}: the capture has no channels besides {TIME_COLUMN}")
            return columns, comments
        raise InputError(f"{self._name}: empty file (no header row)")

    def _first_rows(self) -> np.ndarray:
        """Read a first block so the sample rate can come from ``t``."""
        return self._read_rows(4096)

    def _make_info(self, comments: dict, sample_rate_hz: float | None) -> CaptureInfo:
        metadata = {}
        if "metadata" in comments:
            metadata = parse_metadata_json(comments["metadata"], self._name)
        if sample_rate_hz is None and "sample_rate_hz" in comments:
            try:
                sample_rate_hz = float(comments["sample_rate_hz"])
            except ValueError:
                raise InputError(f"{self._name}: sample_rate_hz {comments['sample_rate_hz']!r} is not a number") from None
        has_t = TIME_COLUMN in self._columns
        if sample_rate_hz is None and has_t and len(self._pending_rows) >= 2:
            t = self._pending_rows[:, self._columns.index(TIME_COLUMN)]
            sample_rate_hz = (len(t) - 1) / (t[-1] - t[0]) if t[-1] != t[0] else float("nan")
        if sample_rate_hz is None:
            raise InputError(f"{self._name}: no sample rate; add '# sample_rate_hz: ...', a t column, or --sample-rate")
        if not np.isfinite(sample_rate_hz) or sample_rate_hz <= 0:
            raise InputError(f"{self._name}: sample rate {sample_rate_hz!r} must be a positive number")
        self._t0 = float(self._pending_rows[0, self._columns.index(TIME_COLUMN)]) if has_t and len(self._pending_rows) else 0.0
        channels = tuple(
            ChannelSpec(name, comments.get(f"units.{name}", "")) for name in self._columns if name != TIME_COLUMN
        )
        return CaptureInfo(self._name, "csv", float(sample_rate_hz), channels, None, metadata)

    def _read_rows(self, n_rows: int) -> np.ndarray:
        first_line = self._line_no + 1
        lines = list(itertools.islice(self._stream, n_rows))
        self._line_no += len(lines)
        lines = [ln for ln in lines if ln.strip() and not ln.lstrip().startswith("#")]
        if not lines:
            return np.empty((0, len(self._columns)))
        try:
            rows = np.loadtxt(lines, delimiter=",", dtype=np.float64, ndmin=2)
        except ValueError as exc:
            raise InputError(f"{self._name}: near line {first_line}: {_short(exc)}") from None
        if rows.shape[1] != len(self._columns):
            raise InputError(
                f"{self._name}: near line {first_line}: rows have {rows.shape[1]} columns, header has {len(self._columns)}"
            )
        return rows

    def _check_time(self, t: np.ndarray, start: int) -> None:
        fs = self.info.sample_rate_hz
        expected = self._t0 + (start + np.arange(len(t))) / fs
        tolerance = _T_TOLERANCE_PERIODS / fs + _T_RELATIVE_DIGITS * np.abs(expected)
        bad = np.flatnonzero(~(np.abs(t - expected) <= tolerance))
        if bad.size:
            i = int(bad[0])
            raise InputError(
                f"{self._name}: non-uniform sampling: t={t[i]!r} at sample {start + i}, expected {expected[i]:.10g}"
            )

    def blocks(self, channels: Sequence[str], block_samples: int) -> Iterator[Chunk]:
        index = {name: self._columns.index(name) for name in channels}
        t_index = self._columns.index(TIME_COLUMN) if TIME_COLUMN in self._columns else None
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
        if self._stream is not sys.stdin and getattr(self, "_stream", None) is not None:
            try:
                self._stream.close()
            except OSError:
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
        # repr-exact float64 round trip: 17 significant digits
        table = np.column_stack([t, *(np.asarray(data[name], dtype=np.float64) for name in self._names)])
        np.savetxt(self._stream, table, delimiter=",", fmt="%.17g")
        self._written += n

    def write_truth(self, truth: Mapping[str, np.ndarray]) -> None:
        """CSV carries no ground truth; the HDF5 layout does."""

    def close(self) -> None:
        self._stream.flush()
