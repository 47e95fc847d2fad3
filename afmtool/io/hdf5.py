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
import os
import signal
import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path

import h5py
import numpy as np

from afmtool.errors import InputError
from afmtool.io.capture import ReaderBase, CaptureInfo, ChannelSpec, Chunk
from afmtool.io.metadata import parse_metadata_json

__all__ = ["Hdf5Reader", "Hdf5Writer"]

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
    if not hasattr(os, "fork"):
        return
    pid = os.fork()
    if pid == 0:  # the child: only os._exit leaves, so no parent state is flushed or cleaned twice
        code = 0
        try:
            signal.signal(signal.SIGINT, signal.SIG_DFL)
            signal.signal(signal.SIGTERM, signal.SIG_DFL)
            with h5py.File(path, "r") as h5:
                _read_every_attribute(h5)
        except BaseException:  # noqa: BLE001 - the parent reads the attributes again and reports errors
            code = 1
        finally:
            os._exit(code)
    deadline = time.monotonic() + timeout_s
    pause = 0.001
    try:
        while True:
            done, status = os.waitpid(pid, os.WNOHANG)
            if done:
                break
            if time.monotonic() > deadline:
                raise InputError(
                    f"{path}: reading its attributes did not finish in {timeout_s:g} s; the file is damaged "
                    "(e.g. a corrupt global heap)"
                )
            time.sleep(pause)
            pause = min(2 * pause, 0.05)
    except BaseException:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        raise
    if os.WIFSIGNALED(status):
        raise InputError(f"{path}: libhdf5 crashed reading its attributes (signal {os.WTERMSIG(status)}); the file is damaged")


def _refuse_external_link(path: Path, h5: h5py.File, dataset_path: str) -> None:
    """Refuse a dataset reached through an external link anywhere along its path."""
    node = ""
    for part in [p for p in dataset_path.split("/") if p]:
        node = f"{node}/{part}"
        try:
            link = h5.get(node, getlink=True)
        except (KeyError, OSError, ValueError):
            return
        if isinstance(link, h5py.ExternalLink):
            raise InputError(f"{path}: {node} is an external link to {link.filename}; refusing data outside the file")
        if link is None:
            return


def _check_local(path: Path, name: str, dataset: h5py.Dataset) -> None:
    """Refuse data that lives outside the input file (external or virtual)."""
    if dataset.is_virtual:
        raise InputError(f"{path}: dataset {name} is a virtual dataset; refusing data outside the file")
    if dataset.external:
        raise InputError(f"{path}: dataset {name} stores its data in external files; refusing")


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
        elif "channels" in h5 and isinstance(h5["channels"], h5py.Group):
            mapping = {name: f"/channels/{name}" for name in h5["channels"]}
        else:
            raise InputError(
                f"{path}: no /channels group; map datasets with --channel NAME=/path/to/dataset"
            )
        datasets = {}
        for name, dataset_path in mapping.items():
            _refuse_external_link(path, h5, dataset_path)
            try:
                obj = h5.get(dataset_path)
            except (KeyError, OSError, ValueError):
                obj = None
            if not isinstance(obj, h5py.Dataset):
                raise InputError(f"{path}: no dataset {dataset_path!r} for channel {name!r}")
            _check_local(path, dataset_path, obj)
            if obj.ndim != 1 or obj.dtype.kind not in "fiu":
                raise InputError(f"{path}: dataset {dataset_path} must be 1-D numeric, is {obj.shape} {obj.dtype}")
            datasets[name] = obj
        if not datasets:
            raise InputError(f"{path}: the capture has no channels")
        lengths = {len(d) for d in datasets.values()}
        if len(lengths) != 1:
            raise InputError(f"{path}: channels have different lengths {sorted(lengths)}")
        return datasets

    def _make_info(self, sample_rate_hz: float | None) -> CaptureInfo:
        path, attrs = self._path, self._file.attrs
        if sample_rate_hz is None:
            if "sample_rate_hz" not in attrs:
                raise InputError(f"{path}: no sample_rate_hz attribute; give --sample-rate")
            sample_rate_hz = float(np.asarray(attrs["sample_rate_hz"]).reshape(-1)[0])
        if not np.isfinite(sample_rate_hz) or sample_rate_hz <= 0:
            raise InputError(f"{path}: sample rate {sample_rate_hz!r} must be a positive number")
        metadata = {}
        if "metadata" in attrs:
            raw = attrs["metadata"]
            text = raw.decode() if isinstance(raw, bytes) else str(raw)
            metadata = parse_metadata_json(text, str(path))
        channels = tuple(
            ChannelSpec(name, _decode_attr(d.attrs.get("units", ""))) for name, d in self._datasets.items()
        )
        n_samples = len(next(iter(self._datasets.values())))
        truth = self._file.get("truth")
        truth_names = tuple(truth) if isinstance(truth, h5py.Group) else ()
        return CaptureInfo(str(path), "hdf5", float(sample_rate_hz), channels, n_samples, metadata, truth_names)

    def blocks(self, channels: Sequence[str], block_samples: int) -> Iterator[Chunk]:
        n = self.info.n_samples
        for start in range(0, n, block_samples):
            stop = min(start + block_samples, n)
            data = {}
            for name in channels:
                buffer = np.empty(stop - start, dtype=np.float64)
                try:
                    self._datasets[name].read_direct(buffer, np.s_[start:stop])
                except (OSError, RuntimeError, ValueError) as exc:
                    raise InputError(f"{self._path}: cannot read {name} at sample {start} ({_first_line(exc)})") from None
                data[name] = buffer
            yield Chunk(start, data)

    def truth(self) -> dict[str, np.ndarray]:
        try:
            group = self._file.get("truth")
            if not isinstance(group, h5py.Group):
                return {}
            return {name: ds[()] for name, ds in group.items() if isinstance(ds, h5py.Dataset)}
        except (OSError, RuntimeError, KeyError, ValueError) as exc:
            raise InputError(f"{self._path}: cannot read /truth ({_first_line(exc)})") from None

    def close(self) -> None:
        self._file.close()


def _first_line(exc: BaseException) -> str:
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]


def _decode_attr(value) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


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
        self._file = h5py.File(path, "w", rdcc_nbytes=0)  # flat memory while appending (see io.results)
        self._file.attrs["sample_rate_hz"] = float(sample_rate_hz)
        if metadata:
            self._file.attrs["metadata"] = json.dumps(dict(metadata))
        group = self._file.create_group("channels", track_order=True)
        filters = {"compression": "gzip", "shuffle": True} if compression == "gzip" else {}
        self._filters = filters
        self._datasets = {}
        for spec in channels:
            ds = group.create_dataset(
                spec.name, shape=(0,), maxshape=(None,), dtype=dtype, chunks=(_WRITE_CHUNK,), **filters
            )
            ds.attrs["units"] = spec.units
            self._datasets[spec.name] = ds

    def write(self, data: Mapping[str, np.ndarray]) -> None:
        for name, ds in self._datasets.items():
            values = np.asarray(data[name])
            start = ds.shape[0]
            ds.resize((start + len(values),))
            ds[start:] = values

    def write_truth(self, truth: Mapping[str, np.ndarray]) -> None:
        group = self._file.require_group("truth")
        for name, values in truth.items():
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
        self._file.close()
