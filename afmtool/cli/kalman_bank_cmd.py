"""``afmtool kalman-bank``: REEP checked by a bank of Kalman filters and an adaptive observer."""

from __future__ import annotations

from pathlib import Path

import typer

from afmtool.cli.common import run_streaming_command
from afmtool.cli.groups import CaptureSource, CommandOutput, capture_options, output_options, with_options
from afmtool.cli.options import CaptureArg
from afmtool.cli.param_flags import param_flags
from afmtool.config.params import KalmanBankParams

__all__ = ["register"]


@with_options(param_flags(KalmanBankParams), output_options(Path("kalman_bank"), capture_run=True), capture_options(segment=False))
def kalman_bank(capture: CaptureArg, *, flags: dict, output: CommandOutput, source: CaptureSource) -> None:
    """Validate REEP's on-sample f0', Q' on a force curve by minimum innovation RMS (thesis §3.4.2).

    Builds steady-state Kalman filters from REEP's model at N points of the
    force curve (sharing the free-air numerator) and runs them in one fused
    loop beside an adaptive observer whose model follows REEP.  Verdict: each
    filter's least RMS must fall in its design z bin, and the adaptive
    observer must have the least RMS most of the time (tolerances in
    report.json).  Writes bank.h5, bank_rms_vs_z.png, report.json and
    config.toml.  Needs dither, deflection and z_piezo.
    """
    run_streaming_command("kalman-bank", capture, source.args(source.calibration(flags["free_air"])), output, flags)


def register(app: typer.Typer) -> None:
    app.command("kalman-bank")(kalman_bank)
