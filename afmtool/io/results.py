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
        for key, value in (attrs or {}).items():
            self._file.attrs[key] = value

    def append(self, columns: Mapping[str, np.ndarray]) -> None:
        """Append equal-length blocks to the series named in ``columns``."""
        for name, values in columns.items():
            values = np.asarray(values)
            ds = self._series.get(name)
            if ds is None:
                ds = self._file.create_dataset(
                    name, shape=(0,), maxshape=(None,), dtype=values.dtype, chunks=(_CHUNK,)
                )
                ds.attrs["units"] = self._units.get(name, "")
                self._series[name] = ds
            start = ds.shape[0]
            ds.resize((start + len(values),))
            ds[start:] = values

    def put(self, name: str, values, units: str = "", attrs: Mapping | None = None) -> None:
        """Store a whole array (an image, a table column) at ``name`` (may contain '/')."""
        ds = self._file.create_dataset(name, data=np.asarray(values))
        ds.attrs["units"] = units
        for key, value in (attrs or {}).items():
            ds.attrs[key] = value

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> ResultWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
