"""Decimated result series in figures: the truth at their rows, and zoom windows.

Result files (``reep.h5``, ``probeloss.h5``, ``decode.h5``, ``bank.h5``)
hold one row per kept sample, ``t`` in seconds.  A figure draws at most
:data:`MAX_PLOT_POINTS` points per line; the rows are read, thinned or by
time window, by :meth:`afmtool.io.result_files.ResultFile.read_rows`, or
gathered as the rows stream (:class:`EveryKth`, :class:`ThinningSink`), so
that a command need not read its own output back for its overview figure.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from afmtool.io.result_files import MAX_PLOT_POINTS

__all__ = ["MAX_PLOT_POINTS", "EveryKth", "ThinningSink", "truth_per_row", "zoom_windows"]


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


def _rows_in(items: Mapping[str, np.ndarray]) -> int:
    return np.shape(next(iter(items.values())))[-1]


class EveryKth:
    """Every ``step``-th row of a stream, the step doubling (every other kept row dropped) past ``2·most``.

    Rows run along the last axis, so a 2-D column (one line per filter, ``(N, rows)``)
    is thinned with the 1-D ones.  Memory: at most about ``2·most`` rows.
    """

    def __init__(self, most: int, step: int = 1) -> None:
        self.most, self.step, self.seen, self.kept = most, max(1, int(step)), 0, 0
        self.parts: list[dict[str, np.ndarray]] = []

    def add(self, items: Mapping[str, np.ndarray], rows: np.ndarray | None = None) -> None:
        """The rows next in the stream: all of ``items``, or those at ``rows``."""
        n = _rows_in(items) if rows is None else len(rows)
        first = -self.seen % self.step  # the next row whose stream position is a multiple of the step
        self.seen += n
        if first < n:
            taken = slice(first, None, self.step) if rows is None else rows[first::self.step]
            # a slice is a view of the caller's block, an index array a copy already
            self.parts.append({name: values[..., taken].copy() if rows is None else values[..., taken]
                               for name, values in items.items()})
            self.kept += _rows_in(self.parts[-1])
        while self.kept > 2 * self.most:
            # kept rows sit at positions 0, step, 2·step, …: every other one is a multiple of 2·step
            self.parts = [{name: values[..., ::2] for name, values in self.items().items()}]
            self.kept = _rows_in(self.parts[0])
            self.step *= 2

    def items(self) -> dict[str, np.ndarray]:
        if not self.parts:
            return {}
        return {name: np.concatenate([part[name] for part in self.parts], axis=-1) for name in self.parts[0]}


class ThinningSink:
    """A result sink that also keeps every k-th row of ``names`` for the overview figure.

    ``append`` hands each chunk's columns on to ``sink`` unchanged; :meth:`rows`
    returns the kept rows (at most about 2·:data:`MAX_PLOT_POINTS`) once the
    stream has ended.  Anything else is the sink's.
    """

    def __init__(self, sink, names: Sequence[str], most: int = MAX_PLOT_POINTS) -> None:
        self._sink = sink
        self._names = tuple(names)
        self._rows = EveryKth(most)

    def append(self, columns: Mapping[str, np.ndarray]) -> None:
        self._sink.append(columns)
        kept = {name: np.asarray(columns[name]) for name in self._names if name in columns}
        if kept:
            self._rows.add(kept)

    def rows(self) -> dict[str, np.ndarray]:
        """The kept rows, ``{name: array}`` (empty when no row came)."""
        return self._rows.items()

    def __getattr__(self, name: str):
        if name.startswith("__") or name == "_sink":
            raise AttributeError(name)
        return getattr(self._sink, name)
