"""Python warnings (numpy's RuntimeWarning, h5py's UserWarning) go into the report, not the terminal.

The CLI calls :func:`capture_warnings` once at start-up; from then on every
warning is recorded here instead of printed, and :func:`drain` hands the
distinct messages, with how often each came, to the report of the run
(``finish_run``).  A run that fails prints its one error line and nothing
else.
"""

from __future__ import annotations

import threading
import warnings

__all__ = ["add", "capture_warnings", "drain", "record", "take"]

_lock = threading.Lock()
_seen: dict[str, int] = {}


def _record(message, category, filename, lineno, file=None, line=None) -> None:
    text = f"{category.__name__}: {message}".strip()
    with _lock:
        _seen[text] = _seen.get(text, 0) + 1


def capture_warnings() -> None:
    """Record every warning from now on instead of printing it (the filters still decide which)."""
    warnings.showwarning = _record


def take() -> dict[str, int]:
    """The warnings recorded so far, ``{text: count}``, and forget them."""
    with _lock:
        taken = dict(_seen)
        _seen.clear()
    return taken


def add(counts: dict[str, int]) -> None:
    """Record warnings another process took (:func:`take`), e.g. the figure process's."""
    with _lock:
        for text, count in counts.items():
            _seen[text] = _seen.get(text, 0) + count


def drain() -> list[str]:
    """The distinct warnings recorded so far (with counts), and forget them."""
    return [text if count == 1 else f"{text} ({count} times)" for text, count in take().items()]


#: The recording ``showwarning`` (the Python API installs it around one run: ``afmtool.api.run.RunSettings``).
record = _record
