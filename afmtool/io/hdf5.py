"""HDF5 captures in the afmtool layout, and foreign HDF5 files by mapping.

Layout::

    /                 attrs: sample_rate_hz (float), metadata (JSON string, optional)
    /channels/<name>  1-D dataset, attr units
    /truth/<name>     optional simulator ground truth; analyses never read it

A foreign file is read by naming datasets: ``{"deflection": "/s"}`` plus a
sample rate.  Files are written without ``libver='latest'`` so that
``h5dump`` reads everything afmtool writes.
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from afmtool.errors import InputError
from afmtool.io.capture import CaptureInfo, ChannelSpec, Chunk, ReaderBase
from afmtool.io.isolated import check_survives
from afmtool.io.metadata import parse_metadata_json
from afmtool.runtime import run_options

__all__ = ["Hdf5Reader", "Hdf5Writer", "dataset_name", "unit_attribute", "UNIT_ATTRIBUTES"]

_WRITE_CHUNK = 1 << 16

#: How long reading every attribute of a file may take before the file is refused, s.
ATTRIBUTE_TIMEOUT_S = 5.0


def _open_h5(path: Path) -> h5py.File:
    try:
        return h5py.File(path, "r")
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except OSError as exc:
        reason = str(exc).split("(")[0].strip() or "unreadable"
        raise InputError(f"{path}: not a readable HDF5 file ({reason})") from None


def _read_every_attribute(h5: h5py.File) -> None:
    for key in h5.attrs:
        h5.attrs[key]

    def visit(name: str, obj) -> None:
        for key in obj.attrs:
            obj.attrs[key]

    h5.visititems(visit)


def check_attributes_terminate(path: Path, timeout_s: float = ATTRIBUTE_TIMEOUT_S) -> None:
    """Read every attribute of ``path`` in a forked child; refuse the file if that hangs or crashes.

    Variable-length strings (``metadata``, ``units``) live in the file's
    global heap.  A damaged heap can send libhdf5 into an endless loop
    inside one ``H5Aread`` (a free-space object of size 0 is never
    stepped over), which holds the GIL: no signal handler or thread of
    this process can stop it.  A child process can be stopped.  Errors the
    child meets are left to the reader, which reads the same attributes
    and reports them; only a child that does not finish, or dies by a
    signal, condemns the file.  Costs a fork and a few milliseconds.

    Raises
    ------
    InputError
        If the child runs longer than ``timeout_s`` or is killed by a signal.
    """
    def read_every_attribute() -> None:
        with h5py.File(path, "r") as h5:
            _read_every_attribute(h5)

    check_survives(read_every_attribute, str(path), "reading its attributes (libhdf5; e.g. a corrupt global heap)",
                   timeout_s)


#: Most attributes the root group may hold (afmtool writes two; every one is read by the child check).
MAX_ROOT_ATTRIBUTES = 10_000


def check_attribute_count(path: Path, h5: h5py.File) -> None:
    """Refuse a root group of more than :data:`MAX_ROOT_ATTRIBUTES` attributes, from its count alone.

    Reading 100,000 attributes took longer than :func:`check_attributes_terminate` allows, which
    then called a sound file damaged; the count is one header query.
    """
    try:
        count = h5.attrs.__len__()
    except (OSError, RuntimeError, KeyError, ValueError) as exc:
        raise InputError(f"{path}: damaged HDF5 structure ({_first_line(exc)})") from None
    if count > MAX_ROOT_ATTRIBUTES:
        raise InputError(f"{path}: the root group holds {count:,} attributes; afmtool reads files of at most "
                         f"{MAX_ROOT_ATTRIBUTES:,} (metadata belongs in the one 'metadata' attribute)")


#: Most soft links followed while resolving one path; more means a loop.
MAX_LINK_HOPS = 32

#: Largest ratio of the bytes a file's datasets claim to the file's own size.  gzip cannot
#: compress better than about 1032:1, so a larger claim is either a lie or fill values.
MAX_COMPRESSION_RATIO = 1000

#: Largest chunk read at once, bytes: a compressed chunk is decompressed whole.
MAX_CHUNK_BYTES = 256 << 20

_TRUTH_KINDS = "fiub"


def _local_path(path: Path, h5: h5py.File, object_path: str) -> str | None:
    """The hard-link path of ``object_path``, following soft links; refuse external ones.

    Every component is resolved by this code, not by libhdf5, so that a soft
    link to an external link (``/channels/x -> /ext/s`` with ``/ext`` external)
    is caught like a direct one.  Relative soft links are relative to the
    group holding them, as in HDF5.  ``None`` when nothing is there.

    Raises
    ------
    InputError
        An external or user-defined link on the way, or a soft-link loop.
    """
    node = "/"
    parts = [p for p in object_path.split("/") if p and p != "."]
    hops = 0
    while parts:
        part = parts.pop(0)
        candidate = node.rstrip("/") + "/" + part
        try:
            link = h5.get(candidate, getlink=True)
        except (KeyError, OSError, ValueError, RuntimeError):
            return None
        if link is None:
            return None
        if isinstance(link, h5py.ExternalLink):
            raise InputError(f"{path}: {candidate} is an external link to {link.filename}; refusing data outside the file")
        if isinstance(link, h5py.SoftLink):
            hops += 1
            if hops > MAX_LINK_HOPS:
                raise InputError(f"{path}: more than {MAX_LINK_HOPS} soft links resolving {object_path} (a loop?)")
            target = [p for p in link.path.split("/") if p and p != "."]
            if link.path.startswith("/"):
                node = "/"
            parts = target + parts
            continue
        if not isinstance(link, h5py.HardLink):
            raise InputError(f"{path}: {candidate} is a {type(link).__name__}; refusing links afmtool cannot check")
        node = candidate
    return node


def _local_object(path: Path, h5: h5py.File, object_path: str):
    """The object at ``object_path`` (links resolved by :func:`_local_path`), or ``None``."""
    resolved = _local_path(path, h5, object_path)
    if resolved is None:
        return None
    obj = h5.get(resolved)
    if isinstance(obj, h5py.Dataset):
        _check_local(path, object_path, obj)
    return obj


def _check_local(path: Path, name: str, dataset: h5py.Dataset) -> None:
    """Refuse data that lives outside the input file (external or virtual)."""
    if dataset.is_virtual:
        raise InputError(f"{path}: dataset {name} is a virtual dataset; refusing data outside the file")
    if dataset.external:
        raise InputError(f"{path}: dataset {name} stores its data in external files; refusing")


def _claimed_bytes(dataset: h5py.Dataset) -> int:
    return int(np.prod(dataset.shape, dtype=object)) * dataset.dtype.itemsize


def _check_claims(path: Path, datasets: Mapping[str, h5py.Dataset], n_samples: int) -> None:
    """Refuse a file whose datasets claim more data than it can hold.

    What a dataset claims (shape x itemsize) is checked against the file
    size times :data:`MAX_COMPRESSION_RATIO` before anything is read: a
    400 kB file claiming 1e15 samples would otherwise be read for ever (the
    missing chunks read as fill values).  ``--max-samples N`` replaces the
    ratio check by ``n_samples <= N`` (the run's :mod:`afmtool.runtime.run_options`).
    """
    file_bytes = max(path.stat().st_size, 1)
    limit = run_options.current().max_samples
    largest_chunk = max(
        (int(np.prod(d.chunks, dtype=object)) * d.dtype.itemsize for d in datasets.values() if d.chunks), default=0
    )
    if largest_chunk > MAX_CHUNK_BYTES:
        raise InputError(
            f"{path}: a dataset has chunks of {largest_chunk / 2**20:.0f} MiB; afmtool reads chunks of at most "
            f"{MAX_CHUNK_BYTES >> 20} MiB"
        )
    if limit is not None:
        for name, d in datasets.items():
            if d.size > limit:
                raise InputError(f"{path}: dataset {name} has {d.size:,} elements, more than --max-samples {limit:,}")
        return
    claimed = sum(_claimed_bytes(d) for d in datasets.values())
    if claimed > file_bytes * MAX_COMPRESSION_RATIO:
        raise InputError(
            f"{path}: its datasets claim {claimed:,} bytes ({n_samples:,} samples per channel) in a "
            f"{file_bytes:,}-byte file, more than {MAX_COMPRESSION_RATIO}x compression; "
            "give afmtool --max-samples N to read it anyway"
        )


class Hdf5Reader(ReaderBase):
    """Read an HDF5 capture, in afmtool layout or through a channel mapping.

    Parameters
    ----------
    path : Path
        The file; opened read-only.
    channel_map : mapping of str to str, optional
        Channel name to dataset path, for foreign files.  Without it the
        datasets under ``/channels`` are the channels.
    sample_rate_hz : float, optional
        Overrides (or supplies) the root attribute ``sample_rate_hz``.
    """

    def __init__(
        self,
        path: Path,
        channel_map: Mapping[str, str] | None = None,
        sample_rate_hz: float | None = None,
    ) -> None:
        self._path = Path(path)
        self._file = _open_h5(self._path)
        try:
            check_attribute_count(self._path, self._file)
            check_attributes_terminate(self._path)
        except BaseException:
            self._file.close()
            raise
        try:
            self._datasets = self._find_datasets(channel_map)
            self.info = self._make_info(sample_rate_hz)
        except (OSError, RuntimeError, KeyError, ValueError, TypeError) as exc:
            # HDF5 reports a damaged file's structure as any of these, at any depth.
            self._file.close()
            raise InputError(f"{self._path}: damaged HDF5 structure ({_first_line(exc)})") from None
        except BaseException:
            self._file.close()
            raise

    def _find_datasets(self, channel_map: Mapping[str, str] | None) -> dict[str, h5py.Dataset]:
        path, h5 = self._path, self._file
        if channel_map:
            mapping = dict(channel_map)
        else:
            group = _local_object(path, h5, "/channels")
            if not isinstance(group, h5py.Group):
                raise InputError(
                    f"{path}: no /channels group; map datasets with --channel NAME=/path/to/dataset"
                )
            mapping = {name: f"/channels/{name}" for name in group}
        datasets = {}
        for name, dataset_path in mapping.items():
            obj = _local_object(path, h5, dataset_path)
            if not isinstance(obj, h5py.Dataset):
                raise InputError(f"{path}: no dataset {dataset_path!r} for channel {name!r}")
            if obj.ndim != 1 or obj.dtype.kind not in "fiu":
                raise InputError(f"{path}: dataset {dataset_path} must be 1-D numeric, is {obj.shape} {obj.dtype}")
            datasets[name] = obj
        if not datasets:
            raise InputError(f"{path}: the capture has no channels")
        lengths = {len(d) for d in datasets.values()}
        if len(lengths) != 1:
            raise InputError(f"{path}: channels have different lengths {sorted(lengths)}")
        self._truth = self._find_truth()
        _check_claims(path, {**datasets, **{f"/truth/{k}": v for k, v in self._truth.items()}}, lengths.pop())
        return datasets

    def _find_truth(self) -> dict[str, h5py.Dataset]:
        """The ``/truth`` datasets, each checked like a channel (local, numeric)."""
        path, h5 = self._path, self._file
        group = _local_object(path, h5, "/truth")
        if group is None:
            return {}
        if not isinstance(group, h5py.Group):
            raise InputError(f"{path}: /truth must be a group of datasets")
        truth = {}
        for name in group:
            obj = _local_object(path, h5, f"/truth/{name}")
            if not isinstance(obj, h5py.Dataset):
                raise InputError(f"{path}: /truth/{name} must be a dataset")
            if obj.dtype.kind not in _TRUTH_KINDS or obj.dtype.fields is not None:
                raise InputError(f"{path}: /truth/{name} must be numeric, is {obj.dtype}")
            truth[name] = obj
        return truth

    def _make_info(self, sample_rate_hz: float | None) -> CaptureInfo:
        path, attrs = self._path, self._file.attrs
        if sample_rate_hz is None:
            if "sample_rate_hz" not in attrs:
                raise InputError(f"{path}: no sample_rate_hz attribute; give --sample-rate")
            sample_rate_hz = _sample_rate_attr(path, attrs["sample_rate_hz"])
        if not np.isfinite(sample_rate_hz) or sample_rate_hz <= 0:
            raise InputError(f"{path}: sample rate {sample_rate_hz!r} must be a positive number")
        metadata = {}
        if "metadata" in attrs:
            metadata = parse_metadata_json(_text_attr(path, "metadata", attrs["metadata"]), str(path))
        channels = tuple(ChannelSpec(name, unit_attribute(path, name, d.attrs)) for name, d in self._datasets.items())
        n_samples = len(next(iter(self._datasets.values())))
        truth_names = tuple(self._truth)
        return CaptureInfo(str(path), "hdf5", float(sample_rate_hz), channels, n_samples, metadata, truth_names)

    def blocks(self, channels: Sequence[str], block_samples: int) -> Iterator[Chunk]:
        n = self.info.n_samples
        windows = {name: _ChunkWindow(self._datasets[name]) for name in channels}
        for start in range(0, n, block_samples):
            stop = min(start + block_samples, n)
            data = {}
            for name in channels:
                try:
                    data[name] = windows[name].read(start, stop)
                except (OSError, RuntimeError, ValueError) as exc:
                    raise _unreadable(self._path, name, start, exc) from None
            yield Chunk(start, data)

    def ranges(self) -> Hdf5Ranges:
        """The channels' datasets by path, for a worker that reads its own ranges (:mod:`afmtool.io.ranges`)."""
        # absolute: a worker runs in its own directory
        return Hdf5Ranges(str(self._path.resolve()), {name: ds.name for name, ds in self._datasets.items()})

    def truth(self) -> dict[str, np.ndarray]:
        try:
            return {name: ds[()] for name, ds in self._truth.items()}
        except (OSError, RuntimeError, KeyError, ValueError) as exc:
            raise InputError(f"{self._path}: cannot read /truth ({_first_line(exc)})") from None

    def close(self) -> None:
        # Close every object explicitly (h5py's close is strong), before the interpreter's
        # teardown, so no finaliser runs libhdf5 later.
        self._datasets, self._truth = {}, {}
        self._file.close()


@dataclass(frozen=True)
class Hdf5Ranges:
    """Samples [start, stop) of an HDF5 capture's channels, read by whoever holds this (a Dask worker).

    ``datasets`` maps each channel to the dataset path :class:`Hdf5Reader`
    resolved and checked when it opened the file; the values are read into
    float64 exactly as its chunks are.
    """

    path: str
    datasets: Mapping[str, str]

    def read(self, channels: Sequence[str], start: int, stop: int) -> dict[str, np.ndarray]:
        out = {}
        with _open_h5(Path(self.path)) as h5:
            for name in channels:
                try:
                    out[name] = _read_float64(h5[self.datasets[name]], start, stop)
                except (OSError, RuntimeError, ValueError, KeyError) as exc:
                    raise _unreadable(self.path, name, start, exc) from None
        return out


def _read_float64(dataset: h5py.Dataset, start: int, stop: int) -> np.ndarray:
    """Samples [start, stop) of ``dataset`` as float64 (libhdf5 converts the stored type)."""
    buffer = np.empty(stop - start, dtype=np.float64)
    if stop > start:
        dataset.read_direct(buffer, np.s_[start:stop])
    return buffer


def _unreadable(path, name: str, start: int, exc: BaseException) -> InputError:
    return InputError(f"{path}: cannot read {name} at sample {start} ({_first_line(exc)})")


class _ChunkWindow:
    """Sequential reads of one dataset in whole chunks, so each chunk is decompressed once.

    A block that ends inside a chunk would make libhdf5 decompress that
    chunk again for the next block (twice or, with chunks much larger than
    the blocks and than the chunk cache, dozens of times).  Reads here
    extend to the next chunk boundary and keep the tail for the next block.
    Contiguous datasets are read as asked.
    """

    def __init__(self, dataset: h5py.Dataset) -> None:
        self._dataset = dataset
        self._n = dataset.shape[0]
        self._chunk = dataset.chunks[0] if dataset.chunks else 0
        self._start = self._stop = 0
        self._buffer = np.empty(0, dtype=np.float64)

    def _read(self, start: int, stop: int) -> np.ndarray:
        return _read_float64(self._dataset, start, stop)

    def read(self, start: int, stop: int) -> np.ndarray:
        if not self._chunk:
            return self._read(start, stop)
        if not self._start <= start <= self._stop:
            self._start = self._stop = start - start % self._chunk
            self._buffer = np.empty(0, dtype=np.float64)
        if stop > self._stop:
            end = min(-(-stop // self._chunk) * self._chunk, self._n)
            kept = self._buffer[start - self._start :]
            self._buffer = np.concatenate([kept, self._read(self._stop, end)])
            self._start, self._stop = start, end
        return self._buffer[start - self._start : stop - self._start].copy()


def _first_line(exc: BaseException) -> str:
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]


def dataset_name(name: str, what: str = "channel") -> str:
    """``name`` if it can be one dataset name inside its group, else :class:`InputError`.

    A channel name from a CSV header or a bag topic becomes an HDF5 link
    name; ``/`` would place it elsewhere in the file (``/truth/x`` would
    plant fake ground truth), and ``.``, ``..`` or control characters are
    not names anyone means.
    """
    if not name or name in (".", "..") or "/" in name or not name.isprintable():
        raise InputError(f"{what} name {name!r} cannot be an HDF5 dataset name (no '/', '.', '..' or control characters)")
    return name


def _sample_rate_attr(path: Path, value) -> float:
    """The root attribute ``sample_rate_hz``: one real number, not a flag, text or array."""
    array = np.asarray(value)
    if array.size != 1 or array.dtype.kind not in "fiu":
        raise InputError(
            f"{path}: attribute sample_rate_hz must be one real number, is {array.dtype} of shape {array.shape}"
        )
    return float(array.reshape(-1)[0])


def _text_attr(path: Path, name: str, value) -> str:
    """A string attribute as text; refuse bytes that are not UTF-8 and non-string values."""
    if isinstance(value, np.ndarray) and value.size == 1:  # a scalar, or a 1-element array
        value = value.reshape(-1)[0]
    if isinstance(value, np.void):
        value = value.tobytes()
    if isinstance(value, bytes):
        try:
            return value.decode("utf-8")
        except UnicodeDecodeError:
            raise InputError(f"{path}: attribute {name} is not UTF-8 text") from None
    if isinstance(value, str):
        return value
    raise InputError(f"{path}: attribute {name} must be a string, is {type(value).__name__}")


def _units_attr(path: Path, channel: str, value) -> str:
    units = _text_attr(path, f"units of {channel}", value).strip("\x00")  # a C buffer's padding
    if not units.isprintable() or len(units) > 64:
        raise InputError(f"{path}: units of {channel} {units[:64]!r} must be one short printable line")
    return units


#: Attribute names that hold a dataset's units, in the order they are looked for: afmtool's own, then
#: what NetCDF (CF conventions), afmformats' HDF5 export and other writers use.
UNIT_ATTRIBUTES = ("units", "unit", "Unit", "Units", "UNITS", "UNIT")


def unit_attribute(path: Path, name: str, attrs) -> str:
    """A dataset's units from its attributes, under any of :data:`UNIT_ATTRIBUTES` (or that name in any case)."""
    for key in UNIT_ATTRIBUTES:
        if key in attrs:
            return _units_attr(path, name, attrs[key])
    for key in attrs:
        if str(key).lower() in ("units", "unit"):
            return _units_attr(path, name, attrs[key])
    return ""


class Hdf5Writer:
    """Write a capture in the afmtool HDF5 layout, block by block.

    Datasets are chunked and resizable so captures of unknown length stream
    in; ``compression="gzip"`` adds gzip with the shuffle filter.
    """

    def __init__(
        self,
        path: Path,
        sample_rate_hz: float,
        channels: Sequence[ChannelSpec],
        metadata: Mapping | None = None,
        *,
        dtype: str = "float64",
        compression: str | None = None,
    ) -> None:
        for spec in channels:
            dataset_name(spec.name)
        self._file = h5py.File(path, "w", rdcc_nbytes=0)  # flat memory while appending (see io.results)
        self._datasets = {}
        self._failed = False
        with self._failing(close=True):
            self._file.attrs["sample_rate_hz"] = float(sample_rate_hz)
            if metadata:
                self._file.attrs["metadata"] = json.dumps(dict(metadata))
            group = self._file.create_group("channels", track_order=True)
            filters = {"compression": "gzip", "shuffle": True} if compression == "gzip" else {}
            self._filters = filters
            for spec in channels:
                ds = group.create_dataset(
                    spec.name, shape=(0,), maxshape=(None,), dtype=dtype, chunks=(_WRITE_CHUNK,), **filters
                )
                ds.attrs["units"] = spec.units
                self._datasets[spec.name] = ds

    @contextmanager
    def _failing(self, *, close: bool = False) -> Iterator[None]:
        """A write that raises marks the file failed: it is then never closed (afmtool.runtime.faults.close_hdf5).

        ``close``: the constructor's writes; nobody else will call :meth:`close` if they fail.
        """
        try:
            yield
        except BaseException:
            self._failed = True
            if close:
                self.close()
            raise

    def write(self, data: Mapping[str, np.ndarray]) -> None:
        with self._failing():
            for name, ds in self._datasets.items():
                values = np.asarray(data[name])
                start = ds.shape[0]
                ds.resize((start + len(values),))
                ds[start:] = values

    def write_truth(self, truth: Mapping[str, np.ndarray]) -> None:
        with self._failing():
            self._write_truth(truth)

    def _write_truth(self, truth: Mapping[str, np.ndarray]) -> None:
        group = self._file.require_group("truth")
        for name, values in truth.items():
            dataset_name(name, "ground-truth")
            values = np.asarray(values)
            if values.ndim == 0:
                group.create_dataset(name, data=values)
            elif name in group:
                ds = group[name]
                start = ds.shape[0]
                ds.resize((start + len(values),) + ds.shape[1:])
                ds[start:] = values
            else:
                group.create_dataset(
                    name, data=values, maxshape=(None,) + values.shape[1:], chunks=True, **self._filters
                )

    def close(self) -> None:
        """Close the file; after a failed write it is left unclosed (afmtool.runtime.faults.close_hdf5)."""
        from afmtool.runtime.faults import close_hdf5

        handle, self._file = self._file, None
        if handle is not None:
            close_hdf5(handle, self._datasets, failed=self._failed)
