"""Error classes shared by every afmtool layer.

Anything the user can fix (a wrong path, a malformed file, a bad parameter)
is raised as an :class:`AfmtoolError`; the CLI turns it into a one-line
message on stderr and exit status 2.  Third-party exceptions are converted
at the I/O boundary with ``raise ... from None`` so the message names the
user's file, not a library internal.
"""

__all__ = ["AfmtoolError", "InputError", "ConfigError"]


class AfmtoolError(Exception):
    """Bad input or usage; the CLI maps it to exit status 2."""


class InputError(AfmtoolError):
    """A capture, table or channel that cannot be read as asked."""


class ConfigError(AfmtoolError):
    """A parameter, config file or flag value that is not valid."""
