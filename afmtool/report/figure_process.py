"""Figures drawn by a forked helper process while the analysis runs.

Importing matplotlib and drawing the first figure took 0.8 s at the end of
``afmtool reep`` on the 25,000-sample sample data, 40 % of the run.  All of
it is Python holding the GIL, so a thread cannot overlap it with the
command's own start-up (numba's, about as long); a second process can.  A
command forks the helper as it starts (:meth:`FigureProcess.start`).  The
helper imports matplotlib and draws a throw-away figure while the command
imports numba and analyses; the command then hands it each figure as a
module-level function with its arguments (:meth:`FigureProcess.draw`), goes
on with its report, and waits for the figures before its outputs are
committed (:meth:`FigureProcess.wait`).

The helper draws only what it is sent, into the paths it is sent, reads no
HDF5 file, and leaves by ``os._exit``: nothing inherited is flushed or
closed twice.  It ignores SIGINT, which reaches the whole process group,
and ends when the command closes its end of the pipe (also when the command
dies).  A figure's error, or a warning it raised, comes back and is raised
or reported by the command, as if the figure had been drawn there.

Where ``fork`` is missing (Windows) or unwise (macOS), or when other threads
already run in this process (a notebook, a Dask worker), the figures are drawn
in this process, as before.  (A pytest-xdist worker has only its main thread:
the CLI tests run in process fork the helper too.)
"""

from __future__ import annotations

import gc
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from afmtool.report.captured_warnings import add, take

__all__ = ["FigureProcess", "FigureSkippedWarning", "NothingToDraw", "draw_or_skip", "skipped_when_empty"]


class NothingToDraw(ValueError):
    """A figure whose data are empty (no rows after decimation, no bins, no curve): it is skipped, not an error."""


class FigureSkippedWarning(UserWarning):
    """A figure was not drawn because it had nothing to draw; the run's other outputs stand."""


def draw_or_skip(function: Callable[..., None], args: tuple, kwargs: dict) -> None:
    """``function(*args, **kwargs)``; a figure with nothing to draw becomes a warning, and no file.

    A capture decimated to no rows (``--decimate`` past its length), or
    sampled so fast that no drive period fits, left an empty figure that
    failed the whole run at its end.  The figure's path is its first
    argument, by convention of every figure writer.
    """
    import warnings

    try:
        function(*args, **kwargs)
    except NothingToDraw as empty:
        target = args[0] if args else kwargs.get("path")
        name = os.path.basename(os.fspath(target)) if isinstance(target, (str, os.PathLike)) else function.__name__
        warnings.warn(f"{name} not drawn: nothing to draw ({empty})", FigureSkippedWarning, stacklevel=2)


def skipped_when_empty(function: Callable[..., None]) -> Callable[..., None]:
    """A figure writer that skips, with a :class:`FigureSkippedWarning`, a figure with nothing to draw."""
    import functools

    @functools.wraps(function)
    def writer(*args: Any, **kwargs: Any) -> None:
        draw_or_skip(function, args, kwargs)

    return writer


class FigureProcess:
    """Draw figures in a forked helper (or, without one, in this process).

    Use :meth:`start` as a context manager around the command; the helper is
    reaped on exit, and killed first if the command failed.
    """

    def __init__(self, connection: Any = None, pid: int | None = None) -> None:
        self._connection = connection
        self._pid = pid
        self._pending = 0

    @classmethod
    def start(cls) -> FigureProcess:
        """Fork the helper now, if this process can fork safely; otherwise draw in this process."""
        if not sys.platform.startswith("linux") or threading.active_count() > 1:
            return cls()
        from multiprocessing.connection import Pipe

        ours, theirs = Pipe()
        # the helper's garbage collector then leaves the inherited objects alone, and their
        # pages shared with this process instead of copying every one it walks
        gc.freeze()
        pid = os.fork()
        if pid == 0:
            code = 0
            try:
                ours.close()
                _serve(theirs)
            except BaseException:  # noqa: BLE001 - the command sees the pipe close and reports it
                code = 1
            finally:
                os._exit(code)
        gc.unfreeze()
        theirs.close()
        return cls(ours, pid)

    @property
    def forked(self) -> bool:
        """Whether figures go to a helper process."""
        return self._connection is not None

    def on_stream_start(self) -> None:
        """Without a helper, start importing matplotlib in a thread as the stream starts."""
        if not self.forked:
            from afmtool.report.images import start_matplotlib_import

            start_matplotlib_import()

    def draw(self, function: Callable[..., None], /, *args: Any, **kwargs: Any) -> None:
        """``function(*args, **kwargs)``, by the helper (it must pickle: a module-level function)."""
        if not self.forked:
            draw_or_skip(function, args, kwargs)
            return
        self._connection.send((function, args, kwargs))
        self._pending += 1

    def wait(self) -> None:
        """Wait for every figure sent; record their warnings; raise the first error one met."""
        error = None
        while self._pending:
            try:
                failure, warnings_seen = self._connection.recv()
            except (EOFError, OSError):
                self._pending = 0
                raise RuntimeError("the figure process ended before drawing every figure") from None
            self._pending -= 1
            add(warnings_seen)
            error = error or failure
        if error is not None:
            raise error

    @contextmanager
    def stopped_on_failure(self) -> Iterator[None]:
        """Kill the helper at once if the block fails, before the caller cleans up.

        Use it inside the output folder's context (``with OutputDir(out) as
        staged, figures.stopped_on_failure():``): a helper still drawing would
        otherwise write a PNG into the staging folder while the failed run
        removes it, and leave the folder behind.
        """
        try:
            yield
        except BaseException:
            self.close(kill=True)
            raise

    def close(self, *, kill: bool = False) -> None:
        """Close the pipe (the helper then leaves) and reap the helper; ``kill`` it first."""
        if not self.forked:
            return
        if kill:
            try:
                os.kill(self._pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        self._connection.close()
        self._connection = None
        try:
            os.waitpid(self._pid, 0)
        except ChildProcessError:
            pass

    def __enter__(self) -> FigureProcess:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close(kill=exc_type is not None)


def _serve(connection) -> None:
    """The helper's life: warm matplotlib up, then draw what arrives until the pipe closes."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    # let go of the command's stdin and stdout: a pipe's other end sees its end when the command's closes
    devnull = os.open(os.devnull, os.O_RDWR)
    os.dup2(devnull, 0)
    os.dup2(devnull, 1)
    os.close(devnull)
    take()  # the command's own warnings, inherited: the command reports them
    from afmtool.report.images import warm_up_figures

    try:
        warm_up_figures()
    except Exception:  # noqa: BLE001 - the first real figure meets it again and reports it
        pass
    take()
    while True:
        try:
            function, args, kwargs = connection.recv()
        except EOFError:
            return
        failure = None
        try:
            draw_or_skip(function, args, kwargs)
        except Exception as exc:  # noqa: BLE001 - sent back and raised by the command
            failure = exc
        seen = take()
        try:
            connection.send((failure, seen))
        except Exception:  # noqa: BLE001 - an error that does not pickle goes back as its text
            connection.send((RuntimeError(f"{type(failure).__name__}: {failure}"), seen))
