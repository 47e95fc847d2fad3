"""An output folder that appears complete or not at all, written by one run at a time.

Analyses write every file into a hidden staging folder beside ``--out``.
On success the staging folder is flushed to disk (every file, then the
folders) and swapped with ``--out`` in one ``renameat2(RENAME_EXCHANGE)``:
at every instant ``--out`` is the complete old folder or the complete new
one, and afterwards it holds exactly this run's files.  The old folder,
now at the staging name, is deleted only after the swap has succeeded.
(Where the exchange is not supported, the old folder is renamed aside
first and put back by the next run if a kill lands between the two
renames.)

A run holds an exclusive ``flock`` on ``.<name>.lock`` beside ``--out``
from start to finish (the file exists only meanwhile): a second run on the
same folder fails at once, or waits with ``afmtool --wait`` (the run's
:mod:`afmtool.runtime.run_options`, or :class:`FolderLock`'s ``wait``).  Under that lock the run first removes the
staging folders that killed runs left behind.

An existing ``--out`` is replaced as a whole, so it must be an afmtool
output folder (it holds ``report.json``) or empty: ``--out .`` in a home
folder is refused rather than emptied.
"""

from __future__ import annotations

import ctypes
import errno
import hashlib
import os
import shutil
import tempfile
import threading
from pathlib import Path

from afmtool.errors import AfmtoolError
from afmtool.runtime import run_options
from afmtool.runtime.atomic import OutputError, _fsync_dir, _fsync_path, _fsync_tree
from afmtool.runtime.faults import environment_fault
from afmtool.runtime.input_guard import refuse_output_over_inputs
from afmtool.runtime.interrupts import signals_deferred

__all__ = ["FolderLock", "OutputDir"]

_STAGING = ".staging-"
_ASIDE = ".old-"
#: The staging folder's scratch folder (:meth:`OutputDir.scratch_folder`), removed before the commit.
_SCRATCH = ".scratch"
#: Characters the staging name adds to the key: "." + key + ".staging-" + 8 random + slack.
_STAGING_EXTRA = 1 + len(_STAGING) + 8 + 8
_NAME_MAX = 255
_AT_FDCWD = -100
_RENAME_EXCHANGE = 2


