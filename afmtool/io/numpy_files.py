"""NumPy captures: ``.npy`` (one array) and ``.npz`` (named arrays), streamed.

**.npy**: a 1-D array is one channel, named after the file (``deflection.npy``
gives ``deflection``); a 2-D array is one channel per column, named ``0``,
``1``, ...: its longer dimension is the samples, so ``(n, 3)`` and ``(3, n)``
are both three channels.  ``--channel deflection=1`` reads column 1 as the
deflection (only mapped columns are read).  The array is memory-mapped
(:class:`afmtool.io.mapped.MappedArray`), whatever its order, so it streams in
flat memory.

**.npz**: each array is a variable (:mod:`afmtool.io.variables`): vectors are
channels by name, ``--channel deflection=NAME`` or ``NAME:K`` maps one, and a
scalar ``fs`` (or ``dt``...) is the sample rate.  Members are read as streams
from the archive, block by block, stored or deflated (``savez_compressed``).

Neither format records units or a rate: channels without units are taken in
afmtool's units (``--units`` says otherwise), and the rate is ``--sample-rate``
or the ``.npz``'s rate variable.  Object and structured arrays are refused
(nothing is unpickled), and so are headers that claim more data than the file
holds (``.npy``) or than deflate can pack into a member (``.npz``).
"""

from __future__ import annotations

import math
import tokenize
import zipfile
import zlib
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

from afmtool.errors import InputError
from afmtool.io.capture import CaptureInfo, ChannelSpec, Chunk, ReaderBase
from afmtool.io.mapped import MappedArray, MappedSamples
from afmtool.io.variables import Variable, choose_channels, rate_variable

__all__ = ["NpyReader", "NpzReader"]

#: Largest ratio of an .npz member's array to its compressed size (deflate stops near 1032).
_MAX_COMPRESSION = 1100
#: Longest .npy header read, bytes (numpy's own default limit).
_MAX_HEADER = 10_000


class _ArrayHeader(NamedTuple):
    """An .npy header: the array's shape, dtype and order, and where its data starts."""

    shape: tuple[int, ...]
    dtype: np.dtype
    fortran_order: bool
    data_offset: int


def _read_header(stream, where: str) -> _ArrayHeader:
    """The .npy header at the start of ``stream`` (a file or a zip member), with numpy's own parser, bounded."""
    from numpy.lib import format as npy

    try:
        version = npy.read_magic(stream)
        if version == (1, 0):
            shape, fortran, dtype = npy.read_array_header_1_0(stream, max_header_size=_MAX_HEADER)
        elif version in ((2, 0), (3, 0)):
            shape, fortran, dtype = npy.read_array_header_2_0(stream, max_header_size=_MAX_HEADER)
        else:
            raise ValueError(f"unknown .npy version {version}")
    except (ValueError, TypeError, SyntaxError, EOFError, OSError, zlib.error, zipfile.BadZipFile,
            RecursionError, MemoryError, UnicodeDecodeError, tokenize.TokenError) as exc:
        raise InputError(f"{where}: not a readable .npy array ({str(exc).splitlines()[0][:200] if str(exc) else type(exc).__name__})") from None
    return _ArrayHeader(tuple(int(n) for n in shape), np.dtype(dtype), bool(fortran), stream.tell())


def _kind(header: _ArrayHeader) -> str:
    """What the array holds, for a message, or ``""`` when it is a numeric array afmtool reads."""
    dtype = header.dtype
    if dtype.hasobject or dtype.fields is not None:
        return f"{dtype} (objects or records)"
    if dtype.kind not in "fiu":
        return f"{dtype}"
    if len(header.shape) > 2:
        return f"a {len(header.shape)}-D array"
    return ""


def _samples_and_columns(shape: tuple[int, ...]) -> tuple[int, int, bool]:
    """(samples, columns, samples_first): the longer dimension of a 2-D array is the samples."""
    if len(shape) == 0:
        return 1, 1, True
    if len(shape) == 1:
        return shape[0], 1, True
    rows, columns = shape
    return (rows, columns, True) if rows >= columns else (columns, rows, False)


