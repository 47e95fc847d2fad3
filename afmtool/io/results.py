"""HDF5 result files (``reep.h5``, ``probeloss.h5``, ...), written as they stream.

Columns are appended chunk by chunk to resizable datasets, each with a
``units`` attribute, so a result of any length is written in flat memory.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import h5py
import numpy as np

__all__ = ["ResultWriter"]

_CHUNK = 1 << 14


class ResultWriter:
    """Append-only writer of named 1-D series plus whole arrays and attributes."""

    def __init__(self, path: Path, units: Mapping[str, str], attrs: Mapping | None = None) -> None:
        # No raw-data chunk cache: with it, HDF5 keeps growing while series are
        # appended (about 15 % of what is written); without it memory is flat
        # and appends are no slower.
        self._file = h5py.File(path, "w", track_order=True, rdcc_nbytes=0)
        self._units = dict(units)
        self._series: dict[str, h5py.Dataset] = {}
        self._pending: dict[str, np.ndarray] = {}  # per series, less than one chunk not yet written
        for key, value in (attrs or {}).items():
            self._file.attrs[key] = value

    def append(self, columns: Mapping[str, np.ndarray]) -> None:
        """Append equal-length blocks to the series named in ``columns``."""
        for name, values in columns.items():
            values = np.asarray(values)
            ds = self._series.get(name)
            if ds is None:
                ds = self._create(name, values)
                ds.attrs["units"] = self._units.get(name, "")
                self._series[name] = ds
            self._extend(name, ds, values)

    def _create(self, name: str, values: np.ndarray) -> h5py.Dataset:
        """A resizable dataset for the series ``name``, from its first block."""
        return self._file.create_dataset(name, shape=(0,), maxshape=(None,), dtype=values.dtype, chunks=(_CHUNK,))

    def _extend(self, name: str, ds: h5py.Dataset, values: np.ndarray) -> None:
        """Append along the last axis in whole HDF5 chunks; the rest (< 1 chunk) waits for the next block.

        With no chunk cache, writing a part chunk and later the rest of it
        makes HDF5 read the chunk back and write it again; that cost as much
        as the REEP kernel.  Whole-chunk writes never touch a chunk twice.
        """
        pending = self._pending.get(name)
        if pending is not None and pending.shape[-1]:
            values = np.concatenate([pending, values.astype(ds.dtype, copy=False)], axis=-1)
        step = ds.chunks[-1]
        whole = values.shape[-1] // step * step
        if whole:
            _write_at_end(ds, values[..., :whole])
        self._pending[name] = values[..., whole:].copy()

    def put(self, name: str, values, units: str = "", attrs: Mapping | None = None) -> None:
        """Store a whole array (an image, a table column) at ``name`` (may contain '/')."""
        ds = self._file.create_dataset(name, data=np.asarray(values))
        ds.attrs["units"] = units
        for key, value in (attrs or {}).items():
            ds.attrs[key] = value

    def close(self) -> None:
        """Write what is still pending and close the file."""
        try:
            for name, rest in self._pending.items():
                if rest.shape[-1]:
                    _write_at_end(self._series[name], rest)
            self._pending.clear()
        finally:
            self._file.close()

    def __enter__(self) -> ResultWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _write_at_end(ds: h5py.Dataset, block: np.ndarray) -> None:
    """Grow ``ds`` along its last axis and write ``block`` there."""
    start = ds.shape[-1]
    ds.resize(start + block.shape[-1], axis=ds.ndim - 1)
    ds[..., start:] = block
