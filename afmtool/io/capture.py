"""Records that describe a capture, and the protocol every reader follows.

A capture is a set of named channels sharing one sample rate, each with
units, plus a metadata mapping (validated by
``schemas/capture-metadata.schema.json``).  Readers yield aligned
:class:`Chunk` blocks so that analyses stream with bounded memory.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING, Protocol

from afmtool.errors import InputError
from afmtool.io.metadata import CaptureMetadata
from afmtool.io.text import clean_label

if TYPE_CHECKING:  # numpy stays out of CLI start-up (afmtool --help)
    import numpy as np

__all__ = [
    "CANONICAL_CHANNELS",
    "DEFAULT_CHUNK_SAMPLES",
    "ChannelSpec",
    "SegmentSpec",
    "CaptureInfo",
    "Chunk",
    "CaptureReader",
    "CaptureWriter",
    "ReaderBase",
]

#: Channel names every analysis understands.  Other names are allowed.
CANONICAL_CHANNELS = ("dither", "deflection", "thermal_current", "v_sub", "v_r", "z_piezo")

#: Default number of samples per chunk (2**20, about 2 s at 500 kHz).
DEFAULT_CHUNK_SAMPLES = 1 << 20


@dataclass(frozen=True)
class ChannelSpec:
    """One channel: its name and physical units (e.g. ``"nm"``, ``"V"``).

    The units are cleaned as the record is made (:func:`afmtool.io.text.clean_label`:
    decoded, NULs and control characters removed), so that whatever a file held, writers
    get one printable line.  The name is a reader's key for the channel, so it is not
    changed here: readers decode it where they read it, and :class:`CaptureInfo` refuses a
    name that is still not one printable line.
    """

    name: str
    units: str = ""

    def __post_init__(self) -> None:
        if not (isinstance(self.units, str) and self.units.isprintable() and self.units == self.units.strip()):
            object.__setattr__(self, "units", clean_label(self.units))


@dataclass(frozen=True)
class SegmentSpec:
    """One segment of a segmented file (a force curve's approach, dwell, retract).

    ``start`` is the segment's first sample in the file's sample stream when
    all segments share one rate (they are then read back to back), and 0
    for segments at different rates (each is then read on its own).
    """

    name: str
    start: int
    n_samples: int
    sample_rate_hz: float


@dataclass(frozen=True)
class CaptureInfo:
    """What is known about a capture before its samples are read.

    ``n_samples`` is ``None`` for streams (CSV on stdin) whose length is
    only known once they have been read to the end.  ``capture_metadata``
    is ``metadata`` validated and typed, once, when the info is made (so
    by every reader): a bad value is an InputError naming the key and
    ``source``.  Analyses read the typed fields; ``metadata`` stays for
    free-form keys and for writing the metadata on unchanged.
    """

    source: str
    format: str
    sample_rate_hz: float
    channels: tuple[ChannelSpec, ...]
    n_samples: int | None
    metadata: Mapping = field(default_factory=dict)
    #: Names of simulator ground-truth series stored with the capture.
    truth_names: tuple[str, ...] = ()
    #: The file's segments (empty for an unsegmented capture); see ``--segment``.
    segments: tuple[SegmentSpec, ...] = ()
    #: False when the file gives no units for channels it cannot be assumed to hold in afmtool's
    #: (a text export without a header, or a vendor export whose columns carry none): ``--units`` must.
    units_declared: bool = True
    capture_metadata: CaptureMetadata = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        for spec in self.channels:
            if not spec.name.isprintable():
                raise InputError(f"{self.source}: channel name {spec.name!r} is not one printable line (NUL or control characters)")
        object.__setattr__(self, "metadata", MappingProxyType(dict(self.metadata)))
        object.__setattr__(self, "capture_metadata", CaptureMetadata.from_mapping(self.metadata, self.source))

    @property
    def channel_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.channels)

    def units(self, name: str) -> str:
        for spec in self.channels:
            if spec.name == name:
                return spec.units
        raise KeyError(name)

    @property
    def duration_s(self) -> float | None:
        return None if self.n_samples is None else self.n_samples / self.sample_rate_hz


@dataclass(frozen=True)
class Chunk:
    """An aligned block of samples: ``data[name][i]`` is sample ``start + i``."""

    start: int
    data: Mapping[str, np.ndarray]

    def __len__(self) -> int:
        return len(next(iter(self.data.values()))) if self.data else 0

    def time_s(self, sample_rate_hz: float) -> np.ndarray:
        """Sample times in seconds, counted from the first sample of the capture."""
        import numpy as np

        return (self.start + np.arange(len(self))) / sample_rate_hz


class CaptureReader(Protocol):
    """A capture opened for reading.  Readers do I/O only; they never estimate."""

    info: CaptureInfo

    def blocks(self, channels: Sequence[str], block_samples: int) -> Iterator[Chunk]:
        """Yield aligned blocks of ``channels`` (float64), in order, once."""
        ...

    def truth(self) -> dict[str, np.ndarray]:
        """Simulator ground truth (``/truth``), empty when the format has none."""
        ...

    def close(self) -> None: ...


class CaptureWriter(Protocol):
    """A capture being written block by block; ``close`` finalises it."""

    def write(self, data: Mapping[str, np.ndarray]) -> None: ...

    def write_truth(self, truth: Mapping[str, np.ndarray]) -> None: ...

    def close(self) -> None: ...


class ReaderBase:
    """Context-manager support shared by the concrete readers."""

    def close(self) -> None:  # pragma: no cover - overridden
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class ReaderView(ReaderBase):
    """A reader over another, ``self._reader``: its truth, and whatever the view does not define, are the inner one's.

    So what the views below record of themselves (unit conversions, calibration,
    a synthesised drive) reads through, e.g. for :func:`afmtool.io.units.calibration_record`.
    """

    _reader: CaptureReader

    def __getattr__(self, name: str):
        if name.startswith("__") or name == "_reader":
            raise AttributeError(name)
        return getattr(self._reader, name)

    def truth(self) -> dict[str, np.ndarray]:
        return self._reader.truth()
