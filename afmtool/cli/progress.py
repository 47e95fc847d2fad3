"""Progress on stderr: a rich bar for long runs, nothing when piped or --quiet."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

__all__ = ["progress_bar", "progress_steps", "stderr_console"]

# Runs shorter than this never show a bar, so quick commands stay quiet.
_SHOW_AFTER_S = 1.0


def stderr_console(quiet: bool = False):
    from rich.console import Console

    return Console(stderr=True, quiet=quiet)


@contextmanager
def progress_bar(description: str, total: int | None, quiet: bool) -> Iterator[Callable[[int], None]]:
    """Yield ``update(done)``; a bar appears on a TTY once the run passes ~1 s."""
    if quiet or not sys.stderr.isatty():
        yield lambda done: None
        return
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    started = time.monotonic()
    progress = Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        TextColumn("{task.completed:,.0f} samples"),
        TimeRemainingColumn(),
        console=stderr_console(),
        transient=True,
    )
    task = None

    def update(done: int) -> None:
        nonlocal task
        if task is None:
            if time.monotonic() - started < _SHOW_AFTER_S:
                return
            progress.start()
            task = progress.add_task(description, total=total)
        progress.update(task, completed=done)

    try:
        yield update
    finally:
        if task is not None:
            progress.stop()


@contextmanager
def progress_steps(description: str, quiet: bool) -> Iterator[Callable[[str], None]]:
    """Yield ``step(text)``: the step a long run is at, as one transient line on a TTY, else nothing.

    Steps printed as lines came before a failed run's one error line (``theory
    controllers`` on a full disk printed its progress first); a status line
    that disappears when the run ends leaves stderr to the outcome.
    """
    if quiet or not sys.stderr.isatty():
        yield lambda text: None
        return
    with stderr_console().status(description) as status:
        yield lambda text: status.update(f"{description}: {text}")
