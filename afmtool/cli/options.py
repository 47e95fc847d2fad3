"""Options shared by commands, as ``Annotated`` aliases, and their parsing."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from afmtool.errors import ConfigError

__all__ = [
    "CaptureArg",
    "OutOpt",
    "JsonOpt",
    "ConfigOpt",
    "QuietOpt",
    "ChannelOpt",
    "TopicOpt",
    "SampleRateOpt",
    "ChunkOpt",
    "SegmentOpt",
    "CurveOpt",
    "GroupOpt",
    "StreamOutOpt",
    "StreamOpt",
    "StreamFormatOpt",
    "NoHashOpt",
    "JobsOpt",
    "SchedulerOpt",
    "check_stream_format",
    "parse_mapping",
    "RUN_OPTIONS_KEY",
    "root_run_options",
]

#: Where the root callback keeps ``--max-samples`` and ``--wait`` (a
#: :class:`~afmtool.runtime.run_options.RunOptions`) in the click context's ``meta``, shared by every command's context.
RUN_OPTIONS_KEY = "afmtool.run_options"

CaptureArg = Annotated[
    str,
    typer.Argument(
        help="Capture file (.h5, .csv, .txt, .bag, ROS2 bag folder, .ibw, .jpk-force, .jpk-qi-series, .jpk-force-map, "
        ".jpk-qi-data, .tdms, .wav, .mat, .npz, .npy, LabOne .h5/.csv, Chiaro .txt/.zip, AFM Workshop .csv, NT-MDT .txt), "
        "or - for CSV on stdin."
    ),
]
OutOpt = Annotated[Path, typer.Option("--out", "-o", help="Output folder; created if missing.")]
DataFormatOpt = Annotated[
    str,
    typer.Option("--format", help="Result arrays as afmtool's HDF5 (h5), NetCDF (netcdf: .nc) or Zarr (zarr: a .zarr "
                 "folder), labelled with CF units; netcdf and zarr open with plain xarray."),
]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print the report as JSON on stdout.")]
ConfigOpt = Annotated[
    Optional[Path],
    typer.Option("--config", help="TOML parameters; flags override it, it overrides packaged defaults."),
]
QuietOpt = Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar or messages on stderr.")]
ChannelOpt = Annotated[
    Optional[list[str]],
    typer.Option(
        "--channel",
        help="Map a channel to an HDF5 dataset (NAME=/path) or rename a file's channel or column (NAME=CH2); repeatable.",
    ),
]
TopicOpt = Annotated[
    Optional[list[str]],
    typer.Option("--topic", help="Map a channel to a bag topic: NAME=/topic (repeatable)."),
]
SampleRateOpt = Annotated[
    Optional[float], typer.Option("--sample-rate", help="Sample rate in Hz; overrides the file's.", min=0.0)
]
SegmentOpt = Annotated[
    Optional[str],
    typer.Option("--segment", help="Read one segment of a segmented file (force curve): its name or number from 0."),
]
StdinTimeoutOpt = Annotated[
    Optional[float],
    typer.Option("--stdin-timeout", metavar="S", help="With - (CSV on stdin): end the run (exit 2) when stdin gives "
                 "no complete chunk for S s; it says 'waiting for input on stdin' after 5 s either way."),
]
CurveOpt = Annotated[
    Optional[str],
    typer.Option("--curve", metavar="N|X,Y",
                 help="Read one curve of a JPK force map or QI data file: its index N, or its grid cell X,Y "
                 "('afmtool info' lists them)."),
]
GroupOpt = Annotated[
    Optional[str],
    typer.Option("--group", metavar="NAME",
                 help="Read one group of a TDMS file: its name or number from 0 ('afmtool info' lists them)."),
]
ChunkOpt = Annotated[
    int, typer.Option("--chunk-samples", help="Samples per streamed chunk (memory vs overhead).", min=1)
]

StreamOutOpt = Annotated[
    Optional[Path], typer.Option("--out", "-o", help="Output folder; created if missing (optional with --stream).")
]
StreamOpt = Annotated[
    bool, typer.Option("--stream", help="Write result rows to stdout as they are computed (live pipelines).")
]
StreamFormatOpt = Annotated[str, typer.Option("--stream-format", help="Rows on stdout: csv or jsonl.")]
NoHashOpt = Annotated[
    bool,
    typer.Option("--no-hash", help="Record no hash of the samples read (live pipelines); by default report.json "
                 "has their XXH3-128, computed as they are read."),
]
JobsOpt = Annotated[
    Optional[int],
    typer.Option("--jobs", "-j", metavar="N", help="Cores that run the estimators on one capture, each chunk started "
                 "a warm-up early (results equal the sequential run's to 1e-9); default: all cores."),
]
SchedulerOpt = Annotated[
    Optional[str],
    typer.Option("--scheduler", metavar="ADDRESS", help="Run the chunks' estimators on a Dask cluster instead "
                 "(tcp://host:8786); chunks go to the workers as they are read."),
]


SchedulerTimeoutOpt = Annotated[
    float,
    typer.Option("--scheduler-timeout", metavar="S", help="Seconds the --scheduler has to accept and answer "
                 "(one line and exit 2 after that)."),
]


def check_stream_format(stream_format: str) -> None:
    if stream_format not in ("csv", "jsonl"):
        raise ConfigError(f"--stream-format {stream_format!r} must be csv or jsonl")


def parse_mapping(items: list[str] | None, option: str) -> dict[str, str]:
    """``["a=/x", "b=/y"]`` -> ``{"a": "/x", "b": "/y"}``, with a clear error."""
    mapping: dict[str, str] = {}
    for item in items or []:
        name, sep, target = item.partition("=")
        if not sep or not name.strip() or not target.strip():
            raise ConfigError(f"{option} {item!r} must look like NAME=VALUE")
        mapping[name.strip()] = target.strip()
    return mapping


def root_run_options():
    """``afmtool --max-samples N`` and ``--wait`` of the command line being run (the defaults outside one).

    Read from the click context, where the root callback put them, by the code that builds the
    run's :class:`~afmtool.api.run.RunSettings` and by ``afmtool batch``.
    """
    try:  # recent typer vendors its own click
        from typer._click.globals import get_current_context
    except ImportError:  # pragma: no cover - older typer uses click itself
        from click import get_current_context
    from afmtool.runtime.run_options import DEFAULTS

    ctx = get_current_context(silent=True)
    return DEFAULTS if ctx is None else ctx.meta.get(RUN_OPTIONS_KEY, DEFAULTS)
