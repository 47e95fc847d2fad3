"""REEP's decimated series against time: segment statistics, tracking error, the figure.

The segment statistics (:class:`SegmentMoments`) and the figure's rows
(:class:`ThinnedRows`) are gathered as the rows stream, by ``run_reep``, or
from a finished ``reep.h5`` (the decimated ``t``, ``f0_hz``, ``q``,
``amplitude``, ``phase_deg``) read in blocks; either way memory stays flat
however long the capture: the statistics are running sums, the figure draws
at most 2·:data:`MAX_PLOT_POINTS` evenly spaced rows per line, and the
percentiles of the tracking error use at most :data:`MAX_PERCENTILE_POINTS`
evenly spaced rows.

The truth (``/truth/f0_hz``, ``/truth/q`` of a simulated capture, one value
per input sample) is never seen by the estimator; it is compared here, after
the run, at each output row's sample index n = round(t·fs).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from afmtool.io.result_files import FLAG_COLUMN, MAX_PLOT_POINTS, open_result_file
from afmtool.records.common import Moments
from afmtool.records.reep import ReepSegments, Segment, TrackingError, TruthTracking
from afmtool.report.timeseries import EveryKth

if TYPE_CHECKING:
    from afmtool.estimators.moments import RunningMoments

__all__ = [
    "MAX_PLOT_POINTS",
    "SegmentMoments",
    "MAX_PERCENTILE_POINTS",
    "FLAG_COLUMN",
    "segment_statistics",
    "tracking_error",
    "truth_at_rows",
    "write_reep_time_series_png",
    "PLOTTED",
    "Thinned",
    "ThinnedRows",
    "read_thinned",
]

#: Most rows over which the tracking-error percentiles are taken.
MAX_PERCENTILE_POINTS = 1_000_000
#: Most flagged rows marked on the figure.
_MAX_FLAG_MARKS = 5000
#: The columns drawn against t.
PLOTTED = ("f0_hz", "q", "amplitude", "phase_deg")


def _open(reep_h5: Path):
    """The decimated series of a finished reep.h5 (b1, b0 are not needed here)."""
    return open_result_file(reep_h5, required=("t", "f0_hz", "q"), what="reep output")


def _moments(moments: RunningMoments) -> Moments:
    """Mean and sample standard deviation (a spread, not the error of the mean); NaN mean without a value."""
    return Moments(count=moments.count, mean=moments.mean, std=moments.std(ddof=1))


class SegmentMoments:
    """Mean and standard deviation of f0' (Hz) and Q' per time segment, fed block by block in time order.

    :func:`segment_statistics` reads a finished reep.h5 through it;
    ``run_reep`` feeds it the rows as they stream, so the command need not
    read the file back.  The parameters are those of :func:`segment_statistics`.
    """

    def __init__(self, warmup_s: float, free_air_segment_s: tuple[float, float] | None) -> None:
        if free_air_segment_s:
            start, end = (float(v) for v in free_air_segment_s)
            # after the segment, REEP needs the same settling as at the start to forget the change
            self.bounds = {"free_air": (max(start, warmup_s), end), "after_free_air": (end + warmup_s, math.inf)}
        else:
            self.bounds = {"settled": (warmup_s, math.inf)}
        # numba loads here, not at import: the figure process imports this module for the figure alone
        from afmtool.estimators.moments import RunningMoments

        self.moments = {seg: {"f0_hz": RunningMoments(), "q": RunningMoments()} for seg in self.bounds}
        # the mean of REEP's per-row standard deviation of f0' (its own uncertainty, not the rows' spread)
        self.row_std = {seg: RunningMoments() for seg in self.bounds}
        self.last_t: float | None = None

    def add(self, t: np.ndarray, f0_hz: np.ndarray, q: np.ndarray, flags: np.ndarray | None = None,
            f0_std_hz: np.ndarray | None = None) -> None:
        """Rows at times ``t`` (s, ascending); a row is left out where NaN or (with ``flags``) flagged.

        ``f0_std_hz``, REEP's per-row standard deviation of f0', is averaged alike when given.
        """
        for seg, (t0, t1) in self.bounds.items():
            start, stop = np.searchsorted(t, (t0, t1), side="left")
            self.moments[seg]["f0_hz"].add(f0_hz, flags, start, stop)
            self.moments[seg]["q"].add(q, flags, start, stop)
            if f0_std_hz is not None:
                self.row_std[seg].add(f0_std_hz, flags, start, stop)
        if len(t):
            self.last_t = float(t[-1])

    def record(self) -> ReepSegments:
        """Each segment with a trusted f0' row: its span, f0' and Q' (:func:`segment_statistics`)."""
        out = {}
        for seg, (t0, t1) in self.bounds.items():
            moments = self.moments[seg]
            if moments["f0_hz"].count == 0:
                continue
            row_std = self.row_std[seg]
            out[seg] = Segment(t_s=(t0, self.last_t if math.isinf(t1) else t1), f0_hz=_moments(moments["f0_hz"]),
                               q=_moments(moments["q"]), f0_row_std_hz=row_std.mean if row_std.count else None)
        return ReepSegments(**out)


