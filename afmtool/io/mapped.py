"""Channels stored as one uncompressed array in a file, read through a memory map.

Igor binary waves and NumPy ``.npy`` files (and the stored members of an
``.npz``) keep their samples as one plain array at a known offset.  Mapping it
reads only the pages a block touches, so a capture larger than memory streams
in flat memory, and a worker that holds the (picklable) :class:`MappedArray`
reads its own ranges (:mod:`afmtool.io.ranges`).

The array has shape ``(n_samples, n_columns)``, stored row-major (``"C"``: a
sample's columns together, as NumPy writes by default) or column-major
(``"F"``: each channel contiguous, as Igor and Fortran-ordered NumPy arrays do).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from afmtool.errors import InputError
from afmtool.io.capture import Chunk

__all__ = ["MappedArray", "MappedSamples"]


@dataclass(frozen=True)
class MappedArray:
    """An ``(n_samples, n_columns)`` array at ``offset`` bytes into ``path``; ``columns`` names each column."""

    path: str
    offset: int
    dtype: str
    n_samples: int
    n_columns: int
    order: str
    columns: Mapping[str, int]

    def check_fits(self, file_size: int) -> None:
        """Refuse an array that the file is too short to hold (a truncated file), before mapping it."""
        need = self.offset + self.n_samples * self.n_columns * np.dtype(self.dtype).itemsize
        if need > file_size:
            raise InputError(f"{self.path}: holds {file_size} bytes; its header declares data up to byte {need} (truncated)")

    def _map(self) -> np.ndarray:
        shape = (self.n_samples, self.n_columns) if self.order == "C" else (self.n_columns, self.n_samples)
        try:
            mapped = np.memmap(self.path, dtype=np.dtype(self.dtype), mode="r", offset=self.offset, shape=shape)
        except (OSError, ValueError) as exc:
            raise InputError(f"{self.path}: cannot map its samples ({str(exc).splitlines()[0][:200]})") from None
        return mapped if self.order == "C" else mapped.T

    def open(self) -> np.ndarray:
        """The mapped array, ``[sample, column]`` (a view: nothing is read until indexed)."""
        return self._map()

    def read(self, channels: Sequence[str], start: int, stop: int, mapped: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Samples [start, stop) of ``channels`` as float64 (NaN and inf are kept, for the chunk check to name)."""
        array = self._map() if mapped is None else mapped
        out = {}
        try:
            with np.errstate(invalid="ignore", over="ignore"):
                for name in channels:
                    out[name] = np.array(array[start:stop, self.columns[name]], dtype=np.float64)
        except OSError as exc:  # an I/O error on a mapped page
            raise InputError(f"{self.path}: cannot read at sample {start} ({exc.strerror})") from None
        return out

    def blocks(self, channels: Sequence[str], block_samples: int) -> Iterator[Chunk]:
        """Aligned blocks of ``channels``, mapped once for the whole pass."""
        mapped = self._map()
        for start in range(0, self.n_samples, block_samples):
            yield Chunk(start, self.read(channels, start, min(start + block_samples, self.n_samples), mapped))


class MappedSamples:
    """What a reader whose samples are one :class:`MappedArray` (``self._array``) does with them.

    Mixed into the readers of memory-mapped formats (``.ibw``, ``.npy``) before
    their reader base: chunks and worker ranges come from the mapped array,
    and there is no truth and nothing to close.
    """

    _array: MappedArray

    def blocks(self, channels: Sequence[str], block_samples: int) -> Iterator[Chunk]:
        return self._array.blocks(channels, block_samples)

    def ranges(self) -> MappedArray:
        """The mapped samples, for a worker that reads its own ranges (:mod:`afmtool.io.ranges`)."""
        return self._array

    def truth(self) -> dict[str, np.ndarray]:
        return {}

    def close(self) -> None:
        pass
