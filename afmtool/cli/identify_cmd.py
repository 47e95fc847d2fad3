"""``afmtool identify gamma``, ``identify thermal`` and ``identify electrostatic`` (thesis ch. 6)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from afmtool.cli.common import finish_command
from afmtool.cli.groups import CaptureSource, CommandOutput, capture_options, output_options, with_options
from afmtool.cli.param_flags import param_flags
from afmtool.config.params import (
    ElectrostaticFitParams,
    GammaParams,
    InvolsParams,
    ThermalParams,
)

#: The capture options of the ch. 6 commands: no synthesised drive, no segment.
_CH6_CAPTURE = capture_options(drive=False, segment=False)

__all__ = ["register"]


def _capture(source: CaptureSource, path: str | None):
    """``path`` with the command line's capture options (:class:`afmtool.api.capture.Capture`); None for none."""
    from afmtool.api.capture import Capture
    from afmtool.cli.calibration_options import capture_options

    if path is None:
        return None
    return Capture(path, capture_options(source.channel, source.topic, source.sample_rate, source.calibration(),
                                         segment=source.selection))


@with_options(param_flags(GammaParams), output_options(Path("gamma")), _CH6_CAPTURE)
def identify_gamma(
    sweep: Annotated[
        str, typer.Argument(help="Sweep near the sample: v_sub, thermal_current and deflection (optical).")
    ],
    contact: Annotated[
        str, typer.Option("--contact", help="The same sweep with the tip in contact: v_sub and thermal_current.")
    ],
    stepped: Annotated[
        bool, typer.Option("--stepped", help="Stepped sines (lock-in per segment); default: auto from metadata.")
    ] = False,
    h1: Annotated[bool, typer.Option("--h1", help="Chirp or broadband drive (H1 estimate).")] = False,
    *, flags: dict, output: CommandOutput, source: CaptureSource
) -> None:
    """Sensing transfer function Gamma_IR,ts with the feed-through removed (thesis eq. 6.15).

    Estimates Gamma_IR,V and Gamma_ts,V from SWEEP, the feed-through Gamma_sp from
    the contact sweep, Gamma_IR,ts = (Gamma_IR,V - Gamma_sp)/Gamma_ts,V and the
    uncorrected ratio of eq. 6.16.  Writes gamma.h5 (/frf/...), FRF tables (CSV),
    Bode plots (PNG) and report.json with the DC sensitivity (uA/nm), the -3 dB
    bandwidth, the roll-off (dB/decade) and the usable band.
    """
    from afmtool.api.run import run_identify_gamma
    from afmtool.errors import ConfigError

    if stepped and h1:
        raise ConfigError("give at most one of --stepped and --h1")
    flags = {**flags, "method": "stepped" if stepped else ("h1" if h1 else None)}
    report = run_identify_gamma(_capture(source, sweep), _capture(source, contact), output.out, flags,
                                output.settings())
    finish_command(report, output.out, output.json_output, output.quiet)


#: The inputs of ``identify thermal``, each optional: what each file must hold.
_THERMAL_INPUTS = {
    "--iv": "I-V ramp capture: v_r and thermal_current (V_R past breakdown).",
    "--z-curve": "Thermal z force curve: z_piezo, v_r and thermal_current.",
    "--vr-sweep": "V_R perturbation sweep: v_r and thermal_current (+ deflection).",
    "--gamma": "gamma.h5 (or folder) from 'identify gamma', for H(jw).",
    "--model": "thermal_sensor.json (or folder) supplying g(T) without --iv.",
}


