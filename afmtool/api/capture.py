"""``afmtool.open`` and :class:`Capture`: a capture for the Python API, read through the one reader stack.

A :class:`Capture` is a description, not an open file: the path (or the numpy
arrays) and the :class:`~afmtool.io.stack.CaptureOptions` it is read with.
Each analysis opens it again through :func:`afmtool.io.stack.open_capture`
(the CLI's own path), so a capture larger than memory is streamed and a
notebook can run several analyses on one capture.
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from afmtool.errors import ConfigError
from afmtool.io.capture import DEFAULT_CHUNK_SAMPLES, CaptureInfo, ChannelSpec, Chunk, SegmentSpec
from afmtool.io.metadata import CaptureMetadata
from afmtool.io.stack import CaptureOptions

if TYPE_CHECKING:
    import numpy as np
    import xarray

    from afmtool.io.capture import CaptureReader

__all__ = ["Capture", "open"]

#: The units a channel given as an array has unless ``units`` says otherwise.
_ARRAY_UNITS = {"deflection": "nm", "dither": "V", "z_piezo": "nm"}


@dataclass(frozen=True)
class Capture:
    """A capture: its samples' source and how they are read.

    Make one with :func:`afmtool.open` (a file) or :meth:`Capture.from_arrays`
    (numpy arrays).  Every analysis function (``afmtool.reep`` ...) takes one.

    Attributes
    ----------
    source : str
        The path or URL (``"<arrays>"`` for arrays).
    options : CaptureOptions
        How it is read (channels, units, calibration, drive).
    """

    source: str
    options: CaptureOptions = field(default_factory=CaptureOptions)
    _arrays: Mapping[str, Any] | None = field(default=None, repr=False, compare=False)
    _info: list = field(default_factory=list, repr=False, compare=False)

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_arrays(
        cls,
        sample_rate_hz: float,
        *,
        deflection: Sequence[float] | np.ndarray,
        dither: Sequence[float] | np.ndarray | None = None,
        z_piezo: Sequence[float] | np.ndarray | None = None,
        units: Mapping[str, str] | None = None,
        metadata: Mapping | None = None,
    ) -> Capture:
        """A capture from numpy arrays sampled at ``sample_rate_hz`` (Hz).

        Parameters
        ----------
        sample_rate_hz : float
            The ADC's rate, Hz.
        deflection : array_like
            The cantilever deflection, nm unless ``units`` says otherwise.
        dither : array_like, optional
            The excitation, V.
        z_piezo : array_like, optional
            The z-piezo position, nm unless ``units`` says otherwise.
        units : mapping, optional
            A channel's units when not the default (``{"deflection": "um"}``); converted once, as a file's are.
        metadata : mapping, optional
            Capture metadata as a file would carry it (``{"free_air": {"start_s": 0, "end_s": 0.01}}``).

        Examples
        --------
        >>> import numpy as np, afmtool
        >>> t = np.arange(50_000) / 500e3
        >>> cap = afmtool.Capture.from_arrays(500e3, deflection=np.sin(2 * np.pi * 70e3 * t),
        ...                                   dither=np.cos(2 * np.pi * 70e3 * t))
        >>> cap.channels
        ('deflection', 'dither')
        """
        import numpy as np

        given = {"deflection": deflection, "dither": dither, "z_piezo": z_piezo}
        arrays = {name: np.asarray(values, dtype=np.float64) for name, values in given.items() if values is not None}
        lengths = {name: values.shape for name, values in arrays.items()}
        if any(len(shape) != 1 for shape in lengths.values()) or len({s[0] for s in lengths.values()}) != 1:
            raise ConfigError(f"the channels must be 1-D arrays of one length; got shapes {lengths}")
        units = dict(units or {})
        unknown = sorted(set(units) - set(arrays))
        if unknown:
            raise ConfigError(f"units names no channel {unknown[0]!r} (has: {', '.join(arrays)})")
        if not (isinstance(sample_rate_hz, (int, float)) and float(sample_rate_hz) > 0):
            raise ConfigError(f"sample_rate_hz={sample_rate_hz!r} must be a number > 0 (Hz)")
        spec = {
            "sample_rate_hz": float(sample_rate_hz),
            "channels": tuple(ChannelSpec(name, units.get(name, _ARRAY_UNITS[name])) for name in arrays),
            "data": arrays,
            "metadata": json.loads(json.dumps(dict(metadata or {}))),
        }
        capture = cls("<arrays>", CaptureOptions(), spec)
        capture.info  # noqa: B018 - the metadata and units are checked now, as afmtool.open checks a file's
        return capture

    # ------------------------------------------------------------------ reading
    def open_reader(self, options: CaptureOptions | None = None) -> CaptureReader:
        """The capture opened through the reader stack (with ``options`` instead of its own); close it."""
        from afmtool.io.stack import open_capture, stack_reader

        options = options or self.options
        if self._arrays is None:
            return open_capture(self.source, options)
        from afmtool.io.memory import ArrayReader

        spec = self._arrays
        reader = ArrayReader(spec["sample_rate_hz"], spec["channels"], spec["data"], spec["metadata"],
                             source=self.source)
        return stack_reader(reader, options)

    @property
    def info(self) -> CaptureInfo:
        """What is known before the samples are read (the stack's view: internal units)."""
        if not self._info:
            with self.open_reader() as reader:
                self._info.append(reader.info)
        return self._info[0]

    @property
    def channels(self) -> tuple[str, ...]:
        """The channels' names."""
        return self.info.channel_names

    @property
    def units(self) -> dict[str, str]:
        """Each channel's units, as the analyses read them (nm, V, µA after conversion)."""
        return {c.name: c.units for c in self.info.channels}

    @property
    def sample_rate_hz(self) -> float:
        """The sample rate, Hz."""
        return self.info.sample_rate_hz

    @property
    def n_samples(self) -> int | None:
        """The number of samples (None for a stream whose length is not known)."""
        return self.info.n_samples

    @property
    def duration_s(self) -> float | None:
        """Its length, s."""
        return self.info.duration_s

    @property
    def metadata(self) -> CaptureMetadata:
        """The typed metadata (cantilever, drive, free_air, scan ...); ``.raw`` is the mapping as stored."""
        return self.info.capture_metadata

    @property
    def segments(self) -> tuple[SegmentSpec, ...]:
        """The file's segments (a force curve's approach, dwell, retract); empty when it has none."""
        return self.info.segments

    def segment(self, which: str | int) -> Capture:
        """One segment (its name or number from 0), as a capture of its own."""
        return Capture(self.source, self.options.replace(segment=str(which)), self._arrays)

    def chunks(self, channels: Sequence[str] | None = None, chunk_samples: int = DEFAULT_CHUNK_SAMPLES) -> Iterator[Chunk]:
        """The samples in aligned chunks (``chunk.data[name]``, ``chunk.start``), read as analyses read them."""
        from afmtool.io.chunks import opened_chunks

        return opened_chunks(self.open_reader, channels, chunk_samples)

    def read(self, channels: Sequence[str] | None = None) -> dict[str, np.ndarray]:
        """Every sample of ``channels`` (default all) in memory, in the analyses' units."""
        import numpy as np

        names = tuple(channels or self.channels)
        blocks = list(self.chunks(names))
        return {name: np.concatenate([b.data[name] for b in blocks]) if blocks else np.empty(0) for name in names}

    def to_xarray(self, channels: Sequence[str] | None = None) -> xarray.Dataset:
        """The samples as an ``xarray.Dataset`` on a ``time`` coordinate (s), units in each variable's attrs.

        The whole capture is read into memory; use :meth:`chunks` for one larger than memory.
        """
        from afmtool.report.labelled import capture_dataset

        return capture_dataset(self, channels)

    def __repr__(self) -> str:
        try:
            info = self.info
        except Exception as exc:  # noqa: BLE001 - a repr must not raise; it says what is wrong instead
            return f"<afmtool.Capture {self.source}: {exc}>"
        channels = ", ".join(f"{c.name} [{c.units or '1'}]" for c in info.channels)
        length = "stream" if info.n_samples is None else f"{info.n_samples} samples, {info.duration_s:.6g} s"
        return f"<afmtool.Capture {self.source}: {length} at {info.sample_rate_hz:g} Hz; {channels}>"


def open(
    path: str | Path,
    *,
    channels: Mapping[str, str] | None = None,
    units: Mapping[str, str] | None = None,
    sample_rate_hz: float | None = None,
    segment: str | int | None = None,
    invols: float | None = None,
    z_sensitivity: float | None = None,
    drive: str | Sequence[tuple[float, float]] | None = None,
    drive_phases: str = "common",
) -> Capture:
    """Open a capture in any format the CLI reads, with the CLI's capture options.

    Parameters
    ----------
    path : str or Path
        HDF5, CSV, ROS bag, Igor ``.ibw``, JPK, TDMS, WAV, LabOne, Chiaro, a Zarr
        store (a folder or an fsspec URL such as ``s3://bucket/run.zarr``).
    channels : mapping, optional
        ``--channel``: which dataset or column is which channel, ``{"deflection": "CH2"}``
        (for a ROS bag, which topic: ``{"deflection": "/afm/deflection"}``).
    units : mapping, optional
        ``--units``: a channel's units, set or overridden (``{"deflection": "mV"}``).
    sample_rate_hz : float, optional
        ``--sample-rate`` (Hz), for files that do not record it.
    segment : str or int, optional
        ``--segment``: one segment of a segmented file (name or number from 0).
    invols : float, optional
        ``--invols`` (nm/V): converts a deflection recorded in V to nm.
    z_sensitivity : float, optional
        ``--z-sensitivity`` (nm/V): converts a z_piezo recorded in V to nm.
    drive : str or sequence of (Hz, V), optional
        ``--drive``: the lines of a dither that was not recorded (``"70000:0.1"`` or ``[(70e3, 0.1)]``);
        their phases are fitted on the free-air segment.
    drive_phases : {"common", "independent"}
        ``--drive-phases``: the lines started together (default; their closure phase helps pin the
        resonance, docs/conventions.md eq. D.4) or were phased apart.

    Returns
    -------
    Capture
        Checked now: a file that cannot be read as asked raises here.

    Raises
    ------
    afmtool.InputError, afmtool.ConfigError
        With the CLI's one-line message.

    Examples
    --------
    >>> import afmtool
    >>> cap = afmtool.open("sample_data/ltv_step.h5")
    >>> cap.sample_rate_hz, cap.units["deflection"]
    (500000.0, 'nm')
    """
    import os

    source = os.fspath(path)
    fmt_keywords: dict[str, Any] = {"channel_map": dict(channels or {})}
    if channels and _is_bag(source):
        fmt_keywords = {"topic_map": dict(channels)}
    if drive is not None and not isinstance(drive, str):
        drive = ",".join(f"{float(f)!r}:{float(a)!r}" for f, a in drive)
    options = CaptureOptions(
        **fmt_keywords, units=dict(units or {}), sample_rate_hz=sample_rate_hz,
        segment=None if segment is None else str(segment), invols_nm_per_v=invols,
        z_sensitivity_nm_per_v=z_sensitivity, drive=drive or None, drive_phases=drive_phases,
    )
    capture = Capture(source, options)
    capture.info  # noqa: B018 - opened once now, so that a bad path or option raises here, not in an analysis
    return capture


def _is_bag(source: str) -> bool:
    path = Path(source)
    return path.suffix.lower() in (".bag", ".mcap", ".db3") or (path / "metadata.yaml").is_file()


def as_capture(capture: Capture | str | Path, what: str = "capture") -> Capture:
    """A :class:`Capture` from a capture or a path (opened with the default options)."""
    if isinstance(capture, Capture):
        return capture
    if isinstance(capture, (str, Path)):
        return open(capture)
    raise ConfigError(f"{what} must be an afmtool.Capture or a path, not {type(capture).__name__}")