def _exchange(a: Path, b: Path) -> bool:
    """Swap ``a`` and ``b`` atomically (Linux ``renameat2``); ``False`` where unsupported."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    if renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    code = ctypes.get_errno()
    if code in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP, errno.ENOTSUP):
        return False
    raise OSError(code, os.strerror(code), str(b))


def _key_for(name: str) -> str:
    """The name the lock and staging folders are made from: long names are hashed, so the
    staging prefix never exceeds NAME_MAX."""
    if len(os.fsencode(name)) + _STAGING_EXTRA > _NAME_MAX:
        return hashlib.sha256(os.fsencode(name)).hexdigest()[:32]
    return name


def _describe(exc: OSError) -> str:
    return exc.strerror or str(exc)


class OutputDir:
    """Stage outputs for ``out`` and publish them together.

    Use as a context manager::

        with OutputDir(out) as staged:
            write_report(staged.path("report.json"), ...)
        # on success ``out`` holds exactly the staged files

    Raises
    ------
    OutputError
        ``out`` is empty, a dangling symlink, a file, a folder that is not
        an afmtool output, an input (or holds or lies in one), locked by
        another run, or cannot be created, staged or swapped in.
    """

    def __init__(self, out: Path) -> None:
        if not os.fspath(out).strip():
            raise OutputError("--out '': give a folder name")
        self.out = Path(out)
        if self.out.is_symlink() and not self.out.exists():
            raise OutputError(f"--out {self.out}: is a dangling symbolic link")
        if self.out.exists() and not self.out.is_dir():
            raise OutputError(f"--out {self.out}: exists and is not a directory")
        # The swap happens where the folder really is (through a symlinked --out or parent).
        self._final = Path(os.path.realpath(self.out))
        name = self._final.name
        if not name:
            raise OutputError(f"--out {self.out}: is the file-system root")
        cwd = Path(os.path.realpath(os.getcwd()))
        if self._final == cwd or self._final in cwd.parents:
            # typer reads --out "" as "."; the folder is replaced as a whole, so never the one we are in
            raise OutputError(f"--out {os.fspath(out)!r}: is the current folder or holds it; name a folder for the outputs")
        if len(os.fsencode(name)) > _NAME_MAX:
            raise OutputError(f"--out {self.out}: file name too long ({len(os.fsencode(name))} bytes, at most {_NAME_MAX})")
        self._key = _key_for(name)
        self._staging: Path | None = None
        self._folder_lock: FolderLock | None = None
        self._created: list[Path] = []
        self._names: list[str] = []
        self._flushing: list[_EarlyFlush] = []

    # -- set-up ---------------------------------------------------------------------------

    def __enter__(self) -> OutputDir:
        refuse_output_over_inputs(self._final, directory=True, what="--out")
        self._refuse_foreign_folder()
        try:
            self._make_parents()
            self._lock()
            self._remove_stale()
            self._staging = Path(tempfile.mkdtemp(prefix=f".{self._key}{_STAGING}", dir=self._final.parent))
        except OSError as exc:
            self._release(failed=True)
            raise OutputError(f"--out {self.out}: {_describe(exc)} ({exc.filename or self._final.parent})") from None
        except BaseException:
            self._release(failed=True)
            raise
        return self

    def _refuse_foreign_folder(self) -> None:
        final = self._final
        try:
            ours = (final / "report.json").is_file() or (final / "failure.json").is_file()  # failure: afmtool batch
            if final.is_dir() and not ours and any(final.iterdir()):
                raise OutputError(
                    f"--out {self.out}: exists and is not an afmtool output folder (no report.json); "
                    "refusing to replace it"
                )
        except OSError as exc:
            raise OutputError(f"--out {self.out}: {_describe(exc)}") from None

    def _make_parents(self) -> None:
        """Create missing parent folders, remembering them so a failed run removes them."""
        missing = []
        parent = self._final.parent
        while not parent.exists():
            missing.append(parent)
            parent = parent.parent
        for folder in reversed(missing):
            folder.mkdir()
            self._created.append(folder)

    def _lock(self) -> None:
        self._folder_lock = FolderLock(self._final, self.out, key=self._key)
        self._folder_lock.acquire()

    def _remove_stale(self) -> None:
        """Under the lock: drop what killed runs left; restore a folder a kill left aside."""
        parent, final = self._final.parent, self._final
        for entry in sorted(parent.iterdir()):
            if entry.name.startswith(f".{self._key}{_ASIDE}") and entry.is_dir() and not entry.is_symlink():
                old = entry / "old"
                if old.is_dir() and not os.path.lexists(final):
                    os.rename(old, final)  # killed between the two renames of the fallback swap
                shutil.rmtree(entry, ignore_errors=True)
            elif entry.name.startswith(f".{self._key}{_STAGING}") and entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry, ignore_errors=True)

    # -- use --------------------------------------------------------------------------------

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

    def scratch_folder(self) -> Path:
        """A folder for a run's own scratch files, on the outputs' disk; never published.

        Whatever is left in it is removed with the staging folder, and it is
        removed before the commit, so a scratch file never reaches ``--out``.
        """
        if self._staging is None:
            raise RuntimeError("OutputDir used outside its context")
        folder = self._staging / _SCRATCH
        folder.mkdir(exist_ok=True)
        return folder

    @property
    def names(self) -> tuple[str, ...]:
        """The outputs named so far that exist (a figure skipped for want of data is not one)."""
        if self._staging is None:
            return tuple(self._names)
        return tuple(name for name in self._names if os.path.lexists(self._staging / name))

    def flush_early(self, name: str) -> None:
        """Start flushing the finished output ``name`` to disk now, beside the rest of the run.

        The commit flushes every file before the swap.  For a result file of
        a gigabyte that took 0.8 s at the end of ``afmtool kalman-bank``,
        after the figures.  Once ``name`` is written, its flush can run in a
        thread (``fsync`` releases the GIL) while the figures are drawn; the
        commit waits for it and raises its error, and the commit's own flush
        of the file then finds little left to write.  A later change to the
        file is flushed by the commit as before.
        """
        flush = _EarlyFlush(self.path(name))
        flush.start()
        self._flushing.append(flush)

    # -- finish -----------------------------------------------------------------------------

    def __exit__(self, exc_type, exc, tb) -> None:
        committed = False
        try:
            code = environment_fault(exc) if exc is not None and not isinstance(exc, AfmtoolError) else None
            if code is not None:
                # a full disk (or a read-only one...) while the analysis wrote into staging
                raise OutputError(f"--out {self.out}: could not be written ({os.strerror(code)})") from None
            if exc_type is None:
                try:
                    self._commit()
                except (OSError, RuntimeError) as error:
                    if isinstance(error, RuntimeError) and environment_fault(error) is None:
                        raise
                    raise OutputError(
                        f"--out {self.out}: could not be written ({_describe(error)}, {error.filename or self._final})"
                    ) from None
                committed = True
        finally:
            if self._staging is not None:
                shutil.rmtree(self._staging, ignore_errors=True)
                self._staging = None
            self._release(failed=not committed)

    def _release(self, *, failed: bool) -> None:
        if self._folder_lock is not None:
            self._folder_lock.release()
            self._folder_lock = None
        if failed:
            for folder in reversed(self._created):
                try:
                    folder.rmdir()
                except OSError:
                    break
            self._created = []

    def _commit(self) -> None:
        # SIGINT/SIGTERM wait until the swap is done; a kill at any point leaves the old
        # folder or the new one (and a staging folder the next run removes).
        with signals_deferred():
            self._swap_into_place()

    def _swap_into_place(self) -> None:
        staging, final = self._staging, self._final
        wanted = set(self._names)
        for entry in staging.iterdir():  # only the outputs this run named
            if entry.name not in wanted:
                shutil.rmtree(entry) if entry.is_dir() and not entry.is_symlink() else entry.unlink()
        staging.chmod(0o777 & ~_umask())
        for flush in self._flushing:
            flush.wait()
        _fsync_tree(staging)
        if not os.path.lexists(final):
            os.rename(staging, final)
        elif _exchange(staging, final):
            shutil.rmtree(staging, ignore_errors=True)  # now the old folder
        else:
            aside = Path(tempfile.mkdtemp(prefix=f".{self._key}{_ASIDE}", dir=final.parent))
            os.rename(final, aside / "old")
            os.rename(staging, final)
            shutil.rmtree(aside, ignore_errors=True)
        self._staging = None
        _fsync_dir(final.parent)


class _EarlyFlush:
    """``fsync`` of one staged file in a daemon thread; :meth:`wait` joins it and raises its error.

    The error must reach the commit: after a failed ``fsync`` Linux may
    report the next one on the same file as a success, though the data
    never reached the disk.
    """

    def __init__(self, path: Path) -> None:
        self._path = path
        self._error: OSError | None = None
        self._thread = threading.Thread(target=self._run, name="afmtool-flush", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        try:
            _fsync_path(self._path)
        except OSError as error:
            self._error = error

    def wait(self) -> None:
        self._thread.join()
        if self._error is not None:
            raise self._error


class FolderLock:
    """An exclusive ``flock`` on ``.<key>.lock`` beside the folder ``final``, held by one run at a time.

    The lock file exists only while a run holds it: the holder deletes it
    before it lets go, so a waiter may wake up holding a file nobody can
    see any more; it then tries again on the new one (the file at the path
    must be the one it locked).  ``afmtool --wait`` waits for the holder
    instead of failing: ``wait``, or when None the run's own option
    (:func:`afmtool.runtime.run_options.current`).  ``out`` is how messages
    name the folder.  Used by :class:`OutputDir` and by ``afmtool batch``
    for its whole ``--out``.
    """

    def __init__(self, final: Path, out: Path | str, *, key: str | None = None, wait: bool | None = None) -> None:
        self.path = Path(final).parent / f".{key or _key_for(Path(final).name)}.lock"
        self._out = out
        self._wait = wait
        self._fd: int | None = None

    def acquire(self) -> None:
        import fcntl

        wait = run_options.current().wait if self._wait is None else self._wait
        while True:
            fd = _open_lock(self.path, self._out)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX if wait else fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                raise OutputError(
                    f"--out {self._out}: another afmtool run is writing this folder; wait for it, or give afmtool --wait"
                ) from None
            except BaseException:
                os.close(fd)
                raise
            try:
                same = os.stat(self.path, follow_symlinks=False).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if same:
                self._fd = fd
                return
            os.close(fd)  # the previous holder removed it while we waited

    def release(self) -> None:
        """Delete the lock file while still holding it, then let go.  Idempotent."""
        if self._fd is None:
            return
        try:
            self.path.unlink()
        except OSError:
            pass
        os.close(self._fd)  # releases the flock
        self._fd = None

    def __enter__(self) -> FolderLock:
        self.acquire()
        return self

    def __exit__(self, *exc) -> None:
        self.release()


def _open_lock(path: Path, out: Path | str) -> int:
    """Open (creating it if need be) the lock file ``path``, never through a link planted there.

    ``O_NOFOLLOW`` makes the open fail on a symbolic link, dangling or not,
    so the file is created in ``--out``'s parent and nowhere else; a lock
    that is not a plain file (a FIFO, a device, a folder) is refused too,
    before anything is written or locked through it.
    """
    import stat

    flags = os.O_RDWR | os.O_CREAT | os.O_CLOEXEC | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0)
    if os.path.islink(path):
        raise OutputError(f"--out {out}: the lock {path} is a symbolic link; refusing to follow it (remove it)")
    try:
        fd = os.open(path, flags, 0o666)
    except OSError as exc:
        if exc.errno == errno.ELOOP or os.path.islink(path):  # planted between the check and the open
            raise OutputError(f"--out {out}: the lock {path} is a symbolic link; refusing to follow it (remove it)") from None
        raise
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise OutputError(f"--out {out}: the lock {path} is not a plain file; refusing to use it (remove it)")
    return fd


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
