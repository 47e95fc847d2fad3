"""The ``afmtool`` console script: quiet exits for signals that arrive while afmtool starts.

Importing the CLI (typer, rich, click) takes a noticeable fraction of a
second.  A Ctrl-C or SIGTERM in that window would otherwise print a
KeyboardInterrupt traceback from the middle of an import.  Nothing has been
read or written yet, so the process just ends with status 130;
:func:`afmtool.cli.main.main` then installs the handlers that unwind a
running analysis.
"""

from __future__ import annotations

import os
import signal


def _while_starting(signum, frame) -> None:  # noqa: ARG001
    os._exit(130)


def main() -> None:
    signal.signal(signal.SIGINT, _while_starting)
    signal.signal(signal.SIGTERM, _while_starting)
    from afmtool.cli.main import main as run

    run()
