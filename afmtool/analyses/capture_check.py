"""Can this capture carry what the command needs?  Checked first, before any model or channel is looked for.

A 2 kHz instrument force curve of a 23 kHz lever cannot hold REEP's answer
whatever the flags: the oscillation is not in the samples.  Left to the
analysis, such a capture failed on whatever was looked for first (a
free-air model, a dither channel, the f0/Q route), and the real reason came
fourth.  :func:`check_capture` runs as the capture is opened, in this order,
and raises one line that says what to do:

1. the resonance and the drive lie below the Nyquist frequency (fs/2): the
   frequencies the command line gives (``--f0``, ``--model``,
   ``--drive-frequency``, ``--drive``), else the capture's metadata
   (``cantilever.f0_hz``, ``drive.frequency_hz``, ``drive.lines``);
2. the channels the command reads are there (a ``dither`` that can be
   synthesised from ``--drive`` or metadata ``drive.lines`` counts).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

from afmtool.errors import InputError

__all__ = ["CaptureNeeds", "check_capture"]


class CaptureNeeds(NamedTuple):
    """What one command needs of a capture, with the frequencies its command line gives.

    Attributes
    ----------
    command : str
        The command, for the message ("reep").
    channels : tuple of str
        Channels it reads.
    f0_hz, drive_hz : float or None
        The resonance (``--f0``, the ``--model``'s) and the drive (``--drive-frequency``) if given.
    drive_lines_hz : tuple of float
        The lines of ``--drive``, if given.
    oscillation : bool
        It analyses the cantilever's oscillation, so the resonance must lie below Nyquist.
    """

    command: str
    channels: tuple[str, ...] = ("deflection", "dither")
    f0_hz: float | None = None
    drive_hz: float | None = None
    drive_lines_hz: tuple[float, ...] = ()
    oscillation: bool = True

    def __call__(self, info, drive_lines_hz: tuple[float, ...] = (), synthesisable: bool = False) -> None:
        """Check ``info`` (the reader stack's hook, :attr:`afmtool.io.stack.CaptureOptions.needs`)."""
        check_capture(info, self._replace(drive_lines_hz=tuple(drive_lines_hz)), synthesisable=synthesisable)


def _positive(value) -> float | None:
    try:
        value = float(value)
    except (TypeError, ValueError):
        return None
    return value if math.isfinite(value) and value > 0 else None


def _frequencies(info, needs: CaptureNeeds) -> list[tuple[str, float, str]]:
    """(what, Hz, where it came from) of the resonance and the drive."""
    metadata = info.capture_metadata
    found: list[tuple[str, float, str]] = []
    f0 = _positive(needs.f0_hz)
    if f0 is not None:
        found.append(("resonance", f0, "given"))
    elif _positive(metadata.cantilever.f0_hz) is not None:
        found.append(("resonance", float(metadata.cantilever.f0_hz), "metadata cantilever.f0_hz"))
    drive = _positive(needs.drive_hz)
    if drive is not None:
        found.append(("drive frequency", drive, "--drive-frequency"))
    elif needs.drive_lines_hz:
        found.append(("drive frequency", max(needs.drive_lines_hz), "--drive"))
    elif _positive(metadata.drive.frequency_hz) is not None:
        found.append(("drive frequency", float(metadata.drive.frequency_hz), "metadata drive.frequency_hz"))
    elif metadata.drive.lines:
        found.append(("drive frequency", max(line.frequency_hz for line in metadata.drive.lines), "metadata drive.lines"))
    return found


def _nyquist(info, needs: CaptureNeeds) -> None:
    fs = _positive(info.sample_rate_hz)
    if fs is None or not needs.oscillation:
        return
    nyquist = fs / 2.0
    above = [(what, hz, where) for what, hz, where in _frequencies(info, needs) if hz >= nyquist]
    if not above:
        return
    what, hz, where = max(above, key=lambda item: item[1])
    others = "".join(f" and the {w} {h:.6g} Hz ({s})" for w, h, s in above if (w, h, s) != (what, hz, where))
    raise InputError(
        f"{info.source}: sampled at {fs:.6g} Hz, so nothing above {nyquist:.6g} Hz (Nyquist) is in it, but the "
        f"{what} is {hz:.6g} Hz ({where}){others}: {needs.command} needs the deflection recorded at more than "
        f"twice that (at least {2.5 * hz:.3g} Hz, e.g. a fast capture of the photodiode signal), not an "
        "instrument's low-rate force curve; if the frequency is wrong, give the right --f0"
    )


def _channels(info, needs: CaptureNeeds, synthesisable: bool) -> None:
    present = frozenset(info.channel_names)
    have = ", ".join(info.channel_names) or "none"
    for name in needs.channels:
        if name in present or (name == "dither" and synthesisable):
            continue
        hint = f"give --channel {name}=NAME if it was recorded under another name"
        if name == "dither":
            hint += ", or --drive 'F1:A1,...' (Hz:V) if the drive was not recorded"
        raise InputError(f"{info.source}: {needs.command} reads channel {name!r}, which the capture lacks "
                         f"(has: {have}); {hint}")


def check_capture(info, needs: CaptureNeeds | None, *, synthesisable: bool = False) -> None:
    """Raise :class:`InputError` (one line: what to do) if ``info`` cannot carry ``needs``; Nyquist first.

    ``synthesisable``: a missing ``dither`` will be synthesised (``--drive`` or metadata ``drive.lines``).
    """
    if needs is None:
        return
    _nyquist(info, needs)
    _channels(info, needs, synthesisable)


def needs_from_flags(command: str, flags, channels: Sequence[str] = ("deflection", "dither"),
                     drive_lines_hz: Sequence[float] = ()) -> CaptureNeeds:
    """The :class:`CaptureNeeds` of a command line: ``--f0`` or the ``--model``'s f0, ``--drive-frequency``."""
    f0 = _positive(flags.get("f0_hz"))
    model = flags.get("model")
    if f0 is None and model:
        f0 = _model_f0(model)
    return CaptureNeeds(command, tuple(channels), f0, _positive(flags.get("drive_frequency_hz")), tuple(drive_lines_hz))


def _model_f0(model: str) -> float | None:
    """The f0 of a ``--model`` file, if it can be read (its own errors are reported where it is loaded)."""
    import json
    from pathlib import Path

    path = Path(model)
    for candidate in (path / "free_air.json", path, path / "report.json"):
        try:
            data = json.loads(candidate.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        if isinstance(data, dict):
            data = (data.get("results") or {}).get("free_air_model") or data
            return _positive(data.get("f0_hz")) if isinstance(data, dict) else None
    return None
