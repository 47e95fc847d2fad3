"""``afmtool theory averaging`` and ``afmtool theory compare``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from afmtool.cli.options import ConfigOpt, JsonOpt, OutOpt, QuietOpt
from afmtool.cli.reep_cmd import finish_command

__all__ = ["app"]

app = typer.Typer(help="Averaging theory (ch. 4) and its check against REEP.", no_args_is_help=True)


@app.command("averaging")
def averaging(
    out: OutOpt = Path("theory"),
    f0: Annotated[Optional[float], typer.Option("--f0", help="Free-air f0 (Hz).")] = None,
    q: Annotated[Optional[float], typer.Option("--q", help="Free-air Q.")] = None,
    force_set: Annotated[Optional[str], typer.Option("--force-set", help="Thesis force parameter set.")] = None,
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

    flags = {"f0_hz": f0, "q": q, "force_set": force_set, "free_amplitude_nm": free_amplitude}
    finish_command(run_averaging_command(out, config, flags), out, json_output, quiet)


@app.command("compare")
def compare(
    reep_dir: Annotated[Path, typer.Argument(help="Output folder of 'afmtool reep' on a simulated force curve.")],
    out: OutOpt = Path("theory_compare"),
    force_set: Annotated[
        Optional[str], typer.Option("--force-set", help="Force parameters (default: the capture's metadata).")
    ] = None,
    json_output: JsonOpt = False,
    config: ConfigOpt = None,
    quiet: QuietOpt = False,
) -> None:
    """Put REEP's f0' and Q' beside averaging theory along a simulated force curve (§3.4.3).

    The theory uses the true separation (/truth) and REEP's measured amplitude;
    the report says how far apart they are and whether that is within tolerance.
    """
    from afmtool.analyses.theory_outputs import run_compare_command

    report = run_compare_command(reep_dir, out, config, {"force_set": force_set})
    finish_command(report, out, json_output, quiet)
