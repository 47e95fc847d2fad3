"""Read ahead: iterate a chunk stream in a background thread.

Readers spend their time in the HDF5 library or the kernel's page cache,
analyses in numba kernels that release the GIL; with the next chunk read
while the current one is computed the two overlap.  The chunks and their
order are unchanged, so results do not depend on it.
"""

from __future__ import annotations

import contextlib
import queue
import threading
from collections.abc import Iterator
from typing import TypeVar

__all__ = ["prefetch"]

T = TypeVar("T")

_DONE = object()


class _Failed:
    def __init__(self, exc: BaseException) -> None:
        self.exc = exc


def prefetch(items: Iterator[T], depth: int = 2) -> Iterator[T]:
    """Yield ``items`` in order, reading up to ``depth`` ahead in a daemon thread.

    Parameters
    ----------
    items : iterator
        Any iterator (e.g. :func:`afmtool.io.chunks.iter_chunks`).  Only the
        background thread advances it once iteration starts.
    depth : int, optional
        Items held ready, >= 1 (memory: ``depth + 2`` items at most).

    Raises
    ------
    Exception
        Whatever ``items`` raised, re-raised in the consumer at the point
        of the failing item.
    """
    if depth < 1:
        raise ValueError(f"{depth=} must be >= 1")
    ready: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def produce() -> None:
        try:
            for item in items:
                while not stop.is_set():
                    try:
                        ready.put(item, timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if stop.is_set():
                    return
            ready.put(_DONE)
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer, which re-raises it
            ready.put(_Failed(exc))

    worker = threading.Thread(target=produce, name="afmtool-prefetch", daemon=True)
    worker.start()
    try:
        while True:
            item = ready.get()
            if item is _DONE:
                return
            if isinstance(item, _Failed):
                raise item.exc
            yield item
    finally:
        stop.set()
        while worker.is_alive():
            with contextlib.suppress(queue.Empty):
                ready.get(timeout=0.05)
        worker.join()