class NpyReader(MappedSamples, ReaderBase):
    """Read a NumPy ``.npy`` array as a capture, memory-mapped.

    Parameters
    ----------
    path : Path
        The ``.npy`` file.
    sample_rate_hz : float
        The rate (an .npy records none); required.
    channel_map : mapping of str to str, optional
        ``{"deflection": "0"}``: columns to read and their channel names.
    """

    def __init__(self, path: Path, sample_rate_hz: float | None = None, channel_map: Mapping[str, str] | None = None) -> None:
        self._path = Path(path)
        try:
            with open(self._path, "rb") as handle:
                header = _read_header(handle, str(self._path))
                file_size = handle.seek(0, 2)
        except OSError as exc:
            raise InputError(f"{self._path}: cannot read ({exc.strerror})") from None
        kind = _kind(header)
        if kind or len(header.shape) == 0:
            raise InputError(f"{self._path}: the array holds {kind or 'one number'}; afmtool reads 1-D or 2-D numeric arrays")
        n, m, samples_first = _samples_and_columns(header.shape)
        columns = self._columns(m, channel_map)
        # C order with samples first, or F order with channels first, keeps a sample's columns together
        order = "C" if samples_first != header.fortran_order else "F"
        self._array = MappedArray(str(self._path), header.data_offset, header.dtype.str, n, m, order, columns)
        self._array.check_fits(file_size)
        if sample_rate_hz is None:
            raise InputError(f"{self._path}: no sample rate (an .npy records none); give --sample-rate")
        if not (math.isfinite(sample_rate_hz) and sample_rate_hz > 0):
            raise InputError(f"{self._path}: sample rate {sample_rate_hz!r} must be a positive number")
        channels = tuple(ChannelSpec(name) for name in columns)
        metadata = {"instrument": {"vendor_format": "NumPy .npy", "shape": list(header.shape)}}
        self.info = CaptureInfo(str(self._path), "npy", float(sample_rate_hz), channels, n, metadata)

    def _columns(self, m: int, channel_map: Mapping[str, str] | None) -> dict[str, int]:
        names = [self._path.stem] if m == 1 else [str(k) for k in range(m)]
        if not channel_map:
            return {name: k for k, name in enumerate(names)}
        chosen = {}
        for channel, source in channel_map.items():
            source = source.strip()
            if source in names:
                chosen[channel] = names.index(source)
            elif m == 1 and source == "0":
                chosen[channel] = 0
            else:
                raise InputError(f"{self._path}: --channel {channel}={source}: the array's columns are {', '.join(names[:20])}")
        return chosen


class _Member(NamedTuple):
    """An .npz member: its zip name, its header, and the variable it is."""

    member: str
    header: _ArrayHeader
    variable: Variable


