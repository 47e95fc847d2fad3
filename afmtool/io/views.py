"""Views over an open capture: one segment of it, or its channels renamed.

Every reader gets ``--segment`` and ``--channel NAME=SOURCE`` through these
wrappers, so that a format's reader only has to report its segments
(:class:`~afmtool.io.capture.SegmentSpec`) and its native channel names.

Segments survive a conversion: readers put them into the metadata key
``capture_segments`` (a list of ``{"name", "start_sample", "n_samples",
"sample_rate_hz"}``), which every writer stores with the rest of the
metadata, so that an afmtool HDF5 or CSV file converted from a force curve
still lists, and selects, its approach and retract.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Mapping, Sequence

from afmtool.errors import InputError
from afmtool.io.capture import CaptureReader, ChannelSpec, Chunk, ReaderBase, SegmentSpec

__all__ = [
    "SEGMENTS_KEY",
    "SegmentView",
    "RenamedView",
    "segments_metadata",
    "segments_from_metadata",
    "select_segment",
    "describe_segments",
]

#: Metadata key under which segments are stored in afmtool's own formats.
SEGMENTS_KEY = "capture_segments"


def segments_metadata(segments: Sequence[SegmentSpec]) -> list[dict]:
    """Segments as JSON-ready records for the ``capture_segments`` metadata key."""
    return [
        {"name": s.name, "start_sample": s.start, "n_samples": s.n_samples, "sample_rate_hz": s.sample_rate_hz}
        for s in segments
    ]


def segments_from_metadata(metadata: Mapping, source: str, n_samples: int | None) -> tuple[SegmentSpec, ...]:
    """Read ``capture_segments`` back, checking each record against the capture's length."""
    records = metadata.get(SEGMENTS_KEY)
    if records is None:
        return ()
    if not isinstance(records, list):
        raise InputError(f"{source}: metadata {SEGMENTS_KEY} must be a list")
    segments = []
    for i, record in enumerate(records):
        try:
            name, start, n = str(record["name"]), record["start_sample"], record["n_samples"]
            rate = float(record["sample_rate_hz"])
        except (KeyError, TypeError, ValueError):
            raise InputError(
                f"{source}: metadata {SEGMENTS_KEY}[{i}] needs name, start_sample, n_samples, sample_rate_hz"
            ) from None
        ok = all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in (start, n))
        if not ok or (n_samples is not None and start + n > n_samples):
            raise InputError(f"{source}: metadata {SEGMENTS_KEY}[{i}] ({name!r}) lies outside the capture")
        segments.append(SegmentSpec(name, start, n, rate))
    return tuple(segments)


def describe_segments(segments: Sequence[SegmentSpec]) -> str:
    """``0 extend (6000 samples, 2000 Hz), 1 retract (...)``, for messages."""
    return ", ".join(f"{i} {s.name} ({s.n_samples} samples, {s.sample_rate_hz:g} Hz)" for i, s in enumerate(segments))


def select_segment(segments: Sequence[SegmentSpec], choice: str, source: str) -> int:
    """The index of ``choice`` (a segment name, or its number from 0) in ``segments``."""
    if not segments:
        raise InputError(f"{source}: --segment {choice!r}: the capture has no segments")
    names = [s.name for s in segments]
    if choice in names:
        return names.index(choice)
    if choice.strip().isdigit() and int(choice) < len(segments):
        return int(choice)
    raise InputError(f"{source}: no segment {choice!r}; the segments are {describe_segments(segments)}")


class SegmentView(ReaderBase):
    """One segment of a capture whose segments share its sample stream.

    Samples are renumbered from 0 at the segment's first sample.
    """

    def __init__(self, reader: CaptureReader, index: int) -> None:
        self._reader = reader
        info = reader.info
        self._segment = segment = info.segments[index]
        # The file's segment table describes the whole file; a copy of one segment records which it was.
        metadata = {k: v for k, v in info.metadata.items() if k != SEGMENTS_KEY}
        metadata["segment"] = {"name": segment.name, "index": index, "start_sample": segment.start}
        self.info = dataclasses.replace(
            info, n_samples=segment.n_samples, sample_rate_hz=segment.sample_rate_hz, metadata=metadata
        )

    def blocks(self, channels: Sequence[str], block_samples: int) -> Iterator[Chunk]:
        first, stop = self._segment.start, self._segment.start + self._segment.n_samples
        done = 0
        # The underlying reader's blocks, trimmed to the segment (earlier samples are read and dropped).
        for chunk in self._reader.blocks(channels, block_samples):
            lo, hi = max(first, chunk.start), min(stop, chunk.start + len(chunk))
            if hi <= lo:
                if chunk.start >= stop:
                    break
                continue
            part = {k: v[lo - chunk.start : hi - chunk.start] for k, v in chunk.data.items()}
            yield Chunk(done, part)
            done += hi - lo
            if hi >= stop:
                break

    def ranges(self):
        """The source's ranges from the segment's first sample (:mod:`afmtool.io.ranges`)."""
        from afmtool.io.ranges import OffsetRanges, range_source

        source = range_source(self._reader)
        return None if source is None else OffsetRanges(source, self._segment.start)

    def truth(self) -> dict:
        return {}

    def close(self) -> None:
        self._reader.close()


class RenamedView(ReaderBase):
    """A capture whose channels are renamed: ``{"deflection": "CH2"}`` reads column CH2 as deflection.

    Channels not named in the mapping keep their names, unless a new name
    takes their place.
    """

    def __init__(self, reader: CaptureReader, mapping: Mapping[str, str]) -> None:
        self._reader = reader
        info = reader.info
        have = {c.name: c for c in info.channels}
        for new, old in mapping.items():
            if old not in have:
                raise InputError(
                    f"{info.source}: --channel {new}={old}: no channel {old!r} (has: {', '.join(have) or 'none'})"
                )
        # In the file's channel order: a mapped channel under its new name(s); an unmapped one under
        # its own, unless a new name takes its place.
        self._source_of = {}
        for name in have:
            news = [new for new, old in mapping.items() if old == name]
            if not news and name not in mapping:
                news = [name]
            for new in news:
                self._source_of[new] = name
        channels = tuple(ChannelSpec(new, have[old].units) for new, old in self._source_of.items())
        self.info = dataclasses.replace(info, channels=channels)

    def blocks(self, channels: Sequence[str], block_samples: int) -> Iterator[Chunk]:
        sources = [self._source_of[name] for name in channels]
        for chunk in self._reader.blocks(sorted(set(sources), key=sources.index), block_samples):
            yield Chunk(chunk.start, {name: chunk.data[self._source_of[name]] for name in channels})

    def truth(self) -> dict:
        return self._reader.truth()

    def close(self) -> None:
        self._reader.close()
