"""``afmtool convert``: any capture format to any other, streamed."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TextIO

from afmtool.io.capture import DEFAULT_CHUNK_SAMPLES, CaptureReader
from afmtool.io.chunks import iter_chunks
from afmtool.io.registry import create_writer

__all__ = ["convert_capture"]


def convert_capture(
    reader: CaptureReader,
    target: Path | TextIO,
    fmt: str,
    *,
    compression: str | None = None,
    chunk_samples: int = DEFAULT_CHUNK_SAMPLES,
    progress: Callable[[int], None] | None = None,
) -> int:
    """Copy every channel (and any ground truth) of ``reader`` to ``target``.

    Returns the number of samples written.  The caller makes ``target``
    atomic; formats without ground truth drop it.
    """
    info = reader.info
    writer = create_writer(target, fmt, info.sample_rate_hz, info.channels, info.metadata, compression=compression)
    n = 0
    try:
        for chunk in iter_chunks(reader, info.channel_names, chunk_samples, progress=progress):
            writer.write(chunk.data)
            n = chunk.start + len(chunk)
        if info.truth_names:
            writer.write_truth(reader.truth())
    finally:
        writer.close()
    return n
