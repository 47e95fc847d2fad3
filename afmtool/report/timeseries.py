"""Decimated result series in figures: the truth at their rows, and zoom windows.

Result files (``reep.h5``, ``probeloss.h5``, ``decode.h5``, ``bank.h5``)
hold one row per kept sample, ``t`` in seconds.  A figure draws at most
:data:`MAX_PLOT_POINTS` points per line; the rows are read, thinned or by
time window, by :meth:`afmtool.io.result_files.ResultFile.read_rows`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from afmtool.io.result_files import MAX_PLOT_POINTS

__all__ = ["MAX_PLOT_POINTS", "truth_per_row", "zoom_windows"]


def truth_per_row(truth: np.ndarray, t_s: np.ndarray, sample_rate_hz: float, *, reduce: str = "sample") -> np.ndarray:
    """The per-sample ``truth`` at the rows' times ``t_s``: n = round(t·fs).

    ``reduce="max"`` gives the maximum over the samples since the previous
    row instead (an indicator such as ``/truth/contact``, 1 for one sample
    per drive period, stays visible when rows are thinned).
    """
    truth = np.asarray(truth)
    index = np.clip(np.rint(np.asarray(t_s) * sample_rate_hz).astype(np.int64), 0, max(0, len(truth) - 1))
    if reduce == "sample" or len(index) == 0:
        return truth[index].astype(np.float64)
    if reduce != "max":
        raise ValueError(f"reduce={reduce!r} must be 'sample' or 'max'")
    starts = np.concatenate(([0], index[:-1] + 1)).clip(max=len(truth) - 1)
    starts = np.minimum(starts, index)
    return np.maximum.reduceat(truth.astype(np.float64), starts)[: len(index)] if len(truth) else np.zeros(0)


def zoom_windows(
    duration_s: float, width_s: float, centres_s: Sequence[float], count: int = 3
) -> list[tuple[float, float]]:
    """Up to ``count`` windows of ``width_s`` (s) around the first, middle and last of ``centres_s``.

    Without centres, evenly spaced windows.  Windows are kept inside
    [0, duration_s]; none when the capture is not longer than five windows.
    """
    if not (duration_s > 5 * width_s > 0):
        return []
    centres = sorted(float(c) for c in centres_s if 0 <= c <= duration_s)
    if centres:
        picks = [centres[0], centres[len(centres) // 2], centres[-1]][:count]
    else:
        picks = [duration_s * (k + 0.5) / count for k in range(count)]
    windows: list[tuple[float, float]] = []
    for centre in picks:
        start = min(max(0.0, centre - width_s / 2), duration_s - width_s)
        window = (start, start + width_s)
        if all(abs(window[0] - w[0]) > width_s / 2 for w in windows):
            windows.append(window)
    return windows
