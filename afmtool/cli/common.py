"""Helpers shared by command modules: opening inputs, writing outputs."""

from __future__ import annotations

import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from afmtool.cli.options import parse_mapping

__all__ = ["open_input", "output_target", "stdout_pipe"]


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


@contextmanager
def open_input(path: str, channel: list[str] | None, topic: list[str] | None, sample_rate: float | None):
    """Open a capture with the shared --channel/--topic/--sample-rate options."""
    from afmtool.io.registry import open_capture

    reader = open_capture(
        path,
        channel_map=parse_mapping(channel, "--channel"),
        topic_map=parse_mapping(topic, "--topic"),
        sample_rate_hz=sample_rate,
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
    from afmtool.report.atomic import atomic_path

    with atomic_path(Path(output), directory=fmt.startswith("ros2")) as temp:
        yield temp
