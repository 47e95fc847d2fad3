"""The ``decode`` command end to end: parameters, run, files, report."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from afmtool.analyses.command_inputs import CommandRun
from afmtool.analyses.decode import SERIES_UNITS, DecodeResult, run_decode
from afmtool.analyses.stream import run_stream
from afmtool.config.params import DecodeParams
from afmtool.io.capture import CaptureReader
from afmtool.io.results import ResultWriter
from afmtool.io.units import calibration_record
from afmtool.report.outputs import OutputDir
from afmtool.report.run import finish_run

__all__ = ["run_decode_command", "run_decode_stream", "write_eye_png", "write_psd_png", "write_l0_png"]

#: Eye-diagram trace style: thin, translucent, one colour.
_EYE_STYLE = {"color": "C0", "linewidth": 0.6, "alpha": 0.25}


def run_decode_command(run: CommandRun) -> dict:
    """Resolve parameters, decode, write every output atomically; return the report."""
    from afmtool.report.images import start_matplotlib_import

    reader = run.reader
    params = run.params(DecodeParams, "decode")
    record = run.input_record()
    with OutputDir(run.out) as staged:
        attrs = {"afmtool_command": "decode", "sample_rate_hz": reader.info.sample_rate_hz}
        with ResultWriter(staged.path("decode.h5"), SERIES_UNITS, attrs, write_behind=True) as writer:
            # matplotlib, for the eye, PSD and ℓ0 figures at the end, loads while the EKF streams
            result = run_decode(reader, params, writer, progress=run.progress, on_stream_start=start_matplotlib_import,
                                split=run.split)
            if result.psd:
                for name in ("frequency_hz", "deflection", "innovation"):
                    units = "Hz" if name == "frequency_hz" else "nm^2/Hz"
                    writer.put(f"psd/{name}", result.psd[name], units)
        staged.flush_early("decode.h5")  # to disk while the figures are drawn
        _write_figures(staged, result)
        _write_time_series(staged, reader, result.results)
        inputs = [{**record.result(), **calibration_record(reader)}]
        return finish_run(staged, "decode", inputs, "decode", params, result.results, result.warnings)


def run_decode_stream(reader: CaptureReader, config: Path | None, flags: Mapping, fmt: str) -> None:
    """Decode with the innovation running mean (t_mean, innovation_mean) as rows on stdout (``--stream``).

    Per-sample innovation rows at MHz rates would swamp a pipe; one row per
    actuation period is what a live display needs.
    """
    run_stream(run_decode, DecodeParams, "decode", reader, config, flags, fmt, row_columns=("t_mean", "innovation_mean"))


def _write_time_series(staged: OutputDir, reader: CaptureReader, results: Mapping) -> None:
    """decode_time_series.png: the running mean with the decided bits and, with /truth/bit, the truth."""
    from afmtool.analyses.decode_timeseries import write_decode_time_series_png

    truth_bit = reader.truth()["bit"] if "bit" in reader.info.truth_names else None
    write_decode_time_series_png(staged.path, staged.path("decode.h5"), results, truth_bit=truth_bit,
                                 sample_rate_hz=reader.info.sample_rate_hz)


def _write_figures(staged: OutputDir, result: DecodeResult) -> None:
    if result.eye:
        write_eye_png(staged.path("eye.png"), result.eye["x"], result.eye["traces"], result.eye["threshold_nm"])
    if result.psd:
        write_psd_png(staged.path("psd.png"), result.psd["frequency_hz"], result.psd["deflection"], result.psd["innovation"])
    if result.l0_curve_nm is not None:
        write_l0_png(staged.path("l0_search.png"), *result.l0_curve_nm, result.results["l0"]["estimate_nm"])


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
