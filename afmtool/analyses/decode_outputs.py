"""The ``decode`` command end to end: parameters, run, files, report."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from afmtool.analyses.command_inputs import CommandRun
from afmtool.analyses.decode import SERIES_UNITS, DecodeResult, run_decode
from afmtool.analyses.stream import run_stream
from afmtool.config.params import DecodeParams
from afmtool.io.capture import CaptureReader
from afmtool.io.results import ResultWriter, row_attrs
from afmtool.io.units import calibration_record
from afmtool.records.decode import DecodeResults
from afmtool.report.figure_process import FigureProcess
from afmtool.report.run import finish_run
from afmtool.runtime.outputs import OutputDir

__all__ = ["run_decode_command", "run_decode_stream"]


def run_decode_command(run: CommandRun) -> dict:
    """Resolve parameters, decode, write every output atomically; return the report."""
    reader = run.reader
    params = run.params(DecodeParams, "decode")
    record = run.input_record()
    with OutputDir(run.out) as staged, run.figures.stopped_on_failure():
        attrs = {"afmtool_command": "decode", "sample_rate_hz": reader.info.sample_rate_hz}
        with ResultWriter(staged.path("decode.h5"), SERIES_UNITS, attrs, write_behind=True,
                          float64=("t_mean",)) as writer:
            # matplotlib, for the eye, PSD and ℓ0 figures at the end, loads while the EKF streams
            result = run_decode(reader, params, writer, progress=run.progress, on_stream_start=run.figures.on_stream_start,
                                split=run.split)
            found = result.results
            writer.set_attrs(row_attrs(found.rows.value, found.row_every_samples, found.row_rate_hz,
                                       reader.info.sample_rate_hz))
            if result.psd:
                for name in ("frequency_hz", "deflection", "innovation"):
                    units = "Hz" if name == "frequency_hz" else "nm^2/Hz"
                    writer.put(f"psd/{name}", result.psd[name], units)
        staged.flush_early("decode.h5")  # to disk while the figures are drawn
        _write_figures(run.figures, staged, result)
        if result.step is None:
            _write_time_series(run.figures, staged, reader, result.results)
        inputs = [{**record.result(), **calibration_record(reader)}]
        run.figures.wait()
        return finish_run(staged, "decode", inputs, "decode", params, result.results, result.warnings)


def run_decode_stream(reader: CaptureReader, config: Path | None, flags: Mapping, fmt: str) -> None:
    """Decode with the innovation running mean (t_mean, innovation_mean) as rows on stdout (``--stream``).

    Per-sample innovation rows at MHz rates would swamp a pipe; one row per
    actuation period is what a live display needs.
    """
    run_stream(run_decode, DecodeParams, "decode", reader, config, flags, fmt, row_columns=("t_mean", "innovation_mean"))


def _write_time_series(figures: FigureProcess, staged: OutputDir, reader: CaptureReader,
                       results: DecodeResults) -> None:
    """decode_time_series.png: the running mean with the decided bits and, with /truth/bit, the truth."""
    from afmtool.analyses.decode_timeseries import write_decode_time_series_png

    truth_bit = reader.truth()["bit"] if "bit" in reader.info.truth_names else None
    write_decode_time_series_png(staged.path, staged.path("decode.h5"), results, truth_bit=truth_bit,
                                 sample_rate_hz=reader.info.sample_rate_hz, figures=figures)


def _write_figures(figures: FigureProcess, staged: OutputDir, result: DecodeResult) -> None:
    from afmtool.analyses.decode_figures import write_eye_png, write_l0_png, write_psd_png, write_step_png

    found = result.results
    if result.step is not None:  # --mode step: the response to the V_phi step
        series, fs = result.step, found.ekf.sample_rate_hz
        figures.draw(write_step_png, staged.path("decode_step.png"), series.deflection, series.innovation,
                     series.amplitude, series.first, round(found.step.time_s * fs), fs, found.ekf.mean_window_samples)

    if result.eye:
        figures.draw(write_eye_png, staged.path("eye.png"), result.eye["x"], result.eye["traces"],
                     result.eye["threshold_nm"])
    if result.psd:
        figures.draw(write_psd_png, staged.path("psd.png"), result.psd["frequency_hz"], result.psd["deflection"],
                     result.psd["innovation"])
    if result.l0_curve_nm is not None:
        figures.draw(write_l0_png, staged.path("l0_search.png"), *result.l0_curve_nm,
                     found.l0.estimate_nm)
