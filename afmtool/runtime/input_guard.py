"""Inputs are sacred: no output may land on an input file or inside an input folder.

Every capture (and every input folder) a run opens is recorded here with
:func:`register_input`; every output path is checked with
:func:`refuse_output_over_inputs` before anything is created.  Paths are
compared after following symlinks and ``..`` (``os.path.realpath``), and
existing files also by device and inode, which catches a hard link to an
input under another name.

The record is process-wide on purpose: the inputs are opened deep inside
``afmtool.io`` and the outputs created deep inside ``afmtool.report``, and
one run is one process.  :func:`forget_inputs` clears it (tests, batch
workers reused for several captures).
"""

from __future__ import annotations

import os
import threading
from pathlib import Path
from typing import NamedTuple

from afmtool.errors import AfmtoolError

__all__ = ["InputOverwriteError", "register_input", "refuse_output_over_inputs", "forget_inputs"]


class InputOverwriteError(AfmtoolError):
    """An output path that is, or lies inside, one of the run's inputs."""


class _Input(NamedTuple):
    real: Path  # symlinks and .. resolved
    device: int
    inode: int
    is_dir: bool


_lock = threading.Lock()
_inputs: list[_Input] = []


def _real(path: Path | str) -> Path:
    return Path(os.path.realpath(os.fspath(path)))


def register_input(path: Path | str) -> None:
    """Record ``path`` (a file or a folder, such as a ROS2 bag) as an input of this run.

    ``-`` (stdin) and paths that do not exist are ignored: there is nothing
    on disk to protect.
    """
    if os.fspath(path) in ("-", ""):
        return
    try:
        st = os.stat(path)
    except OSError:
        return
    record = _Input(_real(path), st.st_dev, st.st_ino, os.path.isdir(path))
    with _lock:
        if record not in _inputs:
            _inputs.append(record)


def forget_inputs() -> None:
    """Clear the record."""
    with _lock:
        _inputs.clear()


def _same_file(path: Path, item: _Input) -> bool:
    try:
        st = os.stat(path)
    except OSError:
        return False
    return (st.st_dev, st.st_ino) == (item.device, item.inode)


def refuse_output_over_inputs(output: Path | str, *, directory: bool = False, what: str = "output") -> None:
    """Raise :class:`InputOverwriteError` if writing ``output`` could change an input.

    Parameters
    ----------
    output : path
        A file, or with ``directory=True`` a folder that will be replaced
        as a whole.
    directory : bool
        ``output`` is a folder replaced as a whole, so an input anywhere
        inside it would be lost as well.
    what : str
        How the message names the output (``--out``, ``--output``).
    """
    real = _real(output)
    with _lock:
        inputs = list(_inputs)
    for item in inputs:
        if real == item.real or _same_file(real, item):
            raise InputOverwriteError(f"{what} {output}: is the input {item.real}; refusing to overwrite an input")
        if item.is_dir and item.real in real.parents:
            raise InputOverwriteError(f"{what} {output}: lies inside the input folder {item.real}; write elsewhere")
        if directory and real in item.real.parents:
            raise InputOverwriteError(f"{what} {output}: holds the input {item.real}; replacing it would delete the input")
