"""Which free-air model an observer runs on, and how the capture's drive reached the plant.

Shared by ``probeloss``, ``kalman-bank`` and ``reep``.  Routes, first that applies:

1. ``f0-q`` from ``--f0``/``--q``;
2. ``model``: ``--model free_air.json``.  A model with a discrete numerator
   identified at the capture's rate (an ARX fit) is used as it is; one given
   by continuous parameters (a sweep, a thermal tune) goes the ``f0-q`` way
   when there is a free-air segment;
3. ``f0-q`` from the metadata ``cantilever.f0_hz``/``q`` when the drive is a
   single tone (metadata ``drive.kind`` "sine", ``sideband_offset_hz`` 0, or
   fewer than three lines near f0 in the segment's dither): a five-parameter
   ARX fit is not identifiable from one line;
4. ``segment``: the bias-compensated ARX fit on the free-air segment.

The ``f0-q`` route (issue 14, item 3): f0 and Q fix the shape
G(s) = ω0²/(s² + (ω0/Q)s + ω0²); on the free-air segment the measured
response H = Y/U at the drive line f_d (least squares at f_d and any side
lines) gives two equations for two unknowns, the gain k = |H|/|G(jω_d)| and
the drive-path delay τ = −arg(H/G(jω_d))/ω_d, so the observer matches the
capture at the drive whatever the hold.  The numerator is then
k·:func:`~afmtool.models.discretisation.line_numerator` (exact at f_d with τ,
DC gain k).  With ``--drive-hold zoh|continuous`` the delay is not fitted:
k is fitted against the zero-order-hold model or the continuous G.

The hold (``--drive-hold auto``, the default) is classified on the same
segment by :func:`~afmtool.models.discretisation.classify_hold` and recorded
with its reason; without a segment it cannot be measured and
``continuous`` is assumed.

The phase misfit (issue 28)
---------------------------
The measured excess phase at the drive, arg(H/G(jω_d)), is explained by a
hold (0 for ``continuous``, ≈ −180°·f_d/fs for ``zoh``) and a causal
drive-path delay of up to one sample (−360°·f_d/fs), within
``PHASE_TOLERANCE_DEG``.  Beyond that the drive is off the model's
resonance, or f0/Q (or the drive frequency) is wrong: the route refuses
with the numbers, rather than fit a delay of half a period and call the
drive continuous.  What the chosen hold leaves unexplained,
``phase_misfit_deg`` = excess − the hold's own excess, is reported; above
``HEADLINE_PHASE_MISFIT_DEG`` the headlines show it instead of scores
(:mod:`afmtool.report.headline`).
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from typing import NamedTuple

import numpy as np

from afmtool.analyses.freeair_source import (
    FreeAirSegment,
    drive_frequency,
    free_air_interval,
    identify_from_segment,
    read_free_air,
)
from afmtool.errors import ConfigError, InputError
from afmtool.io.capture import CaptureReader, Chunk
from afmtool.io.metadata import CaptureMetadata
from afmtool.models.free_air import FreeAirModel
from afmtool.records.common import FreeAirRouteRecord

__all__ = ["DRIVE_HOLD_CHOICES", "HEADLINE_PHASE_MISFIT_DEG", "PHASE_TOLERANCE_DEG", "FreeAirRoute", "drive_lines",
           "line_response", "resolve_free_air", "route_record"]

#: ``--drive-hold`` values.
DRIVE_HOLD_CHOICES = ("auto", "zoh", "continuous")
#: Samples of the free-air segment the line fit uses (its end).
_LINE_FIT_SAMPLES = 1 << 18
#: A measured excess phase farther than this from both holds' predictions is reported (degrees).
_HOLD_MISMATCH_DEG = 5.0
#: Slack on the explained range of the phase misfit (f0/Q uncertainty, the line fit), degrees.
PHASE_TOLERANCE_DEG = 5.0
#: A phase misfit above this (in magnitude) is the run's headline state, not its scores, degrees.
HEADLINE_PHASE_MISFIT_DEG = 30.0


class FreeAirRoute(NamedTuple):
    """The model an analysis runs on, where it came from, and the drive's hold.

    Attributes
    ----------
    model : FreeAirModel
        With ``numerator``/``denominator`` at the capture's rate whenever the
        route fixed them (``f0-q``, ``segment``, an ARX ``model``).
    route : str
        ``"f0-q"``, ``"model"`` or ``"segment"``.
    segment : FreeAirSegment or None
        The free-air segment read ahead, if any.
    drive_hz : float
        The drive line, Hz.
    report : dict
        ``route``, ``f0_q_from``, ``drive_hold``, ``drive_hold_option``,
        ``drive_hold_reason`` and, for ``f0-q``, ``fitted_gain`` and
        ``fitted_delay_s``: for report.json.
    warnings : tuple of str
    """

    model: FreeAirModel
    route: str
    segment: FreeAirSegment | None
    drive_hz: float
    report: dict
    warnings: tuple[str, ...]


def route_record(report: Mapping | FreeAirRouteRecord | None) -> FreeAirRouteRecord | None:
    """A route's ``report`` as report.json's ``free_air_route`` (:class:`~afmtool.records.common.FreeAirRouteRecord`).

    A record (an earlier run's, read back) is returned as it is; None (no route: a model that came with
    ``--reep``) stays None.
    """
    if report is None or isinstance(report, FreeAirRouteRecord):
        return report
    return FreeAirRouteRecord.from_json(report)


def line_response(deflection: np.ndarray, dither: np.ndarray, sample_rate_hz: float, lines_hz) -> complex:
    """Deflection over dither at the first of ``lines_hz`` (complex), by least squares.

    Both signals are fitted by cos/sin at every line plus a constant; the
    ratio of the two phasors at the first line is returned.  Side lines are
    fitted jointly so that their leakage does not bias the main one.
    """
    return complex(line_responses(deflection, dither, sample_rate_hz, lines_hz)[0])


def line_responses(deflection: np.ndarray, dither: np.ndarray, sample_rate_hz: float, lines_hz) -> np.ndarray:
    """Deflection over dither at every one of ``lines_hz`` (complex), as :func:`line_response` fits them."""
    # the last 2^18 samples (0.5 s at 500 kHz) are plenty, and keep the basis small
    deflection = np.asarray(deflection, dtype=np.float64)[-_LINE_FIT_SAMPLES:]
    dither = np.asarray(dither, dtype=np.float64)[-_LINE_FIT_SAMPLES:]
    n = len(deflection)
    t = np.arange(n) / sample_rate_hz
    columns = [np.ones(n)]
    for f in lines_hz:
        w = 2.0 * np.pi * f * t
        columns += [np.cos(w), np.sin(w)]
    basis = np.column_stack(columns)
    coef, *_ = np.linalg.lstsq(basis, np.column_stack([deflection, dither]), rcond=None)
    y = coef[1::2, 0] - 1j * coef[2::2, 0]
    u = coef[1::2, 1] - 1j * coef[2::2, 1]
    if abs(u[0]) == 0.0:
        raise InputError(f"the dither has no line at {lines_hz[0]:g} Hz on the free-air segment")
    with np.errstate(divide="ignore", invalid="ignore"):
        return y / u


def _drive_lines(metadata: CaptureMetadata, drive_hz: float) -> list[float]:
    offset = metadata.drive.sideband_offset_hz or 0.0
    lines = [drive_hz]
    if offset > 0:
        lines += [drive_hz - float(offset), drive_hz + float(offset)]
    return lines


def drive_lines(metadata: CaptureMetadata, segment: FreeAirSegment | None, fs: float, drive_hz: float) -> tuple:
    """The drive line, then its side lines: the metadata's, else those the free-air dither's spectrum shows.

    A capture without afmtool's drive metadata (a converted CSV, TDMS, ...)
    still has its three-sine's side lines; a detector designed for a single
    tone would misread it (:func:`afmtool.estimators.reliability.design_detector`).
    """
    lines = _drive_lines(metadata, drive_hz)
    if len(lines) > 1 or segment is None or segment.data.get("dither") is None:
        return tuple(lines)
    from afmtool.estimators.drive_lines import excitation_lines

    side = [f for f in excitation_lines(segment.data["dither"], fs, drive_hz) if abs(f - drive_hz) > _SAME_LINE_HZ]
    return (drive_hz, *side)


#: Lines of the dither closer than this to the drive are the drive (excitation_lines keeps maxima 500 Hz apart).
_SAME_LINE_HZ = 500.0


def _metadata_f0_q(metadata: CaptureMetadata) -> tuple[float, float] | None:
    f0, q = metadata.cantilever.f0_hz, metadata.cantilever.q
    if f0 is not None and q is not None and f0 > 0 and q > 0.5:
        return f0, q
    return None


def _single_tone(metadata: CaptureMetadata, segment: FreeAirSegment | None, fs: float, f0_hz: float) -> bool:
    drive = metadata.drive
    if drive.kind == "sine" or drive.sideband_offset_hz == 0:
        return True
    if drive.kind in ("three-sine", "multi-sine") or (drive.sideband_offset_hz or 0) > 0:
        return False
    if segment is None:
        return False
    from afmtool.estimators.drive_lines import excitation_lines

    return len(excitation_lines(segment.data["dither"], fs, f0_hz)) < 3


def _fit_f0_q(f0_hz: float, q: float, segment: FreeAirSegment, fs: float, drive_hz: float, lines, hold_option: str,
              f0_q_from: str):
    """Gain (and delay) at the drive for given f0, Q (module docstring); the model and its report."""
    from afmtool.models.discretisation import (
        classify_hold,
        discrete_denominator,
        line_numerator,
        sampled_response,
        zoh_numerator,
    )

    measured = line_response(segment.data["deflection"], segment.data["dither"], fs, lines)
    denominator = tuple(float(b) for b in discrete_denominator(f0_hz, q, fs))
    w0, w = 2.0 * math.pi * f0_hz, 2.0 * math.pi * drive_hz
    continuous = w0 * w0 / complex(w0 * w0 - w * w, w * w0 / q)
    decision = classify_hold(measured, f0_hz, q, drive_hz, fs)
    if hold_option == "zoh":
        unit = tuple(zoh_numerator(f0_hz, q, fs))
        gain = abs(measured) / abs(complex(sampled_response(unit, denominator, drive_hz, fs)))
        delay = 0.0
        reason = "given (--drive-hold zoh); gain fitted at the drive against the zero-order-hold model"
    else:
        gain = abs(measured) / abs(continuous)
        delay = 0.0
        if hold_option == "auto":
            # τ = −arg(H/G)/ω, the phase wrapped to (−π, π]
            delay = -float(np.angle(measured / continuous)) / w
        unit = tuple(line_numerator(f0_hz, q, fs, match_hz=drive_hz, delay_s=delay))
        reason = decision.reason if hold_option == "auto" else "given (--drive-hold continuous); gain fitted at the drive"
    if not (math.isfinite(gain) and gain > 0):
        raise InputError(f"the free-air segment gives no response at the {drive_hz:g} Hz drive")
    hold = decision.hold if hold_option == "auto" else hold_option
    model = FreeAirModel(
        f0_hz=f0_hz, q=q, gain=gain, source=f"f0-q:{f0_q_from}", sample_rate_hz=fs,
        numerator=tuple(gain * a for a in unit), denominator=denominator, delay_s=delay,
    )
    report = {
        "route": "f0-q",
        "f0_q_from": f0_q_from,
        "drive_hold": hold,
        "drive_hold_option": hold_option,
        "drive_hold_reason": reason,
        "fitted_gain": gain,
        "fitted_delay_s": delay,
        "measured_excess_phase_deg": decision.excess_phase_deg,
        "zoh_excess_phase_deg": decision.zoh_excess_deg,
    }
    return model, report


def _record_hold(model: FreeAirModel, segment: FreeAirSegment | None, fs: float, drive_hz: float, lines,
                 hold_option: str) -> dict:
    """The hold for a model that keeps its own numerator or is discretised here."""
    from afmtool.models.discretisation import classify_hold

    if hold_option != "auto":
        return {"drive_hold": hold_option, "drive_hold_option": hold_option,
                "drive_hold_reason": f"given (--drive-hold {hold_option})"}
    if segment is None:
        return {"drive_hold": "continuous", "drive_hold_option": "auto",
                "drive_hold_reason": "no free-air segment to measure it on; a continuous drive is assumed "
                                     "(--drive-hold zoh for a DAC at the ADC's rate)"}
    measured = line_response(segment.data["deflection"], segment.data["dither"], fs, lines)
    decision = classify_hold(measured, model.f0_hz, model.q, drive_hz, fs)
    return {"drive_hold": decision.hold, "drive_hold_option": "auto", "drive_hold_reason": decision.reason,
            "measured_excess_phase_deg": decision.excess_phase_deg,
            "zoh_excess_phase_deg": decision.zoh_excess_deg}


def _hold_warning(report: dict) -> list[str]:
    """A warning when the measured phase matches neither hold (f0/Q off, or a drive-path delay)."""
    excess, zoh = report.get("measured_excess_phase_deg"), report.get("zoh_excess_phase_deg")
    if excess is None or zoh is None or min(abs(excess), abs(excess - zoh)) <= _HOLD_MISMATCH_DEG:
        return []
    return [
        f"the free-air phase at the drive is {excess:+.1f} deg from the continuous model and "
        f"{excess - zoh:+.1f} deg from the zero-order hold's: f0/Q may be off, or the drive path has a delay; "
        f"{report['drive_hold']} was chosen"
    ]


def _check_phase_misfit(report: dict, drive_hz: float, fs: float) -> dict:
    """Add ``phase_misfit_deg`` to a route's report; refuse a phase no hold and delay explain (module docstring)."""
    excess, zoh = report.get("measured_excess_phase_deg"), report.get("zoh_excess_phase_deg")
    if excess is None or zoh is None:
        return report
    misfit = float(excess - (zoh if report["drive_hold"] == "zoh" else 0.0))
    one_sample = 360.0 * drive_hz / fs
    # a continuous drive or a zero-order hold, then up to one sample of causal delay
    explained = (min(0.0, zoh) - one_sample, 0.0)
    report = {**report, "phase_misfit_deg": misfit, "phase_explained_deg": list(explained)}
    if explained[0] - PHASE_TOLERANCE_DEG <= excess <= explained[1] + PHASE_TOLERANCE_DEG:
        return report
    f0_q = report.get("drive_hold_reason", "").partition("(")[2].partition(")")[0]
    raise InputError(
        f"the free-air phase at the {drive_hz:g} Hz drive is {excess:+.1f} deg from the continuous model ({f0_q}); "
        f"a hold and up to one sample of drive delay explain {explained[0]:.1f} to 0 deg: the drive is off the "
        "model's resonance or f0/Q is wrong; give the lever's --f0/--q, --drive-frequency, or --model "
        "(afmtool identify freeair)"
    )


