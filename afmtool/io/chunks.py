"""The chunk iterator every analysis streams through.

``iter_chunks`` asks a reader for aligned blocks of the channels an analysis
needs, checks that those channels exist and that every sample is finite,
and reports progress.  Analyses carry their filter state from one chunk to
the next, so memory stays flat however long the capture is.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence

import numpy as np

from afmtool.errors import InputError
from afmtool.io.capture import DEFAULT_CHUNK_SAMPLES, CaptureInfo, CaptureReader, Chunk

__all__ = ["iter_chunks", "opened_chunks", "require_channels"]


def require_channels(info: CaptureInfo, channels: Sequence[str]) -> None:
    """Raise :class:`InputError` naming the first channel the capture lacks."""
    present = frozenset(info.channel_names)  # once: a 40,000-column CSV made this loop quadratic
    for name in channels:
        if name not in present:
            have = ", ".join(info.channel_names) or "none"
            raise InputError(f"{info.source}: no channel {name!r} (has: {have})")


def iter_chunks(
    reader: CaptureReader,
    channels: Sequence[str],
    chunk_samples: int = DEFAULT_CHUNK_SAMPLES,
    *,
    progress: Callable[[int], None] | None = None,
) -> Iterator[Chunk]:
    """Yield aligned float64 chunks of ``channels``; refuse NaN and inf.

    Parameters
    ----------
    reader : CaptureReader
        An open capture.
    channels : sequence of str
        Channel names to read, all of which must exist.
    chunk_samples : int
        Samples per chunk (the last one may be shorter).
    progress : callable, optional
        Called with the number of samples read so far after each chunk.

    Raises
    ------
    InputError
        A missing channel, or a non-finite sample (afmtool refuses NaN and
        inf rather than letting them poison a recursive estimator; the
        message gives the channel and the sample index).
    """
    if chunk_samples < 1:
        raise InputError(f"{chunk_samples=} must be >= 1")
    require_channels(reader.info, channels)
    done = 0
    for chunk in reader.blocks(list(channels), chunk_samples):
        for name, values in chunk.data.items():
            # A NaN or inf anywhere makes the sum NaN or inf; a finite sum clears the chunk
            # in one pass (isfinite().all() takes two, and a temporary).  Only a sum that
            # overflows, or a real NaN or inf, needs the exact check.
            with np.errstate(invalid="ignore", over="ignore"):  # inf + -inf: the NaN is the answer, not a warning
                total = np.add.reduce(values)
            if not math.isfinite(total) and not np.isfinite(values).all():
                first = int(np.flatnonzero(~np.isfinite(values))[0])
                raise InputError(
                    f"{reader.info.source}: channel {name!r} has NaN or inf at sample {chunk.start + first}"
                )
        done += len(chunk)
        if progress is not None:
            progress(done)
        yield chunk


def opened_chunks(open_reader, channels, chunk_samples: int):
    """The chunks of a capture that ``open_reader()`` opens, closed after the last one (``afmtool.Capture.chunks``).

    ``channels`` None reads every channel.
    """
    with open_reader() as reader:
        yield from iter_chunks(reader, tuple(channels or reader.info.channel_names), chunk_samples)
