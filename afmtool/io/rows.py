"""Result rows on a text stream (``--stream``): CSV or JSON lines, flushed per chunk.

The same ``append(columns)`` interface as :class:`afmtool.io.results.ResultWriter`,
so an analysis writes to a file or to a pipeline without knowing which.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import TextIO

import numpy as np

__all__ = ["RowWriter", "ROW_FORMATS"]

ROW_FORMATS = ("csv", "jsonl")


class RowWriter:
    """Write appended column blocks as rows to ``stream``, flushing after each block."""

    def __init__(self, stream: TextIO, fmt: str = "csv") -> None:
        if fmt not in ROW_FORMATS:
            raise ValueError(f"{fmt=} must be one of {ROW_FORMATS}")
        self._stream = stream
        self._fmt = fmt
        self._names: list[str] | None = None

    def append(self, columns: Mapping[str, np.ndarray]) -> None:
        if self._names is None:
            self._names = list(columns)
            if self._fmt == "csv":
                self._stream.write(",".join(self._names) + "\n")
        table = np.column_stack([np.asarray(columns[name], dtype=np.float64) for name in self._names])
        if self._fmt == "csv":
            np.savetxt(self._stream, table, delimiter=",", fmt="%.10g")
        else:
            for row in table:
                record = {n: (None if not np.isfinite(v) else float(v)) for n, v in zip(self._names, row)}
                self._stream.write(json.dumps(record) + "\n")
        self._stream.flush()

    def put(self, *args, **kwargs) -> None:
        """Whole arrays (tables, images) have no place in a row stream; they are skipped."""

    def close(self) -> None:
        self._stream.flush()

    def __enter__(self) -> RowWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
