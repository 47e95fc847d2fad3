"""``afmtool reep`` and ``afmtool identify freeair``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from afmtool.cli.common import finish_command, open_input, run_capture_analysis
from afmtool.cli.options import (
    CaptureArg,
    ChannelOpt,
    ConfigOpt,
    JsonOpt,
    OutOpt,
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
    lam: Annotated[Optional[float], typer.Option("--lambda", help="Forgetting factor λ (default 0.995).")] = None,
    no_bias_compensation: Annotated[
        bool, typer.Option("--no-bias-compensation", help="Plain EWRLS, for comparison.")
    ] = False,
    no_input: Annotated[
        bool, typer.Option("--no-input", help="Output-only AR(2) tracking (self-excited, drive not recorded).")
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
    segment: SegmentOpt = None,
) -> None:
    """Real-time equivalent f0' and Q' by bias-compensated EW-RLS (thesis ch. 3).

    Writes reep.h5 (t, f0_hz, q, b1, b0, sigma2, amplitude, phase_deg; decimated),
    report.json, config.toml, and with z_piezo force-curve tables and plots,
    with scan metadata per-pixel images (PNG and Gwyddion .gsf).  With --stream
    the decimated rows go to stdout as they are computed, e.g.
    afmtool simulate ltv -o - --format csv | afmtool reep - --stream --free-air 0:0.01 | head
    """
    from afmtool.report.json_report import PendingInputRecord

    # started before the imports below, so that hashing a large capture overlaps them
    capture_record = None if stream or out is None else PendingInputRecord(capture)
    from afmtool.analyses.reep_outputs import run_reep_command, run_reep_stream

    flags = {
        "free_air": free_air,
        "model": str(model) if model else None,
        "lam": lam,
        "bias_compensation": False if no_bias_compensation else None,
        "use_input": False if no_input else None,
        "decimate": decimate,
        "vs": vs,
        "z_bin": z_bin,
    }
    run_capture_analysis(
        "reep", capture, (channel, topic, sample_rate, segment), out, (stream, stream_format), json_output, quiet,
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
    stepped: Annotated[bool, typer.Option("--stepped", help="Sweep route: stepped sines (default H1).")] = False,
    psd: Annotated[
        Optional[Path], typer.Option("--psd", help="Thermal route: CSV with frequency_hz, asd_m_per_sqrt_hz.")
    ] = None,
    temperature: Annotated[
        Optional[float], typer.Option("--temperature", help="Thermal route: temperature (K) for k.")
    ] = None,
    json_output: JsonOpt = False,
    config: ConfigOpt = None,
    quiet: QuietOpt = False,
    channel: ChannelOpt = None,
    topic: TopicOpt = None,
    sample_rate: SampleRateOpt = None,
) -> None:
    """Identify the free-air model: f0, Q, gain and their uncertainties.

    Three routes: an off-sample segment of a capture (ARX fit, bias compensated),
    a frequency sweep (--sweep: H1, then a second-order fit with delay), or a
    thermal-noise spectrum (--psd FILE.csv).  Writes free_air.json for --model.
    """
    from afmtool.analyses.freeair_outputs import run_freeair_command
    from afmtool.errors import ConfigError

    route = "thermal" if psd else ("sweep" if sweep else "segment")
    if route != "thermal" and capture is None:
        raise ConfigError("give a CAPTURE (segment or --sweep route) or --psd FILE.csv (thermal route)")
    flags = {
        "free_air": free_air,
        "route": route,
        "sweep_method": "stepped" if stepped else None,
        "temperature_k": temperature,
    }
    if route == "thermal":
        report = run_freeair_command(None, psd, out, config, flags, lambda done: None)
    else:
        with open_input(capture, channel, topic, sample_rate) as reader:
            with progress_bar("identify", reader.info.n_samples, quiet) as update:
                report = run_freeair_command(reader, capture, out, config, flags, update)
    finish_command(report, out, json_output, quiet)


def register(app: typer.Typer, identify: typer.Typer) -> None:
    app.command()(reep)
    identify.command("freeair")(identify_freeair)
