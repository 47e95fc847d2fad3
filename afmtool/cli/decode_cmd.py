"""``afmtool decode``: EKF bit decoder for electrostatically actuated probes (ch. 7)."""

from __future__ import annotations

import typer

from afmtool.cli.common import run_capture_analysis
from afmtool.cli.groups import CaptureSource, CommandOutput, capture_options, output_options, with_options
from afmtool.cli.options import CaptureArg
from afmtool.cli.param_flags import param_flags
from afmtool.config.params import DecodeParams

__all__ = ["register"]


@with_options(param_flags(DecodeParams), output_options(stream=True), capture_options(drive=False))
def decode(capture: CaptureArg, *, flags: dict, output: CommandOutput, source: CaptureSource) -> None:
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
    capture_record = None if output.stream or output.out is None else PendingInputRecord(capture)
    from afmtool.analyses.decode_outputs import run_decode_command, run_decode_stream

    out, config = output.out, output.config
    run_capture_analysis(
        "decode", capture, source.args(), out, output.stream_mode, output.json_output, output.quiet,
        to_rows=lambda reader: run_decode_stream(reader, config, flags, output.stream_format),
        to_folder=lambda reader, update: run_decode_command(reader, capture, out, config, flags, update, capture_record),
    )


def register(app: typer.Typer) -> None:
    app.command()(decode)
