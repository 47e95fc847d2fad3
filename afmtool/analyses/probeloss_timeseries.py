"""Probe loss against time: the index with its thresholds, the switches, the amplitude, the truth.

Drawn after the run, beside the mask and index images: the overview from rows
kept as they streamed (:class:`~afmtool.report.timeseries.ThinningSink`), so that
probeloss.h5 is not read back for it.  A long capture also gets a few zoomed
segments, centred on the first, middle and last detected loss events, where
single drive periods can be told apart: those windows (300 drive periods each)
are read from the finished ``probeloss.h5``, as the events are known only at the end.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from afmtool.records.probeloss import IndexKind, ProbeLossResults
from afmtool.report.figure_process import FigureProcess

__all__ = ["PLOTTED", "ZOOM_PERIODS", "write_probeloss_time_series"]

#: The columns the figures draw.
PLOTTED = ("t", "index", "switch", "amplitude", "amplitude_switch")

#: Width of a zoomed segment, in drive periods.
ZOOM_PERIODS = 300


def _panels(rows: Mapping[str, np.ndarray], results: ProbeLossResults, amplitude_units: str,
            contact: np.ndarray | None) -> list[dict]:
    t = rows["t"]
    span = np.array([t[0], t[-1]]) if len(t) else np.zeros(2)
    index, baseline = results.index, results.amplitude_baseline
    threshold = {"color": "0.3", "linestyle": ":", "linewidth": 1.0}
    index_series = [(t, rows["index"], "index", {"color": "C0", "linewidth": 0.9})]
    for value, label, style in ((index.on, "switch-on threshold", threshold),
                                (index.off, "switch-off threshold", {**threshold, "linestyle": "--"})):
        index_series.append((span, np.full(2, float(value)), label, style))
    switches = [(t, rows["switch"], "index switch (1 = loss)", {"color": "C0", "drawstyle": "steps-post", "linewidth": 1.2})]
    if "amplitude_switch" in rows:
        # drawn at 0.9 so that the two switches stay apart where they agree
        switches.append((t, 0.9 * rows["amplitude_switch"], "amplitude switch (× 0.9)",
                         {"color": "C1", "drawstyle": "steps-post", "linestyle": "--", "linewidth": 1.0}))
    units = amplitude_units or "input units"
    amplitude = [(t, rows["amplitude"], "lock-in amplitude", {"color": "C2", "linewidth": 0.9})]
    if baseline.upper is not None:
        amplitude.append((span, np.full(2, float(baseline.upper)), "loss threshold A_upper", threshold))
    if baseline.free_amplitude is not None:
        amplitude.append((span, np.full(2, float(baseline.free_amplitude)), "free amplitude A0",
                          {**threshold, "linestyle": "--"}))
    panels = [
        # log axis: the thresholds sit near 1-4 where the index on the sample reaches hundreds
        # the forcing index is a signed projection, about N(0, 1) off the sample: a linear axis
        {"y_label": "index (dimensionless)", "series": index_series,
         "y_scale": "linear" if index.kind is IndexKind.FORCING else "log"},
        {"y_label": "switch (0/1)", "series": switches},
        {"y_label": f"amplitude ({units})", "series": amplitude},
    ]
    if contact is not None:
        panels.append({"y_label": "truth contact (0/1)", "series": [
            (t, contact, "truth: contact in the drive period", {"color": "k", "drawstyle": "steps-post", "linewidth": 1.0})]})
    return panels


def write_probeloss_time_series(
    directory_path,
    probeloss_h5: Path,
    results: ProbeLossResults,
    *,
    amplitude_units: str,
    truth_contact: np.ndarray | None,
    sample_rate_hz: float,
    figures: FigureProcess | None = None,
    overview: Mapping[str, np.ndarray] | None = None,
) -> list[str]:
    """Write ``probeloss_time_series.png`` and, for a long capture, ``probeloss_zoom_<k>.png``.

    Parameters
    ----------
    directory_path : callable
        ``name -> Path`` where to write each file (``OutputDir.path``).
    probeloss_h5 : Path
        The finished result file (``t``, ``index``, ``switch``, ``amplitude``, ``amplitude_switch``).
    results : ProbeLossResults
        The run's results: the thresholds (``index.on``, ``index.off``,
        ``amplitude_baseline.upper``), the drive frequency and the events.
    amplitude_units : str
        The deflection's units.
    truth_contact : ndarray or None
        ``/truth/contact`` per input sample; drawn as its maximum over each
        row's drive period.
    sample_rate_hz : float
        The capture's rate, to place the truth at the rows.
    figures : FigureProcess, optional
        Draws the figure (the command's figure process); by default this process.
    overview : mapping, optional
        The whole run's rows for the overview (``t`` and the drawn columns,
        thinned as they streamed); by default read thinned from ``probeloss_h5``.

    Returns
    -------
    list of str
        The names written.
    """
    from afmtool.io.result_files import open_probeloss_results
    from afmtool.report.images import write_multi_panel_png
    from afmtool.report.timeseries import truth_per_row, zoom_windows

    names = PLOTTED[1:]
    written = []

    def draw(name: str, t_range, title: str) -> None:
        if t_range is None and overview is not None:
            rows = overview
        else:
            with open_probeloss_results(probeloss_h5) as probeloss:
                rows = probeloss.read_rows(names, t_range=t_range)
        if len(rows.get("t", ())) < 2:
            return
        contact = truth_per_row(truth_contact, rows["t"], sample_rate_hz, reduce="max") if truth_contact is not None else None
        (figures or FigureProcess()).draw(
            write_multi_panel_png, directory_path(name), _panels(rows, results, amplitude_units, contact),
            x_label="time t (s)", title=title, x_limits=t_range,
        )
        written.append(name)

    draw("probeloss_time_series.png", None, "Probe loss against time (thesis ch. 2)")
    drive_hz, duration = results.drive_frequency_hz, results.duration_s
    if drive_hz > 0:
        centres = [event.start_s for event in results.events]
        for k, window in enumerate(zoom_windows(float(duration), ZOOM_PERIODS / float(drive_hz), centres), start=1):
            draw(f"probeloss_zoom_{k}.png", window, f"Probe loss, zoom {k}: {window[0] * 1e3:.2f}–{window[1] * 1e3:.2f} ms")
    return written
