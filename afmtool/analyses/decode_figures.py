"""The ``decode`` command's figures: the eye diagram, the PSDs and the ℓ0 search.

Apart from :mod:`afmtool.analyses.decode_outputs` so that the figure process
(:mod:`afmtool.report.figure_process`), which imports the module of each
figure it draws, loads numpy and matplotlib for them, not the decoder.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["write_eye_png", "write_l0_png", "write_psd_png"]

#: Eye-diagram trace style: thin, translucent, one colour.
_EYE_STYLE = {"color": "C0", "linewidth": 0.6, "alpha": 0.25}


def write_eye_png(path: Path, x: np.ndarray, traces: np.ndarray, threshold_nm: float) -> None:
    """Eye diagram: the innovation running mean over ±1 bit period around each cell centre.

    The traces are drawn as one line broken by NaN (fast for hundreds of
    traces), with the decision threshold as a dashed line.
    """
    from afmtool.report.images import write_line_plot_png

    rows = np.asarray(traces, dtype=np.float64)
    pad = np.full((rows.shape[0], 1), np.nan)
    ys = np.hstack([rows, pad]).ravel()
    xs = np.tile(np.append(np.asarray(x, dtype=np.float64), np.nan), rows.shape[0])
    xs[np.isnan(ys)] = np.nan
    xs = np.where(np.isnan(xs), 0.0, xs)  # x must be finite; NaN in y breaks the line
    series = [
        (xs, ys, "", _EYE_STYLE),
        (np.array([x[0], x[-1]]), np.array([threshold_nm, threshold_nm]), "threshold",
         {"color": "C3", "linestyle": "--", "linewidth": 1.0}),
    ]
    write_line_plot_png(
        path, series, x_label="time from the cell centre (bit periods)", y_label="innovation, running mean (nm)",
        title=f"Eye diagram ({rows.shape[0]} bit cells)",
    )


def write_psd_png(path: Path, freqs_hz: np.ndarray, deflection: np.ndarray, innovation: np.ndarray) -> None:
    """PSD of the raw deflection and of the EKF innovation, dB re 1 nm²/Hz (like thesis Fig. 7.8)."""
    from afmtool.report.images import write_line_plot_png

    floor = 1e-30

    def db(values):
        return 10.0 * np.log10(np.maximum(np.asarray(values, dtype=np.float64), floor))

    f_khz = np.asarray(freqs_hz, dtype=np.float64) / 1e3
    write_line_plot_png(
        path,
        [(f_khz, db(deflection), "raw deflection", {"color": "C0"}), (f_khz, db(innovation), "EKF innovation", {"color": "C3"})],
        x_label="frequency (kHz)", y_label="PSD (dB re 1 nm²/Hz)", title="Raw deflection and EKF innovation",
    )


def write_l0_png(path: Path, l0_nm: np.ndarray, rms_nm: np.ndarray, estimate_nm: float) -> None:
    """Innovation RMS against ℓ0 on the nominal segment (§7.4, Fig. 7.4b)."""
    from afmtool.report.images import write_line_plot_png

    write_line_plot_png(
        path, [(np.asarray(l0_nm), np.asarray(rms_nm), "", {"color": "C0", "marker": ".", "markersize": 3})],
        x_label="l0 (nm)", y_label="innovation RMS (nm)", title="l0 search on the nominal segment",
        markers=[(estimate_nm, f"l0 = {estimate_nm:.1f} nm")],
    )
