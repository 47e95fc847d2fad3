"""The compile options of every numba kernel, on the ground floor (issue 29, item 4).

``models/``, ``estimators/`` and ``sim/`` all compile kernels; the one
constant lives here, below all of them, so that no floor imports upward to
reach it (docs/architecture.md, "Floors").  This module imports nothing.
"""

__all__ = ["JIT_OPTIONS"]

#: Compile options of every kernel in the tree, kept in one constant (a test
#: checks that every ``@njit`` uses it, and only it).
#:
#: * ``cache``: compiled kernels are kept on disk, so a command starts in
#:   a fraction of a second after the first run.
#: * ``nogil``: kernels release the GIL, so the read-ahead and side-kernel
#:   threads of the streaming commands run beside them.
#: * ``error_model="numpy"``: a division by zero gives inf or NaN, as IEEE 754
#:   and numpy say, instead of raising ZeroDivisionError from inside a
#:   kernel; the wrappers validate their arguments, and a NaN sample must
#:   flow through a recursion the way it does through the plain-Python
#:   references.
#: * No ``fastmath``: NaN and inf must propagate, and ``contract``/``reassoc``
#:   would make the numba results differ from the plain-Python references.
#:
#: Never change it at run time: the on-disk cache is keyed on these options.
JIT_OPTIONS = {"cache": True, "nogil": True, "error_model": "numpy"}
