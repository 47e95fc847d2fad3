"""The ``afmtool`` command line: thin typer wiring over ``afmtool.analyses``.

Start-up stays fast because nothing heavy (scipy, numba, matplotlib) is
imported until a command runs.  Errors the user can fix print one line on
stderr and exit with status 2; unexpected errors exit with status 1.
"""

from __future__ import annotations

import os
import signal
import sys
from typing import Annotated

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
    probeloss_cmd,
    reep_cmd,
    simulate_cmd,
    theory_cmd,
)
from afmtool.errors import AfmtoolError

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
    version: Annotated[
        bool, typer.Option("--version", callback=_version, is_eager=True, help="Print the version.")
    ] = False,
) -> None:
    """afmtool: capture -> chunks -> kernel -> result -> writer."""


identify_app = typer.Typer(help="Identify models: the free-air cantilever, ...", no_args_is_help=True)

capture_cmds.register(app)
simulate_cmd.register(app)
reep_cmd.register(app, identify_app)
decode_cmd.register(app)
identify_cmd.register(identify_app)
batch_cmd.register(app)
kalman_bank_cmd.register(app)
probeloss_cmd.register(app)
app.add_typer(identify_app, name="identify")
app.add_typer(theory_cmd.app, name="theory")
app.add_typer(design_cmd.app, name="design")
app.add_typer(config_cmd.app, name="config")


def _error(message: str, code: int) -> None:
    first_line = str(message).strip().splitlines()[0] if str(message).strip() else "error"
    print(f"afmtool: error: {first_line}", file=sys.stderr)
    sys.exit(code)


def main(argv: list[str] | None = None) -> None:
    """Console-script entry point with afmtool's exit-code contract."""
    # SIGINT and SIGTERM unwind as KeyboardInterrupt, so staged outputs are cleaned up.
    signals: list[int] = []

    def interrupt(signum, frame) -> None:  # noqa: ARG001
        signals.append(signum)
        raise KeyboardInterrupt

    signal.signal(signal.SIGINT, interrupt)
    signal.signal(signal.SIGTERM, interrupt)
    default_unraisable = sys.unraisablehook

    def unraisable(info) -> None:
        # A signal that lands in a finaliser or weakref callback cannot unwind anything;
        # Python would print it as 'Exception ignored' with a traceback. The run goes on
        # and ends normally, with complete outputs.
        if info.exc_type is not None and issubclass(info.exc_type, KeyboardInterrupt):
            return
        default_unraisable(info)

    sys.unraisablehook = unraisable
    try:
        _run(argv, signals)
    finally:
        # Outputs are committed or cleaned up by now; a signal during interpreter
        # shutdown should end the process, not print a traceback from a finaliser.
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        sys.unraisablehook = default_unraisable


def _run(argv: list[str] | None, signals: list[int]) -> None:
    try:
        # inside the try: building the command evaluates every option's annotations, a
        # moment a signal can land in
        command = typer.main.get_command(app)
        result = command.main(args=argv, prog_name="afmtool", standalone_mode=False)
    except AfmtoolError as exc:
        _error(str(exc), 2)
    except click_exceptions.ClickException as exc:
        if not exc.format_message():  # bare `afmtool`: help was printed already
            sys.exit(2)
        _error(exc.format_message(), 2)
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except (KeyboardInterrupt, typer.Abort):
        print("afmtool: interrupted", file=sys.stderr)
        sys.exit(130)
    except BrokenPipeError:
        # A closed downstream pipe (| head) is a normal way to stop reading.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        sys.exit(0)
    except Exception as exc:  # noqa: BLE001 - the one place unexpected errors are reported
        if signals:
            # the interrupt surfaced as another exception, e.g. an extension module whose
            # import it cut short reports 'ImportError: initialization failed'
            print("afmtool: interrupted", file=sys.stderr)
            sys.exit(130)
        if os.environ.get("AFMTOOL_DEBUG"):
            raise
        _error(f"internal error ({type(exc).__name__}: {exc}); rerun with AFMTOOL_DEBUG=1 for a traceback", 1)
    sys.exit(result if isinstance(result, int) else 0)
