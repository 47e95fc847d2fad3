"""How the console script ends: a successful run skips the interpreter's teardown when nothing needs it."""

from __future__ import annotations

import subprocess
import sys

import pytest

_SCRIPT = """
import atexit, sys, threading
atexit.register(lambda: print("TEARDOWN", flush=True))
{setup}
sys.argv = ["afmtool", *{argv!r}]
from afmtool.cli.entry import main
main()
"""


def _console_script(argv: list[str], setup: str = "") -> subprocess.CompletedProcess:
    script = _SCRIPT.format(setup=setup, argv=argv)
    return subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)


def test_a_successful_run_skips_teardown_and_still_flushes_stdout():
    # stdout is a pipe here, so block-buffered: the version line is there only if it was flushed
    result = _console_script(["--version"])
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("afmtool "), result.stdout
    assert "TEARDOWN" not in result.stdout


def test_a_live_non_daemon_thread_is_waited_for():
    # the thread outlives main(): it waits for the main thread to finish, so Python's exit must wait for it
    setup = "threading.Thread(target=lambda: (threading.main_thread().join(), print('THREAD DONE', flush=True))).start()"
    result = _console_script(["--version"], setup)
    assert result.returncode == 0, result.stderr
    assert "THREAD DONE" in result.stdout and "TEARDOWN" in result.stdout


@pytest.mark.parametrize("argv", [["info", "no-such-capture.h5"], ["reep"]])
def test_a_failed_run_keeps_its_status_and_its_teardown(argv):
    result = _console_script(argv)
    assert result.returncode == 2
    assert "TEARDOWN" in result.stdout
    assert len(result.stderr.strip().splitlines()) >= 1
