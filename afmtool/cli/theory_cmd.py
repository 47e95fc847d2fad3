"""``afmtool theory averaging``, ``theory compare``, ``theory observer`` and ``theory controllers``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from afmtool.cli.common import finish_command
from afmtool.cli.options import ConfigOpt, JsonOpt, OutOpt, QuietOpt

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
def averaging(
    out: OutOpt = Path("theory"),
    f0: Annotated[Optional[float], typer.Option("--f0", help="Free-air f0 (Hz).")] = None,
    q: Annotated[
        Optional[str], typer.Option("--q", help="Free-air Q (dimensionless); several (50,100,200,400) add an overlay figure.")
    ] = None,
    force_set: Annotated[Optional[str], typer.Option("--force-set", help="Thesis force parameter set.")] = None,
    force: Annotated[
        Optional[str], typer.Option("--force", help="Custom force d=NM,wa2=1/S2,wb2=1/S2,ca=1/S,cb=1/S.")
    ] = None,
    free_amplitude: Annotated[Optional[float], typer.Option("--free-amplitude", help="Free amplitude (nm).")] = None,
    json_output: JsonOpt = False,
    config: ConfigOpt = None,
    quiet: QuietOpt = False,
) -> None:
    """Equivalent f0e, Qe and the averaged steady state along a force curve (eqs. 4.6-4.8).

    Approach and retract are followed separately, so bistable jumps show as
    hysteresis; theory.h5 also holds the topography sensitivities of §4.4-4.6.
    """
    from afmtool.analyses.theory_outputs import run_averaging_command

    q_first, q_values = _q_flags(q)
    flags = {"f0_hz": f0, "q": q_first, "q_values": q_values, "force_set": force_set, "force": force,
             "free_amplitude_nm": free_amplitude}
    finish_command(run_averaging_command(out, config, flags), out, json_output, quiet)


@app.command("compare")
def compare(
    reep_dir: Annotated[Path, typer.Argument(help="Output folder of 'afmtool reep' on a force curve.")],
    out: OutOpt = Path("theory_compare"),
    force_set: Annotated[
        Optional[str], typer.Option("--force-set", help="Force parameters (default: the capture's metadata).")
    ] = None,
    force: Annotated[
        Optional[str], typer.Option("--force", help="Custom force d=NM,wa2=1/S2,wb2=1/S2,ca=1/S,cb=1/S.")
    ] = None,
    separation: Annotated[
        Optional[str], typer.Option("--separation", help="auto (/truth when present), truth or z-piezo.")
    ] = None,
    z_sensitivity: Annotated[
        Optional[float], typer.Option("--z-sensitivity", help="nm per z_piezo unit (default: its length units).")
    ] = None,
    contact_z: Annotated[
        Optional[float], typer.Option("--contact-z", help="z_piezo at contact, l = 0 (default: aligned).")
    ] = None,
    json_output: JsonOpt = False,
    config: ConfigOpt = None,
    quiet: QuietOpt = False,
) -> None:
    """Put REEP's f0' and Q' beside averaging theory along a force curve (§3.4.3).

    The theory uses REEP's measured amplitude and the separation: the true one
    (/truth) on a simulation, else l = s·(z_piezo − z_c) with the contact point
    z_c aligned on the approach's amplitude curve (or --contact-z).  The report
    says how far apart they are and whether that is within tolerance.
    """
    from afmtool.analyses.theory_outputs import run_compare_command

    flags = {"force_set": force_set, "force": force, "separation": separation, "z_sensitivity": z_sensitivity,
             "contact_z": None if contact_z is None else repr(contact_z)}
    report = run_compare_command(reep_dir, out, config, flags)
    finish_command(report, out, json_output, quiet)


@app.command("fit")
def fit(
    reep_dir: Annotated[Path, typer.Argument(help="Output folder of 'afmtool reep' on a force curve (needs z).")],
    out: OutOpt = Path("theory_fit"),
    z_sensitivity: Annotated[
        Optional[float], typer.Option("--z-sensitivity", help="nm per z_piezo unit (default: its length units).")
    ] = None,
    json_output: JsonOpt = False,
    config: ConfigOpt = None,
    quiet: QuietOpt = False,
) -> None:
    """Fit d, ωa², ωb², ca, cb and the contact point so averaging theory reproduces the approach.

    scipy.optimize.least_squares on REEP's f0', Q' and amplitude; fit.json holds
    values, uncertainties and which parameters this curve determines (an SVD of
    the Jacobian, as in 'identify electrostatic'); fit.png the curves with the
    fitted theory over them.
    """
    from afmtool.analyses.theory_fit import run_theory_fit_command

    report = run_theory_fit_command(reep_dir, out, config, {"z_sensitivity": z_sensitivity})
    finish_command(report, out, json_output, quiet)


@app.command("observer")
def observer(
    out: OutOpt = Path("theory_observer"),
    f0: Annotated[Optional[float], typer.Option("--f0", help="Nominal (free-air) f0 (Hz).")] = None,
    q: Annotated[Optional[float], typer.Option("--q", help="Nominal Q (dimensionless).")] = None,
    model: Annotated[
        Optional[Path], typer.Option("--model", help="free_air.json (or its folder): f0, Q and gain of the plant.")
    ] = None,
    f0_low: Annotated[
        Optional[float], typer.Option("--f0-low", help="On-sample end of the direction, f0' (Hz).")
    ] = None,
    q_low: Annotated[Optional[float], typer.Option("--q-low", help="On-sample end of the direction, Q' (dimensionless).")] = None,
    reep: Annotated[
        Optional[Path],
        typer.Option("--reep", help="REEP output folder or reep.h5: the direction from its force curve."),
    ] = None,
    force_set: Annotated[
        Optional[str], typer.Option("--force-set", help="Else the direction from averaging theory with this force set.")
    ] = None,
    cycles: Annotated[
        Optional[str], typer.Option("--cycles", help="Gains: error time constants in drive periods, e.g. 4,50.")
    ] = None,
    observers: Annotated[
        Optional[str], typer.Option("--observers", help="Observer models f0_hz:q,... for the directional plots.")
    ] = None,
    recommend: Annotated[
        bool, typer.Option("--recommend", help="Pick the model and gain of most sensitivity that settle in time.")
    ] = False,
    max_cycles: Annotated[
        Optional[float], typer.Option("--max-cycles", help="Recommend: settle within this many drive periods.")
    ] = None,
    json_output: JsonOpt = False,
    config: ConfigOpt = None,
    quiet: QuietOpt = False,
) -> None:
    """Observer-design trade-offs (ch. 5): A_e², its sensitivities, SNR and transients.

    Maps over observer models (f_k, Q_k) at the free-air plant, one per gain, and
    lines as the plant moves along the force-curve direction (eqs. 5.16-5.22).
    With --recommend, the model and gain that maximise |dA_e²| along the force
    curve while the error settles within --max-cycles drive periods.
    """
    from afmtool.analyses.observer_theory_outputs import run_observer_theory_command

    flags = {
        "f0_hz": f0,
        "q": q,
        "model": str(model) if model else None,
        "f0_low_hz": f0_low,
        "q_low": q_low,
        "reep": str(reep) if reep else None,
        "force_set": force_set,
        "cycles": cycles,
        "observers": observers,
        "recommend": True if recommend else None,
        "max_cycles": max_cycles,
    }
    finish_command(run_observer_theory_command(out, config, flags), out, json_output, quiet)


@app.command("controllers")
def controllers(
    out: OutOpt = Path("theory_controllers"),
    line_rates: Annotated[
        Optional[str], typer.Option("--line-rates", help="Line rates (Hz), comma-separated (default 4,8,12,30).")
    ] = None,
    lines: Annotated[Optional[int], typer.Option("--lines", help="Raster lines per table run.", min=1)] = None,
    seed: Annotated[Optional[int], typer.Option("--seed", help="Simulation seed.")] = None,
    figure_lines: Annotated[
        Optional[int], typer.Option("--figure-lines", help="Raster lines of the height images.", min=1)
    ] = None,
    json_output: JsonOpt = False,
    config: ConfigOpt = None,
    quiet: QuietOpt = False,
) -> None:
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
    from afmtool.analyses.controllers import run_controllers_command
    from afmtool.cli.progress import stderr_console

    flags = {"line_rates_hz": line_rates, "lines": lines, "seed": seed, "figure_lines": figure_lines}

    def progress(step: str) -> None:
        stderr_console(quiet).print(f"simulating the three controllers: {step}", highlight=False)

    finish_command(run_controllers_command(out, config, flags, progress), out, json_output, quiet)
