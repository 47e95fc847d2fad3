"""The provenance hash of a capture, computed on its samples in the read pass.

A streaming command (reep, probeloss, decode, kalman-bank) records *which
data* it analysed.  Hashing the file's bytes needs a second pass over the
file, which cost a third of a probeloss run at 1e8 samples (sha256 at
1.3 s per 1.6 GB).  Instead :class:`HashedReader` hashes each chunk as the
analysis reads it, in the read-ahead thread, with xxHash's XXH3-128: the
samples are already in cache, and nothing is read twice.

What is hashed: each channel the analysis reads, as the float64
little-endian values afmtool read (after the units were converted, so the
numbers the analysis saw), in capture order; one XXH3-128 per channel, so
the value does not depend on how the capture was cut into chunks.  The
channels' digests are folded, in name order, with their names and the
sample count.  XXH3 is not a cryptographic hash: it identifies data, it
does not defend against someone forging a collision.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING

from afmtool.io.capture import CaptureReader, Chunk, ReaderView

if TYPE_CHECKING:
    import numpy as np

__all__ = ["ALGORITHM", "SampleDigest", "HashedReader", "capture_hash", "hash_matches"]

#: The algorithm named in every sample hash record.
ALGORITHM = "xxh3-128"

#: Versions the fold below; a change to what is hashed changes it.
_DOMAIN = b"afmtool samples v1\0"


def _as_le_float64(values: np.ndarray) -> np.ndarray:
    import numpy as np

    return np.ascontiguousarray(values, dtype="<f8")


class SampleDigest:
    """XXH3-128 of each channel's samples, folded into one record.

    Parameters
    ----------
    channels : sequence of str
        The channels hashed; every chunk given to :meth:`update` must hold them.
    """

    def __init__(self, channels: Sequence[str]) -> None:
        import xxhash

        self.channels = tuple(sorted(set(channels)))
        self._digests = {name: xxhash.xxh3_128() for name in self.channels}
        self.samples = 0

    def update(self, chunk: Chunk) -> None:
        """Add one chunk (its channels as float64 little-endian bytes)."""
        for name in self.channels:
            self._digests[name].update(_as_le_float64(chunk.data[name]))
        self.samples += len(chunk)

    def value(self) -> str:
        """Hex digest of the fold: domain, then per channel (name order) its name and digest, then the count."""
        import xxhash

        fold = xxhash.xxh3_128(_DOMAIN)
        for name in self.channels:
            fold.update(name.encode() + b"\0" + self._digests[name].digest())
        fold.update(self.samples.to_bytes(8, "little"))
        return fold.hexdigest()

    def record(self) -> dict:
        """``{"algorithm", "value", "over", "channels", "samples"}`` for report.json."""
        return {"algorithm": ALGORITHM, "value": self.value(), "over": "samples", "channels": list(self.channels),
                "samples": self.samples}


class HashedReader(ReaderView):
    """A view that hashes the samples of its first complete pass as they are read.

    ``blocks`` hands every chunk on unchanged; the first pass that reaches
    the end of the capture leaves its :class:`SampleDigest` in
    :attr:`digest`.  Later passes are not hashed
    again.  The hashing runs in whichever thread iterates the blocks: the
    read-ahead thread of :func:`afmtool.pipeline.run_stream`.
    """

    def __init__(self, reader: CaptureReader) -> None:
        self._reader = reader
        self.info = reader.info
        self.digest: SampleDigest | None = None

    def blocks(self, channels: Sequence[str], block_samples: int) -> Iterator[Chunk]:
        digest = SampleDigest(channels) if self.digest is None else None
        for chunk in self._reader.blocks(channels, block_samples):
            if digest is not None:
                digest.update(chunk)
            yield chunk
        if digest is not None and self.digest is None:
            self.digest = digest

    def close(self) -> None:
        self._reader.close()

    def record(self) -> dict:
        """The hash record of the completed pass.

        Raises
        ------
        RuntimeError
            No pass has reached the end of the capture.
        """
        if self.digest is None:
            raise RuntimeError("the capture was not read to its end, so it has no sample hash")
        return self.digest.record()


def capture_hash(reader: CaptureReader, channels: Sequence[str], chunk_samples: int = 1 << 20) -> dict:
    """The sample hash record of ``channels`` of an open capture, read once (e.g. for batch resume)."""
    digest = SampleDigest(channels)
    for chunk in reader.blocks(list(digest.channels), chunk_samples):
        digest.update(chunk)
    return digest.record()


def hash_matches(recorded: dict, reader: CaptureReader) -> bool:
    """Whether ``reader``'s samples have the hash ``recorded`` (a record of :meth:`SampleDigest.record`)."""
    channels = recorded.get("channels")
    if recorded.get("algorithm") != ALGORITHM or not isinstance(channels, list):
        return False
    if any(name not in reader.info.channel_names for name in channels):
        return False
    return capture_hash(reader, channels) == recorded
