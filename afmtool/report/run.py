"""Finishing a run: the effective config and ``report.json`` beside the outputs."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from afmtool.config import parameters_dict, section_to_toml
from afmtool.report.json_report import build_report, dumps
from afmtool.report.outputs import OutputDir

__all__ = ["finish_run"]


def finish_run(
    staged: OutputDir,
    command: str,
    inputs: Sequence[Mapping],
    section: str,
    params: Any,
    results: Mapping,
    warnings: Sequence[str],
) -> dict:
    """Write ``config.toml`` (effective parameters) and ``report.json``; return the report."""
    staged.path("config.toml").write_text(
        "# Effective parameters of this run (packaged defaults < --config < flags).\n"
        + section_to_toml(section, params),
        encoding="utf-8",
    )
    report_path = staged.path("report.json")
    # OutputDir.names lists the outputs that exist: report.json must, to list itself
    report_path.touch()
    from afmtool.report.captured_warnings import drain

    warnings = [*warnings, *drain()]  # numpy/h5py warnings of this run, recorded instead of printed
    report = build_report(command, inputs, parameters_dict(params), results, staged.names, warnings)
    report_path.write_text(dumps(report), encoding="utf-8")
    return report
