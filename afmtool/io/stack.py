"""The one reader stack: how every caller turns a capture into the samples an analysis reads.

A capture is read through layers, each applied here and nowhere else::

    format reader  (io/registry: by suffix; --sample-rate; the format's own --channel / --topic)
      └ views      (io/views: --segment, --channel renames)                       [registry.open_capture]
        └ check    (what the command needs: Nyquist, channels; the real reason first)
          └ units  (io/units.UnitsReader: --units, --invols, --z-sensitivity, mV -> V, um -> nm)
            └ drive (io/synthetic_drive.SyntheticDriveReader: --drive or metadata drive.lines)
              └ hash (io/provenance.HashedReader: the samples the analysis saw, in its read pass)

:class:`CaptureOptions` holds every choice a user makes about the capture
itself (not about the analysis); :func:`open_capture` (also reached as
``afmtool.io.registry.open_capture(path, options)``) applies them to a path,
:func:`stack_reader` to an already open reader (numpy arrays in memory).
The CLI (:func:`afmtool.cli.common.open_calibrated`), ``afmtool batch`` (its
resume check), the Python API (:class:`afmtool.Capture`) and the Dask
workers (through the :mod:`afmtool.io.ranges` sources the stack composes)
all read through it, so the same options give the same converted samples
everywhere.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING

from afmtool.io.capture import CaptureInfo, CaptureReader

if TYPE_CHECKING:
    from afmtool.estimators.drive_lines import DriveResponse
    from afmtool.io.units import Calibration

__all__ = ["CaptureOptions", "open_capture", "stack_reader"]

#: ``needs(info, drive_lines_hz, synthesisable)``: raises :class:`~afmtool.errors.InputError` when the
#: capture cannot carry what a command needs (:class:`afmtool.analyses.capture_check.CaptureNeeds`).
NeedsCheck = Callable[[CaptureInfo, tuple, bool], None]


def _frozen(mapping: Mapping[str, str] | None) -> Mapping[str, str]:
    return MappingProxyType(dict(mapping or {}))


@dataclass(frozen=True)
class CaptureOptions:
    """How to read a capture: every option of the command line's capture group, once.

    Attributes
    ----------
    channel_map : mapping of str to str
        ``--channel NAME=SOURCE``: an HDF5 dataset for HDF5 (``{"deflection": "/s"}``),
        a rename for every other format but bags.
    topic_map : mapping of str to str
        ``--topic NAME=TOPIC`` (bags).
    sample_rate_hz : float or None
        ``--sample-rate`` (Hz), for formats that do not record it.
    segment : str or None
        ``--segment``: one segment (name or number from 0) of a segmented file.
    curve : str or None
        ``--curve``: one curve (``N`` or ``X,Y``) of a JPK force map or QI data file.
    group : str or None
        ``--group``: one group (name or number from 0) of a TDMS file.
    units : mapping of str to str
        ``--units NAME=UNIT``: a channel's units, set or overridden.
    invols_nm_per_v : float or None
        ``--invols`` (nm/V): converts a deflection recorded in V.
    z_sensitivity_nm_per_v : float or None
        ``--z-sensitivity`` (nm/V): converts a z_piezo recorded in V.
    drive : str or None
        ``--drive F1:A1,F2:A2`` (Hz:V): a dither that was not recorded, synthesised.
    drive_phases : {"common", "independent"}
        ``--drive-phases``: the lines started together (the thesis's design; their closure phase
        then pins f0 and Q) or were phased apart (the magnitudes alone).
    free_air : str or None
        ``START:END`` (s) where a synthesised drive's phases are fitted (else metadata ``free_air``).
    drive_response : DriveResponse or None
        The free-air f0 and Q a synthesised drive's phases are fitted against (``--model``,
        ``--f0/--q`` of reep, probeloss, kalman-bank); None: metadata ``cantilever``, else the lines' magnitudes.
    accepts_drive : bool
        The reader may synthesise the dither from metadata ``drive.lines`` (reep, probeloss, kalman-bank).
    raw_deflection : bool
        Leave a deflection in V as V (``identify invols`` measures the InvOLS itself).
    convert_units : bool
        False: apply ``--units`` but keep the file's scale (``info``, ``convert``).
    needs : callable or None
        What the command needs of the capture, checked before anything else is read
        (:class:`afmtool.analyses.capture_check.CaptureNeeds`).
    hash_samples : bool
        Hash the samples as the analysis reads them (the report's input record; ``--no-hash`` turns it off).
    """

    channel_map: Mapping[str, str] = field(default_factory=dict)
    topic_map: Mapping[str, str] = field(default_factory=dict)
    sample_rate_hz: float | None = None
    segment: str | None = None
    curve: str | None = None
    group: str | None = None
    units: Mapping[str, str] = field(default_factory=dict)
    invols_nm_per_v: float | None = None
    z_sensitivity_nm_per_v: float | None = None
    drive: str | None = None
    drive_phases: str = "common"
    free_air: str | None = None
    drive_response: DriveResponse | None = None
    accepts_drive: bool = False
    raw_deflection: bool = False
    convert_units: bool = True
    needs: NeedsCheck | None = None
    hash_samples: bool = False

    def __post_init__(self) -> None:
        for name in ("channel_map", "topic_map", "units"):
            object.__setattr__(self, name, _frozen(getattr(self, name)))
        if self.drive_phases not in ("common", "independent"):
            from afmtool.errors import ConfigError

            raise ConfigError(f"--drive-phases {self.drive_phases!r} must be 'common' or 'independent'")

    def replace(self, **changes) -> CaptureOptions:
        """A copy with ``changes`` (``dataclasses.replace``)."""
        return replace(self, **changes)

    def calibration(self) -> Calibration:
        """The unit options as an :class:`afmtool.io.units.Calibration` (checked: finite, positive, known units)."""
        from afmtool.io.units import Calibration

        return Calibration(
            units=dict(self.units), invols_nm_per_v=self.invols_nm_per_v,
            z_sensitivity_nm_per_v=self.z_sensitivity_nm_per_v, raw_deflection=self.raw_deflection,
        )

    def format_keywords(self) -> dict:
        """The keywords of the format layer (:func:`afmtool.io.registry.open_capture` without options)."""
        return {"channel_map": dict(self.channel_map) or None, "topic_map": dict(self.topic_map) or None,
                "sample_rate_hz": self.sample_rate_hz, "segment": self.segment, "curve": self.curve, "group": self.group}


def open_capture(path: Path | str, options: CaptureOptions | None = None) -> CaptureReader:
    """Open ``path`` through the whole stack: format, segment, channels, check, units, drive, hash.

    Parameters
    ----------
    path : path or str
        A capture file, a ROS2 bag folder, a Zarr store (a path or an fsspec URL), or ``-`` (CSV on stdin).
    options : CaptureOptions, optional
        Default: every unit converted to afmtool's internal units (nm, V, µA, s), nothing else.

    Returns
    -------
    CaptureReader
        Close it (or use it as a context manager).

    Raises
    ------
    InputError, ConfigError
        One line each: a file that cannot be read as asked, an option that is not valid.
    """
    from afmtool.io.registry import open_capture as open_format

    options = options or CaptureOptions()
    reader = open_format(path, **options.format_keywords())
    try:
        return stack_reader(reader, options)
    except BaseException:
        reader.close()
        raise


def _drive_lines(info: CaptureInfo, options: CaptureOptions) -> tuple:
    if options.drive:
        from afmtool.io.synthetic_drive import drive_lines_of

        return drive_lines_of(options.drive)
    if options.accepts_drive and "dither" not in info.channel_names:
        from afmtool.io.synthetic_drive import drive_lines_from_metadata

        return drive_lines_from_metadata(info.metadata)
    return ()


def stack_reader(reader: CaptureReader, options: CaptureOptions | None = None) -> CaptureReader:
    """The layers above the format of an open ``reader``: check, units, synthesised drive, hash.

    Used by :func:`open_capture` and for captures that are not files (numpy arrays,
    :meth:`afmtool.Capture.from_arrays`).  ``reader`` is closed with the result.
    """
    from afmtool.io.units import UnitsReader

    options = options or CaptureOptions()
    calibration = options.calibration()
    lines = _drive_lines(reader.info, options)
    if options.needs is not None:
        # the real reason first: a capture that cannot hold the oscillation, or lacks a channel
        options.needs(reader.info, tuple(line.frequency_hz for line in lines), bool(lines))
    reader = UnitsReader(reader, calibration, convert=options.convert_units)
    if lines:
        from afmtool.config.params import parse_interval
        from afmtool.io.synthetic_drive import SyntheticDriveReader

        reader = SyntheticDriveReader(reader, lines, parse_interval(options.free_air or "", "--free-air"),
                                      response=options.drive_response, phases=options.drive_phases)
    if options.hash_samples:
        from afmtool.io.provenance import HashedReader

        reader = HashedReader(reader)
    return reader
