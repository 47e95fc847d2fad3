"""``afmtool theory averaging``, ``theory compare``, ``theory observer`` and ``theory controllers``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from afmtool.cli.common import finish_command
from afmtool.cli.groups import CommandOutput, output_options, with_options
from afmtool.cli.param_flags import param_flags
from afmtool.config.params import (
    AveragingParams,
    ObserverTheoryParams,
    TheoryCompareParams,
    TheoryControllersParams,
    TheoryFitParams,
)

__all__ = ["app"]

app = typer.Typer(
    help="Averaging theory (ch. 4), its check against REEP, observer design (ch. 5), z-controller gains (ch. 2).",
    no_args_is_help=True,
)


def _q_flags(text: Optional[str]) -> tuple[Optional[float], Optional[str]]:
    """``--q 200`` -> (200, None); ``--q 50,100`` -> (50, "50,100"): the first Q is the main run's."""
    if text is None:
        return None, None
    from afmtool.analyses.theory_q_overlay import parse_q_values

    values = parse_q_values(text)
    if not values:
        raise typer.BadParameter(f"--q {text!r}: give one or more numbers")
    return values[0], (text if len(values) > 1 else None)


@app.command("averaging")
@with_options(param_flags(AveragingParams), output_options(Path("theory")))
def averaging(
    q: Annotated[
        Optional[str], typer.Option("--q", help="Free-air Q (dimensionless); several (50,100,200,400) add an overlay figure.")
    ] = None,
    *, flags: dict, output: CommandOutput
) -> None:
    """Equivalent f0e, Qe and the averaged steady state along a force curve (eqs. 4.6-4.8).

    Approach and retract are followed separately, so bistable jumps show as
    hysteresis; theory.h5 also holds the topography sensitivities of §4.4-4.6.
    """
    from afmtool.api.run import run_folder_command

    q_first, q_values = _q_flags(q)
    flags = {**flags, "q": q_first, "q_values": q_values}
    report = run_folder_command("theory averaging", None, output.out, flags, output.settings())
    finish_command(report, output.out, output.json_output, output.quiet)


@app.command("compare")
@with_options(param_flags(TheoryCompareParams), output_options(Path("theory_compare")))
def compare(
    reep_dir: Annotated[Path, typer.Argument(help="Output folder of 'afmtool reep' on a force curve.")],
    *, flags: dict, output: CommandOutput
) -> None:
    """Put REEP's f0' and Q' beside averaging theory along a force curve (§3.4.3), with a verdict.

    The force comes from --fit FIT_DIR (the output of 'afmtool theory fit' on
    this REEP run: a real capture has no force metadata), --force, --force-set
    or a simulation's metadata; the separation from /truth (a simulation), the
    fitted contact point (--fit), or z_piezo with the contact point aligned on
    the approach's amplitude (or --contact-z).  The theory is windowed as REEP
    is, and the shifts from free air are compared as medians in separation
    bins (--bin nm), with REEP's per-row uncertainty, the theory's sensitivity
    to the amplitude's beat and the separation, and a model floor (--tolerance
    of the theory's shift).  Bins where the tip reaches the repulsive wall, or
    the theory changes more than REEP resolves (attraction onset, low Q), are
    marked ill-conditioned and left out of the verdict, and the report says so.
    Writes compare.png, compare_bins.csv and report.json.

    Examples: afmtool theory fit reep_out --out fit; afmtool theory compare
    reep_out --fit fit --out cmp; afmtool theory compare sim_reep --force-set
    attractive --out cmp
    """
    from afmtool.api.run import run_folder_command

    report = run_folder_command("theory compare", reep_dir, output.out, flags, output.settings())
    finish_command(report, output.out, output.json_output, output.quiet)


@app.command("fit")
@with_options(param_flags(TheoryFitParams), output_options(Path("theory_fit")))
def fit(
    reep_dir: Annotated[Path, typer.Argument(help="Output folder of 'afmtool reep' on a force curve (needs z).")],
    *, flags: dict, output: CommandOutput
) -> None:
    """Fit d, ωa², ωb², ca, cb and the contact point so averaging theory reproduces the approach.

    scipy.optimize.least_squares on REEP's f0', Q' and amplitude; fit.json holds
    values, uncertainties and which parameters this curve determines (an SVD of
    the Jacobian, as in 'identify electrostatic'); fit.png the curves with the
    fitted theory over them.
    """
    from afmtool.api.run import run_folder_command

    report = run_folder_command("theory fit", reep_dir, output.out, flags, output.settings())
    finish_command(report, output.out, output.json_output, output.quiet)


@app.command("observer")
@with_options(param_flags(ObserverTheoryParams), output_options(Path("theory_observer")))
def observer(
    *, flags: dict, output: CommandOutput
) -> None:
    """Observer-design trade-offs (ch. 5): A_e², its sensitivities, SNR and transients.

    Maps over observer models (f_k, Q_k) at the free-air plant, one per gain, and
    lines as the plant moves along the force-curve direction (eqs. 5.16-5.22).
    With --recommend, the model and gain that maximise |dA_e²| along the force
    curve while the error settles within --max-cycles drive periods.
    """
    from afmtool.config.commands import spec

    run_observer_theory_command = spec("theory observer").runner.load()
    with output.settings().writing():
        report = run_observer_theory_command(output.out, output.config, flags)
    finish_command(report, output.out, output.json_output, output.quiet)


@app.command("controllers")
@with_options(param_flags(TheoryControllersParams), output_options(Path("theory_controllers")))
def controllers(*, flags: dict, output: CommandOutput) -> None:
    """Low, high and switching z-controller gains on the calibration grating (thesis ch. 2, §2.5).

    Simulates the closed-loop raster scan once per controller and line rate
    (same surface, noise and seed) and tabulates the probe-loss area (loss of
    contact where the surface falls away, §2.2), the lift-off area (loss the
    controller caused on a level surface) and the peak on-sample force;
    report.json says at each rate whether the high gain loses less than the
    low and least of all, the switching gain's loss is within 1.2x the high
    gain's and its peak force within 1.2x the low gain's.  Writes report.json,
    ch2_table.json, ch2_controllers.png (height images side by side) and
    ch2_loss_force.png.  docs/ch2_table.json and docs/ch2_controllers.png are
    this command with --lines 4 --figure-lines 48.
    """
    from afmtool.cli.progress import progress_steps
    from afmtool.config.commands import spec

    run_controllers_command = spec("theory controllers").runner.load()
    with output.settings().writing(), progress_steps("simulating the three controllers", output.quiet) as progress:
        report = run_controllers_command(output.out, output.config, flags, progress)
    finish_command(report, output.out, output.json_output, output.quiet)
