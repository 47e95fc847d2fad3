"""Where an analysis gets its free-air model, segment and drive frequency (``reep``, ``probeloss``, ``kalman-bank``).

The off-sample segment is ``--free-air START:END`` or the capture metadata
``free_air``; it is read ahead from the single-pass chunk stream
(:func:`~afmtool.pipeline.read_segment`), so stdin works too, and
the free-air model is identified from it by the bias-compensated ARX fit
(:func:`~afmtool.estimators.free_air_fit.free_air_from_segment`) unless the user
gave one (``--model free_air.json``).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import NamedTuple

import numpy as np

from afmtool.config.params import parse_interval
from afmtool.config.samples import interval_samples
from afmtool.errors import InputError
from afmtool.estimators.free_air_fit import free_air_from_segment
from afmtool.io.capture import CaptureInfo, CaptureReader, Chunk
from afmtool.models.free_air import FreeAirModel
from afmtool.pipeline import read_segment

__all__ = ["FreeAirSegment", "free_air_interval", "read_free_air", "identify_from_segment", "drive_frequency"]


class FreeAirSegment(NamedTuple):
    """Samples of an off-sample segment.

    Attributes
    ----------
    interval_s : tuple of 2 floats
        (start, end), s from the capture's first sample.
    start_sample : int
        Index of the segment's first sample.
    data : dict of str to numpy.ndarray
        The segment of each channel read.
    """

    interval_s: tuple[float, float]
    start_sample: int
    data: dict[str, np.ndarray]


def free_air_interval(reader: CaptureReader, text: str, option: str = "--free-air") -> tuple[float, float] | None:
    """The free-air segment (s): ``text`` (START:END) if given, else metadata ``free_air``, else None."""
    interval = parse_interval(text, option)
    free_air = reader.info.capture_metadata.free_air
    if interval is None and free_air is not None:
        interval = (free_air.start_s, free_air.end_s)
    return interval


def read_free_air(
    reader: CaptureReader, chunks: Iterator[Chunk], interval: tuple[float, float], names: tuple[str, ...]
) -> tuple[FreeAirSegment, Iterator[Chunk]]:
    """Read the segment ahead; return it and an iterator over every chunk (read-ahead ones first)."""
    start, end = interval_samples(interval, reader.info.sample_rate_hz, "free-air segment", reader.info.n_samples)
    data, chunks = read_segment(chunks, names, start, end)
    return FreeAirSegment(interval, start, data), chunks


def identify_from_segment(segment: FreeAirSegment, sample_rate_hz: float) -> FreeAirModel:
    """Free-air model from the segment's deflection and dither, with the way out in the error."""
    try:
        return free_air_from_segment(segment.data["deflection"], segment.data["dither"], sample_rate_hz)
    except InputError as exc:
        start, end = segment.interval_s
        raise InputError(
            f"free-air segment {start:g}:{end:g} s: {exc}; or give --model free_air.json "
            "(identify freeair --psd / --sweep)"
        ) from None


def drive_frequency(reader: CaptureReader, given_hz: float, model: FreeAirModel) -> float:
    """The drive frequency, Hz: ``given_hz`` if non-zero, else metadata ``drive.frequency_hz``, else f0.

    Raises
    ------
    InputError
        If it is not below the Nyquist frequency, or one period is longer than the capture.
    """
    metadata_hz = reader.info.capture_metadata.drive.frequency_hz
    if given_hz:
        hz = given_hz
    elif metadata_hz is not None:
        hz = metadata_hz
    else:
        hz = model.f0_hz
    return checked_drive_frequency(hz, reader.info)


def checked_drive_frequency(hz: float, info: CaptureInfo) -> float:
    """``hz`` if a capture of ``info`` can carry a drive there: below Nyquist, and a period within the capture.

    Raises
    ------
    InputError
        Naming the frequency and the limit it breaks.
    """
    fs = info.sample_rate_hz
    if not 0 < hz < fs / 2:
        raise InputError(f"drive frequency {hz:g} Hz is not below the Nyquist frequency {fs / 2:g} Hz")
    if info.n_samples is not None and hz * info.n_samples < fs:  # n/fs < 1/hz, without overflowing 1/hz
        raise InputError(f"drive frequency {hz:g} Hz: one period is longer than the capture "
                         f"({info.n_samples / fs:g} s), so no line at it can be measured")
    return hz
