"""``afmtool batch COMMAND INPUTS... --out DIR``."""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Optional

import typer

from afmtool.cli.options import QuietOpt, SchedulerTimeoutOpt
from afmtool.config.commands import batch_commands

__all__ = ["register"]

#: Commands batch can run, by batch's name: the command's words.  Analyses that take one capture
#: and write an output folder: each spec's ``batch`` (:class:`~afmtool.config.commands.CommandSpec`).
_COMMANDS = batch_commands()


def batch(
    command: Annotated[str, typer.Argument(help=f"Analysis to run: {', '.join(_COMMANDS)}.")],
    inputs: Annotated[list[str], typer.Argument(help="Captures: files, globs or folders.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder; one subfolder per input.")],
    workers: Annotated[int, typer.Option("--workers", help="Local Dask workers.", min=1)] = 2,
    scheduler: Annotated[
        Optional[str], typer.Option("--scheduler", help="Use an existing Dask cluster, e.g. tcp://host:8786.")
    ] = None,
    scheduler_timeout: SchedulerTimeoutOpt = 10.0,
    args: Annotated[
        Optional[list[str]], typer.Option("--arg", help="Extra argument for every run (repeatable), e.g. --arg=--lambda --arg=0.99.")
    ] = None,
    retry_failed: Annotated[bool, typer.Option("--retry-failed", help="Rerun inputs that failed before.")] = False,
    quiet: QuietOpt = False,
) -> None:
    """Run one analysis over many captures in parallel on Dask, and keep going past bad files.

    Each input gets its own subfolder of --out; summary.csv has one row per input
    with its status and headline results.  A JPK force map or QI data file is
    one input per curve (NAME_curveN; the runs get --curve N).  Rerunning skips inputs whose outputs
    are complete.  Exit status 2 when any input failed (one line each on stderr), 1 when one met an internal error.  Needs 'afmtool[cluster]'.
    """
    from afmtool.analyses.batch import expand_inputs, plan_batch, write_summary
    from afmtool.cli.options import root_run_options
    from afmtool.errors import ConfigError
    from afmtool.runtime.atomic import OutputError, atomic_path
    from afmtool.runtime.outputs import FolderLock

    if command not in _COMMANDS:
        raise ConfigError(f"batch command {command!r} must be one of {', '.join(_COMMANDS)}")
    items = plan_batch(expand_inputs(inputs), out)
    if scheduler:  # before anything is created: a peer that refuses, hangs or answers garbage is one line
        from afmtool.io.scheduler import probe_scheduler

        probe_scheduler(scheduler, scheduler_timeout)
    out.parent.mkdir(parents=True, exist_ok=True)
    options = root_run_options()  # afmtool --max-samples / --wait: for this lock and every run's command line
    # one batch (or command) at a time on --out: two batches on one folder mixed their outputs
    with FolderLock(Path(os.path.realpath(out)), out, wait=options.wait):
        before = set(os.listdir(out)) if out.is_dir() else None
        try:
            out.mkdir(parents=True, exist_ok=True)
            outcomes = _run_with_progress(command, items, args or [], workers, (scheduler, scheduler_timeout),
                                          retry_failed, quiet, options)
            faults = [o for o in outcomes if o.fault]
            if faults:
                raise OutputError(f"--out {out}: could not be written ({faults[0].reason.rsplit('(', 1)[-1].rstrip(')')}); "
                                  "this batch kept nothing")
            with atomic_path(out / "summary.csv") as temp:
                write_summary(temp, outcomes)
        except Exception:
            _remove_what_this_run_made(out, before)  # a full disk, an error: no partial batch
            raise
    _report(outcomes, out, quiet)


def _remove_what_this_run_made(out: Path, before: set[str] | None) -> None:
    """The folder if this run created it, else the entries it added (subfolders, manifests); never raises."""
    import shutil

    try:
        if before is None:
            shutil.rmtree(out, ignore_errors=True)
            return
        for name in set(os.listdir(out)) - before:
            path = out / name
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path, ignore_errors=True)
            else:
                path.unlink(missing_ok=True)
    except OSError:
        pass


def _run_with_progress(command, items, args, workers, scheduler: tuple, retry_failed, quiet, options):
    from rich.progress import Progress

    from afmtool.analyses.batch import run_batch
    from afmtool.cli.progress import stderr_console

    console = stderr_console(quiet)
    with Progress(console=console, transient=True, disable=quiet or not sys.stderr.isatty()) as progress:
        task = progress.add_task(f"batch {command}", total=len(items))

        def done(outcome):
            progress.advance(task)

        return run_batch(
            _COMMANDS[command], items, args, workers=workers, scheduler=scheduler[0], on_done=done,
            retry_failed=retry_failed, scheduler_timeout_s=scheduler[1], options=options,
            options_of=capture_options_of,
        )


def capture_options_of(command: Sequence[str], source: str, extra_args: Sequence[str]):
    """The :class:`~afmtool.io.stack.CaptureOptions` a run of ``afmtool COMMAND SOURCE EXTRA_ARGS`` reads with.

    The extra arguments are parsed by the command's own options (click), so ``--invols``,
    ``--units``, ``--channel``, ``--segment``, ``--drive`` mean here what they mean to the run:
    batch's resume check reads the input as the run did.  None when they cannot be parsed (the
    run itself will say why).
    """
    import typer.main

    from afmtool.cli.calibration_options import CaptureCalibration, capture_options
    from afmtool.cli.main import app
    from afmtool.config.commands import capture_commands
    from afmtool.io.registry import Selection

    try:
        click_command = typer.main.get_command(app)
        for word in command:
            click_command = click_command.commands[word]
        values = click_command.make_context("afmtool", [source, *extra_args, "--out", "-"],
                                            resilient_parsing=True).params
        accepts_drive = capture_commands().get(" ".join(command), ((), False))[1]
        calibration = CaptureCalibration(values.get("units"), values.get("invols"), values.get("z_sensitivity"),
                                         values.get("drive"), values.get("drive_phases"), values.get("free_air") or None,
                                         accepts_drive=accepts_drive)
        selection = Selection(values.get("segment"), values.get("curve"), values.get("group"))
        return capture_options(values.get("channel"), values.get("topic"), values.get("sample_rate"), calibration,
                               segment=selection)
    except Exception:  # noqa: BLE001 - click's own usage errors, a bad value: the run reports them; no check here
        return None


def _report(outcomes, out: Path, quiet: bool) -> None:
    """One line per failed input, then the counts; exit status 2 when any input failed."""
    counts = {s: sum(o.status == s for o in outcomes) for s in ("ok", "skipped", "failed")}
    for o in outcomes:
        if o.status == "failed":
            print(f"afmtool: failed: {o.source}: {o.reason}", file=sys.stderr)
    if not quiet:  # with --quiet only the failed inputs, one line each
        print(
            f"afmtool: batch: {counts['ok']} done, {counts['skipped']} skipped (complete), {counts['failed']} failed; "
            f"{out / 'summary.csv'}",
            file=sys.stderr,
        )
    if counts["failed"]:
        # README: 2 for bad input (and a lost worker), 1 when an input met an internal error
        raise typer.Exit(1 if any(o.exit_code == 1 for o in outcomes if o.status == "failed") else 2)


def register(app: typer.Typer) -> None:
    app.command()(batch)
