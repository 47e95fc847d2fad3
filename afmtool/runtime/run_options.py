"""The run's global options that the lowest floors read: ``afmtool --max-samples N`` and ``afmtool --wait``.

The HDF5 readers (:mod:`afmtool.io.hdf5`, MATLAB 7.3) read ``max_samples`` as a
capture opens, and :class:`afmtool.runtime.outputs.FolderLock` reads ``wait``
as a run takes its ``--out``.  Both sit many calls below the command line:
captures open on paths that carry no reader options (overlay, theory's
captures, batch's listing of its inputs), and an output folder is made in
every command's own outputs module.  So the options travel as one frozen
:class:`RunOptions` in a :class:`contextvars.ContextVar`, set for the
duration of a run by :func:`applied`: by the CLI's root callback for the
whole command (its click context closes the scope), and by
:meth:`afmtool.api.run.RunSettings.scope` around each Python API run.

A context variable, not ``os.environ``: it is per thread and per task, it
ends with the run that set it (the next run in the same process starts from
the defaults), and it does not leak into child processes.  A child
``afmtool`` process (``afmtool batch``'s runs) is given the options on its
command line instead (:meth:`RunOptions.args`).  A thread of its own sees
the defaults; every reader and output folder opens in the run's own thread.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass

from afmtool.errors import ConfigError

__all__ = ["DEFAULTS", "RunOptions", "applied", "current"]


@dataclass(frozen=True)
class RunOptions:
    """``afmtool --max-samples N`` and ``afmtool --wait``.

    Attributes
    ----------
    max_samples : int or None
        Accept HDF5 captures of up to N samples per dataset whatever their size on disk;
        None keeps the check that a file claims at most 1000x its size.
    wait : bool
        Wait for another run writing the same ``--out`` instead of failing.
    """

    max_samples: int | None = None
    wait: bool = False

    def __post_init__(self) -> None:
        value = self.max_samples
        if value is None:
            return
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"--max-samples {value!r} must be a whole number")
        if value < 1:
            raise ConfigError(f"--max-samples {value} must be at least 1")

    def args(self) -> list[str]:
        """These options on an ``afmtool`` command line, before the command (none for the defaults)."""
        args = ["--max-samples", str(self.max_samples)] if self.max_samples is not None else []
        return args + (["--wait"] if self.wait else [])


#: The defaults, outside any run (frozen, so one instance serves every reader).
DEFAULTS = RunOptions()
_CURRENT: ContextVar[RunOptions] = ContextVar("afmtool_run_options", default=DEFAULTS)


def current() -> RunOptions:
    """The options of the run in progress (the defaults outside any run)."""
    return _CURRENT.get()


@contextmanager
def applied(options: RunOptions) -> Iterator[RunOptions]:
    """Within the block, :func:`current` is ``options``; the previous options come back after it."""
    token = _CURRENT.set(options)
    try:
        yield options
    finally:
        _CURRENT.reset(token)
