"""``afmtool probeloss``: reliability index, switching signal and probe-loss maps (thesis ch. 2)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from afmtool.cli.calibration_options import (
    CaptureCalibration,
    DriveOpt,
    InvolsOpt,
    UnitsOpt,
    ZSensitivityOpt,
)
from afmtool.cli.common import run_capture_analysis
from afmtool.cli.options import (
    CaptureArg,
    ChannelOpt,
    ConfigOpt,
    DriveHoldOpt,
    F0Opt,
    JsonOpt,
    QOpt,
    QuietOpt,
    SampleRateOpt,
    SegmentOpt,
    StreamFormatOpt,
    StreamOpt,
    StreamOutOpt,
    TopicOpt,
)

__all__ = ["register"]


def probeloss(
    capture: CaptureArg,
    out: StreamOutOpt = None,
    stream: StreamOpt = False,
    stream_format: StreamFormatOpt = "csv",
    free_air: Annotated[
        Optional[str],
        typer.Option("--free-air", help="Off-sample segment START:END (s): model, index level, thresholds, A0."),
    ] = None,
    model: Annotated[
        Optional[Path], typer.Option("--model", help="free_air.json from 'afmtool identify freeair' (or its folder).")
    ] = None,
    f0: F0Opt = None,
    q: QOpt = None,
    drive_hold: DriveHoldOpt = None,
    decay_cycles: Annotated[
        Optional[float], typer.Option("--decay-cycles", help="Observer error decays (1/e) within N drive periods.")
    ] = None,
    kalman: Annotated[
        bool, typer.Option("--kalman", help="Steady-state Kalman gain (DARE) instead of --decay-cycles.")
    ] = False,
    process_noise: Annotated[
        Optional[float], typer.Option("--process-noise", help="Kalman: force noise as static deflection, rms (deflection units).")
    ] = None,
    measurement_noise: Annotated[
        Optional[float], typer.Option("--measurement-noise", help="Kalman: measurement noise rms (deflection units).")
    ] = None,
    window_periods: Annotated[
        Optional[float], typer.Option("--window-periods", help="Index window in drive periods (default 1).")
    ] = None,
    on: Annotated[
        Optional[float], typer.Option("--on", help="Loss when the index (dimensionless) falls below this (default: automatic).")
    ] = None,
    off: Annotated[
        Optional[float], typer.Option("--off", help="Loss ends when the index (dimensionless) rises above this (default: automatic).")
    ] = None,
    index_level: Annotated[
        Optional[float], typer.Option("--index-level", help="Free-air innovation RMS (deflection units); default from the segment.")
    ] = None,
    amplitude_upper: Annotated[
        Optional[float], typer.Option("--amplitude-upper", help="Baseline: loss while the amplitude exceeds this (deflection units).")
    ] = None,
    setpoint: Annotated[
        Optional[float], typer.Option("--setpoint", help="Amplitude set point (deflection units) for the automatic --amplitude-upper.")
    ] = None,
    decimate: Annotated[
        Optional[int], typer.Option("--decimate", help="Keep one sample in N (default: one per drive period).", min=1)
    ] = None,
    json_output: JsonOpt = False,
    config: ConfigOpt = None,
    quiet: QuietOpt = False,
    channel: ChannelOpt = None,
    topic: TopicOpt = None,
    sample_rate: SampleRateOpt = None,
    units: UnitsOpt = None,
    invols: InvolsOpt = None,
    z_sensitivity: ZSensitivityOpt = None,
    drive: DriveOpt = None,
    segment: SegmentOpt = None,
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
    from afmtool.report.json_report import PendingInputRecord

    # started before the imports below, so that hashing a large capture overlaps them
    capture_record = None if stream or out is None else PendingInputRecord(capture)
    from afmtool.analyses.probeloss_outputs import run_probeloss_command, run_probeloss_stream
    from afmtool.errors import ConfigError

    flags = {
        "free_air": free_air,
        "model": str(model) if model else None,
        "f0_hz": f0,
        "q": q,
        "drive_hold": drive_hold,
        "gain": "kalman" if kalman else None,
        "decay_cycles": decay_cycles,
        "process_noise": process_noise,
        "measurement_noise": measurement_noise,
        "window_periods": window_periods,
        "on": on,
        "off": off,
        "index_level": index_level,
        "amplitude_upper": amplitude_upper,
        "setpoint": setpoint,
        "decimate": decimate,
    }
    if kalman and decay_cycles is not None:
        raise ConfigError("--kalman and --decay-cycles choose the gain two ways; give one")
    calibration = CaptureCalibration(units, invols, z_sensitivity, drive, free_air, accepts_drive=True)
    run_capture_analysis(
        "probeloss", capture, (channel, topic, sample_rate, calibration, segment), out, (stream, stream_format), json_output, quiet,
        to_rows=lambda reader: run_probeloss_stream(reader, config, flags, stream_format),
        to_folder=lambda reader, update: run_probeloss_command(reader, capture, out, config, flags, update, capture_record),
    )


def register(app: typer.Typer) -> None:
    app.command()(probeloss)
