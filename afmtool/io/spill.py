"""One read of a capture for a command that needs its samples twice.

``kalman-bank`` designs its bank from REEP's model against z over the whole
force curve (pass 1), and only then runs the bank over the same samples
(pass 2).  Reading the capture twice costs a second read of a file that may be
larger than memory, and is impossible for a stream (stdin).  Instead,
:class:`SpillingReader` hands pass 1 its chunks unchanged and appends the
channels pass 2 needs to a scratch file as they go by; :meth:`SpillingReader.replay`
then gives pass 2 a reader of that file, block by block, so memory stays
flat in both passes.

The spilled samples are the float64 values the reader stack delivered (units
converted, drive synthesised, segment cut), stored as float32 when every one of
them survives the round trip exactly (a float32 file with no unit scale) and
as float64 otherwise, so pass 2 reads exactly what pass 1 saw.  The scratch
file belongs to the caller's folder (the output's staging folder, on the disk
the results go to) and is deleted by :meth:`SpillingReader.close`.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from afmtool.errors import InputError
from afmtool.io.capture import CaptureReader, Chunk, ReaderView

__all__ = ["SpillingReader", "SpilledReader"]

#: Rows copied at a time when a float32 spill has to be widened to float64.
_WIDEN_ROWS = 1 << 20


class SpillingReader(ReaderView):
    """``reader``'s chunks, handed on unchanged, with ``channels`` also appended to ``path``.

    Parameters
    ----------
    reader : CaptureReader
        The open capture (read once, through this view).
    channels : sequence of str
        The channels the replay will need; they are read with whatever a pass asks for.
    path : Path
        The scratch file (created here, removed by :meth:`close`).

    Notes
    -----
    Samples are spilled in capture order: a chunk's samples beyond those already
    spilled are appended, so a pass that re-reads the start of the capture (a
    free-air segment read ahead, a drive-line scan) adds nothing twice and
    leaves no gap.
    """

    def __init__(self, reader: CaptureReader, channels: Sequence[str], path: Path) -> None:
        self._reader = reader
        self.info = reader.info
        self.channels = tuple(channels)
        self.path = Path(path)
        self.spilled = 0
        self.dtype = np.dtype(np.float32)
        self._file = open(self.path, "wb")  # noqa: SIM115 - open for the whole pass, closed in close()

    def blocks(self, channels: Sequence[str], block_samples: int) -> Iterator[Chunk]:
        wanted = list(dict.fromkeys([*channels, *self.channels]))
        for chunk in self._reader.blocks(wanted, block_samples):
            self._spill(chunk)
            yield Chunk(chunk.start, {name: chunk.data[name] for name in channels})

    def _spill(self, chunk: Chunk) -> None:
        skip = self.spilled - chunk.start
        if skip < 0 or skip >= len(chunk):
            return  # already spilled, or beyond a gap no pass in order leaves
        columns = [np.asarray(chunk.data[name][skip:], dtype=np.float64) for name in self.channels]
        if self.dtype == np.float32:
            narrow = [c.astype(np.float32) for c in columns]  # converted once: checked, then stored
            if all(np.array_equal(n, c) for n, c in zip(narrow, columns)):
                columns = narrow
            else:
                self._widen()
        rows = np.empty((len(columns[0]), len(columns)), dtype=self.dtype)
        for k, column in enumerate(columns):
            rows[:, k] = column
        self._file.write(memoryview(rows).cast("B"))
        self.spilled += len(rows)

    def _widen(self) -> None:
        """Rewrite the float32 samples spilled so far as float64: a later chunk needs the precision."""
        self._file.flush()
        wide = self.path.with_name(self.path.name + ".f8")
        with open(wide, "wb") as out:
            if self.spilled:
                narrow = np.memmap(self.path, dtype=np.float32, mode="r", shape=(self.spilled, len(self.channels)))
                for start in range(0, self.spilled, _WIDEN_ROWS):
                    out.write(memoryview(np.asarray(narrow[start:start + _WIDEN_ROWS], dtype=np.float64)).cast("B"))
                del narrow
        self._file.close()
        os.replace(wide, self.path)
        self._file = open(self.path, "ab")  # noqa: SIM115 - see __init__
        self.dtype = np.dtype(np.float64)

    def replay(self) -> SpilledReader:
        """A reader of the spilled samples (the capture as pass 1 read it); call once pass 1 has ended."""
        self._file.flush()
        info = dataclasses.replace(self.info, n_samples=self.spilled)
        return SpilledReader(self.path, self.dtype, self.channels, info, self._reader)

    def close(self) -> None:
        """Delete the scratch file (the capture itself is its opener's to close)."""
        self._file.close()
        self.path.unlink(missing_ok=True)


class SpilledReader(ReaderView):
    """The spilled samples, read block by block: the capture for a second pass.

    Blocks are read into fresh buffers, not through a memory map: a map's
    touched pages stay resident, so a pass over a 1.2 GB spill would grow
    the process's RSS by that much.
    """

    def __init__(self, path: Path, dtype: np.dtype, columns: Sequence[str], info, original: CaptureReader) -> None:
        self._path = path
        self._dtype = np.dtype(dtype)
        self._columns = {name: k for k, name in enumerate(columns)}
        self.info = info
        self._reader = original

    def blocks(self, channels: Sequence[str], block_samples: int) -> Iterator[Chunk]:
        n, width = self.info.n_samples, len(self._columns)
        with open(self._path, "rb") as file:
            for start in range(0, n, block_samples):
                rows = np.empty((min(block_samples, n - start), width), dtype=self._dtype)
                if file.readinto(memoryview(rows).cast("B")) != rows.nbytes:
                    raise InputError(f"{self._path}: the scratch spill ended at sample {start} of {n}")
                yield Chunk(start, {name: rows[:, self._columns[name]].astype(np.float64) for name in channels})

    def ranges(self) -> None:
        """None, though the capture below may offer ranges: a split pass sends the samples with each task.

        The scratch file lies in this machine's output folder, which Dask workers
        elsewhere may not see, and reading the capture's ranges would read it twice.
        """
        return None

    def close(self) -> None:
        pass
