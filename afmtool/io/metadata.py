"""Validation of capture metadata.

The contract is ``schemas/capture-metadata.schema.json``; this module checks
the typed keys of that schema without a runtime dependency on a JSON-schema
engine.  ``tests/test_metadata.py`` keeps the two in step by running the same
good and bad examples through both.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from typing import Any

from afmtool.errors import InputError

__all__ = ["MAX_JSON_DEPTH", "json_depth", "parse_metadata_json", "validate_metadata"]

_POSITIVE = "a number > 0"


#: Largest scan image (lines x pixels per line) accepted: 2^26 pixels, 512 MiB as float64.
MAX_SCAN_PIXELS = 1 << 26


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _check_number(where: str, value: Any, *, minimum: float = 0.0, exclusive: bool = True) -> None:
    ok = _is_number(value) and (value > minimum if exclusive else value >= minimum)
    if not ok:
        bound = f"> {minimum:g}" if exclusive else f">= {minimum:g}"
        raise InputError(f"metadata {where}={value!r} must be a number {bound}")


def _check_int(where: str, value: Any) -> None:
    if not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
        raise InputError(f"metadata {where}={value!r} must be an integer >= 1")


def _check_object(where: str, value: Any) -> Mapping:
    if not isinstance(value, Mapping):
        raise InputError(f"metadata {where} must be an object, got {type(value).__name__}")
    return value


def validate_metadata(metadata: Any) -> dict:
    """Check the typed keys of capture metadata and return it as a dict.

    Raises
    ------
    InputError
        Naming the first offending key and its value.
    """
    meta = dict(_check_object("root", metadata))
    if "cantilever" in meta:
        cantilever = _check_object("cantilever", meta["cantilever"])
        for key in ("f0_hz", "q", "spring_constant_n_per_m", "deflection_sensitivity_nm_per_v"):
            if key in cantilever:
                _check_number(f"cantilever.{key}", cantilever[key])
    if "free_air" in meta:
        free_air = _check_object("free_air", meta["free_air"])
        for key in ("start_s", "end_s"):
            if key not in free_air:
                raise InputError(f"metadata free_air needs {key}")
        _check_number("free_air.start_s", free_air["start_s"], exclusive=False)
        _check_number("free_air.end_s", free_air["end_s"])
        if free_air["end_s"] <= free_air["start_s"]:
            raise InputError("metadata free_air.end_s must be after free_air.start_s")
    if "scan" in meta:
        scan = _check_object("scan", meta["scan"])
        for key in ("lines", "pixels_per_line", "scan_size_m", "line_rate_hz"):
            if key not in scan:
                raise InputError(f"metadata scan needs {key}")
        _check_int("scan.lines", scan["lines"])
        _check_int("scan.pixels_per_line", scan["pixels_per_line"])
        if scan["lines"] * scan["pixels_per_line"] > MAX_SCAN_PIXELS:
            raise InputError(
                f"metadata scan of {scan['lines']} x {scan['pixels_per_line']} pixels exceeds {MAX_SCAN_PIXELS:,} "
                "(an image afmtool would have to hold in memory)"
            )
        _check_number("scan.scan_size_m", scan["scan_size_m"])
        _check_number("scan.line_rate_hz", scan["line_rate_hz"])
        if "trace_retrace" in scan and not isinstance(scan["trace_retrace"], bool):
            raise InputError(f"metadata scan.trace_retrace={scan['trace_retrace']!r} must be true or false")
        if "start_s" in scan:
            _check_number("scan.start_s", scan["start_s"], exclusive=False)
    if "drive" in meta:
        drive = _check_object("drive", meta["drive"])
        if "frequency_hz" in drive:
            _check_number("drive.frequency_hz", drive["frequency_hz"])
        if "sideband_offset_hz" in drive:
            _check_number("drive.sideband_offset_hz", drive["sideband_offset_hz"], exclusive=False)
    if "segments" in meta:
        if not isinstance(meta["segments"], list):
            raise InputError("metadata segments must be a list")
        for i, segment in enumerate(meta["segments"]):
            segment = _check_object(f"segments[{i}]", segment)
            for key in ("start_s", "end_s", "frequency_hz"):
                if key not in segment:
                    raise InputError(f"metadata segments[{i}] needs {key}")
            _check_number(f"segments[{i}].start_s", segment["start_s"], exclusive=False)
            _check_number(f"segments[{i}].end_s", segment["end_s"])
            _check_number(f"segments[{i}].frequency_hz", segment["frequency_hz"])
    if "scenario" in meta and not isinstance(meta["scenario"], str):
        raise InputError("metadata scenario must be a string")
    return meta


def parse_metadata_json(text: str, where: str) -> dict:
    """Parse and validate a metadata JSON string found in ``where``."""
    depth = json_depth(text)
    if depth > MAX_JSON_DEPTH:
        raise InputError(f"{where}: metadata JSON is nested {depth} deep, more than {MAX_JSON_DEPTH}")
    try:
        value = json.loads(text)
    except (json.JSONDecodeError, TypeError, RecursionError) as exc:
        raise InputError(f"{where}: metadata is not valid JSON ({exc})") from None
    return validate_metadata(value)


#: Deepest nesting of arrays and objects accepted in metadata JSON (the schema needs 3).
MAX_JSON_DEPTH = 64


def json_depth(text: str) -> int:
    """The deepest nesting of ``[`` and ``{`` in JSON ``text``, outside strings; linear, no recursion.

    Measured before parsing: Python's ``json`` recurses once per level and
    ends in RecursionError (or, at 1e5 levels, a stack overflow).
    """
    depth = deepest = 0
    in_string = escaped = False
    for char in text:
        if in_string:
            if escaped:
                escaped = False
            elif char == "\\":
                escaped = True
            elif char == '"':
                in_string = False
        elif char == '"':
            in_string = True
        elif char in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif char in "]}":
            depth -= 1
    return deepest
