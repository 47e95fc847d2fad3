"""Reading a capture from stdin: say when it stalls, and end the run when told to.

A writer that sends a CSV header and then trickles bytes (or nothing) left
``afmtool info -`` waiting silently for ever.  The capture's stdin is read
through :class:`WatchedStdin`, which waits for bytes with ``select`` in
short slices, so it notices time passing even when no byte comes.  The
clock is the time since the reader last started on a chunk: when it
passes :data:`NOTICE_S` the run says ``waiting for input on stdin`` once
on stderr; when it passes the ``--stdin-timeout`` the read fails with an
:class:`~afmtool.errors.InputError` (one line, exit 2), in the main
thread, where every other read error is raised.  Time the analysis spends
between chunks is not counted: the clock restarts when the reader asks
for the next chunk (:class:`WatchedReader`).
"""

from __future__ import annotations

import io
import math
import os
import select
import time
from collections.abc import Iterator, Sequence

from afmtool.errors import ConfigError, InputError
from afmtool.io.capture import CaptureReader, Chunk, ReaderBase

__all__ = ["NOTICE_S", "WAITING_MESSAGE", "WatchedReader", "WatchedStdin", "set_stdin_timeout", "stdin_timeout"]

#: Seconds without a complete chunk after which the run says it is waiting.
NOTICE_S = 5.0
WAITING_MESSAGE = "afmtool: waiting for input on stdin"
#: How often a wait is looked at, s.
_SLICE_S = 0.25

_timeout_s: float | None = None


def set_stdin_timeout(timeout_s: float | None) -> None:
    """End runs that read stdin when it gives no complete chunk for ``timeout_s`` (None: wait for ever)."""
    global _timeout_s
    if timeout_s is not None:
        value = float(timeout_s)
        if not (math.isfinite(value) and value > 0):
            raise ConfigError(f"--stdin-timeout {timeout_s!r} must be a number of seconds > 0")
        timeout_s = value
    _timeout_s = timeout_s


def stdin_timeout() -> float | None:
    """The ``--stdin-timeout`` in force, s (None: none)."""
    return _timeout_s


class WatchedStdin(io.RawIOBase):
    """File descriptor ``fd`` (stdin) as a raw binary stream that notices stalls.

    Parameters
    ----------
    fd : int
        The descriptor to read (0).
    timeout_s : float or None
        Fail a read once this long has passed since :meth:`restart` without
        the reader finishing a chunk; None waits for ever.
    notice_s : float
        Say :data:`WAITING_MESSAGE` once after this long.
    """

    def __init__(self, fd: int = 0, timeout_s: float | None = None, notice_s: float = NOTICE_S) -> None:
        super().__init__()
        self._fd = fd
        self._timeout_s = timeout_s
        self._notice_s = notice_s
        self._noticed = False
        self._since = time.monotonic()

    def restart(self) -> None:
        """The reader starts on a new chunk: the clock starts again."""
        self._since = time.monotonic()

    def readable(self) -> bool:
        return True

    def fileno(self) -> int:
        return self._fd

    def readinto(self, buffer) -> int:
        while True:
            self._check_wait()  # bytes that trickle in do not make a chunk: the clock runs on
            try:
                ready, _, _ = select.select([self._fd], [], [], _SLICE_S)
            except (OSError, ValueError):  # not a selectable descriptor (a closed one): just read it
                ready = [self._fd]
            if ready:
                data = os.read(self._fd, len(buffer))
                buffer[: len(data)] = data
                return len(data)

    def _check_wait(self) -> None:
        waited = time.monotonic() - self._since
        if not self._noticed and waited >= self._notice_s:
            self._noticed = True
            try:
                os.write(2, (WAITING_MESSAGE + "\n").encode())
            except (OSError, ValueError, AttributeError):
                pass
        if self._timeout_s is not None and waited >= self._timeout_s:
            raise InputError(
                f"<stdin>: no complete chunk of samples in {self._timeout_s:g} s (--stdin-timeout); "
                "is the writer still running?"
            )

    def close(self) -> None:  # the process's stdin stays open
        super().close()


class WatchedReader(ReaderBase):
    """``reader`` (of stdin) whose chunks restart ``watch``'s clock each time the next one is asked for."""

    def __init__(self, reader: CaptureReader, watch: WatchedStdin) -> None:
        self._reader = reader
        self._watch = watch
        self.info = reader.info

    def blocks(self, channels: Sequence[str], block_samples: int) -> Iterator[Chunk]:
        self._watch.restart()
        for chunk in self._reader.blocks(channels, block_samples):
            yield chunk
            self._watch.restart()

    def truth(self) -> dict:
        return self._reader.truth()

    def close(self) -> None:
        self._reader.close()

    def __getattr__(self, name: str):
        return getattr(self._reader, name)