def segment_statistics(
    reep_h5: Path, warmup_s: float, free_air_segment_s: tuple[float, float] | None
) -> ReepSegments:
    """Mean and standard deviation of f0' (Hz) and Q' per time segment, after the warm-up.

    Parameters
    ----------
    reep_h5 : Path
        A finished ``reep.h5``.
    warmup_s : float
        Rows with t < warmup_s (s) are left out: the EW-RLS of eq. 3.39 has
        not forgotten its initial P yet.
    free_air_segment_s : (float, float) or None
        The off-sample segment (s).  With it, the segments are ``free_air``
        (inside it) and ``after_free_air`` (t ≥ its end + warmup_s, the same
        settling allowed after the change as at the start): f0' and Q'
        before and after the tip meets the sample, or a step.  Without it, one
        segment ``settled`` (every row after the warm-up).

    Returns
    -------
    ReepSegments
        Per segment its span ``t_s`` (start, end) and the moments of ``f0_hz``
        and ``q``; std is the sample standard deviation of the rows (a
        spread, not the error of the mean).  Rows flagged in reep.h5's
        ``flag`` column (0 = valid) are left out, as the summary leaves them.
    """
    moments = SegmentMoments(warmup_s, free_air_segment_s)
    with _open(reep_h5) as reep:
        for start_row, t in reep.blocks("t"):
            rows = slice(start_row, start_row + len(t))
            row_std = reep.trusted("f0_std_hz", rows) if "f0_std_hz" in reep else None
            moments.add(t, reep.trusted("f0_hz", rows), reep.trusted("q", rows), f0_std_hz=row_std)
    return moments.record()


def _percentiles(values: np.ndarray, units: str) -> TrackingError:
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return TrackingError(median_abs=None, p95_abs=None, units=units)
    return TrackingError(median_abs=float(np.median(finite)), p95_abs=float(np.percentile(finite, 95.0)), units=units)


def tracking_error(reep_h5: Path, truth: Mapping[str, np.ndarray], sample_rate_hz: float,
                   warmup_s: float) -> TruthTracking | None:
    """Median and 95th percentile of |f0' − f0| (Hz) and |Q' − Q| after the warm-up.

    Parameters
    ----------
    reep_h5 : Path
        A finished ``reep.h5``.
    truth : mapping
        The capture's ``/truth``; needs ``f0_hz`` and ``q`` (one value per
        input sample), else None is returned.
    sample_rate_hz : float
        The capture's rate: row t belongs to input sample n = round(t·fs).
    warmup_s : float
        Rows before it (s) are left out, as in the report's summary.

    Returns
    -------
    TruthTracking or None
        The median and 95th percentile of |f0' − f0| (Hz) and |Q' − Q|, from
        ``after_s``, over ``rows_compared`` rows.  Flagged rows (NaN f0')
        and rows with a non-zero ``flag`` are left out.  Percentiles over more than
        :data:`MAX_PERCENTILE_POINTS` rows use that many evenly spaced ones.
    """
    if "f0_hz" not in truth or "q" not in truth:
        return None
    truth_f0 = np.asarray(truth["f0_hz"], dtype=np.float64)
    truth_q = np.asarray(truth["q"], dtype=np.float64)
    with _open(reep_h5) as reep:
        n_rows = len(reep["t"])
        step = max(1, math.ceil(n_rows / MAX_PERCENTILE_POINTS))
        t = reep["t"][::step]
        f0 = reep.trusted("f0_hz", slice(None, None, step))
        q = reep.trusted("q", slice(None, None, step))
    index = np.rint(t * sample_rate_hz).astype(np.int64)
    keep = (t >= warmup_s) & (index >= 0) & (index < min(len(truth_f0), len(truth_q)))
    if not np.any(keep):
        return None
    err_f0 = np.abs(f0[keep] - truth_f0[index[keep]])
    err_q = np.abs(q[keep] - truth_q[index[keep]])
    return TruthTracking(f0_hz=_percentiles(err_f0, "Hz"), q=_percentiles(err_q, ""), after_s=float(warmup_s),
                         rows_compared=int(np.count_nonzero(np.isfinite(err_f0))), row_step=step)


class Thinned(NamedTuple):
    """The rows a figure draws: evenly spaced rows, and (some of) the flagged ones."""

    t: np.ndarray
    columns: dict[str, np.ndarray]
    flagged_t: np.ndarray
    flagged: dict[str, np.ndarray]


