"""``afmtool simulate SCENARIO -o FILE``: captures whose ground truth is known."""

from __future__ import annotations

import tomllib
from typing import Annotated, Optional

import typer

from afmtool.cli.common import output_target
from afmtool.cli.options import ConfigOpt, QuietOpt

__all__ = ["register", "parse_settings"]


def parse_settings(items: list[str] | None) -> dict:
    """``["f0_hz=7e4", "drive=three-sine"]`` -> typed values (TOML syntax, bare words as strings)."""
    from afmtool.errors import ConfigError

    settings = {}
    for item in items or []:
        key, sep, raw = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"--set {item!r} must look like KEY=VALUE")
        try:
            value = tomllib.loads(f"v = {raw.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            value = raw.strip()
        settings[key.strip()] = value
    return settings


def simulate(
    scenario: Annotated[str, typer.Argument(help="Scenario name; 'afmtool simulate list' shows them.")],
    output: Annotated[
        Optional[str], typer.Option("--output", "-o", help="Capture file to write, or - for CSV on stdout.")
    ] = None,
    fmt: Annotated[
        Optional[str],
        typer.Option("--format", "-f", help="hdf5, csv, ros1, ros2-mcap or ros2-sqlite3 (default: from --output)."),
    ] = None,
    seed: Annotated[int, typer.Option("--seed", help="Random seed; the same seed gives the same capture.")] = 0,
    settings: Annotated[
        Optional[list[str]],
        typer.Option("--set", help="Scenario parameter KEY=VALUE (repeatable); see 'afmtool simulate SCENARIO --params'."),
    ] = None,
    show_params: Annotated[bool, typer.Option("--params", help="List the scenario's parameters and exit.")] = False,
    config: ConfigOpt = None,
    quiet: QuietOpt = False,
) -> None:
    """Simulate a capture (tapping, ltv, ...) with ground truth stored in /truth (HDF5).

    Parameters come from the scenario's defaults, then the simulate.SCENARIO table of
    --config, then --set.  Only HDF5 keeps the ground truth.
    """
    from afmtool import sim
    from afmtool.analyses.convert import convert_capture
    from afmtool.config import load_toml, section_to_toml
    from afmtool.errors import ConfigError
    from afmtool.io.memory import ArrayReader
    from afmtool.io.registry import FORMATS, format_for_path

    if scenario == "list":
        for name in sim.scenario_names():
            typer.echo(name)
        return
    if scenario not in sim.scenario_names():
        raise ConfigError(f"unknown scenario {scenario!r}; one of: {', '.join(sim.scenario_names())}")
    if show_params:
        typer.echo(section_to_toml(f"simulate.{scenario}", sim.scenario_defaults(scenario)), nl=False)
        return
    if output is None:
        raise ConfigError("--output/-o is required (a file, or - for CSV on stdout)")
    fmt = fmt or format_for_path(output)
    if fmt not in FORMATS:
        raise ConfigError(f"--format {fmt!r} must be one of {', '.join(FORMATS)}")
    overrides = {}
    if config is not None:
        overrides.update(load_toml(config).get("simulate", {}).get(scenario, {}))
    overrides.update(parse_settings(settings))
    captured = sim.simulate(scenario, overrides, seed=seed)
    reader = ArrayReader(
        captured.sample_rate_hz, captured.channels, captured.data, captured.metadata, captured.truth, f"<{scenario}>"
    )
    with output_target(output, fmt) as target:
        convert_capture(reader, target, fmt)


def register(app: typer.Typer) -> None:
    app.command()(simulate)
