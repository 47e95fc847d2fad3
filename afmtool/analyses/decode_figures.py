"""The ``decode`` command's figures: the eye diagram, the PSDs and the ℓ0 search.

Apart from :mod:`afmtool.analyses.decode_outputs` so that the figure process
(:mod:`afmtool.report.figure_process`), which imports the module of each
figure it draws, loads numpy and matplotlib for them, not the decoder.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["write_eye_png", "write_l0_png", "write_psd_png", "write_step_png"]

#: Points drawn per panel of the step figure (min/max envelopes keep the spikes).
_STEP_POINTS = 4000

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


def write_step_png(path: Path, deflection: np.ndarray, innovation: np.ndarray, amplitude: np.ndarray,
                   first_sample: int, step_sample: int, sample_rate_hz: float, mean_window: int) -> None:
    """The V_phi step (§7.7, Figs. 7.9-7.12): deflection, its amplitude, the innovation and its running mean.

    Time in ms from the step; the step is a dotted line through every panel.
    """
    from afmtool.report.images import write_multi_panel_png

    n = deflection.size
    t_ms = (first_sample + np.arange(n) - step_sample) / sample_rate_hz * 1e3
    c = np.concatenate(([0.0], np.cumsum(innovation)))
    mean = np.full(n, np.nan)
    mean[mean_window - 1:] = (c[mean_window:] - c[:-mean_window]) / mean_window
    step = max(1, n // _STEP_POINTS)

    def panel(values, label, colour):
        return {"y_label": label, "series": [(t_ms[::step], values[::step], "", {"color": colour, "linewidth": 0.8})]}

    write_multi_panel_png(
        path,
        [panel(deflection, "deflection (nm)", "C0"), panel(amplitude, "amplitude at f_a (nm)", "C1"),
         panel(innovation, "EKF innovation (nm)", "C2"), panel(mean, "innovation, running mean (nm)", "C3")],
        x_label="time from the V_phi step (ms)",
        title="Step in the surface potential (thesis Figs. 7.9-7.12)",
        markers=[(0.0, "V_phi step")],
    )
