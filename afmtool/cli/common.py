"""Helpers shared by command modules: opening inputs, writing outputs."""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from afmtool.cli.options import check_stream_format
from afmtool.cli.progress import progress_bar, stderr_console

__all__ = [
    "open_input", "open_calibrated", "output_target", "stdout_pipe", "finish_command", "run_capture_analysis",
    "run_streaming_command", "figure_process", "print_stderr_lines",
]


@contextmanager
def stdout_pipe() -> Iterator[None]:
    """A closed downstream pipe (``| head``) ends the command quietly with status 0.

    click turns EPIPE into status 1 on its own, so commands that write to
    stdout catch it here first.
    """
    import os

    import typer

    try:
        yield
        sys.stdout.flush()
    except BrokenPipeError:
        # Point stdout at /dev/null so the interpreter's final flush is silent.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        raise typer.Exit(0) from None


def open_calibrated(
    path, channel, topic, sample_rate, calibration=None, *, convert_units: bool = True, segment=None,
    hash_samples: bool = False,
):
    """Open a capture through the one reader stack (:func:`afmtool.io.stack.open_capture`).

    ``segment`` is ``--segment``, or the :class:`afmtool.io.registry.Selection` of ``--segment``,
    ``--curve`` and ``--group``.

    Its units are parsed and converted there (``--units``, ``--invols``), a drive not
    recorded is synthesised (``--drive``), and with ``hash_samples`` its samples are hashed as read.
    """
    from afmtool.cli.calibration_options import capture_options
    from afmtool.io.stack import open_capture

    return open_capture(path, capture_options(channel, topic, sample_rate, calibration, convert_units=convert_units,
                                              segment=segment, hash_samples=hash_samples))


@contextmanager
def open_input(
    path: str,
    channel: list[str] | None,
    topic: list[str] | None,
    sample_rate: float | None,
    calibration=None,
    segment=None,
    *,
    convert_units: bool = True,
):
    """Open a capture with the shared --channel/--topic/--sample-rate/--segment/--curve/--group (and calibration) options.

    ``convert_units=False`` (``info``, ``convert``) applies ``--units`` but keeps the file's scale.
    """
    reader = open_calibrated(
        path, channel, topic, sample_rate, calibration, convert_units=convert_units, segment=segment
    )
    try:
        yield reader
    finally:
        reader.close()


@contextmanager
def output_target(output: str, fmt: str) -> Iterator[Path | object]:
    """Yield where to write a capture: stdout for ``-``, else an atomic temp path."""
    if output == "-":
        with stdout_pipe():
            yield sys.stdout
        return
    from afmtool.runtime.atomic import atomic_path

    with atomic_path(Path(output), directory=fmt.startswith("ros2")) as temp:
        yield temp


def finish_command(report: dict, out: Path, json_output: bool, quiet: bool) -> None:
    """The run's answer, once its outputs are committed: the headline on stderr, or the report on stdout.

    Without ``--json``: the headline lines (:func:`afmtool.report.headline.terminal_lines`:
    the numbers with units and uncertainties, the warnings, where the files
    went) on stderr, whole lines however narrow the terminal or wherever
    stderr goes.  With ``--json`` the report goes to stdout and its warnings
    to stderr, as before.  ``--quiet`` prints nothing on stderr.
    """
    import typer

    from afmtool.report.json_report import dumps

    if json_output:
        typer.echo(dumps(report), nl=False)
        for warning in report["warnings"]:
            stderr_console(quiet).print(f"[yellow]warning:[/] {warning}", highlight=False, markup=True)
        return
    if quiet:
        return
    from afmtool.report.headline import terminal_lines

    print_stderr_lines(terminal_lines(report, str(out)))


def print_stderr_lines(lines: list[str]) -> None:
    """Lines on stderr as they are (no wrapping, no markup); "warning:" in yellow on a terminal."""
    colour = sys.stderr.isatty() and not os.environ.get("NO_COLOR")
    for line in lines:
        if colour and line.startswith("warning:"):
            line = "\x1b[33mwarning:\x1b[0m" + line[len("warning:"):]
        sys.stderr.write(line + "\n")
    sys.stderr.flush()


def run_capture_analysis(
    name: str,
    capture: str,
    source: tuple,
    out: Path | None,
    stream: tuple[bool, str],
    json_output: bool,
    quiet: bool,
    *,
    to_rows: Callable[[object], None],
    to_folder: Callable[[object, Callable[[int], None]], dict],
) -> None:
    """Open the capture and run an analysis into stdout rows (``--stream``) or into ``--out``.

    Parameters
    ----------
    name : str
        The command, for the progress bar.
    capture, source
        The capture and its ``(--channel, --topic, --sample-rate)``, optionally
        followed by its :class:`~afmtool.cli.calibration_options.CaptureCalibration`
        and ``--segment``.
    out : Path or None
        ``--out``; required without ``--stream``.
    stream : (bool, str)
        ``--stream`` and ``--stream-format``.
    to_rows : callable
        ``to_rows(reader)`` writes the rows to stdout.
    to_folder : callable
        ``to_folder(reader, progress) -> report`` writes the output folder.
    """
    from afmtool.errors import ConfigError

    streaming, stream_format = stream
    if streaming:
        check_stream_format(stream_format)
        with open_input(capture, *source) as reader, stdout_pipe():
            to_rows(reader)
        return
    if out is None:
        raise ConfigError("--out is required (or use --stream)")
    with open_input(capture, *source) as reader:
        with progress_bar(name, reader.info.n_samples, quiet) as update:
            report = to_folder(reader, update)
    finish_command(report, out, json_output, quiet)


def run_streaming_command(name: str, capture: str, source_args: tuple, output, flags: dict) -> None:
    """reep, probeloss, decode and kalman-bank: ``--stream`` rows on stdout, or the folder ``--out``.

    Both go through :mod:`afmtool.api.run` (the Python API's own path): the capture is
    read through the one reader stack with the command line's options
    (:func:`afmtool.cli.calibration_options.capture_options`), hashed as it is read
    unless ``--no-hash``, split over ``--jobs``.  ``output`` is the command's
    :class:`~afmtool.cli.groups.CommandOutput`; the analysis is the one ``name``'s spec binds
    (:mod:`afmtool.config.commands`).
    """
    from afmtool.api.capture import Capture
    from afmtool.api.run import run_capture_command, run_stream_rows
    from afmtool.cli.calibration_options import capture_options
    from afmtool.errors import ConfigError

    channel, topic, sample_rate, calibration, segment = (*source_args, None, None)[:5]
    source = Capture(capture, capture_options(channel, topic, sample_rate, calibration, segment=segment))
    streaming, stream_format = output.stream_mode
    if streaming:
        check_stream_format(stream_format)
        with stdout_pipe():
            run_stream_rows(name, source, flags, output.settings(), stream_format)
        return
    if output.out is None:
        raise ConfigError("--out is required (or use --stream)")
    with figure_process(output) as figures:
        report = run_capture_command(name, source, output.out, flags, output.settings(figures, split=True))
    finish_command(report, output.out, output.json_output, output.quiet)


def figure_process(output):
    """The helper that draws a folder run's figures, forked now, before numba loads and threads start.

    ``--stream`` draws none: the figures are then drawn (never) in this process.
    """
    from afmtool.report.figure_process import FigureProcess

    streaming, _ = output.stream_mode
    return FigureProcess() if streaming or output.out is None else FigureProcess.start()
