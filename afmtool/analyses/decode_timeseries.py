"""Decoding against time: the innovation's running mean, the decided bits and the truth (thesis Fig. 7.9).

Drawn from the finished ``decode.h5`` (``t_mean``, ``innovation_mean``,
``bit_times_s``, ``bits``, ``soft``).  A stream of many bits is shown over
its first :data:`WINDOW_BITS` bit periods after the clock is acquired, where
single cells can be read; the eye diagram shows all of them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from afmtool.records.decode import DecodeResults
from afmtool.report.figure_process import FigureProcess

__all__ = ["WINDOW_BITS", "write_decode_time_series_png"]

#: Bit periods shown.
WINDOW_BITS = 60


def write_decode_time_series_png(
    directory_path,
    decode_h5: Path,
    results: DecodeResults,
    *,
    truth_bit: np.ndarray | None,
    sample_rate_hz: float,
    figures: FigureProcess | None = None,
) -> bool:
    """Innovation running mean with the threshold and cell values over the decided bits and the truth.

    Parameters
    ----------
    directory_path : callable
        ``name -> Path`` where to write ``decode_time_series.png`` (``OutputDir.path``),
        called only when there is a figure to write.
    decode_h5 : Path
        The finished result file.
    results : DecodeResults
        The run's results: ``bits.threshold_nm``, ``clock.rate_hz`` and, with
        truth, ``truth.decoder.latency_s``.
    truth_bit : ndarray or None
        ``/truth/bit`` per input sample; drawn delayed by the decoder's
        latency (the alignment its BER was counted with).
    sample_rate_hz : float
        The capture's rate.
    figures : FigureProcess, optional
        Draws the figure (the command's figure process); by default this process.

    Returns
    -------
    bool
        Whether a figure was written (not without decoded bits).
    """
    from afmtool.io.result_files import open_decode_results
    from afmtool.report.images import write_multi_panel_png

    if results.clock is None or results.clock.rate_hz <= 0:
        return False
    rate = results.clock.rate_hz
    with open_decode_results(decode_h5) as decoded:
        if "bit_times_s" not in decoded.names() or len(decoded["bit_times_s"]) == 0:
            return False
        # only the first WINDOW_BITS cells are drawn: read their window, not every bit of the run
        start = float(decoded["bit_times_s"][0]) - 0.5 / rate
        window = (start, start + WINDOW_BITS / rate)
        bit_rows = decoded.read_rows(("bits", "soft"), time="bit_times_s", t_range=window, max_points=10**9)
        if "bits" not in bit_rows:
            return False
        cells = (bit_rows["bit_times_s"] >= window[0]) & (bit_rows["bit_times_s"] < window[1])
        means = decoded.read_rows(("innovation_mean",), time="t_mean", t_range=window)
    t_bits = bit_rows["bit_times_s"][cells]
    mean_series = [(means["t_mean"], means["innovation_mean"], "innovation running mean", {"color": "C0", "linewidth": 1.0})]
    if "soft" in bit_rows:
        mean_series.append((t_bits, bit_rows["soft"][cells], "cell value", {"color": "C1", "linestyle": "none", "marker": "o", "markersize": 3}))
    if results.bits is not None:
        threshold = float(results.bits.threshold_nm)
        mean_series.append((np.array(window), np.full(2, threshold), "threshold", {"color": "C3", "linestyle": "--", "linewidth": 1.0}))
    bit_series = [(t_bits, bit_rows["bits"][cells].astype(np.float64), "decided bit",
                   {"color": "C0", "drawstyle": "steps-mid", "linewidth": 1.5})]
    latency = results.truth.decoder.latency_s if results.truth is not None else None
    if truth_bit is not None and len(truth_bit):
        delay = float(latency) if latency is not None and np.isfinite(latency) else 0.0
        first = max(0, int(np.floor((window[0] - delay) * sample_rate_hz)))
        last = min(len(truth_bit), int(np.ceil((window[1] - delay) * sample_rate_hz)) + 1)
        if last > first:
            n = np.arange(first, last)
            bit_series.append((n / sample_rate_hz + delay, 0.9 * np.asarray(truth_bit[first:last], dtype=np.float64),
                               f"truth (× 0.9, delayed {delay * 1e6:.1f} µs)",
                               {"color": "k", "linestyle": "--", "drawstyle": "steps-post", "linewidth": 1.0}))
    panels = [
        {"y_label": "innovation mean (nm)", "series": mean_series},
        {"y_label": "bit (0/1)", "series": bit_series},
    ]
    count = int(np.count_nonzero(cells))
    (figures or FigureProcess()).draw(
        write_multi_panel_png, directory_path("decode_time_series.png"), panels, x_label="time t (s)", x_limits=window,
        title=f"EKF innovation and decided bits: the first {count} bits ({rate / 1e3:.4g} kbit/s)",
    )
    return True
