"""Open any capture by its path; create a writer for any output format.

Readers are chosen from one table, :data:`READERS`, by suffix (and by content
where formats share a suffix: LabOne and AFM Workshop ``.csv``, Chiaro and
NT-MDT ``.txt``; a ROS2 bag is a directory holding ``metadata.yaml``); writers by
an explicit format name or the output suffix.
"""

from __future__ import annotations

import io
import os
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple, TextIO

from afmtool.errors import InputError
from afmtool.io.capture import CaptureReader, CaptureWriter, ChannelSpec

if TYPE_CHECKING:
    from afmtool.io.stack import CaptureOptions

__all__ = ["FORMATS", "READERS", "SELECTIONS", "ReaderEntry", "Selection", "check_writable_rate", "companion_files",
           "open_capture", "create_writer", "format_for_path", "input_format", "reader_entry"]

#: Output format names accepted by ``--format`` and ``convert``.
FORMATS = ("hdf5", "csv", "ros1", "ros2-mcap", "ros2-sqlite3")

#: What a reader may be asked for beyond its path and ``--sample-rate``, as keyword arguments.
SELECTIONS = ("segment", "curve", "group")


class Selection(NamedTuple):
    """Which part of a file to read: ``--segment`` (name or number), ``--curve`` (``N`` or ``X,Y``), ``--group``."""

    segment: str | None = None
    curve: str | None = None
    group: str | None = None


class ReaderEntry(NamedTuple):
    """One input format: the suffixes that name it, the reader class, and what that reader takes itself.

    ``takes`` lists the keyword arguments the class accepts: ``channel_map`` (the
    format maps ``--channel NAME=SOURCE`` onto its own datasets or variables, instead
    of a rename), ``topic_map`` (bags), and the selections it makes natively
    (``segment``, ``curve``, ``group``).  ``--segment`` on a reader that does not take it is
    applied from the segments it reports; ``--curve`` and ``--group`` are refused.
    """

    format: str
    suffixes: tuple[str, ...]
    module: str
    reader: str
    takes: frozenset[str] = frozenset()
    description: str = ""


#: Every input format, in the order ``--help`` and error messages list them.  Adding a format is adding a row
#: (and, if its suffix is shared, a sniff in :func:`_sniff`).
READERS: tuple[ReaderEntry, ...] = (
    ReaderEntry("hdf5", (".h5", ".hdf5", ".hdf"), "hdf5", "Hdf5Reader", frozenset({"channel_map"}), "afmtool HDF5"),
    ReaderEntry("csv", (".csv",), "csv", "CsvReader", frozenset(), "CSV or a text export"),
    ReaderEntry("ros1", (".bag",), "rosbag", "RosbagReader", frozenset({"topic_map"}), "ROS1 bag"),
    ReaderEntry("ros2", (".mcap", ".db3"), "rosbag", "RosbagReader", frozenset({"topic_map"}), "ROS2 bag folder"),
    ReaderEntry("ibw", (".ibw",), "ibw", "IbwReader", frozenset(), "Igor binary wave"),
    ReaderEntry("jpk", (".jpk-force", ".jpk-qi-series", ".jpk-force-map", ".jpk-qi-data"), "jpk", "JpkReader",
                frozenset({"segment", "curve"}), "JPK force curve, map or QI data"),
    ReaderEntry("tdms", (".tdms",), "tdms", "TdmsReader", frozenset({"group"}), "NI TDMS"),
    ReaderEntry("wav", (".wav",), "wav", "WavReader", frozenset(), "WAV"),
    ReaderEntry("mat", (".mat",), "matlab", "MatReader", frozenset({"channel_map"}), "MATLAB v5 or v7.3"),
    ReaderEntry("npz", (".npz",), "numpy_files", "NpzReader", frozenset({"channel_map"}), "NumPy .npz"),
    ReaderEntry("npy", (".npy",), "numpy_files", "NpyReader", frozenset({"channel_map"}), "NumPy .npy"),
    ReaderEntry("text", (".txt",), "text_exports", "TextExportReader", frozenset(), "text export"),
    ReaderEntry("chiaro", (".zip",), "chiaro", "ChiaroReader", frozenset(), "Optics11 Chiaro export"),
    # recognised by content (see _sniff, input_format), never by suffix alone
    ReaderEntry("zarr", (), "zarr_capture", "ZarrReader", frozenset(), "Zarr store"),
    ReaderEntry("labone-csv", (), "labone", "LaboneCsvReader", frozenset(), "Zurich Instruments LabOne CSV"),
    ReaderEntry("labone-hdf5", (), "labone", "LaboneHdf5Reader", frozenset({"segment"}), "Zurich Instruments LabOne HDF5"),
    ReaderEntry("afm-workshop", (), "text_exports", "AfmWorkshopReader", frozenset(), "AFM Workshop CSV"),
    ReaderEntry("ntmdt", (), "text_exports", "NtmdtReader", frozenset(), "NT-MDT Nova text export"),
)
_BY_FORMAT = {entry.format: entry for entry in READERS}
_BY_SUFFIX = {suffix: entry.format for entry in READERS for suffix in entry.suffixes}
#: Suffixes of several dots, matched before Path.suffix.
_LONG_SUFFIXES = tuple(sorted((s for s in _BY_SUFFIX if s.count(".") > 1 or "-" in s), key=len, reverse=True))
#: Output suffixes and the format they imply.
_OUTPUT_SUFFIXES = {".h5": "hdf5", ".hdf5": "hdf5", ".hdf": "hdf5", ".csv": "csv", ".bag": "ros1",
                    ".mcap": "ros2-mcap", ".db3": "ros2-sqlite3"}


