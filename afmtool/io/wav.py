"""WAV files (``.wav``) from sound-card and scope DAQs, read with scipy.io.wavfile.

Each WAV channel becomes a capture channel ``ch1`` .. ``chN`` (as scopes
label them; ``--channel deflection=ch2`` names them).  WAV carries no
physical units, so the channels have none: integer PCM samples are ADC
counts and IEEE-float samples are whatever the writer stored.  The reader
reports the PCM type and its full scale in the metadata and never scales
the samples; give the units with ``--units`` and calibrate from there.

The file is memory-mapped (``mmap=True``), so blocks are read as they are
needed; formats numpy cannot map (24-bit PCM) are read whole.  A file
shorter than its header says is refused.
"""

from __future__ import annotations

import math
import struct
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from afmtool.errors import InputError
from afmtool.io.capture import CaptureInfo, ChannelSpec, Chunk, ReaderBase

__all__ = ["WavReader"]

#: Most RIFF chunks walked before reading (a WAV has three or four).
MAX_CHUNKS = 10_000

# What scipy.io.wavfile raises on a damaged or truncated file.
_WAV_ERRORS = (
    ValueError, EOFError, KeyError, IndexError, TypeError, ArithmeticError, MemoryError, struct.error,
    UnboundLocalError,  # scipy 1.17 on a file with no data chunk
)


def _first_line(exc: BaseException) -> str:
    return ((str(exc).strip().splitlines() or [type(exc).__name__])[0])[:200]


class WavReader(ReaderBase):
    """Read a WAV file as a capture.

    Parameters
    ----------
    path : Path
        The ``.wav`` file; opened read-only.
    sample_rate_hz : float, optional
        Overrides the header's sample rate (an integer in WAV, so a
        1.15 MHz recording may need the exact value here).
    """

    def __init__(self, path: Path, sample_rate_hz: float | None = None) -> None:
        self._path = Path(path)
        rate, data = self._load()
        if data.ndim == 1:
            data = data[:, None]
        if data.ndim != 2 or data.shape[1] == 0 or data.dtype.kind not in "fiu":
            raise InputError(f"{path}: WAV data of shape {data.shape} {data.dtype} is not a set of channels")
        self._data = data
        rate = float(sample_rate_hz if sample_rate_hz is not None else rate)
        if not (math.isfinite(rate) and rate > 0):
            raise InputError(f"{path}: sample rate {rate!r} must be a positive number")
        channels = tuple(ChannelSpec(f"ch{i + 1}") for i in range(data.shape[1]))
        instrument: dict = {"vendor_format": "WAV", "sample_type": str(data.dtype)}
        if data.dtype.kind in "iu":
            instrument["full_scale_counts"] = int(np.iinfo(data.dtype).max) + 1
        self.info = CaptureInfo(str(path), "wav", rate, channels, len(data), {"instrument": instrument})

    def _load(self) -> tuple[int, np.ndarray]:
        from scipy.io import wavfile

        self._check_chunks()
        try:
            with warnings.catch_warnings():
                # scipy warns, and reads on, when the file ends before its header's data size
                warnings.simplefilter("error", wavfile.WavFileWarning)
                try:
                    return wavfile.read(str(self._path), mmap=True)
                except ValueError as exc:
                    if "mmap length is greater than file size" in str(exc):
                        raise InputError(f"{self._path}: truncated WAV file (shorter than its header says)") from None
                    if "mmap" not in str(exc):
                        raise
                return wavfile.read(str(self._path), mmap=False)  # e.g. 24-bit PCM, which numpy cannot map
        except OSError as exc:
            raise InputError(f"{self._path}: cannot read ({exc.strerror or _first_line(exc)})") from None
        except wavfile.WavFileWarning as exc:
            raise InputError(f"{self._path}: truncated or damaged WAV file ({_first_line(exc)})") from None
        except _WAV_ERRORS as exc:
            raise InputError(f"{self._path}: not a readable WAV file ({_first_line(exc)})") from None

    def _check_chunks(self) -> None:
        """Walk the RIFF chunks (at most :data:`MAX_CHUNKS`, each skipped by its size): exactly one ``data`` chunk.

        scipy reads the first ``data`` chunk and stops, so a file holding two (a
        recorder that appended a second take) read as the first one's samples alone.
        """
        try:
            with open(self._path, "rb") as handle:
                size = handle.seek(0, 2)
                handle.seek(0)
                head = handle.read(12)
                if len(head) < 12 or head[:4] not in (b"RIFF", b"RIFX", b"RF64") or head[8:12] != b"WAVE":
                    return  # scipy says what it is not
                order = ">" if head[:4] == b"RIFX" else "<"
                at, data_chunks = 12, 0
                for _ in range(MAX_CHUNKS):
                    handle.seek(at)
                    header = handle.read(8)
                    if len(header) < 8:
                        break
                    data_chunks += header[:4] == b"data"
                    length = struct.unpack(order + "I", header[4:])[0]
                    at += 8 + length + (length & 1)
                    if at >= size:
                        break
        except OSError as exc:
            raise InputError(f"{self._path}: cannot read ({exc.strerror})") from None
        if data_chunks > 1:
            raise InputError(f"{self._path}: {data_chunks} data chunks; a WAV capture holds one (scipy would read "
                             "the first alone)")

    def blocks(self, channels: Sequence[str], block_samples: int) -> Iterator[Chunk]:
        columns = [int(name[2:]) - 1 for name in channels]
        for start in range(0, len(self._data), block_samples):
            block = self._data[start : start + block_samples]
            try:
                with np.errstate(invalid="ignore", over="ignore"):  # NaN/inf are refused by name downstream
                    data = {name: np.array(block[:, i], dtype=np.float64) for name, i in zip(channels, columns)}
            except OSError as exc:  # a mapped file that shrank under us
                raise InputError(f"{self._path}: cannot read at sample {start} ({exc.strerror})") from None
            yield Chunk(start, data)

    def truth(self) -> dict[str, np.ndarray]:
        return {}

    def close(self) -> None:
        self._data = np.empty((0, 0))  # drops the memory map
