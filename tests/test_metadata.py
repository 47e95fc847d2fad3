"""Capture metadata: the runtime validator agrees with schemas/capture-metadata.schema.json."""

from __future__ import annotations

import jsonschema
import pytest

from afmtool.errors import InputError
from afmtool.io.metadata import parse_metadata_json, validate_metadata
from tests.conftest import load_schema

GOOD = [
    {},
    {"cantilever": {"f0_hz": 70000.0, "q": 200, "spring_constant_n_per_m": 2.0}, "operator": "free-form"},
    {"free_air": {"start_s": 0, "end_s": 0.01}},
    {"scan": {"lines": 64, "pixels_per_line": 128, "scan_size_m": 1e-5, "line_rate_hz": 4.0, "trace_retrace": True}},
    {"segments": [{"start_s": 0.0, "end_s": 0.1, "frequency_hz": 1000.0}]},
    {"drive": {"frequency_hz": 70000.0, "sideband_offset_hz": 6000.0}},
]
BAD = [
    {"cantilever": {"f0_hz": -1.0}},
    {"cantilever": {"q": "high"}},
    {"free_air": {"start_s": 0.0}},
    {"free_air": {"start_s": -1.0, "end_s": 1.0}},
    {"scan": {"lines": 0, "pixels_per_line": 1, "scan_size_m": 1.0, "line_rate_hz": 1.0}},
    {"scan": {"lines": 2, "pixels_per_line": 1.5, "scan_size_m": 1.0, "line_rate_hz": 1.0}},
    {"scan": {"lines": 2, "pixels_per_line": 2, "scan_size_m": 1.0}},
    {"segments": [{"start_s": 0.0, "end_s": 1.0}]},
    {"drive": {"frequency_hz": 0}},
    {"scenario": 3},
]


@pytest.mark.parametrize("metadata", GOOD)
def test_good_metadata_passes_both(metadata):
    jsonschema.validate(metadata, load_schema("capture-metadata.schema.json"))
    assert validate_metadata(metadata) == metadata


@pytest.mark.parametrize("metadata", BAD)
def test_bad_metadata_fails_both(metadata):
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(metadata, load_schema("capture-metadata.schema.json"))
    with pytest.raises(InputError):
        validate_metadata(metadata)


def test_not_json():
    with pytest.raises(InputError, match="not valid JSON"):
        parse_metadata_json("{oops", "file.h5")


def test_simulator_metadata_matches_schema():
    from afmtool import sim

    for name in sim.scenario_names():
        captured = sim.simulate(name, {"duration_s": 0.002}, seed=0)
        jsonschema.validate(dict(captured.metadata), load_schema("capture-metadata.schema.json"))
