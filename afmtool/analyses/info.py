"""``afmtool info``: what a capture holds, with per-channel statistics.

Statistics are accumulated chunk by chunk, so a capture of any length is
summarised in flat memory.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from afmtool.io.capture import DEFAULT_CHUNK_SAMPLES, CaptureReader, Chunk, SegmentSpec
from afmtool.pipeline import run_stream

__all__ = ["ChannelStats", "CaptureSummary", "summarize"]


@dataclass(frozen=True)
class ChannelStats:
    name: str
    units: str
    min: float
    max: float
    mean: float
    rms: float


@dataclass(frozen=True)
class CaptureSummary:
    source: str
    format: str
    sample_rate_hz: float
    n_samples: int
    duration_s: float
    channels: tuple[ChannelStats, ...]
    metadata: dict
    truth_names: tuple[str, ...]
    #: The file's segments (``--segment`` reads one), empty when it has none.
    segments: tuple[SegmentSpec, ...] = ()


class _RunningStats:
    """min, max, sum and sum of squares, combined over chunks."""

    def __init__(self) -> None:
        self.n = 0
        self.min = math.inf
        self.max = -math.inf
        self.total = 0.0
        self.total_sq = 0.0

    def add(self, values: np.ndarray) -> None:
        if values.size == 0:
            return
        self.n += values.size
        self.min = min(self.min, float(values.min()))
        self.max = max(self.max, float(values.max()))
        self.total += float(values.sum())
        self.total_sq += float(np.square(values).sum())  # not np.dot: BLAS start-up costs ms per call

    def finish(self, name: str, units: str) -> ChannelStats:
        if self.n == 0:
            nan = float("nan")
            return ChannelStats(name, units, nan, nan, nan, nan)
        return ChannelStats(name, units, self.min, self.max, self.total / self.n, math.sqrt(self.total_sq / self.n))


class _SummaryStage:
    """Per-channel running statistics over the chunk stream (a :class:`afmtool.pipeline.Stage`)."""

    def __init__(self, names) -> None:
        self.stats = {name: _RunningStats() for name in names}
        self.n_samples = 0

    def prepare(self, head) -> None:
        """Nothing to set up."""

    def step(self, chunk: Chunk) -> None:
        for name, values in chunk.data.items():
            self.stats[name].add(values)
        self.n_samples = chunk.start + len(chunk)

    def finish(self) -> _SummaryStage:
        return self


def summarize(
    reader: CaptureReader,
    chunk_samples: int = DEFAULT_CHUNK_SAMPLES,
    progress: Callable[[int], None] | None = None,
) -> CaptureSummary:
    """Stream every channel once and summarise it.

    A capture known to be empty (its reader says 0 samples) is summarised
    without streaming, with NaN statistics: that it is empty is the answer.
    """
    info = reader.info
    stage = _SummaryStage(info.channel_names)
    if info.n_samples != 0:
        run_stream(reader, [stage], channels=info.channel_names, chunk_samples=chunk_samples, progress=progress)
    channels = tuple(stage.stats[c.name].finish(c.name, c.units) for c in info.channels)
    return CaptureSummary(
        info.source,
        info.format,
        info.sample_rate_hz,
        stage.n_samples,
        stage.n_samples / info.sample_rate_hz,
        channels,
        dict(info.metadata),
        info.truth_names,
        info.segments,
    )
