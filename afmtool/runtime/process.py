"""The process around a run: one outcome line, signals that unwind it, and the way it exits (issue 29, item 4).

The CLI (:func:`afmtool.cli.main.main`) calls these; they are the run's
infrastructure, not its wiring:

* one outcome line per run: the first of an error (:func:`error`) and
  "interrupted" (:meth:`Signals.report`) is printed, never both;
* SIGINT and SIGTERM unwind the run as KeyboardInterrupt, so staged outputs
  are cleaned up, and end the process within :data:`INTERRUPT_DEADLINE_S`
  whatever it is doing (:func:`install_handlers`);
* the exit: without the interpreter's teardown when it is unsafe
  (:func:`exit_now_if_teardown_unsafe`) or needless
  (:func:`exit_now_after_success`).
"""

from __future__ import annotations

import os
import signal
import sys
import threading

__all__ = [
    "INTERRUPT_DEADLINE_S", "Signals", "after_run", "claim_outcome", "error", "exit_now_after_success",
    "exit_now_if_teardown_unsafe", "give_up", "install_handlers", "new_run",
]


#: Held once the run's one outcome line (an error, or "interrupted") is on its way to stderr; a new one per run.
_OUTCOME = threading.Lock()
#: The exit status of the error line printed, if one was.
_ERROR_CODE: list[int] = []


def claim_outcome() -> bool:
    """Whether this caller is the one to print the run's outcome (the first to ask)."""
    return _OUTCOME.acquire(blocking=False)


def error(message: str, code: int) -> None:
    """Print the run's one error line (unless \"interrupted\" was printed) and exit with ``code``."""
    first_line = str(message).strip().splitlines()[0] if str(message).strip() else "error"
    if not claim_outcome():
        # "interrupted" is printed already: a refusal the interrupt raised on its way out adds no line
        sys.exit(130)
    if threading.current_thread() is threading.main_thread():
        # a SIGTERM now must not add "interrupted" after the one error line (huge_claim refused during a SIGTERM)
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
    _ERROR_CODE.append(code)
    print(f"afmtool: error: {first_line}", file=sys.stderr)
    sys.exit(code)


#: After a SIGINT or SIGTERM the process ends within this time, s, whatever it is doing.
INTERRUPT_DEADLINE_S = 1.5


class Signals:
    """What the handlers saw: signals received, interrupts raised and swallowed."""

    def __init__(self) -> None:
        self.received: list[int] = []
        self.raised = 0
        self.swallowed = 0
        self.reported = False
        self.deadline: threading.Timer | None = None

    def __bool__(self) -> bool:
        return bool(self.received)

    def report(self) -> None:
        if not self.reported:
            self.reported = True
            if claim_outcome():  # not after an error line
                os.write(2, b"afmtool: interrupted\n")


def give_up(state: Signals) -> None:
    # The unwinding did not finish in time (a signal swallowed where nothing can unwind, a
    # long call into a library): end the process. Outputs are staged; the next run removes
    # what this one leaves, and --out is the old folder or the new one.
    state.report()
    os._exit(_ERROR_CODE[0] if _ERROR_CODE else 130)  # an error line printed already keeps its status


def install_handlers(state: Signals) -> None:
    """SIGINT and SIGTERM unwind the run as KeyboardInterrupt; finalisers and faults print nothing after the outcome."""
    from afmtool.runtime.faults import environment_fault
    from afmtool.runtime.interrupts import interrupt_now

    # SIGINT and SIGTERM unwind as KeyboardInterrupt, so staged outputs are cleaned up.
    def interrupt(signum, frame) -> None:
        state.received.append(signum)
        if state.deadline is None:
            state.deadline = threading.Timer(INTERRUPT_DEADLINE_S, give_up, (state,))
            state.deadline.daemon = True
            state.deadline.start()
        if state.raised > state.swallowed or state.reported:
            return  # one interrupt is already unwinding the run, or the run has ended
        if interrupt_now(signum):
            state.raised += 1
            raise KeyboardInterrupt

    signal.signal(signal.SIGINT, interrupt)
    signal.signal(signal.SIGTERM, interrupt)
    default_unraisable = sys.unraisablehook

    def unraisable(info) -> None:
        # A signal that lands in a finaliser or weakref callback (h5py closes objects in
        # them) cannot unwind anything there; Python would print it as 'Exception ignored'.
        # Deliver the signal again a moment later, where it can unwind the run.
        if info.exc_value is not None and environment_fault(info.exc_value) is not None:
            # h5py dropping an object of a file the disk has no room for: remembered, so the
            # file is never flushed again (runtime.faults.close_hdf5), and reported as one line
            from afmtool.runtime.faults import note_swallowed

            note_swallowed(info.exc_value)
            return
        if info.exc_type is not None and issubclass(info.exc_type, KeyboardInterrupt):
            state.swallowed += 1
            signum = state.received[-1] if state.received else signal.SIGINT
            again = threading.Timer(0.01, os.kill, (os.getpid(), signum))
            again.daemon = True
            again.start()
            return
        default_unraisable(info)

    sys.unraisablehook = unraisable
    default_excepthook = sys.excepthook

    def excepthook(exc_type, exc, tb) -> None:
        # Cython finalisers (h5py's ObjectID) print through sys.excepthook before the
        # unraisable hook; a full disk is reported once, as the run's one line.
        if exc is not None and environment_fault(exc) is not None:
            return
        default_excepthook(exc_type, exc, tb)

    sys.excepthook = excepthook