def reader_entry(fmt: str) -> ReaderEntry:
    """The :class:`ReaderEntry` of an input format name (as :func:`input_format` returns it)."""
    return _BY_FORMAT[fmt]


def input_format(path: Path | str) -> str:
    """The format of an existing input: by suffix (and content, where a suffix is shared), or a ROS2 bag directory."""
    if str(path) == "-":
        return "csv"
    from afmtool.io.zarr_capture import is_zarr_store

    if is_zarr_store(path):
        return "zarr"
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such file")
    if path.is_dir():
        if (path / "metadata.yaml").is_file():
            return "ros2"
        raise InputError(f"{path}: a directory that is not a ROS2 bag (no metadata.yaml)")
    fmt = _BY_SUFFIX.get(_suffix(path))
    if fmt is None:
        known = ", ".join(sorted(_BY_SUFFIX))
        raise InputError(f"{path}: unknown extension {path.suffix or '(none)'!r}; expected one of {known}")
    if path.stat().st_size == 0:
        raise InputError(f"{path}: empty file")
    return _sniff(path, fmt)


def _sniff(path: Path, fmt: str) -> str:
    """The format of a file whose suffix several formats share, from its first bytes."""
    if fmt in ("hdf5", "csv"):
        from afmtool.io.labone import sniff_labone

        fmt = sniff_labone(path, fmt)
    if fmt in ("csv", "text"):
        from afmtool.io.text_exports import sniff_text_export

        fmt = sniff_text_export(path, fmt)
    return fmt


def _suffix(path: Path) -> str:
    name = path.name.lower()
    for suffix in _LONG_SUFFIXES:
        if name.endswith(suffix):
            return suffix
    return path.suffix.lower()


def format_for_path(path: Path | str) -> str:
    """The output format implied by an output path's suffix."""
    if str(path) == "-":
        return "csv"
    fmt = _OUTPUT_SUFFIXES.get(Path(path).suffix.lower())
    if fmt is None:
        raise InputError(f"{path}: cannot tell the output format from the extension; give --format")
    return fmt


