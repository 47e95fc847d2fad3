"""The one in-memory sink of the tests: a ResultWriter stand-in that keeps what is written.

``append`` collects the streamed columns chunk by chunk; ``put`` keeps whole
arrays (bits, tables).  ``sink[name]`` is a column joined over the chunks,
or else a whole array.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np


class MemorySink:
    """Columns and arrays in memory, as :class:`afmtool.io.results.ResultWriter` would write them."""

    def __init__(self) -> None:
        self.parts: dict[str, list[np.ndarray]] = {}
        self.arrays: dict[str, np.ndarray] = {}

    def append(self, columns: Mapping[str, np.ndarray]) -> None:
        for name, values in columns.items():
            self.parts.setdefault(name, []).append(np.asarray(values))

    def put(self, name: str, values, units: str = "", attrs=None) -> None:
        self.arrays[name] = np.asarray(values)

    def __getitem__(self, name: str) -> np.ndarray:
        return np.concatenate(self.parts[name]) if name in self.parts else self.arrays[name]
