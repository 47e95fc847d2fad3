"""``afmtool simulate SCENARIO -o FILE``: captures whose ground truth is known."""

from __future__ import annotations

import tomllib
from typing import Annotated, Optional

import typer

from afmtool.cli.common import output_target
from afmtool.cli.options import ConfigOpt, QuietOpt

__all__ = ["SCENARIO_USES", "register", "parse_settings", "scenario_list"]


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


#: What each built-in scenario's capture is for: the commands that read it.
SCENARIO_USES = {
    "bits": "decode",
    "es-approach": "identify electrostatic",
    "iv-ramp": "identify thermal --iv (--set ramp=z: --z-curve)",
    "ltv": "reep, identify freeair (a known f0(t), Q(t) step; --set drive=chirp: a sweep)",
    "raster": "probeloss, reep (images), theory controllers",
    "tapping": "reep, kalman-bank, theory compare/fit (a force curve; --set program=steps|line-scan|constant)",
    "thermal-sweep": "identify gamma, identify thermal --vr-sweep",
    "vphi-step": "decode (the V_phi step of §7.7)",
}


def scenario_list() -> str:
    """``afmtool simulate list``: each scenario, what it simulates and which commands read it."""
    from afmtool import sim

    names = sim.scenario_names()
    width = max(len(name) for name in names)
    lines = []
    for name in names:
        lines.append(f"{name.ljust(width)}  {sim.scenario_info(name).summary}")
        if name in SCENARIO_USES:
            lines.append(f"{' ' * width}  for: {SCENARIO_USES[name]}")
    lines.append("")
    lines.append("afmtool simulate SCENARIO --params lists a scenario's parameters; --set KEY=VALUE changes one.")
    return "\n".join(lines)


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
    drive: Annotated[
        Optional[str],
        typer.Option("--drive", help="Play a designed dither: lines.json or excitation.wav of 'afmtool design "
                     "excitation' (tapping; same as --set drive_file=FILE)."),
    ] = None,
    config: ConfigOpt = None,
    quiet: QuietOpt = False,
) -> None:
    """Simulate a capture (tapping, ltv, ...) with ground truth stored in /truth (HDF5).

    Parameters come from the scenario's defaults, then the simulate.SCENARIO table of
    --config, then --set.  Only HDF5 keeps the ground truth.  When the file is
    written, a few lines on stderr say what it holds (--quiet: none).
    """
    from afmtool import sim
    from afmtool.analyses.convert import convert_capture
    from afmtool.config import load_toml, section_to_toml
    from afmtool.errors import ConfigError
    from afmtool.io.memory import ArrayReader
    from afmtool.io.registry import FORMATS, format_for_path

    if scenario == "list":
        typer.echo(scenario_list())
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
    if drive is not None:
        overrides["drive_file"] = drive
    captured = sim.simulate(scenario, overrides, seed=seed)
    reader = ArrayReader(
        captured.sample_rate_hz, captured.channels, captured.data, captured.metadata, captured.truth, f"<{scenario}>"
    )
    with output_target(output, fmt) as target:
        convert_capture(reader, target, fmt)
    if not quiet and output != "-":  # into a pipe, the samples are the answer: stderr stays quiet
        from afmtool.cli.common import print_stderr_lines

        print_stderr_lines(_summary(scenario, captured, output, fmt))


def _summary(scenario: str, captured, output: str, fmt: str) -> list[str]:
    """What the simulated capture holds, as the end-of-run lines on stderr."""
    names = ", ".join(f"{c.name} ({c.units})" if c.units else c.name for c in captured.channels)
    lines = [
        f"afmtool simulate {scenario}",
        f"  {captured.n_samples:,} samples at {captured.sample_rate_hz:.6g} Hz ({captured.duration_s:.6g} s)",
        f"  channels: {names}",
    ]
    if captured.truth:
        kept = "" if fmt == "hdf5" else f" (not kept by {fmt}: only HDF5 keeps /truth)"
        lines.append(f"  ground truth: {', '.join(captured.truth)}{kept}")
    drive = captured.metadata.get("drive") or {}
    if drive.get("kind") == "designed":
        lines.append(f"  drive: {len(drive['lines'])} designed lines from {drive['source']}")
    lines.append(f"wrote {output}")
    return lines


def register(app: typer.Typer) -> None:
    app.command()(simulate)