class ThinnedRows:
    """The rows of REEP's figure, gathered as the rows stream (memory bounded, no second read of reep.h5).

    Every ``step``-th row, the step starting at ⌈expected_rows / MAX_PLOT_POINTS⌉
    (1 when the length is unknown) and doubling whenever more than
    2·MAX_PLOT_POINTS rows are held; likewise up to about 2·``_MAX_FLAG_MARKS``
    evenly spaced flagged rows (flag ≠ 0, or f0′ not finite).

    Parameters
    ----------
    names : tuple of str
        The columns drawn besides ``t``.
    expected_rows : int, optional
        Rows the stream will have, if known.
    """

    def __init__(self, names: tuple[str, ...], expected_rows: int | None = None) -> None:
        self.names = names
        step = math.ceil(expected_rows / MAX_PLOT_POINTS) if expected_rows else 1
        self._rows = EveryKth(MAX_PLOT_POINTS, step)
        self._flagged = EveryKth(_MAX_FLAG_MARKS)

    def add(self, t: np.ndarray, columns: Mapping[str, np.ndarray], flags: np.ndarray | None = None) -> None:
        """Rows at times ``t`` with their ``columns`` (those of ``names`` present) and ``flag`` values."""
        present = {"t": t, **{name: columns[name] for name in self.names if name in columns}}
        self._rows.add(present)
        bad = ~np.isfinite(columns["f0_hz"]) if "f0_hz" in columns else np.zeros(len(t), dtype=bool)
        if flags is not None:
            bad |= flags != 0
        self._flagged.add(present, np.flatnonzero(bad))

    def result(self) -> Thinned:
        rows, flagged = self._rows.items(), self._flagged.items()
        columns = {name: rows[name] for name in self.names if name in rows}
        if not flagged:
            return Thinned(rows.get("t", np.zeros(0)), columns, np.zeros(0), {name: np.zeros(0) for name in columns})
        return Thinned(rows["t"], columns, flagged["t"], {name: flagged[name] for name in columns})


def read_thinned(reep_h5: Path, names: tuple[str, ...]) -> Thinned:
    """:class:`ThinnedRows` of a finished reep.h5, read in blocks."""
    with _open(reep_h5) as h5:
        thinned = ThinnedRows(names, len(h5["t"]))
        present = [name for name in names if name in h5]
        for start, t in h5.blocks("t"):
            rows = slice(start, start + len(t))
            flags = h5[FLAG_COLUMN][rows] if FLAG_COLUMN in h5 else None
            thinned.add(t, {name: h5[name][rows] for name in present}, flags)
    return thinned.result()


def truth_at_rows(t: np.ndarray, truth: Mapping[str, np.ndarray], sample_rate_hz: float) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Each ``/truth`` series (one value per input sample) at the rows' times ``t`` (s).

    Returns ``{name: (t, values)}``, leaving out rows beyond the truth's
    end: what :func:`write_reep_time_series_png` draws, a few thousand
    values instead of one per sample.
    """
    index = np.rint(t * sample_rate_hz).astype(np.int64)
    at_rows = {}
    for name, values in truth.items():
        inside = (index >= 0) & (index < len(values))
        if np.any(inside):
            at_rows[name] = (t[inside], np.asarray(values)[index[inside]])
    return at_rows


def write_reep_time_series_png(
    path: Path,
    data: Thinned,
    *,
    amplitude_units: str,
    truth: Mapping[str, tuple[np.ndarray, np.ndarray]] | None = None,
    free_air_segment_s: tuple[float, float] | None = None,
    warmup_s: float = 0.0,
) -> None:
    """f0', Q', amplitude and phase against time, the truth drawn over them (thesis Figs. 3.6-3.8).

    The free-air segment is shaded, the warm-up (before the forgetting
    window has passed) marked, and flagged rows ((b1, b0) outside the
    under-damped region of eq. 3.48, or a non-zero ``flag`` in reep.h5)
    marked with red crosses: at their value, or at the panel's median where
    the value is NaN.  ``data``: the rows gathered in the stream
    (:class:`ThinnedRows`), or read from a finished reep.h5 (:func:`read_thinned`).
    ``truth``: ``{name: (t, values)}`` at the rows (:func:`truth_at_rows`).
    """
    from afmtool.report.images import write_multi_panel_png

    reep_style = {"color": "C0", "linewidth": 1.0}
    truth_style = {"color": "k", "linestyle": "--", "linewidth": 1.2}
    labels = {
        "f0_hz": "f0' (Hz)",
        "q": "Q' (dimensionless)",
        "amplitude": f"amplitude ({amplitude_units})" if amplitude_units else "amplitude (input units)",
        "phase_deg": "phase (deg)",
    }
    panels = []
    for name, label in labels.items():
        if name not in data.columns:
            continue
        series = [(data.t, data.columns[name], "REEP" if name in ("f0_hz", "q") else "lock-in", reep_style)]
        if truth and name in truth:
            series.append((*truth[name], "truth", truth_style))
        if data.flagged_t.size:
            # flagged rows are NaN in f0', Q': mark them at the panel's median so they show on the axis
            finite = data.columns[name][np.isfinite(data.columns[name])]
            level = float(np.median(finite)) if finite.size else 0.0
            y = np.where(np.isfinite(data.flagged[name]), data.flagged[name], level)
            series.append((data.flagged_t, y, "flagged", {"color": "C3", "linestyle": "none", "marker": "x", "markersize": 4}))
        panels.append({"y_label": label, "series": series})
    spans = []
    if free_air_segment_s:
        start, end = (float(v) for v in free_air_segment_s)
        if end > start:
            spans.append((start, end, "free-air segment"))
    markers = [(float(warmup_s), "end of warm-up")] if warmup_s > 0 else []
    write_multi_panel_png(path, panels, x_label="time t (s)", title="REEP against time", spans=spans, markers=markers)
