"""What a command's result record gives report.json: ``to_json()``.

The analyses return frozen dataclasses (``ReepResult``, ``ProbeLossResult``,
``DecodeResult``, ``KalmanBankResult``, ``TheoryComparisonResult``, ...);
each knows how to write itself as the ``results`` section of report.json,
so the JSON conversion (numpy scalars and arrays to lists, non-finite
floats to null, as :func:`afmtool.report.json_report.to_jsonable`) happens
in one place.
"""

from __future__ import annotations

from collections.abc import Mapping

from afmtool.report.json_report import to_jsonable

__all__ = ["JsonResults"]


class JsonResults:
    """Base of the result records whose report section is their ``results`` mapping."""

    results: Mapping

    def to_json(self) -> dict:
        """``results`` as report.json holds them: JSON types only, non-finite floats as null."""
        return to_jsonable(self.results)
