"""Readers and writers: captures in, capture files out."""

from afmtool.io.capture import (
    CANONICAL_CHANNELS,
    DEFAULT_CHUNK_SAMPLES,
    CaptureInfo,
    CaptureReader,
    CaptureWriter,
    ChannelSpec,
    Chunk,
)

__all__ = [
    "CANONICAL_CHANNELS",
    "DEFAULT_CHUNK_SAMPLES",
    "CaptureInfo",
    "CaptureReader",
    "CaptureWriter",
    "ChannelSpec",
    "Chunk",
]