def open_capture(
    path: Path | str,
    options: CaptureOptions | None = None,
    *,
    channel_map: Mapping[str, str] | None = None,
    topic_map: Mapping[str, str] | None = None,
    sample_rate_hz: float | None = None,
    segment: str | None = None,
    curve: str | None = None,
    group: str | None = None,
) -> CaptureReader:
    """Open a capture for streaming; use as a context manager or call ``close``.

    ``channel_map`` names HDF5 datasets (``{"deflection": "/s"}``), MATLAB or
    NumPy variables (``{"deflection": "defl"}``, ``"data:1"`` for a column), and
    renames channels (``{"deflection": "CH2"}``) for every other format but
    bags.  ``segment`` (a name or a number from 0) reads one segment of a
    segmented file; ``curve`` (``N`` or ``X,Y``) one curve of a JPK force map or
    QI data file; ``group`` (a name or number) one group of a TDMS file.

    With ``options`` (:class:`afmtool.io.stack.CaptureOptions`) the whole reader stack is
    applied (:func:`afmtool.io.stack.open_capture`: units, calibration, a synthesised drive,
    the sample hash), and the keywords must not be given; without, the file as recorded.
    """
    if options is not None:
        given = (channel_map, topic_map, sample_rate_hz, segment, curve, group)
        if any(value is not None and value != {} for value in given):
            raise TypeError("give the format's keywords inside CaptureOptions, not beside it")
        from afmtool.io.stack import open_capture as open_stack

        return open_stack(path, options)
    fmt = input_format(path)
    entry = _BY_FORMAT[fmt]
    from afmtool.runtime.input_guard import register_input

    register_input(path)  # so that no output of this run can overwrite it
    for companion in companion_files(path, fmt):
        register_input(companion)  # nor any other file of a multi-file input
    options = {"channel_map": channel_map, "topic_map": topic_map, "segment": segment, "curve": curve, "group": group}
    _check_options(path, entry, options)
    native = {key: value for key, value in options.items() if value and key in entry.takes}
    watch = _stdin_watch() if str(path) == "-" else None
    if watch is not None:
        from afmtool.io.csv import CsvReader, _text_stream

        reader = CsvReader(path, sample_rate_hz, stream=_text_stream(io.BufferedReader(watch, buffer_size=1 << 16)))
    else:
        reader = _open_entry(path, entry, sample_rate_hz, native)
    try:
        rename = channel_map if "channel_map" not in entry.takes else None
        reader = _views(reader, rename, segment if "segment" not in entry.takes else None)
    except BaseException:
        reader.close()
        raise
    if watch is not None:
        from afmtool.io.stdin_watch import WatchedReader

        reader = WatchedReader(reader, watch)
    return reader


def _stdin_watch():
    """stdin as a :class:`~afmtool.io.stdin_watch.WatchedStdin` (None where it has no descriptor to watch)."""
    from afmtool.io.stdin_watch import WatchedStdin, stdin_timeout

    try:
        fd = sys.stdin.fileno()
    except (AttributeError, OSError, ValueError):
        return None
    return WatchedStdin(fd, stdin_timeout())


def companion_files(path: Path | str, fmt: str) -> list[Path]:
    """The files beside ``path`` that belong to the same capture, which no output may replace.

    A LabOne CSV export is a folder of sample files (``STEM_00000.csv``, ...) and
    header files (``STEM_header_00000.csv``, where the clockbase is); a TDMS
    file may have its ``.tdms_index``; a ROS2 storage file (``.mcap``,
    ``.db3``) given on its own lies in its bag folder.  Only files that
    exist are returned; listing the folder is one pass over its names.
    """
    import re

    if str(path) == "-":
        return []
    path = Path(path)
    found: list[Path] = []
    if fmt == "labone-csv":
        match = re.match(r"^(?P<stem>.*)_(?:header_)?\d+\.csv$", path.name)
        found.append(path.with_name(f"{path.stem}_header.csv"))
        if match:
            sibling = re.compile(re.escape(match["stem"]) + r"_(?:header_)?\d+\.csv")
            try:
                found += [path.with_name(e.name) for e in os.scandir(path.parent) if sibling.fullmatch(e.name)]
            except OSError:
                pass
    elif fmt == "tdms":
        found.append(path.with_name(path.name + "_index"))
    elif fmt == "ros2" and path.is_file() and (path.parent / "metadata.yaml").is_file():
        found.append(path.parent)
    return [p for p in found if p != path and os.path.lexists(p)]


def _check_options(path, entry: ReaderEntry, options: Mapping) -> None:
    """Refuse an option the format has no meaning for, naming what it is for."""
    if options["topic_map"] and "topic_map" not in entry.takes:
        hint = {"hdf5": "; use --channel NAME=/dataset for HDF5", "csv": "; CSV columns are channels",
                "zarr": "; use --channel NAME=ARRAY for Zarr"}.get(entry.format, "")
        raise InputError(f"{path}: --topic maps bag topics{hint or '; use --channel NAME=CHANNEL'}")
    if options["channel_map"] and "topic_map" in entry.takes:
        raise InputError(f"{path}: --channel maps HDF5 datasets and renames channels; use --topic for bags")
    for key, what in (("curve", "a curve of a JPK force map or QI data file"), ("group", "a group of a TDMS file")):
        if options[key] is not None and key not in entry.takes:
            raise InputError(f"{path}: --{key} selects {what}; this is a {entry.description or entry.format} file")


