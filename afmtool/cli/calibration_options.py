"""``--units``, ``--invols``, ``--z-sensitivity`` and ``--drive``: how a capture's channels are read.

The options are bundled in :class:`CaptureCalibration` and, with the format's
options, become one :class:`afmtool.io.stack.CaptureOptions` (:func:`capture_options`),
applied where the capture is opened by the one reader stack
(:func:`afmtool.io.stack.open_capture`): units are parsed and converted once
there (:mod:`afmtool.io.units`), and a drive that was not recorded is
synthesised (:mod:`afmtool.io.synthetic_drive`).
"""

from __future__ import annotations

from typing import Annotated, NamedTuple, Optional

import typer

__all__ = [
    "UnitsOpt", "InvolsOpt", "ZSensitivityOpt", "DriveOpt", "DrivePhasesOpt", "CaptureCalibration", "capture_options",
]

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
        help="Dither not recorded: its lines 'F1:A1,F2:A2,...' (Hz:V), or the lines.json of 'afmtool design "
        "excitation' (its phases kept between the lines); phases are fitted on the free-air segment.",
    ),
]

DrivePhasesOpt = Annotated[
    Optional[str],
    typer.Option(
        "--drive-phases",
        help="How --drive's lines were phased: 'common' (started together, as the thesis's three sines: f0 and Q "
        "from the lines' magnitudes and their closure phase) or 'independent' (phases set apart: from the "
        "magnitudes alone, with a wider stated uncertainty). Default common.",
    ),
]


class CaptureCalibration(NamedTuple):
    """The calibration options of one command line (None: not given)."""

    units: list[str] | None = None
    invols_nm_per_v: float | None = None
    z_sensitivity_nm_per_v: float | None = None
    drive: str | None = None
    #: ``--drive-phases``: "common" or "independent" (None: common).
    drive_phases: str | None = None
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


def capture_options(channel, topic, sample_rate, calibration: CaptureCalibration | None = None, *,
                    convert_units: bool = True, segment=None, hash_samples: bool = False):
    """The command line's capture options as one :class:`afmtool.io.stack.CaptureOptions`.

    ``segment`` is ``--segment``'s value, or the :class:`afmtool.io.registry.Selection` of
    ``--segment``, ``--curve`` and ``--group`` together.
    """
    from afmtool.cli.options import parse_mapping
    from afmtool.io.registry import Selection
    from afmtool.io.stack import CaptureOptions

    selection = segment if isinstance(segment, Selection) else Selection(segment=segment)
    calibration = calibration or CaptureCalibration()
    return CaptureOptions(
        channel_map=parse_mapping(channel, "--channel"), topic_map=parse_mapping(topic, "--topic"),
        sample_rate_hz=sample_rate, segment=selection.segment, curve=selection.curve, group=selection.group,
        units=parse_mapping(calibration.units, "--units"),
        invols_nm_per_v=calibration.invols_nm_per_v, z_sensitivity_nm_per_v=calibration.z_sensitivity_nm_per_v,
        drive=calibration.drive, drive_phases=calibration.drive_phases or "common", free_air=calibration.free_air,
        accepts_drive=calibration.accepts_drive,
        raw_deflection=calibration.raw_deflection, convert_units=convert_units, needs=calibration.needs,
        hash_samples=hash_samples,
    )
