"""A result writer that also streams (N, T) matrices, e.g. the RMS of N observers.

:class:`afmtool.io.results.ResultWriter` appends 1-D series; a bank of N
observers produces N series that share one time axis, which belong in one
(N, T) dataset.  This writer appends 2-D blocks along their last axis and
1-D blocks as the base class does, so memory stays flat however long the
capture is.
"""

from __future__ import annotations

from collections.abc import Mapping

import h5py
import numpy as np

from afmtool.io.results import ResultWriter

__all__ = ["MatrixResultWriter"]

#: Columns per HDF5 chunk of a matrix dataset (the chunk is N × this).
_CHUNK_COLUMNS = 1 << 12


class MatrixResultWriter(ResultWriter):
    """:class:`ResultWriter` whose ``append`` also takes (N, T) blocks, appended along T."""

    def append(self, columns: Mapping[str, np.ndarray]) -> None:
        """Append blocks with one length T: 1-D (T,) series or 2-D (N, T) matrices."""
        for name, values in columns.items():
            ds = self._series.get(name)
            rows = np.shape(values)[0] if np.ndim(values) == 2 else None
            if ds is not None and ds.ndim == 2 and rows != ds.shape[0]:
                raise ValueError(f"{name}: block has {rows} rows, the dataset {ds.shape[0]}")
        super().append(columns)

    def _create(self, name: str, values: np.ndarray) -> h5py.Dataset:
        if values.ndim != 2:
            return super()._create(name, values)
        rows = values.shape[0]
        return self._file.create_dataset(
            name, shape=(rows, 0), maxshape=(rows, None), dtype=self._stored_dtype(name, values),
            chunks=(rows, _CHUNK_COLUMNS)
        )
