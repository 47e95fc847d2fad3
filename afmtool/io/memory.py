"""A capture held in memory (simulator output), readable like any file."""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence

import numpy as np

from afmtool.io.capture import CaptureInfo, ChannelSpec, Chunk, ReaderBase

__all__ = ["ArrayReader"]


class ArrayReader(ReaderBase):
    """Serve in-memory channel arrays through the :class:`CaptureReader` protocol."""

    def __init__(
        self,
        sample_rate_hz: float,
        channels: Sequence[ChannelSpec],
        data: Mapping[str, np.ndarray],
        metadata: Mapping | None = None,
        truth: Mapping[str, np.ndarray] | None = None,
        source: str = "<memory>",
    ) -> None:
        lengths = {len(data[c.name]) for c in channels}
        if len(lengths) != 1:
            raise ValueError(f"channels have different lengths {sorted(lengths)}")
        self._data = {c.name: np.asarray(data[c.name], dtype=np.float64) for c in channels}
        self._truth = dict(truth or {})
        self.info = CaptureInfo(
            source, "memory", float(sample_rate_hz), tuple(channels), lengths.pop(), metadata or {}, tuple(self._truth)
        )

    def blocks(self, channels: Sequence[str], block_samples: int) -> Iterator[Chunk]:
        for start in range(0, self.info.n_samples, block_samples):
            stop = start + block_samples
            yield Chunk(start, {name: self._data[name][start:stop] for name in channels})

    def truth(self) -> dict[str, np.ndarray]:
        return dict(self._truth)

    def close(self) -> None:
        pass
