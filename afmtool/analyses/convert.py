"""``afmtool convert``: any capture format to any other, streamed."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TextIO

from afmtool.io.capture import DEFAULT_CHUNK_SAMPLES, CaptureReader, Chunk
from afmtool.io.registry import check_writable_rate, create_writer
from afmtool.pipeline import run_stream

__all__ = ["convert_capture"]


class _CopyStage:
    """Write each chunk to ``writer`` as it passes (a :class:`afmtool.pipeline.Stage`); memory one chunk."""

    def __init__(self, writer) -> None:
        self._writer = writer
        self.n_samples = 0

    def prepare(self, head) -> None:
        """Nothing to set up."""

    def step(self, chunk: Chunk) -> None:
        self._writer.write(chunk.data)
        self.n_samples = chunk.start + len(chunk)

    def finish(self) -> int:
        return self.n_samples


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
    atomic; formats without ground truth drop it.  A capture known to be
    empty (its reader says 0 samples) becomes an empty one of ``fmt``.
    """
    info = reader.info
    check_writable_rate(info.sample_rate_hz, info.source)  # named after the capture, before anything is written
    writer = create_writer(target, fmt, info.sample_rate_hz, info.channels, info.metadata, compression=compression)
    n = 0
    try:
        if info.n_samples != 0:
            (n,) = run_stream(reader, [_CopyStage(writer)], channels=info.channel_names,
                              chunk_samples=chunk_samples, progress=progress)
        if info.truth_names:
            writer.write_truth(reader.truth())
    finally:
        writer.close()
    return n
