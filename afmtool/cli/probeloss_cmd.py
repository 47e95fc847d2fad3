"""``afmtool probeloss``: reliability index, switching signal and probe-loss maps (thesis ch. 2)."""

from __future__ import annotations

from typing import Annotated

import typer

from afmtool.cli.common import run_streaming_command
from afmtool.cli.groups import CaptureSource, CommandOutput, capture_options, output_options, with_options
from afmtool.cli.options import CaptureArg
from afmtool.cli.param_flags import param_flags
from afmtool.config.params import ProbeLossParams

__all__ = ["register"]


@with_options(param_flags(ProbeLossParams), output_options(stream=True, capture_run=True), capture_options())
def probeloss(
    capture: CaptureArg,
    kalman: Annotated[
        bool, typer.Option("--kalman", help="Steady-state Kalman gain (DARE) instead of --decay-cycles.")
    ] = False,
    *, flags: dict, output: CommandOutput, source: CaptureSource
) -> None:
    """Probe loss from the reliability index (thesis ch. 2), beside the amplitude threshold.

    An observer on the free-air model runs beside the deflection; its innovation
    RMS over one drive period, divided by its free-air level, is the reliability
    index: low when the free-air model fits, i.e. when the tip is off the sample.
    Writes probeloss.h5 (t, index, switch, amplitude, amplitude_switch; decimated),
    report.json (loss fraction, events, index lead over the amplitude baseline, and
    with /truth/contact precision, recall and latency of both) and config.toml;
    with scan metadata, probe-loss mask and index images (PNG and .gsf).
    """
    from afmtool.errors import ConfigError

    if kalman and flags["decay_cycles"] is not None:
        raise ConfigError("--kalman and --decay-cycles choose the gain two ways; give one")
    flags = {**flags, "gain": "kalman" if kalman else None}
    from afmtool.analyses.capture_check import needs_from_flags

    calibration = source.calibration(flags["free_air"], accepts_drive=True, needs=needs_from_flags("probeloss", flags))
    run_streaming_command("probeloss", capture, source.args(calibration), output, flags)


def register(app: typer.Typer) -> None:
    app.command()(probeloss)
