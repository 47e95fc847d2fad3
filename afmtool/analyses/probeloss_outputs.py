"""The ``probeloss`` command end to end: parameters, run, files, report."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from afmtool.analyses.command_inputs import CommandRun, channel_units, given_free_air_model, model_input_records
from afmtool.analyses.probeloss import SERIES_UNITS, ProbeLossResult, run_probeloss
from afmtool.analyses.probeloss_timeseries import PLOTTED
from afmtool.analyses.stream import run_stream_with_model
from afmtool.config.params import ProbeLossParams
from afmtool.io.capture import CaptureReader
from afmtool.io.results import ResultWriter, row_attrs
from afmtool.io.units import calibration_record
from afmtool.records.probeloss import ProbeLossResults
from afmtool.report.figure_process import FigureProcess
from afmtool.report.images import ImageStyle
from afmtool.report.run import finish_run
from afmtool.report.timeseries import ThinningSink
from afmtool.runtime.outputs import OutputDir

__all__ = ["run_probeloss_command", "run_probeloss_stream"]

_IMAGE_STYLES = {
    "loss": ImageStyle("probe-loss fraction", "", stem="loss_mask", cmap="gray_r", z_range=(0.0, 1.0)),
    "index": ImageStyle("reliability index", ""),
}


def _units(reader: CaptureReader) -> dict[str, str]:
    return dict(SERIES_UNITS, amplitude=channel_units(reader, "deflection"))


def run_probeloss_command(run: CommandRun) -> dict:
    """Resolve parameters, run the probe-loss analysis, write every output atomically; return the report."""
    reader = run.reader
    params = run.params(ProbeLossParams, "probeloss")
    model = given_free_air_model(params.model)
    capture_record = run.input_record()
    with OutputDir(run.out) as staged, run.figures.stopped_on_failure():
        with ResultWriter(staged.path("probeloss.h5"), _units(reader), {"afmtool_command": "probeloss"},
                          write_behind=True, float64=("t",)) as writer:
            # the overview figure's rows are kept as they stream: probeloss.h5 is not read back for them
            sink = ThinningSink(writer, PLOTTED)
            # matplotlib, for the figures at the end, loads while the observer streams
            result = run_probeloss(reader, params, sink, model=model, progress=run.progress, split=run.split,
                                   on_stream_start=run.figures.on_stream_start)
            results = result.results
            writer.set_attrs(row_attrs(results.rows, results.row_every_samples, results.row_rate_hz,
                                       reader.info.sample_rate_hz))
            _write_images(staged, writer, result, run.figures)
        staged.flush_early("probeloss.h5")  # to disk while the figures are drawn
        _write_time_series(run.figures, staged, reader, results, sink.rows())
        if result.setup is not None and result.setup.model_source == "segment":
            result.setup.model.save(staged.path("free_air.json"))
        inputs = [{**capture_record.result(), **calibration_record(reader)}, *model_input_records(params.model)]
        run.figures.wait()
        return finish_run(staged, "probeloss", inputs, "probeloss", params, results, result.warnings)


def run_probeloss_stream(reader: CaptureReader, config: Path | None, flags: Mapping, fmt: str) -> None:
    """Run the analysis and write decimated rows to stdout as each chunk completes (``--stream``)."""

    run_stream_with_model(run_probeloss, ProbeLossParams, "probeloss", reader, config, flags, fmt)


def _write_time_series(figures: FigureProcess, staged: OutputDir, reader: CaptureReader, results: ProbeLossResults,
                       overview: Mapping) -> None:
    """The index, switches, amplitude and truth contact against time: ``overview`` rows, zooms from probeloss.h5."""
    from afmtool.analyses.probeloss_timeseries import write_probeloss_time_series

    contact = reader.truth()["contact"] if "contact" in reader.info.truth_names else None
    write_probeloss_time_series(
        staged.path, staged.path("probeloss.h5"), results, amplitude_units=_units(reader)["amplitude"],
        truth_contact=contact, sample_rate_hz=reader.info.sample_rate_hz, figures=figures, overview=overview,
    )


def _write_images(staged: OutputDir, writer: ResultWriter, result: ProbeLossResult, figures: FigureProcess) -> None:
    """Probe-loss mask (fraction of each pixel's samples in loss) and index images, PNG and .gsf."""
    if result.geometry is None:
        return
    from afmtool.report.images import write_scan_images

    write_scan_images(staged.path, result.images, result.geometry, _IMAGE_STYLES.__getitem__, writer.put, figures)
