"""``afmtool reep`` and ``afmtool identify freeair``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from afmtool.cli.common import finish_command, run_streaming_command
from afmtool.cli.groups import CaptureSource, CommandOutput, capture_options, output_options, with_options
from afmtool.cli.options import CaptureArg
from afmtool.cli.param_flags import param_flags
from afmtool.config.params import FreeAirParams, ReepParams, SpringConstantParams

__all__ = ["register"]


@with_options(param_flags(ReepParams), output_options(stream=True, capture_run=True), capture_options())
def reep(capture: CaptureArg, *, flags: dict, output: CommandOutput, source: CaptureSource) -> None:
    """Real-time equivalent f0' and Q' by bias-compensated EW-RLS (thesis ch. 3).

    Writes reep.h5 (t, f0_hz, q, their standard deviations f0_std_hz and q_std,
    b1, b0, sigma2, amplitude, phase_deg, offset, flag; decimated), report.json, config.toml, and with z_piezo force-curve tables and plots,
    with scan metadata per-pixel images (PNG and Gwyddion .gsf).  With --stream
    the decimated rows go to stdout as they are computed, e.g.
    afmtool simulate ltv -o - --format csv | afmtool reep - --stream --free-air 0:0.01 | head

    Samples whose fit cannot be trusted (not under-damped, amplitude below 1 %
    of the free amplitude, sigma^2 above 4x its free-air level, a static offset
    drifting within the window) are flagged: NaN in the summary, force curves
    and images, counted in the report (reep.h5 keeps them with 'flag').
    """
    from afmtool.analyses.capture_check import needs_from_flags

    channels = ("deflection", "dither") if flags.get("use_input") is not False else ("deflection",)
    calibration = source.calibration(flags["free_air"], accepts_drive=True,
                                     needs=needs_from_flags("reep", flags, channels))
    run_streaming_command("reep", capture, source.args(calibration), output, flags)


@with_options(
    param_flags(FreeAirParams), param_flags(SpringConstantParams, "spring"), output_options(Path("freeair")),
    capture_options(segment=False),
)
def identify_freeair(
    capture: Annotated[
        Optional[str], typer.Argument(help="Capture with dither and deflection (segment or sweep route).")
    ] = None,
    sweep: Annotated[bool, typer.Option("--sweep", help="The capture is a chirp or stepped-sine sweep.")] = False,
    stepped: Annotated[
        bool, typer.Option("--stepped", help="Sweep route: same as --sweep-method stepped (lock-in per step).")
    ] = False,
    psd: Annotated[
        Optional[Path],
        typer.Option("--psd", help="Thermal route: a spectrum table (CSV): ASD or PSD, in m, nm or V (with --invols), "
                     "per sqrt(Hz) or per Hz; columns found by name and units."),
    ] = None,
    thermal: Annotated[
        Optional[str],
        typer.Option("--thermal", help="Thermal route: a thermal-noise time record (deflection, no drive); its "
                     "Welch spectrum is fitted."),
    ] = None,
    *, flags: dict, spring: dict, output: CommandOutput, source: CaptureSource
) -> None:
    """Identify the free-air model: f0, Q, gain, the spring constant, and their uncertainties.

    Three routes: an off-sample segment of a capture (ARX fit, bias compensated),
    a frequency sweep (--sweep: by default the second-order model with delay
    fitted to the whole record's spectra with a transient term, exact for fast
    or slow chirps and stepped sines), or thermal noise: a spectrum table
    (--psd FILE.csv) or a time record (--thermal CAPTURE, Welch spectrum).
    Writes free_air.json for --model; the sweep route also writes
    sweep_frf.csv and sweep_bode.png (the data with the fitted transient
    removed, beside the model).  The thermal route fits the spectrum by
    maximum likelihood (each bin of an averaged periodogram is Gamma
    distributed), gives its goodness of fit, refits in half and double the
    band (--band LOW:HIGH sets it) and with linear weighting and reports
    their spread as a systematic uncertainty where it exceeds the noise;
    k by equipartition with the Butt-Jaschke optical-lever factor, and with
    --length/--width by the Sader method (warned when the two disagree); k
    goes into free_air.json, where 'reep --model' finds it.

    Examples: afmtool identify freeair --psd tune.csv --band 170e3:190e3 --out fa;
    afmtool identify freeair --psd tune_volts.csv --invols 52.3 --out fa;
    afmtool identify freeair --thermal record.h5 --temperature 298 --out fa
    """
    from afmtool.api.capture import Capture
    from afmtool.api.run import run_identify_freeair
    from afmtool.cli.calibration_options import capture_options
    from afmtool.errors import ConfigError

    if stepped and flags["sweep_method"] not in (None, "stepped"):
        raise ConfigError(f"--stepped contradicts --sweep-method {flags['sweep_method']}")
    flags = {**flags, "route": "thermal" if (psd or thermal) else ("sweep" if sweep else "segment"), "spring": spring}
    if stepped:
        flags["sweep_method"] = "stepped"
    options = capture_options(source.channel, source.topic, source.sample_rate, source.calibration())

    def opened(path):
        return None if path is None else Capture(path, options)

    report = run_identify_freeair(opened(capture), output.out, flags, output.settings(), psd=psd,
                                  thermal=opened(thermal), invols=source.invols)
    finish_command(report, output.out, output.json_output, output.quiet)


def register(app: typer.Typer, identify: typer.Typer) -> None:
    app.command()(reep)
    identify.command("freeair")(identify_freeair)
