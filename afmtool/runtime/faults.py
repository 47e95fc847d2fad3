"""Faults of the environment (disk full, read-only, permissions, names) as one-line errors.

A full disk reaches afmtool as an ``OSError`` from Python, or as an
exception from h5py whose message carries the C library's ``errno = 28``
somewhere in a multi-line libhdf5 error stack.  Either way it is not an
internal error: :func:`environment_fault` recognises it, and the CLI
prints one line naming the path and the cause, with exit status 2.
"""

from __future__ import annotations

import errno
import os
import re
import sys

__all__ = ["FAULT_ERRNOS", "close_hdf5", "environment_fault", "fault_message", "keep_until_exit", "note_swallowed"]

#: errno values that mean "the environment refused", not "afmtool is wrong".
FAULT_ERRNOS = frozenset(
    code
    for code in (
        errno.ENOSPC,
        getattr(errno, "EDQUOT", None),
        errno.EROFS,
        errno.EACCES,
        errno.EPERM,
        errno.ENAMETOOLONG,
        errno.ELOOP,
        errno.EFBIG,
        errno.EIO,
        errno.ENOTDIR,
        errno.EISDIR,
        errno.EMFILE,
        errno.ENFILE,
    )
    if code is not None
)

_ERRNO_IN_TEXT = re.compile(r"(?:errno\s*=\s*|\[Errno\s+)(\d+)")
#: Messages of libraries that carry no errno: SQLite (a ROS2 db3 bag) on a full disk or quota.
_FAULT_TEXTS = (
    ("database or disk is full", errno.ENOSPC),
    ("attempt to write a readonly database", errno.EROFS),
    ("disk i/o error", errno.EIO),
)


def environment_fault(exc: BaseException) -> int | None:
    """The errno of ``exc`` (or of an exception it wraps) if it is an environment fault."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        code = getattr(exc, "errno", None)
        if isinstance(code, int) and code in FAULT_ERRNOS:
            return code
        text = str(exc)
        match = _ERRNO_IN_TEXT.search(text)
        if match and int(match.group(1)) in FAULT_ERRNOS:
            return int(match.group(1))
        if type(exc).__module__ == "sqlite3" or type(exc).__name__ == "OperationalError":
            lowered = text.lower()
            for needle, fault in _FAULT_TEXTS:
                if needle in lowered:
                    return fault
        exc = exc.__cause__ or exc.__context__
    return None


def fault_message(exc: BaseException, code: int, where: object = None) -> str:
    """One line: the path (``exc.filename``, else ``where``) and the cause."""
    path = getattr(exc, "filename", None) or where
    cause = os.strerror(code)
    return f"{path}: {cause}" if path else cause


_kept: list[object] = []
#: Environment faults raised where Python cannot raise them (h5py's finalisers), first first.
_swallowed: list[BaseException] = []


def note_swallowed(exc: BaseException) -> None:
    """Record a fault a finaliser met: an HDF5 dataset whose cached data could not be written when it was
    dropped.  libhdf5 is then in a state where flushing the file crashed (SIGSEGV in H5D__flush_all_cb), so
    :func:`close_hdf5` neither flushes nor closes it afterwards, and raises the fault instead."""
    _swallowed.append(exc)


def keep_until_exit(*objects: object) -> None:
    """Hold ``objects`` (h5py files whose close failed, and the traceback) so no finaliser runs on them.

    Dropping an h5py object of a file that could not be flushed makes
    libhdf5 try the flush again in the finaliser, which prints a traceback
    from inside h5py and has crashed libhdf5.  The CLI ends such a run with
    ``os._exit`` after its one-line error, so these are never finalised.
    The traceback is kept too: h5py's ``File.close`` holds the ids it could
    not close in its own frame.
    """
    _kept.extend(objects)


def close_hdf5(handle: object, *objects: object, failed: bool = False) -> None:
    """Close an HDF5 file being written, never where libhdf5 can crash.

    A file whose write already failed (``failed``: an exception is leaving
    the writer, a full disk most often) is not closed at all: closing it
    makes libhdf5 flush again, and it crashed there (SIGSEGV in
    ``H5Fclose``, reep on a force curve at 4 KiB free).  It is kept from
    every finaliser instead (:func:`keep_until_exit`); it lies in a staging
    folder or a temporary file that the failed run removes, and the run ends
    by ``os._exit``.  Otherwise the file is flushed first: a flush that
    fails (the library failing inside its own flush) raises here, and the
    file is kept the same way, unclosed; after a good flush, close has
    nothing left to write.
    """
    if failed or _swallowed:
        keep_until_exit(handle, *objects)
        if not failed:  # a write failed in a finaliser (h5py dropping a dataset): raise it now
            code = environment_fault(_swallowed[0]) or errno.EIO
            raise OSError(code, os.strerror(code), getattr(handle, "filename", None))
        return
    try:
        handle.flush()
    except BaseException:
        keep_until_exit(handle, *objects, sys.exc_info()[2])
        raise
    try:
        handle.close()
    except BaseException:
        keep_until_exit(handle, *objects, sys.exc_info()[2])
        raise
