"""Finishing a run: the effective config and ``report.json`` beside the outputs."""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from typing import TYPE_CHECKING, Any

from afmtool.config import parameters_dict, section_to_toml
from afmtool.report.json_report import build_report, dumps
from afmtool.runtime.outputs import OutputDir

if TYPE_CHECKING:
    from afmtool.records import Record

__all__ = ["finish_run", "result_format"]

#: ``--format`` of the run in progress: its result arrays as afmtool's HDF5 (``h5``), ``netcdf`` or ``zarr``.
#: Set around a runner by :meth:`afmtool.api.run.RunSettings.writing` (a context variable: a thread or task of
#: its own sees the default).
_RESULT_FORMAT: ContextVar[str] = ContextVar("afmtool_result_format", default="h5")


@contextmanager
def result_format(data_format: str) -> Iterator[None]:
    """Within the block, :func:`finish_run` writes the run's result arrays in ``data_format``."""
    from afmtool.errors import ConfigError
    from afmtool.report.labelled import DATA_FORMATS

    if data_format not in DATA_FORMATS:
        raise ConfigError(f"--format {data_format!r} must be one of {', '.join(DATA_FORMATS)}")
    token = _RESULT_FORMAT.set(data_format)
    try:
        yield
    finally:
        _RESULT_FORMAT.reset(token)


def finish_run(
    staged: OutputDir,
    command: str,
    inputs: Sequence[Mapping],
    section: str,
    params: Any,
    results: Record | Mapping,
    warnings: Sequence[str],
) -> dict:
    """Write ``config.toml`` (effective parameters) and ``report.json``; return the report.

    Under :func:`result_format` ``netcdf`` or ``zarr``, the run's result HDF5 files are first
    replaced by labelled-array files (:func:`afmtool.report.labelled.convert_result_files`).
    """
    staged.path("config.toml").write_text(
        "# Effective parameters of this run (packaged defaults < --config < flags).\n"
        + section_to_toml(section, params),
        encoding="utf-8",
    )
    data_format = _RESULT_FORMAT.get()
    if data_format != "h5":
        from afmtool import __version__
        from afmtool.report.headline import headline
        from afmtool.report.labelled import convert_result_files

        stub = {"command": command, "afmtool_version": __version__, "parameters": parameters_dict(params),
                "inputs": list(inputs), "headline": headline(command, results)}
        convert_result_files(staged, stub, data_format)
    report_path = staged.path("report.json")
    # OutputDir.names lists the outputs that exist: report.json must, to list itself
    report_path.touch()
    from afmtool.report.captured_warnings import drain

    warnings = [*warnings, *drain()]  # numpy/h5py warnings of this run, recorded instead of printed
    report = build_report(command, inputs, parameters_dict(params), results, staged.names, warnings)
    report_path.write_text(dumps(report), encoding="utf-8")
    return report
