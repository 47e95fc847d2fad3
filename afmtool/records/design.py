"""``design excitation``'s results: the three-sine REEP dither, as ``lines.json`` and report.json hold it."""

from __future__ import annotations

import enum

from afmtool.records.base import Item, Record, record

__all__ = ["LineRole", "ExcitationLineRecord", "DesignModelRecord", "DesignResults"]


class LineRole(enum.Enum):
    """Which of the three lines."""

    MAIN = "main"  # at the drive frequency
    LOWER = "lower"  # the side line below it
    UPPER = "upper"  # the side line above it


@record
class ExcitationLineRecord(Record):
    """One line of the dither, u(t) = amplitude_v·sin(2π·frequency_hz·t + phase_deg), and the free-air response to it.

    Attributes
    ----------
    role : LineRole
        Main line or a side line.
    frequency_hz : float
        Its frequency (Hz).
    amplitude_v : float
        Its amplitude (V).
    phase_deg : float
        Its sine phase (degrees).
    response_nm : float
        The predicted free-air response's amplitude, in the model's deflection units (nm).
    response_phase_deg : float
        The predicted response's sine phase (degrees).
    """

    role: LineRole
    frequency_hz: float
    amplitude_v: float
    phase_deg: float
    response_nm: float
    response_phase_deg: float


@record
class DesignModelRecord(Record):
    """The free-air model the dither is designed for.

    Attributes
    ----------
    f0_hz : float
        Resonant frequency (Hz).
    q : float
        Quality factor.
    gain : float
        DC gain, deflection units per drive unit (nm/V).
    """

    f0_hz: float
    q: float
    gain: float


@record
class DesignResults(Record):
    """The three-sine dither designed for a cantilever (``lines.json``; §3.3.2).

    Attributes
    ----------
    convention : str
        How the lines add up to the drive and the response.
    lines : tuple of ExcitationLineRecord
        The main line, then the lower and upper side lines.
    offset_hz : float
        The side lines' offset from the main line (Hz).
    offset_reason : str
        Why that offset.
    side_scale : float
        Side-line amplitude over the main line's.
    envelope_beat : float
        Relative beat of the response's envelope, (R₊ + R₋)/R_d.
    beat_tolerance : float
        The largest envelope beat allowed.
    amplitude_beat : float
        Relative beat of the response's amplitude.
    phase_swing_deg : float
        The response phase's swing over a beat (degrees).
    dac_rate_hz : float
        The sample rate of the exported loop (Hz).
    loop_samples : int
        Samples in the loop.
    loop_beats : int
        Beat periods in the loop.
    loop_s : float
        The loop's length (s).
    peak_v : float
        The dither's peak (V).
    wav_full_scale_v : float
        Volts at full scale (1.0) of excitation.wav (V).
    free_air_model : DesignModelRecord
        The cantilever's free-air model.
    """

    convention: str
    lines: tuple[ExcitationLineRecord, ...]
    offset_hz: float
    offset_reason: str
    side_scale: float
    envelope_beat: float
    beat_tolerance: float
    amplitude_beat: float
    phase_swing_deg: float
    dac_rate_hz: float
    loop_samples: int
    loop_beats: int
    loop_s: float
    peak_v: float
    wav_full_scale_v: float
    free_air_model: DesignModelRecord

    HEADLINE = (
        Item("main line", "lines.0.frequency_hz", "Hz"),
        Item("main line amplitude", "lines.0.amplitude_v", "V"),
        Item("lower side line", "lines.1.frequency_hz", "Hz"),
        Item("upper side line", "lines.2.frequency_hz", "Hz"),
        Item("side-line amplitude", "lines.1.amplitude_v", "V"),
        Item("free-air response", "lines.0.response_nm", "nm"),
        Item("envelope beat (R₊ + R₋)/R_d", "envelope_beat", ""),
        Item("amplitude beat", "amplitude_beat", ""),
        Item("loop length", "loop_s", "s"),
    )
