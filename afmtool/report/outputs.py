"""An output folder that appears complete or not at all.

Analyses write every file into a hidden staging folder beside ``--out``;
``commit`` moves each one into place with ``os.replace`` (atomic on one
filesystem).  If the run fails or is killed first, the staging folder is
removed and ``--out`` is untouched: no half-written output, ever.
"""

from __future__ import annotations

import os
import shutil
import signal
import tempfile
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from afmtool.errors import AfmtoolError

__all__ = ["OutputDir"]

_DEFERRED_SIGNALS = {signal.SIGINT, signal.SIGTERM}


@contextmanager
def _signals_deferred() -> Iterator[None]:
    """Hold SIGINT and SIGTERM for the duration; they are delivered on exit."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, _DEFERRED_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


class OutputDir:
    """Stage outputs for ``out`` and publish them together.

    Use as a context manager::

        with OutputDir(out) as staged:
            write_report(staged.path("report.json"), ...)
        # on success every staged file is now in ``out``
    """

    def __init__(self, out: Path) -> None:
        self.out = Path(out)
        if self.out.exists() and not self.out.is_dir():
            raise AfmtoolError(f"--out {self.out}: exists and is not a directory")
        self._staging: Path | None = None
        self._names: list[str] = []

    def __enter__(self) -> OutputDir:
        parent = self.out.resolve().parent
        # "created if missing" includes its parents: `--out results/reep` on a fresh checkout
        try:
            parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise AfmtoolError(f"--out {self.out}: cannot create parent folder {parent}: {exc.strerror}") from None
        self._staging = Path(tempfile.mkdtemp(prefix=f".{self.out.name}.staging-", dir=parent))
        return self

    def path(self, name: str) -> Path:
        """A path inside the staging folder for the output ``name``."""
        if self._staging is None:
            raise RuntimeError("OutputDir used outside its context")
        relative = Path(name)
        if relative.is_absolute() or ".." in relative.parts or len(relative.parts) != 1:
            raise AfmtoolError(f"output name {name!r} must be a plain file name inside --out")
        if name not in self._names:
            self._names.append(name)
        return self._staging / name

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self._names)

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if exc_type is None:
                self._commit()
        finally:
            if self._staging is not None:
                shutil.rmtree(self._staging, ignore_errors=True)
                self._staging = None

    def _commit(self) -> None:
        # SIGINT/SIGTERM wait until every file is in place: a run interrupted
        # here would otherwise leave new files beside old ones.
        with _signals_deferred():
            self._move_into_place()

    def _move_into_place(self) -> None:
        self.out.mkdir(parents=False, exist_ok=True)
        for name in self._names:
            staged = self._staging / name
            if not staged.exists():
                continue
            final = self.out / name
            if staged.is_dir():
                if final.exists():
                    shutil.rmtree(final)
                os.replace(staged, final)
            else:
                os.replace(staged, final)