def resolve_free_air(
    reader: CaptureReader,
    chunks: Iterator[Chunk],
    *,
    given: FreeAirModel | None,
    free_air: str = "",
    f0_hz: float = 0.0,
    q: float = 0.0,
    drive_hold: str = "auto",
    drive_frequency_hz: float = 0.0,
    names: tuple[str, ...] = ("deflection", "dither"),
    required: bool = True,
) -> tuple[FreeAirRoute | None, Iterator[Chunk]]:
    """Choose the free-air route (module docstring), reading the free-air segment ahead.

    Parameters
    ----------
    reader, chunks
        The capture and its single-pass chunk stream.
    given : FreeAirModel, optional
        ``--model``.
    free_air : str
        ``--free-air START:END`` (empty: metadata ``free_air``).
    f0_hz, q : float
        ``--f0`` (Hz) and ``--q``; 0 = not given.
    drive_hold : {"auto", "zoh", "continuous"}
        ``--drive-hold``.
    drive_frequency_hz : float
        ``--drive-frequency``; 0 = metadata, else f0.
    names : tuple of str
        Channels to read for the segment (must include deflection and dither).
    required : bool
        Raise when no route applies (else return None).

    Returns
    -------
    (FreeAirRoute or None, iterator of Chunk)
    """
    if drive_hold not in DRIVE_HOLD_CHOICES:
        raise ConfigError(f"drive_hold={drive_hold!r} must be one of {DRIVE_HOLD_CHOICES}")
    if bool(f0_hz) != bool(q):
        raise ConfigError(f"--f0 and --q go together (got f0={f0_hz!r}, q={q!r})")
    interval = free_air_interval(reader, free_air)
    segment = None
    if interval is not None:
        segment, chunks = read_free_air(reader, chunks, interval, names)
    source = _f0_q_source(reader, given, segment, f0_hz, q)
    if source is not None:
        return _f0_q_route(reader, source, segment, drive_hold, drive_frequency_hz), chunks
    if given is None and segment is None:
        if not required:
            return None, chunks
        raise ConfigError(
            "no free-air model: give --free-air START:END, --model free_air.json, --f0/--q with a free-air "
            "segment, or capture metadata free_air"
        )
    return _model_route(reader, given, segment, drive_hold, drive_frequency_hz), chunks


