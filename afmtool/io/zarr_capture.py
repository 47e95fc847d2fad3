"""Zarr captures: a folder or an fsspec URL (``s3://``, ``gs://``, ``memory://``), read by chunk and by range.

The layout is the one ``afmtool.Capture.to_xarray().to_zarr(store)`` writes (and
``xarray.Dataset.to_zarr`` of any Dataset shaped like it): one 1-D array per
channel, with a ``units`` attribute, on a ``time`` coordinate (s); the group's
attributes ``sample_rate_hz`` and ``metadata`` (JSON text, the capture
metadata).  Without ``sample_rate_hz`` the rate comes from the ``time``
coordinate's step, else from ``--sample-rate``.

Because a Zarr store is random access from anywhere that can reach it,
:class:`ZarrReader` offers :meth:`ZarrReader.ranges`: on a Dask cluster
(``--scheduler``) each worker opens the store itself and reads only its chunk
and warm-up (:mod:`afmtool.io.ranges`), so a capture in object storage is
analysed with no shared file system.  fsspec resolves the URL; ``memory://``
stores live in one process (a local cluster with ``processes=False`` shares it).
"""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from afmtool.errors import InputError
from afmtool.io.capture import CaptureInfo, ChannelSpec, Chunk, ReaderBase

__all__ = ["ZarrReader", "ZarrRanges", "is_zarr_store"]

_TIME = "time"


def is_zarr_store(path) -> bool:
    """A URL (``scheme://``: afmtool reads only Zarr through fsspec), or a folder that is a Zarr group."""
    import os

    text = os.fspath(path)
    if "://" in text:
        return True
    return os.path.isdir(text) and (text.rstrip("/").endswith(".zarr") or os.path.isfile(os.path.join(text, "zarr.json"))
                                    or os.path.isfile(os.path.join(text, ".zgroup")))


@functools.lru_cache(maxsize=8)
def _group(url: str):
    """The store's root group, opened once per process (a Dask worker reads many ranges of it)."""
    try:
        import zarr
    except ImportError:
        raise InputError(f"{url}: reading Zarr needs zarr: pip install 'afmtool[xarray]'") from None
    try:
        return zarr.open_group(url, mode="r")
    except Exception as exc:  # noqa: BLE001 - zarr, fsspec and the object store raise their own kinds; one line here
        raise InputError(f"{url}: not a readable Zarr store ({type(exc).__name__}: {exc})".splitlines()[0]) from None


def _rate(url: str, group, arrays: Mapping, given: float | None) -> float:
    attrs = dict(group.attrs)
    rate = given if given is not None else attrs.get("sample_rate_hz")
    if rate is None and _TIME in arrays and arrays[_TIME].shape[0] > 1:
        step = float(arrays[_TIME][1] - arrays[_TIME][0])
        rate = 1.0 / step if step > 0 else None
    if not (isinstance(rate, (int, float)) and not isinstance(rate, bool) and math.isfinite(rate) and rate > 0):
        raise InputError(f"{url}: no sample rate (group attribute sample_rate_hz or a time coordinate); "
                         "give --sample-rate")
    return float(rate)


class ZarrReader(ReaderBase):
    """A Zarr capture, streamed in blocks; random access for Dask workers (:meth:`ranges`)."""

    def __init__(self, url: str, sample_rate_hz: float | None = None) -> None:
        self.url = str(url)
        group = _group(self.url)
        arrays = {name: array for name, array in group.arrays()}
        channels = {name: a for name, a in arrays.items() if name != _TIME and len(a.shape) == 1}
        if not channels:
            raise InputError(f"{self.url}: no 1-D channel arrays in the Zarr store")
        lengths = {a.shape[0] for a in channels.values()}
        if len(lengths) != 1:
            raise InputError(f"{self.url}: channels of different lengths {sorted(lengths)}")
        try:
            metadata = json.loads(group.attrs.get("metadata", "{}") or "{}")
        except (TypeError, ValueError):
            raise InputError(f"{self.url}: group attribute metadata is not JSON") from None
        specs = tuple(ChannelSpec(name, str(a.attrs.get("units", ""))) for name, a in channels.items())
        self._arrays = channels
        self.info = CaptureInfo(self.url, "zarr", _rate(self.url, group, arrays, sample_rate_hz), specs,
                                lengths.pop(), metadata if isinstance(metadata, dict) else {})

    def blocks(self, channels: Sequence[str], block_samples: int) -> Iterator[Chunk]:
        n = self.info.n_samples
        for start in range(0, n, block_samples):
            stop = min(start + block_samples, n)
            yield Chunk(start, _read(self.url, self._arrays, channels, start, stop))

    def ranges(self) -> ZarrRanges:
        """Samples by range, read by whoever holds this (a Dask worker), from the store itself."""
        return ZarrRanges(self.url)

    def truth(self) -> dict:
        return {}

    def close(self) -> None:
        pass


def _read(url: str, arrays: Mapping, channels: Sequence[str], start: int, stop: int) -> dict[str, np.ndarray]:
    out = {}
    for name in channels:
        try:
            out[name] = np.asarray(arrays[name][start:stop], dtype=np.float64)
        except Exception as exc:  # noqa: BLE001 - a store's own errors (network, codec) become one line
            raise InputError(f"{url}: cannot read {name} at sample {start} ({type(exc).__name__}: {exc})"
                             .splitlines()[0]) from None
    return out


@dataclass(frozen=True)
class ZarrRanges:
    """Samples [start, stop) of a Zarr capture's channels, as float64 (picklable: the store's URL)."""

    url: str

    def read(self, channels: Sequence[str], start: int, stop: int) -> dict[str, np.ndarray]:
        group = _group(self.url)
        return _read(self.url, {name: group[name] for name in channels}, channels, start, stop)
