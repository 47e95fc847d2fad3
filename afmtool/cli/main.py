"""The ``afmtool`` command line: thin typer wiring over ``afmtool.analyses``.

Start-up stays fast because nothing heavy (scipy, numba, matplotlib) is
imported until a command runs.  Errors the user can fix print one line on
stderr and exit with status 2; unexpected errors exit with status 1.
"""

from __future__ import annotations

import os
import sys
from typing import Annotated, Optional

import typer

try:  # recent typer vendors its own click
    from typer._click import exceptions as click_exceptions
except ImportError:  # pragma: no cover - older typer uses click itself
    from click import exceptions as click_exceptions

import afmtool
from afmtool.cli import (
    batch_cmd,
    capture_cmds,
    config_cmd,
    decode_cmd,
    design_cmd,
    identify_cmd,
    kalman_bank_cmd,
    overlay_cmd,
    probeloss_cmd,
    reep_cmd,
    simulate_cmd,
    theory_cmd,
)
from afmtool.cli.help import arrange_help
from afmtool.errors import AfmtoolError
from afmtool.runtime import process

__all__ = ["app", "main"]

app = typer.Typer(
    name="afmtool",
    help="Model-mismatch analysis of high-rate AFM recordings (dither, deflection, thermal current, ...).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"afmtool {afmtool.__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    ctx: typer.Context,
    version: Annotated[
        bool, typer.Option("--version", callback=_version, is_eager=True, help="Print the version.")
    ] = False,
    max_samples: Annotated[
        Optional[int],
        typer.Option(
            "--max-samples",
            min=1,
            help="Accept HDF5 captures of up to N samples per dataset whatever their size on disk "
            "(by default what a file claims may be at most 1000x its size).",
        ),
    ] = None,
    wait: Annotated[
        bool, typer.Option("--wait", help="Wait for another run writing the same --out, instead of failing.")
    ] = False,
) -> None:
    """afmtool: capture -> chunks -> kernel -> result -> writer."""
    from afmtool.cli.options import RUN_OPTIONS_KEY
    from afmtool.runtime.run_options import RunOptions, applied

    options = RunOptions(max_samples, wait)
    # Kept on the context for the RunSettings the command builds, and in force until the root context
    # closes after the command: HDF5 captures and output folders open far below, on paths that carry no
    # RunSettings (info, convert, overlay, batch).  Not os.environ: that outlived the run in this process
    # and reached every child; batch hands its runs the options on their command lines.
    ctx.meta[RUN_OPTIONS_KEY] = options
    ctx.with_resource(applied(options))


identify_app = typer.Typer(help="Identify models: the free-air cantilever, ...", no_args_is_help=True)

capture_cmds.register(app)
simulate_cmd.register(app)
reep_cmd.register(app, identify_app)
decode_cmd.register(app)
identify_cmd.register(identify_app)
batch_cmd.register(app)
kalman_bank_cmd.register(app)
probeloss_cmd.register(app)
overlay_cmd.register(app)
app.add_typer(identify_app, name="identify")
app.add_typer(theory_cmd.app, name="theory")
app.add_typer(design_cmd.app, name="design")
app.add_typer(config_cmd.app, name="config")


def main(argv: list[str] | None = None) -> None:
    """Console-script entry point with afmtool's exit-code contract (the process: :mod:`afmtool.runtime.process`)."""
    from afmtool.report.captured_warnings import capture_warnings

    state = process.new_run()
    process.install_handlers(state)
    capture_warnings()
    try:
        _run(argv, state)
    except SystemExit as done:
        process.exit_now_if_teardown_unsafe(done.code)
        raise
    finally:
        process.after_run()


def _run(argv: list[str] | None, signals: process.Signals) -> None:
    try:
        # inside the try: building the command evaluates every option's annotations, a
        # moment a signal can land in
        command = typer.main.get_command(app)
        arrange_help(command)
        result = command.main(args=argv, prog_name="afmtool", standalone_mode=False)
    except AfmtoolError as exc:
        process.error(str(exc), 2)
    except click_exceptions.ClickException as exc:
        if not exc.format_message():  # bare `afmtool`: help was printed already
            sys.exit(2)
        process.error(exc.format_message(), 2)
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except (KeyboardInterrupt, typer.Abort):
        signals.report()
        sys.exit(130)
    except BrokenPipeError:
        # A closed downstream pipe (| head) is a normal way to stop reading.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        sys.exit(0)
    except Exception as exc:  # the one place unexpected errors are reported
        from afmtool.runtime.faults import environment_fault, fault_message

        code = environment_fault(exc)
        if code is not None:  # disk full, read-only, permissions: the environment, not a bug
            process.error(fault_message(exc, code), 2)
        if signals:
            # the interrupt surfaced as another exception, e.g. an extension module whose
            # import it cut short reports 'ImportError: initialization failed'
            signals.report()
            sys.exit(130)
        if os.environ.get("AFMTOOL_DEBUG"):
            raise
        process.error(f"internal error ({type(exc).__name__}: {exc}); rerun with AFMTOOL_DEBUG=1 for a traceback", 1)
    if result == 130 or (signals and result not in (0, None)):
        # typer turns a KeyboardInterrupt it meets into a bare return value of 130
        signals.report()
        sys.exit(130)
    if result in (0, None):
        from afmtool.report.captured_warnings import drain

        for warning in drain():  # commands without a report.json: afmtool's one-line form, at the end
            print(f"afmtool: warning: {warning}", file=sys.stderr)
    sys.exit(result if isinstance(result, int) else 0)
