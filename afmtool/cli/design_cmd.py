"""``afmtool design excitation``: the three-sine REEP dither for an identified cantilever."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from afmtool.cli.common import finish_command
from afmtool.cli.groups import CommandOutput, output_options, with_options
from afmtool.cli.param_flags import param_flags
from afmtool.config.params import DesignExcitationParams

__all__ = ["app"]

app = typer.Typer(help="Design experiments for an identified cantilever: the REEP excitation.", no_args_is_help=True)



@app.command("excitation")
@with_options(param_flags(DesignExcitationParams), output_options(Path("excitation")))
def excitation(
    model: Annotated[Path, typer.Option("--model", help="free_air.json (or its folder) from 'identify freeair'.")],
    *, flags: dict, output: CommandOutput
) -> None:
    """The three-sine dither of §3.3.2: main line at the drive, side lines at ±Δf.

    The main line gives the requested free-air amplitude; the side lines are
    the thesis's half of it, scaled down where the cantilever attenuates them
    too little to keep the response envelope's beat under --beat-tolerance.
    Writes lines.json/lines.csv (for a multi-frequency lock-in), excitation.wav
    (float32) and excitation.csv at --dac-rate (a seamless loop of whole beat
    periods, for an arbitrary waveform generator) and excitation.png.
    """
    from afmtool.api.run import run_folder_command

    report = run_folder_command("design excitation", model, output.out, flags, output.settings())
    finish_command(report, output.out, output.json_output, output.quiet)
