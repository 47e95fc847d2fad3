"""Atomic output: a file or directory appears complete, or not at all.

Every writer in afmtool writes to a hidden temporary path next to the final
one and renames it into place only when the write has succeeded, so an
interrupted run (an error, Ctrl-C) never leaves a truncated report, image or
capture under the name the user asked for, and never destroys an earlier
good one.

The temporary path is in the same directory as the final one, so the rename
stays on one filesystem and is atomic (``os.replace``).  For a file it is
``.{name}.tmp-XXXXXXXX{suffix}``: hidden, recognisable, and still ending in
the final suffix for libraries that choose a format from it.  For a
directory (a ROS 2 bag) it is ``.{name}.tmp-XXXXXXXX/{name}``, a path that
does not exist yet and has the final name, because bag writers refuse an
existing directory and name the files inside after it.

Use :func:`atomic_path` around a write that has a beginning and an end, and
:class:`PendingPath` directly in writers that open in ``__init__`` and
finish in ``close()``.  A process killed with SIGKILL can leave a hidden
``.*.tmp-*`` entry behind; it is never mistaken for output.
"""

from __future__ import annotations

import os
import secrets
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from afmtool.errors import AfmtoolError
from afmtool.runtime.input_guard import refuse_output_over_inputs

__all__ = ["OutputError", "PendingPath", "atomic_path", "write_bytes_atomic", "write_text_atomic"]

_TOKEN_BYTES = 4
_CREATE_ATTEMPTS = 100


class OutputError(AfmtoolError):
    """An output path that cannot be written (missing directory, permissions)."""


def _fsync_path(path: Path) -> None:
    """Flush a file's data to disk (the file is opened by name, read-only on POSIX)."""
    with open(path, "rb+" if os.name == "nt" else "rb") as fh:
        os.fsync(fh.fileno())


def _fsync_dir(path: Path) -> None:
    """Flush a directory entry to disk; best effort (not possible on Windows or some filesystems)."""
    if os.name == "nt":
        return
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _fsync_tree(root: Path) -> None:
    """Flush every file under ``root``, then every directory, deepest first."""
    for dirpath, _dirnames, filenames in os.walk(root, topdown=False):
        for name in filenames:
            path = Path(dirpath, name)
            if not path.is_symlink():
                _fsync_path(path)
        _fsync_dir(Path(dirpath))


def _remove(path: Path) -> None:
    """Remove a file or directory tree if it exists; never raises."""
    try:
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)
    except OSError:
        pass


