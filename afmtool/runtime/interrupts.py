"""SIGINT and SIGTERM: never lost, never in the middle of publishing an output folder.

The CLI's signal handler (``afmtool.cli.main``) asks :func:`interrupt_now`
whether to raise ``KeyboardInterrupt`` at once.  Inside
:func:`signals_deferred` (the swap of a finished output folder) it does
not: the signal is remembered and raised when the section ends.  Blocking
the signals with ``pthread_sigmask`` alone is not enough, because the
kernel then hands a process-directed signal to another thread (a prefetch
or hashing thread), and Python runs the handler in the main thread anyway.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["interrupt_now", "signals_deferred"]

_DEFERRED_SIGNALS = {signal.SIGINT, signal.SIGTERM}
_pending: list[int] = []
_depth = [0]


def interrupt_now(signum: int) -> bool:
    """``True`` if the handler may raise now; else the signal is kept for later."""
    if _depth[0]:
        _pending.append(signum)
        return False
    return True


@contextmanager
def signals_deferred() -> Iterator[None]:
    """Hold SIGINT and SIGTERM for the duration; one that arrived is raised on exit.

    Raises
    ------
    KeyboardInterrupt
        On leaving the section normally, if a signal arrived inside it.
    """
    main = threading.current_thread() is threading.main_thread()
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, _DEFERRED_SIGNALS) if main else None
    _depth[0] += 1
    try:
        yield
    finally:
        _depth[0] -= 1
        if previous is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, previous)  # a blocked signal runs the handler here
    if not _depth[0] and _pending:
        _pending.clear()
        raise KeyboardInterrupt