@with_options(param_flags(ThermalParams), output_options(Path("thermal")), _CH6_CAPTURE)
def identify_thermal(
    iv: Annotated[Optional[str], typer.Option("--iv", help=_THERMAL_INPUTS["--iv"])] = None,
    z_curve: Annotated[Optional[str], typer.Option("--z-curve", help=_THERMAL_INPUTS["--z-curve"])] = None,
    vr_sweep: Annotated[Optional[str], typer.Option("--vr-sweep", help=_THERMAL_INPUTS["--vr-sweep"])] = None,
    gamma: Annotated[Optional[Path], typer.Option("--gamma", help=_THERMAL_INPUTS["--gamma"])] = None,
    model: Annotated[Optional[Path], typer.Option("--model", help=_THERMAL_INPUTS["--model"])] = None,
    *, flags: dict, output: CommandOutput, source: CaptureSource
) -> None:
    """Thermal sensor from its current alone: g(T), K_TP, K_TP(t_s), C(jw), H(jw) (thesis 6.5.2, 6.6.2).

    --iv: R = V/I and P = V^2/R, the breakdown knee P_k, K_TP = (T_k - T_r)/P_k and
    g(T) as a table and a polynomial fit.  --z-curve: K_TP against t_s with the
    snap-in as t_s = 0.  --vr-sweep: C(jw) by eq. 6.11 and, with --gamma, H(jw)
    by eq. 6.12.  Writes thermal_sensor.json (for 'identify electrostatic'),
    tables (CSV, thermal.h5), plots and report.json.
    """
    from afmtool.api.run import run_identify_thermal

    inputs = {"iv": _capture(source, iv), "z": _capture(source, z_curve), "vr": _capture(source, vr_sweep),
              "gamma": gamma, "model": model}
    report = run_identify_thermal(inputs, output.out, flags, output.settings())
    finish_command(report, output.out, output.json_output, output.quiet)


@with_options(param_flags(ElectrostaticFitParams), output_options(Path("electrostatic")), _CH6_CAPTURE)
def identify_electrostatic(
    capture: Annotated[
        str, typer.Argument(help="Quasi-static V_sub ramp up and down: v_sub and deflection, or v_r and thermal_current.")
    ],
    thermal_model: Annotated[
        Optional[Path], typer.Option("--thermal-model", help="thermal_sensor.json (or folder) from 'identify thermal'.")
    ] = None,
    *, flags: dict, output: CommandOutput, source: CaptureSource
) -> None:
    """Electrostatic parameters from an approach curve before snap-in (thesis eqs. 6.6, 6.7).

    Selects the approach before snap-in, fits l0, K_esf/k, alpha_R (and t_h, thermal)
    by nonlinear least squares, and reports uncertainties and which parameter
    combinations the curve cannot identify (k and K_esf separately: only their
    ratio, unless --spring-constant is given).  Writes electrostatic.json, fit.csv,
    electrostatic_fit.png and report.json.
    """
    from afmtool.api.run import run_identify_electrostatic

    report = run_identify_electrostatic(_capture(source, capture), output.out, flags, output.settings(), thermal_model)
    finish_command(report, output.out, output.json_output, output.quiet)


@with_options(
    param_flags(InvolsParams), output_options(Path("invols")), capture_options(invols=False, drive=False)
)
def identify_invols(
    force_curve: Annotated[
        str, typer.Argument(metavar="CURVE", help="Force curve on a hard sample: deflection (V) and z_piezo.")
    ],
    *, flags: dict, output: CommandOutput, source: CaptureSource
) -> None:
    """InvOLS (nm/V) from the contact part of a force curve on a hard sample, with its uncertainty.

    Finds the contact point (a hinge fit), fits the contact part with a line and
    reports its slope, InvOLS = 1/|slope| with its standard deviation when the
    deflection is in V, and the capture's own InvOLS (metadata) beside it.  A
    deflection already in a length gives the slope (1 on a hard sample) and the
    InvOLS it implies.  Writes invols.png, report.json and config.toml.
    """
    from afmtool.api.run import run_identify_invols

    report = run_identify_invols(_capture(source, force_curve), output.out, flags, output.settings())
    finish_command(report, output.out, output.json_output, output.quiet)


def register(identify: typer.Typer) -> None:
    identify.command("gamma")(identify_gamma)
    identify.command("thermal")(identify_thermal)
    identify.command("electrostatic")(identify_electrostatic)
    identify.command("invols")(identify_invols)
