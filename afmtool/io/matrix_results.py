"""A result writer that also streams (N, T) matrices, e.g. the RMS of N observers.

:class:`afmtool.io.results.ResultWriter` appends 1-D series; a bank of N
observers produces N series that share one time axis, which belong in one
(N, T) dataset.  This writer appends 2-D blocks along their last axis and
1-D blocks as the base class does, so memory stays flat however long the
capture is.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from afmtool.io.results import ResultWriter

__all__ = ["MatrixResultWriter"]

#: Columns per HDF5 chunk of a matrix dataset (the chunk is N × this).
_CHUNK_COLUMNS = 1 << 12


class MatrixResultWriter(ResultWriter):
    """:class:`ResultWriter` whose ``append`` also takes (N, T) blocks, appended along T."""

    def append(self, columns: Mapping[str, np.ndarray]) -> None:
        """Append blocks with one length T: 1-D (T,) series or 2-D (N, T) matrices."""
        flat = {}
        for name, values in columns.items():
            values = np.asarray(values)
            if values.ndim != 2:
                flat[name] = values
                continue
            ds = self._series.get(name)
            if ds is None:
                rows = values.shape[0]
                ds = self._file.create_dataset(
                    name,
                    shape=(rows, 0),
                    maxshape=(rows, None),
                    dtype=values.dtype,
                    chunks=(rows, _CHUNK_COLUMNS),
                )
                ds.attrs["units"] = self._units.get(name, "")
                self._series[name] = ds
            if values.shape[0] != ds.shape[0]:
                raise ValueError(f"{name}: block has {values.shape[0]} rows, the dataset {ds.shape[0]}")
            start = ds.shape[1]
            ds.resize((ds.shape[0], start + values.shape[1]))
            ds[:, start:] = values
        if flat:
            super().append(flat)