def new_run() -> Signals:
    """Fresh outcome state for a run (main runs more than once in a test process) and its signal record."""
    global _OUTCOME
    _OUTCOME = threading.Lock()  # one outcome line per run
    _ERROR_CODE.clear()
    return Signals()


def after_run() -> None:
    """Once the outcome is printed: signals are ignored and finalisers print nothing."""
    # Outputs are committed or cleaned up by now, and the outcome printed: a signal
    # during interpreter shutdown (or one re-delivered late) changes nothing.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    # The run has reported its outcome in one line; what finalisers meet while the
    # interpreter tears down (h5py objects on a full disk) is not printed after it.
    sys.unraisablehook = _silent


def _silent(info) -> None:
    return


def _hdf5_files_open() -> bool:
    """Whether h5py still holds a file open (one a failed write could not close)."""
    h5py = sys.modules.get("h5py")
    if h5py is None:
        return False
    try:
        return bool(h5py.h5f.get_obj_ids(types=h5py.h5f.OBJ_FILE))
    except Exception:  # noqa: BLE001 - asking must never fail the exit
        return True


def _hdf5_objects_open() -> bool:
    """Whether libhdf5 still holds any file, dataset, group or attribute open.

    A dataset left open after its file was closed is freed by libhdf5's own
    exit handler, and that crashed (SIGSEGV in ``H5D_close`` from
    ``H5_term_library``) after a failed ``theory fit`` on a full disk.
    """
    h5py = sys.modules.get("h5py")
    if h5py is None:
        return False
    try:
        kinds = h5py.h5f.OBJ_FILE | h5py.h5f.OBJ_DATASET | h5py.h5f.OBJ_GROUP | h5py.h5f.OBJ_ATTR
        return bool(h5py.h5f.get_obj_ids(types=kinds))
    except Exception:  # noqa: BLE001 - asking must never fail the exit
        return True


def _threads_still_running() -> bool:
    """Whether a helper thread (the input hash, a read-ahead) outlived the failed run."""
    main_thread = threading.main_thread()
    return any(t is not main_thread and t.is_alive() for t in threading.enumerate())


def exit_now_if_teardown_unsafe(code: object) -> None:
    """End a failed run without the interpreter's teardown when it is not safe.

    Two states make teardown unsafe.  A daemon thread still inside C code
    that released the GIL (hashlib on a large block, an HDF5 read) when an
    interrupt ends the run: CPython finalises around it, and the thread's
    return into the interpreter aborted the process (SIGABRT, "PyThreadState_Get:
    the function must be called with the GIL held") in about 1 in 40 SIGTERMs.
    And an HDF5 file that is still open.

    A file whose flush failed (a full disk) cannot be closed: libhdf5 tries
    the flush again, in h5py's finalisers at teardown or in an explicit
    close, and has crashed there (SIGSEGV, SIGBUS).  The run's outcome is
    decided and printed, its outputs are staged and removed, so nothing is
    lost by skipping teardown: flush Python's own streams and leave.
    """
    if code in (0, None):
        return
    if not (_hdf5_objects_open() or _threads_still_running()):
        return
    flush_and_exit(code if isinstance(code, int) else 1)


def exit_now_after_success(code: object) -> None:
    """End a successful console-script run without the interpreter's teardown, when nothing needs it.

    Teardown finalises every module and object: numba's LLVM objects,
    matplotlib, h5py.  That took 0.4-0.6 s after each command (``reep`` on
    the 25,000-sample sample data: 2.3 s in all, 0.55 s of it after the
    outputs were committed), and it does nothing for afmtool's outputs,
    which are written, closed and moved into place by now.  It is skipped
    unless something could still need it: an HDF5 file open (a result file
    would be flushed on close), a non-daemon thread alive (Python would
    wait for it) or a child process alive (multiprocessing would end it).

    Only the console script calls this; a caller of :func:`main` in its own
    process goes on after it returns.
    """
    if code not in (0, None) or _hdf5_files_open():
        return
    main_thread = threading.main_thread()
    if any(t is not main_thread and t.is_alive() and not t.daemon for t in threading.enumerate()):
        return
    multiprocessing = sys.modules.get("multiprocessing")
    if multiprocessing is not None and multiprocessing.active_children():
        return
    flush_and_exit(0)


def flush_and_exit(code: int) -> None:
    """Flush Python's own streams and end the process at once (``os._exit``)."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(code)
