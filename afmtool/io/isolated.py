"""Run a library's parse of a hostile file in a forked child first, where a crash cannot take afmtool down.

Some parsers are C code that a damaged file can send into a segmentation
fault (scipy's MATLAB v5 reader, ``scipy.io.matlab._mio5_utils``) or an
endless loop holding the GIL (libhdf5 on a damaged global heap, see
:func:`afmtool.io.hdf5.check_attributes_terminate`).  No exception handler or
signal handler in this process can catch either; a child process can die or be
stopped instead.  The child's *exceptions* are ignored: the parent then does the
same work and reports them as usual.  Costs a fork and the work done twice.
"""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Callable

from afmtool.errors import InputError

__all__ = ["check_survives"]


def check_survives(work: Callable[[], object], where: str, what: str, timeout_s: float = 10.0) -> None:
    """Run ``work()`` in a forked child; refuse the input if the child dies by a signal or runs past ``timeout_s``.

    Raises
    ------
    InputError
        Naming ``where`` (the file) and ``what`` was being done.
    """
    if not hasattr(os, "fork"):
        return
    pid = os.fork()
    if pid == 0:  # the child: only os._exit leaves, so nothing of the parent's is flushed or cleaned twice
        try:
            signal.signal(signal.SIGINT, signal.SIG_DFL)
            signal.signal(signal.SIGTERM, signal.SIG_DFL)
            work()
        except BaseException:  # noqa: BLE001 - the parent does the work again and reports what it raises
            pass
        finally:
            os._exit(0)
    deadline, pause = time.monotonic() + timeout_s, 0.001
    try:
        while True:
            done, status = os.waitpid(pid, os.WNOHANG)
            if done:
                break
            if time.monotonic() > deadline:
                raise InputError(f"{where}: {what} did not finish in {timeout_s:g} s; the file is damaged")
            time.sleep(pause)
            pause = min(2 * pause, 0.05)
    except BaseException:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        raise
    if os.WIFSIGNALED(status):
        raise InputError(f"{where}: {what} crashed (signal {os.WTERMSIG(status)}); the file is damaged")
