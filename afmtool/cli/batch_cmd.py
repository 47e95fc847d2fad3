"""``afmtool batch COMMAND INPUTS... --out DIR``."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated, Optional

import typer

from afmtool.cli.options import QuietOpt

__all__ = ["register"]

#: Commands batch can run: (words, takes a capture argument).
#: Analyses that take one capture and write an output folder.
_COMMANDS = {
    "reep": ("reep",),
    "freeair": ("identify", "freeair"),
    "probeloss": ("probeloss",),
    "kalman-bank": ("kalman-bank",),
    "decode": ("decode",),
}


def batch(
    command: Annotated[str, typer.Argument(help=f"Analysis to run: {', '.join(_COMMANDS)}.")],
    inputs: Annotated[list[str], typer.Argument(help="Captures: files, globs or folders.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder; one subfolder per input.")],
    workers: Annotated[int, typer.Option("--workers", help="Local Dask workers.", min=1)] = 2,
    scheduler: Annotated[
        Optional[str], typer.Option("--scheduler", help="Use an existing Dask cluster, e.g. tcp://host:8786.")
    ] = None,
    args: Annotated[
        Optional[list[str]], typer.Option("--arg", help="Extra argument for every run (repeatable), e.g. --arg=--lambda --arg=0.99.")
    ] = None,
    retry_failed: Annotated[bool, typer.Option("--retry-failed", help="Rerun inputs that failed before.")] = False,
    quiet: QuietOpt = False,
) -> None:
    """Run one analysis over many captures in parallel on Dask, and keep going past bad files.

    Each input gets its own subfolder of --out; summary.csv has one row per input
    with its status and headline results.  Rerunning skips inputs whose outputs
    are complete.  Exit status 1 when any input failed.  Needs 'afmtool[cluster]'.
    """
    from afmtool.analyses.batch import expand_inputs, plan_batch, run_batch, write_summary
    from afmtool.cli.progress import stderr_console
    from afmtool.errors import ConfigError
    from afmtool.report.atomic import atomic_path

    if command not in _COMMANDS:
        raise ConfigError(f"batch command {command!r} must be one of {', '.join(_COMMANDS)}")
    items = plan_batch(expand_inputs(inputs), out)
    out.mkdir(parents=True, exist_ok=True)
    console = stderr_console(quiet)
    from rich.progress import Progress

    with Progress(console=console, transient=True, disable=quiet or not sys.stderr.isatty()) as progress:
        task = progress.add_task(f"batch {command}", total=len(items))

        def done(outcome):
            progress.advance(task)
            if outcome.status == "failed":
                console.print(f"[red]failed[/] {outcome.source}: {outcome.reason}", highlight=False)

        outcomes = run_batch(
            _COMMANDS[command], items, args or [], workers=workers, scheduler=scheduler, on_done=done,
            retry_failed=retry_failed,
        )
    with atomic_path(out / "summary.csv") as temp:
        write_summary(temp, outcomes)
    counts = {s: sum(o.status == s for o in outcomes) for s in ("ok", "skipped", "failed")}
    console.print(f"{counts['ok']} done, {counts['skipped']} skipped (complete), {counts['failed']} failed; {out / 'summary.csv'}")
    failed = [o for o in outcomes if o.status == "failed"]
    if failed:
        for o in failed:
            print(f"afmtool: failed: {o.source}: {o.reason}", file=sys.stderr)
        raise typer.Exit(1)


def register(app: typer.Typer) -> None:
    app.command()(batch)
