"""``afmtool decode``: EKF bit decoder for electrostatically actuated probes (ch. 7)."""

from __future__ import annotations

import typer

from afmtool.cli.common import run_streaming_command
from afmtool.cli.groups import CaptureSource, CommandOutput, capture_options, output_options, with_options
from afmtool.cli.options import CaptureArg
from afmtool.cli.param_flags import param_flags
from afmtool.config.params import DecodeParams

__all__ = ["register"]


@with_options(param_flags(DecodeParams), output_options(stream=True, capture_run=True), capture_options(drive=False))
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
    from afmtool.analyses.capture_check import needs_from_flags

    calibration = source.calibration(needs=needs_from_flags("decode", flags, ("deflection",)))
    run_streaming_command("decode", capture, source.args(calibration), output, flags)


def register(app: typer.Typer) -> None:
    app.command()(decode)
