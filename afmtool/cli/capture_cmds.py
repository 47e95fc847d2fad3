"""``afmtool info`` and ``afmtool convert``."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated, Optional

import typer

from afmtool.cli.common import output_target, stdout_pipe
from afmtool.cli.groups import CaptureSource, capture_options, with_options
from afmtool.cli.options import CaptureArg, ChunkOpt, JsonOpt, QuietOpt
from afmtool.cli.progress import progress_bar
from afmtool.io.capture import DEFAULT_CHUNK_SAMPLES

__all__ = ["register"]

#: info and convert read a capture as its file has it: --units, but no calibration or drive.
_AS_RECORDED = capture_options(invols=False, z_sensitivity=False, drive=False)


@with_options(_AS_RECORDED)
def info(
    capture: CaptureArg,
    json_output: JsonOpt = False,
    chunk_samples: ChunkOpt = DEFAULT_CHUNK_SAMPLES,
    quiet: QuietOpt = False,
    *,
    source: CaptureSource,
) -> None:
    """Channels, units, sample rate, length, segments, metadata and min/max/mean/rms per channel.

    Statistics are computed by streaming, so any size of capture works.
    Segmented files (force curves) list their segments; --segment NAME|N
    summarises one of them.  A file whose segments have different sample
    rates or channels is summarised segment by segment, and a TDMS file
    whose groups differ group by group (with --json, as a list).  A JPK
    force map or QI data file lists its curves and their grid positions;
    --curve N or --curve X,Y summarises one.
    """
    from afmtool.errors import SelectionNeeded
    from afmtool.report.json_report import dumps, to_jsonable

    try:
        summaries = [_summarize(capture, source, chunk_samples, quiet)]
    except SelectionNeeded as exc:
        field = exc.option.lstrip("-")
        if getattr(source, field) is not None:
            raise
        if exc.option == "--curve":  # a map: the list of its curves, not thousands of summaries
            _print_listing(capture, exc, json_output)
            return
        summaries = [_summarize(capture, source._replace(**{field: choice}), chunk_samples, quiet)
                     for choice in exc.choices]
    with stdout_pipe():
        if json_output:
            typer.echo(dumps(to_jsonable(summaries[0] if len(summaries) == 1 else summaries)), nl=False)
        else:
            for summary in summaries:
                _print_summary(summary)


def _print_listing(capture: str, exc, json_output: bool) -> None:
    """The curves of a map (index, grid cell, position), when no --curve chose one."""
    from afmtool.report.json_report import dumps

    listing = {"source": capture, **exc.listing,
               "choose": f"{exc.option} N or {exc.option} X,Y"}
    with stdout_pipe():
        if json_output:
            typer.echo(dumps(listing), nl=False)
            return
        curves = exc.listing.get("curves", [])
        shape = exc.listing.get("grid_shape")
        lines = [f"{capture} ({listing['format']}): {len(curves)} curves"
                 + (f" on a {shape[0]} x {shape[1]} grid" if shape else "") + f"; choose one with {listing['choose']}",
                 f"{'curve':>6} {'grid x,y':>9} {'x (m)':>14} {'y (m)':>14}"]
        for c in curves:
            cell = ",".join(str(v) for v in c["grid_index"]) if c["grid_index"] else "-"
            x, y = c["position_m"] or (float("nan"), float("nan"))
            lines.append(f"{c['curve']:>6} {cell:>9} {x:>14.6g} {y:>14.6g}")
        sys.stdout.write("\n".join(lines) + "\n")


def _summarize(capture: str, source: CaptureSource, chunk_samples: int, quiet: bool):
    from afmtool.analyses.info import summarize

    with source.open(capture, convert_units=False) as reader:
        with progress_bar("info", reader.info.n_samples, quiet) as update:
            return summarize(reader, chunk_samples, update)


#: The width ``info`` lays its table out at when stdout is not a terminal: wide enough that nothing is cut.
_PIPED_WIDTH = 10_000

#: Above this many channels ``info`` prints plain lines instead of a rich table.
_RICH_TABLE_ROWS = 200


def _print_summary(summary) -> None:
    from rich.console import Console
    from rich.table import Table

    # piped, rich would lay the table out at 80 columns and cut values with "…": give it room instead
    console = Console() if sys.stdout.isatty() else Console(width=_PIPED_WIDTH)
    chosen = summary.metadata.get("segment") if isinstance(summary.metadata.get("segment"), dict) else None
    segment = f", segment {chosen.get('index')} {chosen.get('name')}" if chosen else ""
    console.print(f"[bold]{summary.source}[/] ({summary.format}{segment})")
    console.print(
        f"sample rate {summary.sample_rate_hz:,.6g} Hz, {summary.n_samples:,} samples, {summary.duration_s:.6g} s"
    )
    if len(summary.channels) > _RICH_TABLE_ROWS:
        # rich lays a table out in time that grows fast with its rows (20 s of CPU for 40,000 CSV
        # columns); plain aligned lines cost microseconds each.
        lines = [f"{'channel':24} {'units':8} {'min':>13} {'max':>13} {'mean':>13} {'rms':>13}"]
        lines += [
            f"{c.name:24} {c.units:8} {c.min:13.6g} {c.max:13.6g} {c.mean:13.6g} {c.rms:13.6g}" for c in summary.channels
        ]
        sys.stdout.write("\n".join(lines) + "\n")
    else:
        table = Table("channel", "units", "min", "max", "mean", "rms")
        for c in summary.channels:
            table.add_row(c.name, c.units, f"{c.min:.6g}", f"{c.max:.6g}", f"{c.mean:.6g}", f"{c.rms:.6g}")
        console.print(table)
    if summary.segments:
        console.print(
            "segments: "
            + ", ".join(
                f"{i} {s.name} ({s.n_samples:,} samples, {s.sample_rate_hz:,.6g} Hz)" for i, s in enumerate(summary.segments)
            ),
            highlight=False,
        )
    if summary.metadata:
        console.print("metadata: " + json.dumps(summary.metadata), highlight=False, soft_wrap=True)
    if summary.truth_names:
        console.print("ground truth: " + ", ".join(summary.truth_names))


@with_options(capture_options(invols=False, z_sensitivity=False, drive=False, keyword="reading"))
def convert(
    source: CaptureArg,
    output: Annotated[str, typer.Argument(help="Output file (.h5, .csv, .bag, .mcap folder...) or - for CSV on stdout.")],
    fmt: Annotated[
        Optional[str],
        typer.Option("--format", "-f", help="hdf5, csv, ros1, ros2-mcap or ros2-sqlite3 (default: from OUTPUT)."),
    ] = None,
    compression: Annotated[
        Optional[str], typer.Option("--compression", help="HDF5 only: 'gzip' (with shuffle); default none.")
    ] = None,
    chunk_samples: ChunkOpt = DEFAULT_CHUNK_SAMPLES,
    quiet: QuietOpt = False,
    *,
    reading: CaptureSource,
) -> None:
    """Convert any readable capture (HDF5, CSV, bags, .ibw, JPK, .tdms, LabOne, .wav, Chiaro) to HDF5, CSV or a bag.

    Units, metadata and segments are kept; a file whose segments have different
    rates is converted one segment at a time (--segment).

    The output appears only when complete (written to a temp name, then renamed).
    ROS2 outputs are bag folders; without --format a name ending in .mcap or
    .db3 picks the storage.
    """
    from afmtool.analyses.convert import convert_capture
    from afmtool.errors import ConfigError
    from afmtool.io.registry import FORMATS, format_for_path

    fmt = fmt or format_for_path(output)
    if fmt not in FORMATS:
        raise ConfigError(f"--format {fmt!r} must be one of {', '.join(FORMATS)}")
    if compression not in (None, "gzip"):
        raise ConfigError(f"--compression {compression!r} must be gzip")
    with reading.open(source, convert_units=False) as reader:
        with progress_bar("convert", reader.info.n_samples, quiet) as update, output_target(output, fmt) as target:
            convert_capture(
                reader, target, fmt, compression=compression, chunk_samples=chunk_samples, progress=update
            )


def report(
    folder: Annotated[Path, typer.Argument(help="An afmtool output folder (holding report.json).")],
    output: Annotated[
        Optional[Path], typer.Option("--output", "-o", help="HTML file to write (default: FOLDER/report.html).")
    ] = None,
    quiet: QuietOpt = False,
) -> None:
    """One self-contained HTML page (plots embedded) from any analysis output folder.

    The page opens with the headline numbers (units, uncertainties), then the
    figures, the warnings, and the inputs and parameters collapsed.  A batch
    folder gives one page with a row per input, linked to a page per run.
    Only regular files inside FOLDER are read (no symbolic links, no FIFOs).
    """
    from afmtool.cli.progress import stderr_console
    from afmtool.report.html import report_pages
    from afmtool.runtime.atomic import write_text_atomic

    _check_report_folder(folder, output or folder / "report.html")
    pages = report_pages(folder, output)
    for path, page in pages:
        write_text_atomic(path, page)
    stderr_console(quiet).print(f"wrote {pages[-1][0]}", highlight=False)


def _check_report_folder(folder: Path, target: Path) -> None:
    """The page is HTML, never replaces the folder's report or the run's inputs; report.json is sound.

    report.json comes from disk and may be anything: its shape is checked
    here (an object with the fields the page shows, of their types) so that
    a damaged one is one line and exit 2, not an internal error.
    """
    from afmtool.errors import ConfigError, InputError
    from afmtool.io.metadata import MAX_JSON_DEPTH, json_depth
    from afmtool.runtime.input_guard import register_input

    if target.suffix.lower() not in (".html", ".htm"):
        raise ConfigError(f"--output {target}: must end in .html or .htm (refusing to overwrite other files)")
    report_path = folder / "report.json"
    if not report_path.is_file() and (folder / "summary.csv").is_file():
        return  # a batch folder: report_pages renders each run's page from its own report
    if not report_path.is_file():
        raise InputError(f"{folder}: no report.json (not an afmtool output folder)")
    register_input(report_path)
    try:
        text = report_path.read_text(encoding="utf-8")
        if json_depth(text) > MAX_JSON_DEPTH:
            raise InputError(f"{report_path}: nested more than {MAX_JSON_DEPTH} deep; not an afmtool report")
        report = json.loads(text)
    except (UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"{report_path}: not valid JSON ({exc})") from None
    shape = {"command": str, "inputs": list, "outputs": list, "warnings": list, "results": dict, "parameters": dict}
    if not isinstance(report, dict) or not isinstance(report.get("command"), str):
        raise InputError(f"{report_path}: not an afmtool report")
    for key, kind in shape.items():
        if key in report and not isinstance(report[key], kind):
            raise InputError(f"{report_path}: {key} must be a JSON {kind.__name__}; not an afmtool report")
    if not all(isinstance(i, dict) for i in report.get("inputs", [])) or not all(
        isinstance(w, str) for w in report.get("warnings", []) + report.get("outputs", [])
    ):
        raise InputError(f"{report_path}: inputs, outputs or warnings of the wrong type; not an afmtool report")
    for item in report.get("inputs", []):
        if isinstance(item.get("path"), str):
            register_input(item["path"])


def register(app: typer.Typer) -> None:
    app.command()(info)
    app.command()(convert)
    app.command()(report)
