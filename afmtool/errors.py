"""Error classes shared by every afmtool layer.

Anything the user can fix (a wrong path, a malformed file, a bad parameter)
is raised as an :class:`AfmtoolError`; the CLI turns it into a one-line
message on stderr and exit status 2.  Third-party exceptions are converted
at the I/O boundary with ``raise ... from None`` so the message names the
user's file, not a library internal.
"""

__all__ = ["AfmtoolError", "InputError", "ConfigError", "SelectionNeeded", "SegmentsAtDifferentRates", "SampleShareWarning",
           "CaptureWarning", "one_line"]


class AfmtoolError(Exception):
    """Bad input or usage; the CLI maps it to exit status 2.

    The message is kept to one line: control characters that come from the
    input itself (a topic name with a newline in a damaged bag, say) are
    written as escapes, so the user sees all of it on one line.
    """

    def __init__(self, message: object = "", *args: object) -> None:
        super().__init__(one_line(str(message)), *args)


def one_line(text: str) -> str:
    """``text`` stripped, with its control characters (newlines too) written as escapes."""
    text = text.strip()
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


class InputError(AfmtoolError):
    """A capture, table or channel that cannot be read as asked."""


class ConfigError(AfmtoolError):
    """A parameter, config file or flag value that is not valid."""


class SelectionNeeded(InputError):
    """A file that holds several captures which cannot be read as one: one must be chosen.

    ``option`` is the flag that chooses (``--segment``, ``--curve``, ``--group``) and
    ``choices`` the values it takes, one per capture, so that ``info`` can describe or
    summarise each one instead; ``listing`` describes the file's captures (JSON-ready).
    """

    def __init__(self, message: object, option: str, choices: tuple = (), listing: dict | None = None) -> None:
        super().__init__(message)
        self.option = option
        self.choices = tuple(str(c) for c in choices)
        self.listing = dict(listing or {})


class SegmentsAtDifferentRates(SelectionNeeded):
    """A segmented file whose segments are sampled at different rates, or hold different channels:
    one must be chosen (``--segment``).

    ``segments`` lists them (:class:`afmtool.io.capture.SegmentSpec`), so that ``info`` can
    summarise each one instead.
    """

    def __init__(self, message: object, segments: tuple = ()) -> None:
        super().__init__(message, "--segment", tuple(range(len(segments))))
        self.segments = tuple(segments)


class SampleShareWarning(str):
    """A warning about some of a run's samples, that knows their share.

    It is the warning's text (a ``str`` everywhere warnings go), with
    ``share`` = ``count / total`` beside it: ``report.json`` records the
    share (``warning_shares``) and the HTML page sets the warning's
    severity by it, so that 1 flagged sample in 14,777 is not shown as
    loudly as a run whose every sample is in doubt.
    """

    share: float

    def __new__(cls, text: str, count: int, total: int) -> "SampleShareWarning":
        warning = super().__new__(cls, text)
        warning.share = count / total if total > 0 else 1.0
        return warning


class CaptureWarning(UserWarning):
    """A capture read, but not wholly as its file says (a scaling afmtool cannot apply, a note read in part).

    Raised through :mod:`warnings` by the readers; the CLI records it in the run's report, or
    prints it once at the end of ``info`` and ``convert``.
    """