class PendingPath:
    """A temporary path that becomes ``final`` on :meth:`commit`.

    Parameters
    ----------
    final : Path
        Where the output must appear.  Its directory must exist.
    directory : bool, optional
        Produce a directory instead of a file.  :attr:`tmp` then does not
        exist yet; the writer creates it.

    Attributes
    ----------
    final : Path
        The destination.
    tmp : Path
        Where to write.  For a file it exists (empty, permissions from the
        umask) when the constructor returns.

    Raises
    ------
    OutputError
        The directory of ``final`` does not exist or is not writable, or
        ``final`` is an existing directory and ``directory`` is false.

    Notes
    -----
    A replaced file gets the new file's permissions, not the old one's.
    """

    def __init__(self, final: Path, *, directory: bool = False) -> None:
        final = Path(final)
        if final.name in ("", ".", ".."):
            raise ValueError(f"final={str(final)!r} must name a file or directory, not {final.name!r}")
        refuse_output_over_inputs(final, directory=directory)
        parent = final.parent
        if not parent.is_dir():
            raise OutputError(f"{final}: directory {parent} does not exist")
        if not directory and final.is_dir() and not final.is_symlink():
            raise OutputError(f"{final}: is a directory; refusing to replace it with a file")
        self.final = final
        self.directory = directory
        self._done = False
        if directory:
            self._box = self._make_box()
            self.tmp = self._box / final.name
        else:
            self._box = None
            self.tmp = self._make_file()

    def _make_file(self) -> Path:
        final = self.final
        for _ in range(_CREATE_ATTEMPTS):
            tmp = final.with_name(f".{final.name}.tmp-{secrets.token_hex(_TOKEN_BYTES)}{final.suffix}")
            try:
                # 0o666 so the umask decides the permissions, as for an ordinary open().
                fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
            except FileExistsError:
                continue
            except OSError as exc:
                raise OutputError(f"{final}: cannot create a file in {final.parent} ({exc.strerror})") from None
            os.close(fd)
            return tmp
        raise OutputError(f"{final}: could not find a free temporary name in {final.parent}")

    def _make_box(self) -> Path:
        final = self.final
        for _ in range(_CREATE_ATTEMPTS):
            box = final.with_name(f".{final.name}.tmp-{secrets.token_hex(_TOKEN_BYTES)}")
            try:
                box.mkdir(mode=0o700)
            except FileExistsError:
                continue
            except OSError as exc:
                raise OutputError(
                    f"{final}: cannot create a directory in {final.parent} ({exc.strerror})"
                ) from None
            return box
        raise OutputError(f"{final}: could not find a free temporary name in {final.parent}")

    def commit(self) -> None:
        """Flush the temporary output to disk and rename it to :attr:`final`.

        On failure the temporary output is removed, ``final`` is left as it
        was, and :class:`OutputError` is raised.
        """
        if self._done:
            raise RuntimeError(f"{self.final}: already committed or aborted")
        try:
            if self.directory:
                self._commit_dir()
            else:
                self._commit_file()
        except OSError as exc:
            self.abort()
            raise OutputError(f"{self.final}: could not be written ({exc.strerror or exc})") from None
        except BaseException:
            self.abort()
            raise
        self._done = True
        if self._box is not None:
            _remove(self._box)  # holds the replaced directory, if there was one
        _fsync_dir(self.final.parent)

    def _commit_file(self) -> None:
        if not self.tmp.is_file():
            raise OutputError(f"{self.final}: the writer removed its temporary file {self.tmp}")
        _fsync_path(self.tmp)
        os.replace(self.tmp, self.final)

    def _commit_dir(self) -> None:
        new, final = self.tmp, self.final
        if not new.is_dir():
            raise OutputError(f"{final}: the writer did not create the directory {new}")
        _fsync_tree(new)
        if not os.path.lexists(final):
            os.rename(new, final)
            return
        # A directory cannot be replaced in one rename: move the old one into
        # the private temporary directory, move the new one in, drop the old.
        aside = new.with_name(f"{final.name}.old")
        os.rename(final, aside)
        try:
            os.rename(new, final)
        except BaseException:
            try:
                os.rename(aside, final)
            except OSError:
                # Keep the box so abort() cannot delete the only copy of the old output.
                self._box = None
                raise OutputError(
                    f"{final}: replacing it failed and the previous version could not be put back; "
                    f"it is in {aside}"
                ) from None
            raise

    def abort(self) -> None:
        """Remove the temporary output; ``final`` is left as it was.  Idempotent."""
        if self._done:
            return
        self._done = True
        _remove(self._box if self._box is not None else self.tmp)


@contextmanager
def atomic_path(final: Path, *, directory: bool = False) -> Iterator[Path]:
    """Yield a temporary path that replaces ``final`` when the block succeeds.

    Parameters
    ----------
    final : Path
        Where the output must appear.  Its directory must exist.  An existing
        file (or, with ``directory=True``, an existing directory) is replaced.
    directory : bool, optional
        Yield a directory path that does not exist yet, for writers that
        create a directory (ROS 2 bags).

    Yields
    ------
    Path
        The temporary path to write.  A file path exists and is empty; it ends
        in ``final``'s suffix.  A directory path has ``final``'s name.

    Raises
    ------
    OutputError
        ``final`` cannot be created or renamed into place.

    Notes
    -----
    On success the file (every file, for a directory) is fsynced, then
    renamed over ``final`` with ``os.replace``.  If the block raises anything,
    including ``KeyboardInterrupt``, the temporary output is removed and the
    exception propagates unchanged; ``final`` is untouched.

    Examples
    --------
    >>> with atomic_path(Path("scan.png")) as tmp:  # doctest: +SKIP
    ...     fig.savefig(tmp)
    """
    pending = PendingPath(final, directory=directory)
    try:
        yield pending.tmp
    except BaseException:
        pending.abort()
        raise
    pending.commit()


def write_bytes_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (see :func:`atomic_path`)."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text_atomic(path: Path, text: str, *, encoding: str = "utf-8") -> None:
    """Write ``text`` to ``path`` atomically, encoded as given, line endings unchanged."""
    write_bytes_atomic(path, text.encode(encoding))
