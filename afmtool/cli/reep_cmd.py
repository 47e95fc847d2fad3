"""``afmtool reep`` and ``afmtool identify freeair``."""

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
from afmtool.cli.common import finish_command, open_input, run_capture_analysis
from afmtool.cli.options import (
    CaptureArg,
    ChannelOpt,
    ConfigOpt,
    DriveHoldOpt,
    F0Opt,
    JsonOpt,
    OutOpt,
    QOpt,
    QuietOpt,
    SampleRateOpt,
    SegmentOpt,
    StreamFormatOpt,
    StreamOpt,
    StreamOutOpt,
    TopicOpt,
)
from afmtool.cli.progress import progress_bar

__all__ = ["register"]


def reep(
    capture: CaptureArg,
    out: StreamOutOpt = None,
    stream: StreamOpt = False,
    stream_format: StreamFormatOpt = "csv",
    free_air: Annotated[
        Optional[str], typer.Option("--free-air", help="Off-sample segment START:END (s) for the free-air model.")
    ] = None,
    model: Annotated[
        Optional[Path], typer.Option("--model", help="free_air.json from 'afmtool identify freeair' (or its folder).")
    ] = None,
    f0: F0Opt = None,
    q: QOpt = None,
    drive_hold: DriveHoldOpt = None,
    lam: Annotated[Optional[float], typer.Option("--lambda", help="Forgetting factor λ (dimensionless, default 0.995).")] = None,
    no_bias_compensation: Annotated[
        bool, typer.Option("--no-bias-compensation", help="Plain EWRLS, for comparison.")
    ] = False,
    no_input: Annotated[
        bool, typer.Option("--no-input", help="Output-only AR(2) tracking (self-excited, drive not recorded).")
    ] = False,
    no_static_offset: Annotated[
        bool,
        typer.Option("--no-static-offset", help="No constant regressor: eq. 3.40 as the thesis has it, for comparison."),
    ] = False,
    decimate: Annotated[
        Optional[int], typer.Option("--decimate", help="Keep one sample in N (default: one per drive period).", min=1)
    ] = None,
    vs: Annotated[Optional[str], typer.Option("--vs", help="Force curves: 'z' bins against z_piezo, 'time' never.")] = None,
    z_bin: Annotated[Optional[float], typer.Option("--z-bin", help="Force-curve bin width (z_piezo units).")] = None,
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
    """Real-time equivalent f0' and Q' by bias-compensated EW-RLS (thesis ch. 3).

    Writes reep.h5 (t, f0_hz, q, b1, b0, sigma2, amplitude, phase_deg, offset,
    flag; decimated), report.json, config.toml, and with z_piezo force-curve tables and plots,
    with scan metadata per-pixel images (PNG and Gwyddion .gsf).  With --stream
    the decimated rows go to stdout as they are computed, e.g.
    afmtool simulate ltv -o - --format csv | afmtool reep - --stream --free-air 0:0.01 | head

    Samples whose fit cannot be trusted (not under-damped, amplitude below 1 %
    of the free amplitude, sigma^2 above 4x its free-air level, a static offset
    drifting within the window) are flagged: NaN in the summary, force curves
    and images, counted in the report (reep.h5 keeps them with 'flag').
    """
    from afmtool.report.json_report import PendingInputRecord

    # started before the imports below, so that hashing a large capture overlaps them
    capture_record = None if stream or out is None else PendingInputRecord(capture)
    from afmtool.analyses.reep_outputs import run_reep_command, run_reep_stream

    flags = {
        "free_air": free_air,
        "model": str(model) if model else None,
        "f0_hz": f0,
        "q": q,
        "drive_hold": drive_hold,
        "lam": lam,
        "bias_compensation": False if no_bias_compensation else None,
        "use_input": False if no_input else None,
        "static_offset": False if no_static_offset else None,
        "decimate": decimate,
        "vs": vs,
        "z_bin": z_bin,
    }
    calibration = CaptureCalibration(units, invols, z_sensitivity, drive, free_air, accepts_drive=True)
    run_capture_analysis(
        "reep", capture, (channel, topic, sample_rate, calibration, segment), out, (stream, stream_format), json_output, quiet,
        to_rows=lambda reader: run_reep_stream(reader, config, flags, stream_format),
        to_folder=lambda reader, update: run_reep_command(reader, capture, out, config, flags, update, capture_record),
    )


def identify_freeair(
    capture: Annotated[
        Optional[str], typer.Argument(help="Capture with dither and deflection (segment or sweep route).")
    ] = None,
    out: OutOpt = Path("freeair"),
    free_air: Annotated[
        Optional[str], typer.Option("--free-air", help="Off-sample segment START:END (s); default: metadata.")
    ] = None,
    sweep: Annotated[bool, typer.Option("--sweep", help="The capture is a chirp or stepped-sine sweep.")] = False,
    stepped: Annotated[
        bool, typer.Option("--stepped", help="Sweep route: same as --sweep-method stepped (lock-in per step).")
    ] = False,
    sweep_method: Annotated[
        Optional[str],
        typer.Option(
            "--sweep-method",
            help="Sweep route: record (default; whole-record fit, exact at any sweep rate), "
            "h1 or stepped (spectral fits that need a steady state).",
        ),
    ] = None,
    drive_hold: Annotated[
        Optional[str],
        typer.Option("--drive-hold", help="Sweep route: zoh, continuous or auto (default; from the delay)."),
    ] = None,
    psd: Annotated[
        Optional[Path], typer.Option("--psd", help="Thermal route: CSV with frequency_hz, asd_m_per_sqrt_hz.")
    ] = None,
    temperature: Annotated[
        Optional[float], typer.Option("--temperature", help="Thermal route: temperature (K) for k.")
    ] = None,
    detection: Annotated[
        Optional[str],
        typer.Option("--detection", help="Thermal route: optical-lever (k factor 0.817, default) or displacement."),
    ] = None,
    length: Annotated[
        Optional[float], typer.Option("--length", help="Thermal route, Sader k: cantilever length L (um).", min=0.0)
    ] = None,
    width: Annotated[
        Optional[float], typer.Option("--width", help="Thermal route, Sader k: cantilever width b (um).", min=0.0)
    ] = None,
    fluid: Annotated[Optional[str], typer.Option("--fluid", help="Thermal route, Sader k: air (default) or water.")] = None,
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
) -> None:
    """Identify the free-air model: f0, Q, gain and their uncertainties.

    Three routes: an off-sample segment of a capture (ARX fit, bias compensated),
    a frequency sweep (--sweep: by default the second-order model with delay
    fitted to the whole record's spectra with a transient term, exact for fast
    or slow chirps and stepped sines), or a thermal-noise spectrum
    (--psd FILE.csv).  Writes free_air.json for --model; the sweep route also
    writes sweep_frf.csv and sweep_bode.png (the data with the fitted transient
    removed, beside the model); the thermal route also
    reports the spring constant by equipartition with the Butt-Jaschke
    optical-lever factor, and with --length/--width by the Sader method, and
    plots the spectrum and its fit (thermal_fit.png).
    """
    from afmtool.analyses.freeair_outputs import run_freeair_command
    from afmtool.errors import ConfigError

    route = "thermal" if psd else ("sweep" if sweep else "segment")
    if route != "thermal" and capture is None:
        raise ConfigError("give a CAPTURE (segment or --sweep route) or --psd FILE.csv (thermal route)")
    if stepped and sweep_method not in (None, "stepped"):
        raise ConfigError(f"--stepped contradicts --sweep-method {sweep_method}")
    flags = {
        "free_air": free_air,
        "route": route,
        "sweep_method": "stepped" if stepped else sweep_method,
        "drive_hold": drive_hold,
        "temperature_k": temperature,
        "spring": {"detection": detection, "length_um": length, "width_um": width, "fluid": fluid},
    }
    if route == "thermal":
        report = run_freeair_command(None, psd, out, config, flags, lambda done: None)
    else:
        calibration = CaptureCalibration(units, invols, z_sensitivity, drive, free_air, accepts_drive=True)
        with open_input(capture, channel, topic, sample_rate, calibration) as reader:
            with progress_bar("identify", reader.info.n_samples, quiet) as update:
                report = run_freeair_command(reader, capture, out, config, flags, update)
    finish_command(report, out, json_output, quiet)


def register(app: typer.Typer, identify: typer.Typer) -> None:
    app.command()(reep)
    identify.command("freeair")(identify_freeair)
