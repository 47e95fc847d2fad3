"""Reading decimated result series back for figures: thinned, windowed, with the truth at their rows.

Result files (``reep.h5``, ``probeloss.h5``, ``decode.h5``, ``bank.h5``)
hold one row per kept sample, ``t`` in seconds.  A figure draws at most a
few tens of thousands of points per line, so the rows are read with an
HDF5 stride (memory stays flat however long the capture), or, for a zoomed
segment, only the rows inside it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

__all__ = ["MAX_PLOT_POINTS", "read_rows", "truth_per_row", "zoom_windows"]

#: Most rows drawn per line.
MAX_PLOT_POINTS = 20000


def read_rows(
    path: Path,
    names: Sequence[str],
    *,
    time: str = "t",
    t_range: tuple[float, float] | None = None,
    max_points: int = MAX_PLOT_POINTS,
) -> dict[str, np.ndarray]:
    """Columns ``time`` and ``names`` of a result file, evenly thinned to at most ``max_points`` rows.

    Parameters
    ----------
    path : Path
        An HDF5 result file with 1-D datasets of one length.
    names : sequence of str
        Columns wanted; absent ones are left out of the result.
    time : str
        The time column (s), ascending.
    t_range : (float, float), optional
        Only rows with ``t_range[0] <= t < t_range[1]`` (s).
    max_points : int
        Most rows returned; every k-th row beyond that.

    Returns
    -------
    dict
        ``{name: array}`` including ``time``, plus ``"_rows"``: the row
        numbers read (int64).
    """
    import h5py

    with h5py.File(path, "r") as h5:
        t_all = h5[time]
        n = len(t_all)
        start, stop = 0, n
        if t_range is not None:
            # t is ascending: find the window by bisection on the dataset, never reading all of it
            start, stop = _bisect(t_all, float(t_range[0]), n), _bisect(t_all, float(t_range[1]), n)
        step = max(1, math.ceil((stop - start) / max_points))
        rows = np.arange(start, stop, step, dtype=np.int64)
        out = {time: t_all[start:stop:step]}
        for name in names:
            if name in h5 and name != time and len(h5[name]) == n:
                out[name] = h5[name][start:stop:step]
    out["_rows"] = rows
    return out


def _bisect(dataset, value: float, n: int) -> int:
    lo, hi = 0, n
    while lo < hi:
        mid = (lo + hi) // 2
        if float(dataset[mid]) < value:
            lo = mid + 1
        else:
            hi = mid
    return lo


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
