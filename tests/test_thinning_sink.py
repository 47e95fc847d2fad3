"""Rows kept for an overview figure as they stream (issue 33: no command reads its own output back)."""

from __future__ import annotations

import numpy as np

from afmtool.report.timeseries import EveryKth, ThinningSink


class _Collect:
    def __init__(self) -> None:
        self.chunks: list[dict] = []
        self.attrs = {"kept": True}

    def append(self, columns) -> None:
        self.chunks.append(columns)


def test_the_sink_hands_every_row_on_and_keeps_every_kth_of_1d_and_2d_columns():
    rng = np.random.default_rng(4)
    n = 50_003
    t = np.arange(n) / 1e5
    rms = rng.random((3, n))  # one line per filter, rows along the last axis
    inner = _Collect()
    sink = ThinningSink(inner, ("t", "rms"), most=1000)
    start = 0
    while start < n:
        stop = min(n, start + int(rng.integers(1, 4000)))
        sink.append({"t": t[start:stop], "rms": rms[:, start:stop], "other": t[start:stop]})
        start = stop
    np.testing.assert_array_equal(np.concatenate([c["t"] for c in inner.chunks]), t)
    np.testing.assert_array_equal(np.concatenate([c["rms"] for c in inner.chunks], axis=-1), rms)
    rows = sink.rows()
    assert set(rows) == {"t", "rms"}
    step = round((rows["t"][1] - rows["t"][0]) * 1e5)
    # evenly spaced from the first row, between most and 2·most of them, 2-D columns thinned alike
    assert 1000 <= len(rows["t"]) <= 2000
    np.testing.assert_array_equal(rows["t"], t[::step])
    np.testing.assert_array_equal(rows["rms"], rms[:, ::step])
    assert sink.attrs == {"kept": True}  # the rest is the wrapped sink's


def test_every_kth_of_a_short_stream_keeps_every_row():
    kept = EveryKth(most=100)
    kept.add({"t": np.arange(10.0)})
    kept.add({"t": np.arange(10.0, 15.0)})
    np.testing.assert_array_equal(kept.items()["t"], np.arange(15.0))
    assert EveryKth(most=5).items() == {}
