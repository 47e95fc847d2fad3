"""Probe-loss events: runs of a switching signal, truth events from contact, and scores.

An event is a maximal run of samples where a switching signal reads 1,
``[start, end)`` in capture sample indices.  :func:`runs_update` extracts
them chunk by chunk with one carried integer (the start of a run still open
at the chunk's end), so the events of a capture of any length come out in
one pass.

Truth (simulated captures)
--------------------------
``/truth/contact`` is 1 in each sample period where the tip came within the
force's range.  Tapping touches once per drive period, so the tip is off the
sample where contact stays 0 for longer than ``gap_periods`` drive periods
(default 1.5): those stretches are the truth loss events.  A stretch that
begins at the first sample (before the tip ever touched) is loss but has no
onset; it counts for precision, not for recall or latency.

Scores
------
For events at least ``min_periods`` drive periods long (acceptance: 5):

* recall: truth onsets overlapped by a detected event / truth onsets;
* precision: detected events overlapping a truth loss stretch (any length) /
  detected events;
* detection time of an onset: start of the first detected event that
  overlaps it and began after the previous loss stretch ended (the tip was
  back on the sample and the detector had the chance to release); an
  onset overlapped only by an older detection is "carried over": recalled,
  but with no detection time;
* latency: detection time minus the truth start (negative: the detector
  fired before the last contact, as the interaction faded);
* lead of one detector over another on a truth onset: the difference of
  their detection times (positive: the first detector fired earlier).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from afmtool.errors import ConfigError

__all__ = [
    "Events",
    "RunState",
    "RunStep",
    "runs_update",
    "runs_finish",
    "truth_loss_events",
    "TruthEvents",
    "EventScore",
    "score_events",
    "detection_times",
    "overlapping_lead",
]

_EMPTY = np.zeros(0, dtype=np.int64)


class Events(NamedTuple):
    """Disjoint, sorted events ``[start, end)`` in capture samples."""

    start: np.ndarray
    end: np.ndarray

    @property
    def duration(self) -> np.ndarray:
        """end − start, samples."""
        return self.end - self.start

    def __len__(self) -> int:  # type: ignore[override]
        return int(self.start.shape[0])

    def longer_than(self, samples: float) -> Events:
        """The events at least ``samples`` long."""
        keep = self.duration >= samples
        return Events(self.start[keep], self.end[keep])

    @classmethod
    def concatenate(cls, parts: list[Events]) -> Events:
        if not parts:
            return cls(_EMPTY, _EMPTY)
        return cls(np.concatenate([p.start for p in parts]), np.concatenate([p.end for p in parts]))


class RunState(NamedTuple):
    """Start of the run still open after the last chunk, or −1."""

    open_start: int = -1


class RunStep(NamedTuple):
    """Events closed within the chunk, and the next state."""

    events: Events
    state: RunState


def runs_update(state: RunState, values, offset: int) -> RunStep:
    """Runs of nonzero ``values`` (a chunk starting at sample ``offset``), streaming.

    Parameters
    ----------
    state : RunState
        From the previous chunk (``RunState()`` at the start).
    values : array_like, shape (T,)
        The switching signal of the chunk (nonzero = in an event).
    offset : int
        Capture index of ``values[0]``.

    Returns
    -------
    RunStep
        The events that ended inside the chunk (a run reaching its last
        sample stays open in the state).  Chunked runs give the same events
        as one call.
    """
    if not isinstance(state, RunState):
        raise ConfigError(f"state must be a RunState, got {type(state).__name__}")
    v = np.asarray(values)
    if v.ndim != 1:
        raise ConfigError(f"values must be 1-D, got shape {v.shape}")
    if v.size == 0:
        return RunStep(Events(_EMPTY, _EMPTY), state)
    was_open = state.open_start >= 0
    flags = np.empty(v.size + 1, dtype=np.int8)
    flags[0] = 1 if was_open else 0
    np.not_equal(v, 0, out=flags[1:].view(bool))
    edges = np.diff(flags)
    rises = np.flatnonzero(edges == 1) + offset
    falls = np.flatnonzero(edges == -1) + offset
    starts = np.concatenate([[state.open_start], rises]).astype(np.int64) if was_open else rises.astype(np.int64)
    open_start = -1
    if starts.size > falls.size:
        open_start = int(starts[-1])
        starts = starts[:-1]
    return RunStep(Events(starts, falls.astype(np.int64)), RunState(open_start))


def runs_finish(state: RunState, n_samples: int) -> Events:
    """Close the run still open at the end of a capture of ``n_samples`` samples."""
    if state.open_start < 0:
        return Events(_EMPTY, _EMPTY)
    return Events(np.array([state.open_start], dtype=np.int64), np.array([n_samples], dtype=np.int64))


class TruthEvents(NamedTuple):
    """Truth loss from the contact indicator.

    Attributes
    ----------
    stretches : Events
        Every stretch without contact longer than the gap (loss).
    onsets : Events
        The stretches that follow a contact (the tip was lost).
    rearmed : numpy.ndarray
        For each onset, the end of the loss stretch before it (0 for the
        first): a detection of the onset must begin after it, once the tip
        was back on the sample.
    """

    stretches: Events
    onsets: Events
    rearmed: np.ndarray

    def longer_than(self, samples: float) -> TruthEvents:
        """The same stretches, with the onsets at least ``samples`` long."""
        keep = self.onsets.duration >= samples
        return TruthEvents(self.stretches, Events(self.onsets.start[keep], self.onsets.end[keep]), self.rearmed[keep])


def truth_loss_events(contact, period_samples: float, gap_periods: float = 1.5) -> TruthEvents:
    """Loss stretches: no contact for more than ``gap_periods`` drive periods.

    Parameters
    ----------
    contact : array_like, shape (N,)
        Truth contact per sample (nonzero = the tip touched in that period).
    period_samples : float
        Drive period, samples.
    gap_periods : float, optional
        Shortest stretch without contact that counts as loss, drive periods.
    """
    if not (period_samples > 0 and gap_periods > 0):
        raise ConfigError(f"period_samples={period_samples!r} and gap_periods={gap_periods!r} must be > 0")
    no_contact = np.asarray(contact) == 0
    step = runs_update(RunState(), no_contact, 0)
    events = Events.concatenate([step.events, runs_finish(step.state, no_contact.size)])
    stretches = events.longer_than(math.nextafter(gap_periods * period_samples, math.inf))
    onset = stretches.start > 0
    previous_end = np.concatenate([[0], stretches.end[:-1]]).astype(np.int64)
    return TruthEvents(stretches, Events(stretches.start[onset], stretches.end[onset]), previous_end[onset])


def _first_overlap(events: Events, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Index of the first event overlapping each [start, end), or −1."""
    if len(events) == 0:
        return np.full(start.shape[0], -1, dtype=np.int64)
    k = np.searchsorted(events.end, start, side="right")
    inside = k < len(events)
    hit = np.zeros(start.shape[0], dtype=bool)
    hit[inside] = events.start[k[inside]] < end[inside]
    return np.where(hit, k, -1)


