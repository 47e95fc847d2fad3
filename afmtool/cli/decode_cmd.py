"""``afmtool decode``: EKF bit decoder for electrostatically actuated probes (ch. 7)."""

from __future__ import annotations

from typing import Annotated, Optional

import typer

from afmtool.cli.calibration_options import CaptureCalibration, InvolsOpt, UnitsOpt, ZSensitivityOpt
from afmtool.cli.common import run_capture_analysis
from afmtool.cli.options import (
    CaptureArg,
    ChannelOpt,
    ConfigOpt,
    JsonOpt,
    QuietOpt,
    SampleRateOpt,
    SegmentOpt,
    StreamFormatOpt,
    StreamOpt,
    StreamOutOpt,
    TopicOpt,
)

__all__ = ["register"]

# Help texts are literal (not read from DecodeParams) so that `afmtool --help` does not import
# the parameter models; `afmtool config init` shows the full help of every [decode] parameter.
_HELP = {
    "bit_rate_hz": "Bit rate (Hz); default: recover the clock from the transitions.",
    "nominal": "Bit-free nominal segment START:END (s) for l0 and the noise levels; default: metadata nominal.",
    "l0_nm": "Lever-sample separation l0 (nm); default: estimated on the nominal segment (thesis 7.4).",
    "voltage_channel": "Channel holding the lever-sample voltage V (V); default: V = alpha_R*v_r - v_sub.",
    "process_noise": "EKF force-noise ASD (N/sqrt(Hz)); default: estimated (mean NIS = 1 on the nominal segment).",
    "measurement_noise": "EKF measurement noise (nm rms); default: the PSD floor of the nominal segment.",
    "actuation_hz": "Actuation frequency (Hz); default: metadata drive, else the strongest line of V^2.",
    "bits_from": "Start of the bit stream (s); default: the end of the nominal segment.",
    "clock_window": "Clock acquisition window at the start of the bit stream (s) (default 0.005).",
    "polarity": "Innovation sign of a 1 bit: negative (default: a raised sample attracts more) or positive.",
}


def decode(
    capture: CaptureArg,
    out: StreamOutOpt = None,
    stream: StreamOpt = False,
    stream_format: StreamFormatOpt = "csv",
    bit_rate: Annotated[Optional[float], typer.Option("--bit-rate", help=_HELP["bit_rate_hz"], min=0.0)] = None,
    nominal: Annotated[Optional[str], typer.Option("--nominal", help=_HELP["nominal"])] = None,
    l0: Annotated[Optional[float], typer.Option("--l0", help=_HELP["l0_nm"], min=0.0)] = None,
    voltage_channel: Annotated[Optional[str], typer.Option("--voltage-channel", help=_HELP["voltage_channel"])] = None,
    process_noise: Annotated[
        Optional[float], typer.Option("--process-noise", help=_HELP["process_noise"], min=0.0)
    ] = None,
    measurement_noise: Annotated[
        Optional[float], typer.Option("--measurement-noise", help=_HELP["measurement_noise"], min=0.0)
    ] = None,
    actuation_hz: Annotated[Optional[float], typer.Option("--actuation-hz", help=_HELP["actuation_hz"], min=0.0)] = None,
    bits_from: Annotated[Optional[float], typer.Option("--bits-from", help=_HELP["bits_from"])] = None,
    clock_window: Annotated[Optional[float], typer.Option("--clock-window", help=_HELP["clock_window"])] = None,
    polarity: Annotated[Optional[str], typer.Option("--polarity", help=_HELP["polarity"])] = None,
    json_output: JsonOpt = False,
    config: ConfigOpt = None,
    quiet: QuietOpt = False,
    channel: ChannelOpt = None,
    topic: TopicOpt = None,
    sample_rate: SampleRateOpt = None,
    units: UnitsOpt = None,
    invols: InvolsOpt = None,
    z_sensitivity: ZSensitivityOpt = None,
    segment: SegmentOpt = None,
) -> None:
    """Decode bits read by an electrostatically actuated probe with an EKF (thesis ch. 7).

    Needs deflection (nm) and v_sub, v_r (V) channels, or --voltage-channel.  l0 and
    the noise levels come from a bit-free nominal segment (--nominal or metadata).
    Writes decode.h5 (t, innovation, innovation_mean, bit_times_s, bits, soft, baseline),
    report.json (l0, noise, clock, bits; BER and confusion counts when /truth has bits,
    also for the lock-in amplitude baseline), config.toml, eye.png, psd.png, l0_search.png.
    With --stream the EKF innovation's running mean over each actuation period
    (t_mean, innovation_mean in nm: the signal the bits are sliced from) goes to
    stdout as it is computed; the bits themselves need the whole record's
    two-class threshold and are written only to decode.h5.
    """
    from afmtool.report.json_report import PendingInputRecord

    # started before the imports below, so that hashing a large capture overlaps them
    capture_record = None if stream or out is None else PendingInputRecord(capture)
    from afmtool.analyses.decode_outputs import run_decode_command, run_decode_stream

    flags = {
        "bit_rate_hz": bit_rate,
        "nominal": nominal,
        "l0_nm": l0,
        "voltage_channel": voltage_channel,
        "process_noise_n_per_rthz": process_noise,
        "measurement_noise_nm": measurement_noise,
        "actuation_hz": actuation_hz,
        "bits_from_s": bits_from,
        "clock_window_s": clock_window,
        "polarity": polarity,
    }
    calibration = CaptureCalibration(units, invols, z_sensitivity)
    run_capture_analysis(
        "decode", capture, (channel, topic, sample_rate, calibration, segment), out, (stream, stream_format), json_output, quiet,
        to_rows=lambda reader: run_decode_stream(reader, config, flags, stream_format),
        to_folder=lambda reader, update: run_decode_command(reader, capture, out, config, flags, update, capture_record),
    )


def register(app: typer.Typer) -> None:
    app.command()(decode)
