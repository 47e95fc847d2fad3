"""MATLAB captures (``.mat``): version 5 (and 4) through scipy.io, version 7.3 (HDF5) through h5py, streamed.

Many labs' DAQ scripts end in ``save('capture.mat', 'dither', 'deflection',
'fs')`` (the thesis's own tool chain was MATLAB).  Each variable is a
:class:`~afmtool.io.variables.Variable`: vectors are channels by name,
``--channel deflection=NAME`` (or ``NAME:K`` for column ``K`` of a matrix)
maps one, and a scalar ``fs``, ``Fs``, ``sample_rate`` (Hz) or ``dt`` (s) is
the sample rate, unless ``--sample-rate`` is given.

**Version 5** files are read by :func:`scipy.io.loadmat`, which reads a
variable whole: the variable list comes first (:func:`scipy.io.whosmat`,
headers only), each size is checked against the file's and
:data:`MAX_V5_BYTES`, and only the variables needed are loaded, first in a
forked child (:mod:`afmtool.io.isolated`): scipy's C reader crashes on some
damaged files, and the child dies in afmtool's place.

**Version 7.3** files are HDF5 with a 512-byte MATLAB header; a variable is a
dataset with a ``MATLAB_class`` attribute, stored transposed (MATLAB's r x c
is HDF5's (c, r)).  Datasets are read in blocks as the capture streams, with
the HDF5 reader's guards (nothing behind external or soft links, no claims
beyond the file, attributes read in a child that may be stopped).  A
dataset's unit attribute, under any common name (``units``, ``unit``,
``Unit``, ``UNITS``), gives the channel's units; MATLAB itself writes none.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path

import numpy as np

from afmtool.errors import InputError
from afmtool.io.capture import CaptureInfo, ChannelSpec, Chunk, ReaderBase
from afmtool.io.isolated import check_survives
from afmtool.io.variables import INTERVAL_NAMES, RATE_NAMES, ChannelSource, Variable, choose_channels, rate_variable

__all__ = ["MatReader", "MAX_V5_BYTES", "mat_version"]

#: Largest version-5 variable loaded (scipy reads a variable whole), bytes.
MAX_V5_BYTES = 2 << 30
#: Largest ratio of a v5 file's declared array bytes to its size (zlib-compressed variables stop near 1032).
_MAX_COMPRESSION = 1100
#: MATLAB classes that hold numbers.
_NUMERIC_CLASSES = frozenset({"double", "single", "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64"})
#: What scipy.io raises on a damaged file, at any depth.
_SCIPY_ERRORS = (ValueError, TypeError, KeyError, IndexError, EOFError, OverflowError, MemoryError, zlib.error,
                 AttributeError, UnicodeDecodeError, NotImplementedError, AssertionError)


def mat_version(path: Path) -> str:
    """``"7.3"`` for an HDF5-based MAT file, else ``"5"`` (scipy also reads version 4)."""
    try:
        with open(path, "rb") as handle:
            head = handle.read(128)
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror})") from None
    if len(head) == 128 and head[124:126] in (b"\x00\x02", b"\x02\x00"):
        return "7.3"
    return "5"


class MatReader(ReaderBase):
    """Read a MATLAB ``.mat`` file (version 4, 5 or 7.3) as a capture.

    Parameters
    ----------
    path : Path
        The ``.mat`` file; opened read-only.
    sample_rate_hz : float, optional
        Overrides (or supplies) the rate variable.
    channel_map : mapping of str to str, optional
        ``{"deflection": "defl"}`` or ``{"deflection": "data:1"}`` (see :mod:`afmtool.io.variables`).
    """

    def __init__(self, path: Path, sample_rate_hz: float | None = None, channel_map: Mapping[str, str] | None = None) -> None:
        self._path = Path(path)
        self._version = mat_version(self._path)
        self._source: _V5 | _V73 = _V73(self._path) if self._version == "7.3" else _V5(self._path)
        try:
            variables = self._source.variables()
            self._sources = choose_channels(self._path, variables, channel_map)
            if sample_rate_hz is None:
                sample_rate_hz = rate_variable(self._path, self._source.scalars(variables))
            if sample_rate_hz is None:
                raise InputError(f"{self._path}: no sample rate (no {', '.join(RATE_NAMES[:4])} or "
                                 f"{INTERVAL_NAMES[0]} variable); give --sample-rate")
            if not (math.isfinite(sample_rate_hz) and sample_rate_hz > 0):
                raise InputError(f"{self._path}: sample rate {sample_rate_hz!r} must be a positive number")
            self._source.prepare(self._sources)
            n = variables[next(iter(self._sources.values())).variable].n_samples
            channels = tuple(ChannelSpec(name, variables[s.variable].units) for name, s in self._sources.items())
            metadata = {"instrument": {"vendor_format": f"MATLAB v{self._version}", "variables": list(variables)[:200]}}
            self.info = CaptureInfo(str(self._path), "mat", float(sample_rate_hz), channels, n, metadata)
        except BaseException:
            self._source.close()
            raise

    def blocks(self, channels: Sequence[str], block_samples: int) -> Iterator[Chunk]:
        n = self.info.n_samples
        for start in range(0, n, block_samples):
            stop = min(start + block_samples, n)
            yield Chunk(start, {name: self._source.read(self._sources[name], start, stop) for name in channels})

    def truth(self) -> dict[str, np.ndarray]:
        return {}

    def close(self) -> None:
        self._source.close()


def _vector_shape(shape: tuple[int, ...]) -> tuple[int, int] | None:
    """(samples, columns) of a MATLAB array shape (r, c); the longer dimension is the samples; None past 2-D."""
    dims = [int(d) for d in shape]
    while len(dims) > 2 and dims[-1] == 1:
        dims.pop()
    if len(dims) == 1:
        dims.append(1)
    if len(dims) != 2 or min(dims) < 1:
        return None
    rows, columns = dims
    return (rows, columns) if rows >= columns else (columns, rows)


class _V5:
    """A version-5 (or 4) file, through scipy.io: variables listed from their headers, loaded when needed."""

    def __init__(self, path: Path) -> None:
        self._path = path
        self._loaded: dict[str, np.ndarray] = {}

    def _whos(self) -> list[tuple[str, tuple, str]]:
        from scipy.io import whosmat
        from scipy.io.matlab import MatReadError

        try:
            return whosmat(str(self._path))
        except OSError as exc:
            raise InputError(f"{self._path}: cannot read ({exc.strerror or _first_line(exc)})") from None
        except (*_SCIPY_ERRORS, MatReadError) as exc:
            raise InputError(f"{self._path}: not a readable MATLAB file ({_first_line(exc)})") from None

    def variables(self) -> dict[str, Variable]:
        size = self._path.stat().st_size
        variables, claimed = {}, 0
        for name, shape, kind in self._whos():
            dims = _vector_shape(shape) if kind in _NUMERIC_CLASSES else None
            if dims is None:
                variables[name] = Variable(name, None, None, kind if kind not in _NUMERIC_CLASSES else f"{len(shape)}-D {kind}")
                continue
            claimed += dims[0] * dims[1] * np.dtype(_numpy_type(kind)).itemsize
            variables[name] = Variable(name, dims[0], dims[1], kind)
        if claimed > _MAX_COMPRESSION * size + (1 << 16):
            raise InputError(f"{self._path}: its variables claim {claimed:,} bytes in a {size:,}-byte file")
        return variables

    def _load(self, names: Sequence[str]) -> None:
        from scipy.io import loadmat
        from scipy.io.matlab import MatReadError

        wanted = [name for name in names if name not in self._loaded]
        if not wanted:
            return

        def load():
            return loadmat(str(self._path), variable_names=wanted, squeeze_me=False, mat_dtype=False)

        # scipy's v5 reader is C code that a damaged file sends into a segmentation fault (the long fuzz
        # run, mat5 cases 486, 1490, ...): it reads in a child first, which may die instead
        check_survives(load, str(self._path), "scipy.io reading its variables")
        try:
            loaded = load()
        except OSError as exc:
            raise InputError(f"{self._path}: cannot read ({exc.strerror or _first_line(exc)})") from None
        except (*_SCIPY_ERRORS, MatReadError) as exc:
            raise InputError(f"{self._path}: not a readable MATLAB file ({_first_line(exc)})") from None
        for name in wanted:
            if name not in loaded:
                raise InputError(f"{self._path}: variable {name!r} could not be read")
            self._loaded[name] = np.asarray(loaded[name])

    def scalars(self, variables: Mapping[str, Variable]) -> dict[str, float | None]:
        names = [n for n in (*RATE_NAMES, *INTERVAL_NAMES) if n in variables]
        self._load([n for n in names if variables[n].numeric])
        values = {}
        for name in names:
            value = self._loaded.get(name)
            ok = value is not None and value.size == 1 and value.dtype.kind in "fiu" and np.isfinite(value.reshape(-1)[0])
            values[name] = float(value.reshape(-1)[0]) if ok else None
        return values

    def prepare(self, sources: Mapping[str, ChannelSource]) -> None:
        needed = {s.variable for s in sources.values()}
        self._load(sorted(needed))
        for name in needed:
            array = self._loaded[name]
            if array.nbytes > MAX_V5_BYTES:
                raise InputError(f"{self._path}: variable {name!r} is {array.nbytes:,} bytes; at most {MAX_V5_BYTES:,}")
            if array.dtype.kind not in "fiu":
                raise InputError(f"{self._path}: variable {name!r} holds {array.dtype}, not real numbers")
            rows, columns = array.shape[0], (array.shape[1] if array.ndim > 1 else 1)
            self._loaded[name] = array.reshape(rows, columns) if rows >= columns else array.reshape(rows, columns).T

    def read(self, source: ChannelSource, start: int, stop: int) -> np.ndarray:
        with np.errstate(invalid="ignore", over="ignore"):
            return np.array(self._loaded[source.variable][start:stop, source.column], dtype=np.float64)

    def close(self) -> None:
        self._loaded = {}


def _numpy_type(matlab_class: str) -> str:
    return {"double": "f8", "single": "f4"}.get(matlab_class, matlab_class.replace("uint", "u").replace("int", "i"))


class _V73:
    """A version-7.3 file: HDF5, each variable a dataset with MATLAB_class, read in blocks."""

    def __init__(self, path: Path) -> None:
        from afmtool.io.hdf5 import _open_h5, check_attributes_terminate

        self._path = path
        check_attributes_terminate(path)
        self._file = _open_h5(path)
        self._datasets: dict = {}

    def variables(self) -> dict[str, Variable]:
        import h5py

        from afmtool.io.hdf5 import _local_object, unit_attribute

        variables = {}
        try:
            for name in self._file:
                obj = _local_object(self._path, self._file, name)
                if obj is None:  # a link to nothing
                    variables[name] = Variable(name, None, None, "a link to nothing")
                    continue
                kind = _matlab_class(obj)
                if not isinstance(obj, h5py.Dataset) or kind not in _NUMERIC_CLASSES or obj.dtype.kind not in "fiu":
                    variables[name] = Variable(name, None, None, kind or type(obj).__name__.lower())
                    continue
                dims = _vector_shape(tuple(reversed(obj.shape)))  # HDF5 stores MATLAB's r x c as (c, r)
                if dims is None:
                    variables[name] = Variable(name, None, None, f"{obj.ndim}-D {kind}")
                    continue
                self._datasets[name] = obj
                variables[name] = Variable(name, dims[0], dims[1], kind, unit_attribute(self._path, name, obj.attrs))
        except (OSError, RuntimeError, KeyError, ValueError, TypeError) as exc:
            raise InputError(f"{self._path}: damaged MATLAB 7.3 (HDF5) structure ({_first_line(exc)})") from None
        return variables

    def scalars(self, variables: Mapping[str, Variable]) -> dict[str, float | None]:
        values = {}
        for name in (*RATE_NAMES, *INTERVAL_NAMES):
            if name in variables:
                dataset = self._datasets.get(name)
                ok = dataset is not None and dataset.size == 1
                value = float(np.asarray(dataset[()]).reshape(-1)[0]) if ok else None
                values[name] = value if value is not None and math.isfinite(value) else None
        return values

    def prepare(self, sources: Mapping[str, ChannelSource]) -> None:
        from afmtool.io.hdf5 import _check_claims

        needed = {s.variable: self._datasets[s.variable] for s in sources.values()}
        n = max(_vector_shape(tuple(reversed(d.shape)))[0] for d in needed.values())
        _check_claims(self._path, needed, n)

    def read(self, source: ChannelSource, start: int, stop: int) -> np.ndarray:
        dataset = self._datasets[source.variable]
        shape = dataset.shape  # (c, r) for MATLAB's r x c
        try:
            if len(shape) == 1:
                block = dataset[start:stop]
            elif shape[1] >= shape[0]:  # samples along HDF5's last axis: MATLAB's rows are the samples
                block = dataset[source.column, start:stop]
            else:
                block = dataset[start:stop, source.column]
        except (OSError, RuntimeError, ValueError) as exc:
            raise InputError(f"{self._path}: cannot read {source.variable} at sample {start} ({_first_line(exc)})") from None
        with np.errstate(invalid="ignore", over="ignore"):
            return np.asarray(block, dtype=np.float64).reshape(-1)

    def close(self) -> None:
        self._datasets = {}
        if self._file is not None:
            self._file.close()
            self._file = None


def _matlab_class(obj) -> str:
    """A dataset's ``MATLAB_class`` attribute as text ("" when absent or unreadable)."""
    try:
        value = obj.attrs.get("MATLAB_class", b"")
    except (OSError, RuntimeError, KeyError, TypeError):
        return ""
    if isinstance(value, np.ndarray) and value.size == 1:
        value = value.reshape(-1)[0]
    if isinstance(value, bytes):
        return value.decode("latin-1")
    return value if isinstance(value, str) else ""


def _first_line(exc: BaseException) -> str:
    return ((str(exc).strip().splitlines() or [type(exc).__name__])[0])[:200]
