"""Random access to an opened capture's samples, for whoever holds a picklable description of it.

A split run on a Dask cluster (:func:`afmtool.pipeline.run_stream` with
``--scheduler``) lets each worker read its own chunk and warm-up from the
shared file, so that the samples do not travel through the scheduler.  The
reading process still reads every chunk (the sample hash and the in-order
accounting need them), but sends only ``(start, stop)``.

A reader offers this through a ``ranges()`` method returning a
:class:`RangeSource`: the HDF5 reader (:class:`~afmtool.io.hdf5.Hdf5Ranges`),
and the views that can sit over it (:class:`~afmtool.io.views.SegmentView`,
:class:`~afmtool.io.units.UnitsReader`), which wrap its source with the
same arithmetic their ``blocks`` apply, so a range reads exactly the values
the chunks carry.  Other readers (sequential formats, whose channels
:class:`~afmtool.io.views.RenamedView` renames) and views (a synthesised
drive) have none: :func:`range_source` returns None, and the samples are
then sent with the task.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from afmtool.io.capture import CaptureReader

__all__ = ["RangeSource", "OffsetRanges", "ScaledRanges", "range_source"]


class RangeSource(Protocol):
    """A picklable way to read samples [start, stop) of named channels, as float64 in the reader's units."""

    def read(self, channels: Sequence[str], start: int, stop: int) -> dict[str, np.ndarray]: ...


def range_source(reader: CaptureReader) -> RangeSource | None:
    """The reader's :class:`RangeSource`, or None when it (or a view over it) has no random access."""
    ranges = getattr(reader, "ranges", None)
    return ranges() if callable(ranges) else None


@dataclass(frozen=True)
class OffsetRanges:
    """A segment's samples: sample 0 is ``first`` of the source (:class:`~afmtool.io.views.SegmentView`)."""

    source: RangeSource
    first: int

    def read(self, channels: Sequence[str], start: int, stop: int) -> dict[str, np.ndarray]:
        return self.source.read(channels, start + self.first, stop + self.first)


@dataclass(frozen=True)
class ScaledRanges:
    """Samples times a per-channel factor, as :class:`~afmtool.io.units.UnitsReader` converts them."""

    source: RangeSource
    factors: Mapping[str, float]

    def read(self, channels: Sequence[str], start: int, stop: int) -> dict[str, np.ndarray]:
        data = self.source.read(channels, start, stop)
        for name in channels:
            if name in self.factors:
                data[name] = data[name] * self.factors[name]
        return data
