"""``afmtool overlay RUN_DIR... --out DIR``: several REEP runs side by side."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from afmtool.cli.options import JsonOpt, QuietOpt

__all__ = ["register"]


def overlay(
    runs: Annotated[list[Path], typer.Argument(help="Output folders of 'afmtool reep' (two or more).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")] = Path("overlay"),
    labels: Annotated[
        Optional[str],
        typer.Option("--labels", help="One label per run, comma-separated, in order, e.g. '0,45 min,2 h,16 h'."),
    ] = None,
    label_key: Annotated[
        Optional[str],
        typer.Option("--label-key", help="Label each run by 'q' or 'f0' (its free-air Q', f0') or a key of its "
                     "capture's metadata, e.g. time, sample, experiment.time."),
    ] = None,
    vs: Annotated[
        str, typer.Option("--vs", help="x axis of the force curves: z, or separation from each run's contact point.")
    ] = "z",
    leg: Annotated[str, typer.Option("--leg", help="approach, retract or both.")] = "approach",
    json_output: JsonOpt = False,
    quiet: QuietOpt = False,
) -> None:
    """Overlay force curves and time series of several REEP runs (thesis Figs. 3.17, 4.6-4.9, 3.1b).

    One figure per quantity: f0', Q', amplitude, phase and the interaction
    quantities (force gradient, tip-sample damping, Phi_c, Phi_d, energy per
    cycle) against z or the separation, one line per run, and f0', Q',
    amplitude, phase against time.  Writes overlay_*.png, overlay.csv (tidy:
    label, run, kind, leg, x, quantity, value, units), report.json and
    report.html.  Nothing is estimated again: the runs' reep.h5 are read.
    """
    from afmtool.cli.common import finish_command
    from afmtool.config.commands import spec
    from afmtool.errors import ConfigError
    from afmtool.report.figure_process import FigureProcess

    run_overlay_command = spec("overlay").runner.load()
    if labels is not None and label_key is not None:
        raise ConfigError("give --labels or --label-key, not both")
    names = [part.strip() for part in labels.split(",")] if labels is not None else None
    with FigureProcess.start() as figures:
        report = run_overlay_command(runs, out, labels=names, label_key=label_key, vs=vs, leg=leg, figures=figures)
    finish_command(report, out, json_output, quiet)


def register(app: typer.Typer) -> None:
    app.command()(overlay)
