"""The ``afmtool`` console script: process-wide settings made before anything else.

* Quiet exits for signals that arrive while afmtool starts.  Importing the
  CLI (typer, rich, click) takes a noticeable fraction of a second.  A
  Ctrl-C or SIGTERM in that window would otherwise print a
  KeyboardInterrupt traceback from the middle of an import.  Nothing has
  been read or written yet, so the process just ends with status 130;
  :func:`afmtool.cli.main.main` then installs the handlers that unwind a
  running analysis.
* glibc keeps freed chunk buffers for reuse, in one arena for all threads
  (:func:`_reuse_freed_memory`).
* A successful run ends without the interpreter's teardown
  (:func:`afmtool.runtime.process.exit_now_after_success`): 0.4-0.6 s saved per command.
"""

from __future__ import annotations

import os
import signal
import sys

#: glibc's mallopt parameters (malloc.h) and the values set.
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_ARENA_MAX = -1, -3, -8
_TRIM_THRESHOLD_BYTES = 64 << 20
_MMAP_THRESHOLD_BYTES = 32 << 20
_ARENA_MAX = 1


def _while_starting(signum, frame) -> None:
    os.write(2, b"afmtool: interrupted\n")
    os._exit(130)


def _reuse_freed_memory() -> None:
    """Let glibc keep up to 64 MiB of freed memory instead of handing it back at once.

    A streaming analysis allocates and frees the same few MB-sized arrays
    for every chunk.  By default glibc serves blocks of that size with
    fresh mmap()s or trims them off the heap as soon as they are freed, so
    every chunk pays page faults and zeroing again: at 1e8 samples that was
    0.6 s of system time in ``afmtool decode`` (of 1.7 s).  Blocks up to
    32 MiB now come from the heap and stay there for the next chunk.

    All threads share one arena (issue 33).  A chunk's buffers are allocated
    by the read-ahead thread, its columns by the split workers, the side
    thread and the writer thread; glibc gave each thread its own arena, and
    each arena kept up to the trim threshold of freed buffers that no other
    thread could reuse: at 1e8 samples 120 MB of the heap was free at the end
    of ``afmtool reep`` (35 MB in use).  With one arena the freed buffers
    serve every thread: peak RSS at 1e8 float32 samples reep 391 -> 341 MB,
    probeloss 414 -> 343 MB, decode 504 -> 452 MB, at the same speed (the
    threads allocate a few large blocks per chunk, so they hardly contend
    for the arena's lock).  No effect (and no error) off glibc.
    """
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD_BYTES)
        libc.mallopt(_M_TRIM_THRESHOLD, _TRIM_THRESHOLD_BYTES)
        # before any thread starts: a thread takes its arena at its first allocation
        libc.mallopt(_M_ARENA_MAX, _ARENA_MAX)
    except (OSError, AttributeError):
        pass


class _ClosedStdout:
    """Stands for a stdout the caller closed: writing to it is a one-line error (exit 2)."""

    encoding = "utf-8"
    errors = "strict"

    def write(self, text: str) -> int:
        from afmtool.errors import AfmtoolError

        if not text:
            return 0
        raise AfmtoolError("stdout is closed; nothing can be printed (redirect it, e.g. > file)")

    def flush(self) -> None:
        pass

    def isatty(self) -> bool:
        return False

    def fileno(self) -> int:
        return 1


def _occupy_closed_standard_fds() -> None:
    """Put /dev/null on a closed fd 0, 1 or 2, and make a closed stdout an error.

    A process started with a standard fd closed would otherwise hand that
    number to the next file it opens: an output file on fd 1 would receive
    whatever a library prints.  Python sets ``sys.stdin``/``sys.stdout`` to
    None then, which fails deep inside a command; stdin now reads as empty.
    """
    for fd in (0, 1, 2):
        try:
            os.fstat(fd)
        except OSError:
            opened = os.open(os.devnull, os.O_RDWR)
            if opened != fd:  # a lower fd was closed too and took it; fixed on its turn
                os.dup2(opened, fd)
                os.close(opened)
    if sys.stdin is None:
        sys.stdin = open(0, encoding="utf-8", closefd=False)  # noqa: SIM115 - lives as long as the process
    if sys.stdout is None:
        sys.stdout = _ClosedStdout()
    if sys.stderr is None:
        sys.stderr = open(2, "w", encoding="utf-8", closefd=False)  # noqa: SIM115 - lives as long as the process


def main() -> None:
    signal.signal(signal.SIGINT, _while_starting)
    signal.signal(signal.SIGTERM, _while_starting)
    _occupy_closed_standard_fds()
    _reuse_freed_memory()
    from afmtool.cli.main import main as run
    from afmtool.runtime.process import exit_now_after_success

    try:
        run()
    except SystemExit as done:
        exit_now_after_success(done.code)
        raise
    except KeyboardInterrupt:
        # a signal that landed after the run's outcome was decided (in the last
        # finalisers); Python would otherwise end the process by SIGINT
        os._exit(130)
