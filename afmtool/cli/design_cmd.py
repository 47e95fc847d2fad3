"""``afmtool design excitation``: the three-sine REEP dither for an identified cantilever."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from afmtool.cli.common import finish_command
from afmtool.cli.options import ConfigOpt, JsonOpt, OutOpt, QuietOpt
from afmtool.config import help_for
from afmtool.config.params import DesignExcitationParams

__all__ = ["app"]

app = typer.Typer(help="Design experiments for an identified cantilever: the REEP excitation.", no_args_is_help=True)


def _help(name: str) -> str:
    return help_for(DesignExcitationParams, name)


@app.command("excitation")
def excitation(
    model: Annotated[Path, typer.Option("--model", help="free_air.json (or its folder) from 'identify freeair'.")],
    amplitude: Annotated[Optional[float], typer.Option("--amplitude", help=_help("amplitude_nm"))] = None,
    out: OutOpt = Path("excitation"),
    dac_rate: Annotated[Optional[float], typer.Option("--dac-rate", help=_help("dac_rate_hz"))] = None,
    drive_frequency: Annotated[
        Optional[float], typer.Option("--drive-frequency", help=_help("drive_frequency_hz"))
    ] = None,
    offset: Annotated[Optional[float], typer.Option("--offset", help=_help("offset_hz"))] = None,
    beat_tolerance: Annotated[Optional[float], typer.Option("--beat-tolerance", help=_help("beat_tolerance"))] = None,
    resolution: Annotated[Optional[float], typer.Option("--resolution", help=_help("resolution_hz"))] = None,
    json_output: JsonOpt = False,
    config: ConfigOpt = None,
    quiet: QuietOpt = False,
) -> None:
    """The three-sine dither of §3.3.2: main line at the drive, side lines at ±Δf.

    The main line gives the requested free-air amplitude; the side lines are
    the thesis's half of it, scaled down where the cantilever attenuates them
    too little to keep the response envelope's beat under --beat-tolerance.
    Writes lines.json/lines.csv (for a multi-frequency lock-in), excitation.wav
    (float32) and excitation.csv at --dac-rate (a seamless loop of whole beat
    periods, for an arbitrary waveform generator) and excitation.png.
    """
    from afmtool.analyses.design_excitation import run_design_excitation_command

    flags = {"amplitude_nm": amplitude, "dac_rate_hz": dac_rate, "drive_frequency_hz": drive_frequency,
             "offset_hz": offset, "beat_tolerance": beat_tolerance, "resolution_hz": resolution}
    finish_command(run_design_excitation_command(model, out, config, flags), out, json_output, quiet)
