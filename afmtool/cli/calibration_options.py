"""``--units``, ``--invols``, ``--z-sensitivity`` and ``--drive``: how a capture's channels are read.

The options are bundled in :class:`CaptureCalibration` and applied where the
capture is opened (:func:`afmtool.cli.common.open_input`): units are parsed
and converted once there (:mod:`afmtool.io.units`), and a drive that was
not recorded is synthesised (:mod:`afmtool.analyses.synthetic_drive`).
"""

from __future__ import annotations

from typing import Annotated, NamedTuple, Optional

import typer

__all__ = ["UnitsOpt", "InvolsOpt", "ZSensitivityOpt", "DriveOpt", "CaptureCalibration", "apply_calibration"]

UnitsOpt = Annotated[
    Optional[list[str]],
    typer.Option("--units", help="Set or override a channel's units: NAME=UNIT, e.g. deflection=um (repeatable)."),
]
InvolsOpt = Annotated[
    Optional[float],
    typer.Option("--invols", help="Deflection sensitivity (InvOLS), nm/V: converts a deflection recorded in V."),
]
ZSensitivityOpt = Annotated[
    Optional[float],
    typer.Option("--z-sensitivity", help="z-piezo sensitivity, nm/V: converts a z_piezo recorded in V."),
]
DriveOpt = Annotated[
    Optional[str],
    typer.Option(
        "--drive",
        help="Dither not recorded: its lines 'F1:A1,F2:A2,...' (Hz:V); phases are fitted on the free-air segment.",
    ),
]


class CaptureCalibration(NamedTuple):
    """The calibration options of one command line (None: not given)."""

    units: list[str] | None = None
    invols_nm_per_v: float | None = None
    z_sensitivity_nm_per_v: float | None = None
    drive: str | None = None
    #: ``--free-air``: where the drive's phases are fitted (else metadata ``free_air``, else the first
    #: 65,536 samples); a ``free_air`` set only in a --config file is not seen here, the flag or metadata is.
    free_air: str | None = None
    #: The command can use a synthesised dither (reep, probeloss, kalman-bank): metadata drive.lines apply.
    accepts_drive: bool = False
    #: Leave a deflection in V as V (``identify invols``).
    raw_deflection: bool = False
    #: What the command needs of the capture (:class:`afmtool.analyses.capture_check.CaptureNeeds`),
    #: checked as it is opened, before anything else; None checks nothing.
    needs: object = None


def apply_calibration(reader, calibration: CaptureCalibration | None, *, convert_units: bool = True):
    """Wrap ``reader`` so that its channels come out in internal units, with a synthesised dither if asked."""
    from afmtool.cli.options import parse_mapping
    from afmtool.io.units import Calibration, UnitsReader

    calibration = calibration or CaptureCalibration()
    spec = Calibration(
        units=parse_mapping(calibration.units, "--units"),
        invols_nm_per_v=calibration.invols_nm_per_v,
        z_sensitivity_nm_per_v=calibration.z_sensitivity_nm_per_v,
        raw_deflection=calibration.raw_deflection,
    )
    lines = ()
    if calibration.drive:
        from afmtool.estimators.drive_lines import parse_drive_lines

        lines = parse_drive_lines(calibration.drive)
    elif calibration.accepts_drive and "dither" not in reader.info.channel_names:
        from afmtool.analyses.synthetic_drive import drive_lines_from_metadata

        lines = drive_lines_from_metadata(reader.info.metadata)
    if calibration.needs is not None:
        # the real reason first: a capture that cannot hold the oscillation, or lacks a channel
        from afmtool.analyses.capture_check import check_capture

        needs = calibration.needs._replace(drive_lines_hz=tuple(line.frequency_hz for line in lines))
        check_capture(reader.info, needs, synthesisable=bool(lines))
    reader = UnitsReader(reader, spec, convert=convert_units)
    if lines:
        from afmtool.analyses.synthetic_drive import SyntheticDriveReader
        from afmtool.config.params import parse_interval

        reader = SyntheticDriveReader(reader, lines, parse_interval(calibration.free_air or "", "--free-air"))
    return reader