def _open_entry(path, entry: ReaderEntry, sample_rate_hz: float | None, native: Mapping) -> CaptureReader:
    import importlib

    reader_class = getattr(importlib.import_module(f"afmtool.io.{entry.module}"), entry.reader)
    if entry.format == "zarr":  # a folder or an fsspec URL, not a local Path
        return reader_class(str(path), sample_rate_hz)
    return reader_class(path if str(path) == "-" else Path(path), sample_rate_hz=sample_rate_hz, **native)


def _views(reader: CaptureReader, channel_map: Mapping[str, str] | None, segment: str | None):
    import dataclasses

    from afmtool.io.views import SEGMENTS_KEY, RenamedView, SegmentView, segments_from_metadata, select_segment

    info = reader.info
    if not info.segments and SEGMENTS_KEY in info.metadata:
        segments = segments_from_metadata(info.metadata, info.source, info.n_samples)
        reader.info = dataclasses.replace(info, segments=segments)
    if segment is not None:
        reader = SegmentView(reader, select_segment(reader.info.segments, segment, info.source))
    if channel_map:
        reader = RenamedView(reader, channel_map)
    return reader


def check_writable_rate(sample_rate_hz: float, target: Path | str) -> None:
    """Refuse a sample rate no output can carry: not finite, not positive, or with a period
    (1/rate, the step of a CSV ``t`` column and of bag time stamps) that overflows or is subnormal.

    Every writer stores the rate or the period; an infinite one made an output
    that nothing, afmtool included, could read back.
    """
    import math

    try:
        rate = float(sample_rate_hz)
    except (TypeError, ValueError):
        raise InputError(f"{target}: sample rate {sample_rate_hz!r} is not a number") from None
    period = 1.0 / rate if math.isfinite(rate) and rate > 0 else math.nan
    if not (math.isfinite(period) and period >= sys.float_info.min):
        raise InputError(
            f"{target}: sample rate {rate!r} Hz cannot be written (it must be finite and positive, "
            f"with a finite, normal period 1/rate); give --sample-rate"
        )


def create_writer(
    target: Path | TextIO,
    fmt: str,
    sample_rate_hz: float,
    channels: Sequence[ChannelSpec],
    metadata: Mapping | None = None,
    *,
    compression: str | None = None,
) -> CaptureWriter:
    """A writer for ``fmt`` at ``target`` (a path, or a text stream for CSV)."""
    if fmt not in FORMATS:
        raise InputError(f"format {fmt!r} must be one of {', '.join(FORMATS)}")
    check_writable_rate(sample_rate_hz, target if isinstance(target, Path) else "-")
    if fmt == "csv":
        from afmtool.io.csv import CsvWriter

        if isinstance(target, Path):
            stream = open(target, "w", encoding="utf-8", newline="")  # noqa: SIM115 - _ClosingCsvWriter closes it with the writer
            return _ClosingCsvWriter(CsvWriter(stream, sample_rate_hz, channels, metadata), stream)
        return CsvWriter(target if target is not None else sys.stdout, sample_rate_hz, channels, metadata)
    if not isinstance(target, Path):
        raise InputError(f"format {fmt} cannot be written to a stream; only csv can")
    if fmt == "hdf5":
        from afmtool.io.hdf5 import Hdf5Writer

        return Hdf5Writer(target, sample_rate_hz, channels, metadata, compression=compression)
    from afmtool.io.rosbag import RosbagWriter

    version = "ros1" if fmt == "ros1" else "ros2"
    storage = "sqlite3" if fmt == "ros2-sqlite3" else "mcap"
    return RosbagWriter(target, sample_rate_hz, channels, metadata, version=version, storage=storage)


class _ClosingCsvWriter:
    """A CSV writer that owns its file."""

    def __init__(self, writer, stream) -> None:
        self._writer, self._stream = writer, stream

    def write(self, data) -> None:
        self._writer.write(data)

    def write_truth(self, truth) -> None:
        self._writer.write_truth(truth)

    def close(self) -> None:
        self._writer.close()
        self._stream.close()