def detection_times(detected: Events, truth: Events, rearmed: np.ndarray | None = None) -> np.ndarray:
    """Start of the first detected event overlapping each truth event (samples), or −1.

    With ``rearmed``, only events that begin at or after ``rearmed[i]`` count
    for truth event i: a detector still flagging the previous loss when
    this one began (it never released while the tip was back on the
    sample) has not detected it.
    """
    if len(detected) == 0:  # nothing detected (e.g. a baseline that never switched)
        return np.full(len(truth), -1, dtype=np.int64)
    if rearmed is None:
        k = _first_overlap(detected, truth.start, truth.end)
        return np.where(k >= 0, detected.start[np.maximum(k, 0)], -1)
    # first event starting at or after the re-arm sample that ends after the truth start
    k = np.maximum(np.searchsorted(detected.start, rearmed, side="left"),
                   np.searchsorted(detected.end, truth.start, side="right"))
    inside = k < len(detected)
    hit = np.zeros(len(truth), dtype=bool)
    hit[inside] = detected.start[k[inside]] < truth.end[inside]
    return np.where(hit, detected.start[np.minimum(k, len(detected) - 1)], -1)


class EventScore(NamedTuple):
    """Per-event scores of one detector against the truth (module docstring).

    Attributes
    ----------
    truth_events, detected_events : int
        Truth onsets and detected events at least the minimum length.
    recall, precision : float or None
        None when there is nothing to divide by.
    latency_samples : numpy.ndarray
        Latency of each onset detected after re-arming, samples.
    detection_samples : numpy.ndarray
        Detection time of each truth onset (≥ minimum), −1 if not detected
        after re-arming.
    carried_over : int
        Onsets overlapped only by a detection that began before the tip was
        back on the sample (recalled, but with no detection time of their own).
    """

    truth_events: int
    detected_events: int
    recall: float | None
    precision: float | None
    latency_samples: np.ndarray
    detection_samples: np.ndarray
    carried_over: int


def score_events(detected: Events, truth: TruthEvents, min_samples: float) -> EventScore:
    """Recall, precision and latency of ``detected`` for events at least ``min_samples`` long."""
    scored = truth.longer_than(min_samples)
    onsets = scored.onsets
    long_detected = detected.longer_than(min_samples)
    overlapped = detection_times(detected, onsets) >= 0
    found = detection_times(detected, onsets, scored.rearmed)
    hit = found >= 0
    true_positive = _first_overlap(truth.stretches, long_detected.start, long_detected.end) >= 0
    return EventScore(
        len(onsets),
        len(long_detected),
        float(overlapped.mean()) if len(onsets) else None,
        float(true_positive.mean()) if len(long_detected) else None,
        (found - onsets.start)[hit],
        found,
        int(np.count_nonzero(overlapped & ~hit)),
    )


def overlapping_lead(first: Events, second: Events) -> np.ndarray:
    """For each event of ``first``: start of the first ``second`` event overlapping it minus its start.

    Samples; NaN where no ``second`` event overlaps.  Positive: ``first``
    started earlier (it leads).
    """
    k = _first_overlap(second, first.start, first.end)
    lead = np.full(len(first), np.nan)
    hit = k >= 0
    lead[hit] = second.start[k[hit]] - first.start[hit]
    return lead
