"""What the command runners (``*_outputs.py``) read before they run: the given model, units, records.

The runners of reep, probeloss and kalman-bank each began with the same
lines: load ``--model`` if given, record it as an input, and take the units
of a channel the capture may lack.  They live here once.
"""

from __future__ import annotations

from pathlib import Path

from afmtool.io.capture import CaptureReader
from afmtool.models.free_air import FreeAirModel, load_free_air_model

__all__ = ["channel_units", "given_free_air_model", "model_input_records"]


def given_free_air_model(model: str) -> FreeAirModel | None:
    """The free-air model of ``--model`` (a ``free_air.json``, its folder or a ``report.json``); None if not given."""
    return load_free_air_model(Path(model)) if model else None


def model_input_records(model: str) -> list[dict]:
    """The input record (path, role, sha256) of the ``--model`` file, as a list: empty if not given."""
    from afmtool.report.json_report import input_record

    if not model:
        return []
    path = Path(model)
    return [input_record(path / "free_air.json" if path.is_dir() else path, "model")]


def channel_units(reader: CaptureReader, name: str) -> str:
    """Units of channel ``name``; "" when the capture has no such channel."""
    return reader.info.units(name) if name in reader.info.channel_names else ""