def _f0_q_source(reader: CaptureReader, given: FreeAirModel | None, segment, f0_hz: float, q: float):
    """((f0, Q), origin) when the f0/Q route applies: flags, a model without this rate's numerator, or metadata."""
    fs = reader.info.sample_rate_hz
    metadata = reader.info.capture_metadata
    if f0_hz:
        return (float(f0_hz), float(q)), "flags"
    if given is not None:
        if given.numerator is not None and given.sample_rate_hz == fs:
            return None
        return ((given.f0_hz, given.q), "model") if segment is not None else None
    meta = _metadata_f0_q(metadata)
    if meta is not None and _single_tone(metadata, segment, fs, meta[0]):
        return meta, "metadata"
    return None


def _f0_q_route(reader: CaptureReader, source, segment, drive_hold: str, drive_frequency_hz: float) -> FreeAirRoute:
    """The f0/Q route: gain and phase fitted at the drive on the free-air segment."""
    (f0_use, q_use), origin = source
    if segment is None:
        raise ConfigError(
            f"the f0/Q route ({origin}) fits the gain and phase at the drive on a free-air segment: "
            "give --free-air START:END or capture metadata free_air"
        )
    fs = reader.info.sample_rate_hz
    metadata = reader.info.capture_metadata
    drive_hz = drive_frequency(reader, drive_frequency_hz, FreeAirModel(f0_use, q_use))
    model, report = _fit_f0_q(f0_use, q_use, segment, fs, drive_hz, _drive_lines(metadata, drive_hz),
                              drive_hold, origin)
    report = _check_phase_misfit(report, drive_hz, fs)
    return FreeAirRoute(model, "f0-q", segment, drive_hz, report, tuple(_hold_warning(report)))