class NpzReader(ReaderBase):
    """Read a NumPy ``.npz`` archive of named arrays as a capture, streamed from the archive.

    Parameters
    ----------
    path : Path
        The ``.npz`` file.
    sample_rate_hz : float, optional
        Overrides (or supplies) the rate variable.
    channel_map : mapping of str to str, optional
        ``{"deflection": "defl"}`` or ``{"deflection": "data:1"}`` (see :mod:`afmtool.io.variables`).
    """

    def __init__(self, path: Path, sample_rate_hz: float | None = None, channel_map: Mapping[str, str] | None = None) -> None:
        self._path = Path(path)
        try:
            self._zip = zipfile.ZipFile(self._path)
        except (zipfile.BadZipFile, EOFError, ValueError, NotImplementedError) as exc:
            raise InputError(f"{self._path}: not a readable .npz (not a complete ZIP archive: {_first_line(exc)})") from None
        except OSError as exc:
            raise InputError(f"{self._path}: cannot read ({exc.strerror})") from None
        try:
            self._open(sample_rate_hz, channel_map)
        except (zipfile.BadZipFile, zlib.error, EOFError, ValueError, NotImplementedError, RuntimeError, OSError) as exc:
            self._zip.close()
            raise InputError(f"{self._path}: damaged .npz ({_first_line(exc)})") from None
        except BaseException:
            self._zip.close()
            raise

    def _open(self, sample_rate_hz: float | None, channel_map: Mapping[str, str] | None) -> None:
        self._members = self._read_members()
        variables = {name: m.variable for name, m in self._members.items()}
        self._sources = choose_channels(self._path, variables, channel_map)
        if sample_rate_hz is None:
            sample_rate_hz = rate_variable(self._path, self._scalars())
        if sample_rate_hz is None:
            raise InputError(f"{self._path}: no sample rate (no fs, Fs, sample_rate or dt array); give --sample-rate")
        if not (math.isfinite(sample_rate_hz) and sample_rate_hz > 0):
            raise InputError(f"{self._path}: sample rate {sample_rate_hz!r} must be a positive number")
        first = next(iter(self._sources.values()))
        n = variables[first.variable].n_samples
        channels = tuple(ChannelSpec(name) for name in self._sources)
        metadata = {"instrument": {"vendor_format": "NumPy .npz", "arrays": list(variables)[:200]}}
        self.info = CaptureInfo(str(self._path), "npz", float(sample_rate_hz), channels, n, metadata)

    def _read_members(self) -> dict[str, _Member]:
        members = {}
        for item in self._zip.infolist():
            if not item.filename.endswith(".npy") or item.is_dir():
                continue
            name = item.filename[: -len(".npy")]
            with self._zip.open(item) as stream:
                header = _read_header(stream, f"{self._path}: {item.filename}")
            claimed = math.prod(header.shape) * header.dtype.itemsize
            if claimed > _MAX_COMPRESSION * item.compress_size + (1 << 16) or claimed > item.file_size:
                raise InputError(f"{self._path}: {item.filename} claims {claimed:,} bytes in a member of "
                                 f"{item.file_size:,} ({item.compress_size:,} packed)")
            kind = _kind(header)
            if kind:
                variable = Variable(name, None, None, kind)
            else:
                n, m, _ = _samples_and_columns(header.shape)
                variable = Variable(name, n, m, "numbers")
            members[name] = _Member(item.filename, header, variable)
        if not members:
            raise InputError(f"{self._path}: no arrays (.npy members); not an .npz")
        return members

    def _scalars(self) -> dict[str, float | None]:
        """The one-element arrays, as numbers (None where one is not a finite real)."""
        values = {}
        for name, member in self._members.items():
            if member.variable.numeric and math.prod(member.header.shape) == 1:
                with self._zip.open(member.member) as stream:
                    stream.read(member.header.data_offset)
                    raw = stream.read(member.header.dtype.itemsize)
                value = np.frombuffer(raw, dtype=member.header.dtype)
                values[name] = float(value[0]) if value.size == 1 and np.isfinite(value[0]) else None
        return values

    def blocks(self, channels: Sequence[str], block_samples: int) -> Iterator[Chunk]:
        streams = {name: _ColumnStream(self._zip, self._members[self._sources[name].variable], self._sources[name].column)
                   for name in channels}
        try:
            for start in range(0, self.info.n_samples, block_samples):
                count = min(block_samples, self.info.n_samples - start)
                try:
                    data = {name: streams[name].read(count) for name in channels}
                except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError) as exc:
                    raise InputError(f"{self._path}: cannot read at sample {start} ({_first_line(exc)})") from None
                yield Chunk(start, data)
        finally:
            for stream in streams.values():
                stream.close()

    def truth(self) -> dict[str, np.ndarray]:
        return {}

    def close(self) -> None:
        self._zip.close()


class _ColumnStream:
    """One column of an .npz member, read in order from the (stored or deflated) member stream.

    A sample-major array (rows of columns) is read a block of rows at a time and the
    column taken; a column-major one is skipped to its column, which is then contiguous.
    """

    def __init__(self, archive: zipfile.ZipFile, member: _Member, column: int) -> None:
        header = member.header
        self._dtype = header.dtype
        self._n, self._m, samples_first = _samples_and_columns(header.shape)
        self._interleaved = samples_first != header.fortran_order and self._m > 1
        self._column = column
        self._stream = archive.open(member.member)
        skip = header.data_offset + (0 if self._interleaved else column * self._n * self._dtype.itemsize)
        while skip > 0:
            got = len(self._stream.read(min(skip, 1 << 20)))
            if got == 0:
                raise EOFError("member ends before its data")
            skip -= got

    def read(self, count: int) -> np.ndarray:
        width = self._m if self._interleaved else 1
        size = count * width * self._dtype.itemsize
        raw = self._stream.read(size)
        if len(raw) != size:
            raise EOFError(f"member ends {size - len(raw)} bytes early")
        values = np.frombuffer(raw, dtype=self._dtype)
        if self._interleaved:
            values = values.reshape(count, width)[:, self._column]
        with np.errstate(invalid="ignore", over="ignore"):
            return values.astype(np.float64)

    def close(self) -> None:
        self._stream.close()


def _first_line(exc: BaseException) -> str:
    return ((str(exc).strip().splitlines() or [type(exc).__name__])[0])[:200]