def _model_route(
    reader: CaptureReader, given: FreeAirModel | None, segment, drive_hold: str, drive_frequency_hz: float
) -> FreeAirRoute:
    """The given model, or the ARX fit on the segment (the metadata f0/Q route if that fit fails)."""
    fs = reader.info.sample_rate_hz
    metadata = reader.info.capture_metadata
    warnings: list[str] = []
    if given is not None:
        model, route = given, "model"
    else:
        try:
            model, route = identify_from_segment(segment, fs), "segment"
            if _single_tone(metadata, segment, fs, model.f0_hz):
                warnings.append(
                    "the dither has fewer than three lines near resonance, so the five-parameter ARX free-air fit is "
                    "not identifiable; give the cantilever's --f0 and --q (or metadata cantilever f0_hz/q)"
                )
        except InputError:
            meta = _metadata_f0_q(metadata)
            if meta is None:
                raise
            warnings.append("the ARX fit on the free-air segment failed; the metadata cantilever f0/Q are used")
            drive_hz = drive_frequency(reader, drive_frequency_hz, FreeAirModel(*meta))
            model, report = _fit_f0_q(*meta, segment, fs, drive_hz, _drive_lines(metadata, drive_hz), drive_hold,
                                      "metadata")
            report = _check_phase_misfit(report, drive_hz, fs)
            return FreeAirRoute(model, "f0-q", segment, drive_hz, report, tuple(warnings))
    drive_hz = drive_frequency(reader, drive_frequency_hz, model)
    report = {"route": route, "f0_q_from": None,
              **_record_hold(model, segment, fs, drive_hz, _drive_lines(metadata, drive_hz), drive_hold)}
    if route == "segment" or (model.numerator is not None and model.sample_rate_hz == fs):
        report["drive_hold_reason"] += "; the numerator is the data-driven ARX fit, which needs no hold"
    else:
        # continuous parameters and no segment to fit on: discretise with the hold, matched at the drive
        numerator = model.numerator_at(fs, report["drive_hold"], match_hz=drive_hz)
        model = FreeAirModel(
            **{**model.to_dict(), "sample_rate_hz": fs, "numerator": numerator, "denominator": model.denominator_at(fs)}
        )
        report = _check_phase_misfit(report, drive_hz, fs)
    warnings += _hold_warning(report)
    return FreeAirRoute(model, route, segment, drive_hz, report, tuple(warnings))
