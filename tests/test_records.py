"""Typed result records (issue 29, item 2): generated to_json, from_json and schema, and the headline on them."""

from __future__ import annotations

import enum
import json
import math
import re
from collections.abc import Mapping
from pathlib import Path

import jsonschema
import numpy as np
import pytest

from afmtool.config.commands import SPECS, Kind, results
from afmtool.config.schema import RESULT_SCHEMA_DIR, result_schemas, write_schemas
from afmtool.errors import InputError
from afmtool.records import Item, Record, inline, lookup, optional, record, resolve
from afmtool.records.base import walk_schema_objects

PACKAGE = Path(__file__).resolve().parents[1] / "afmtool"


class _Route(enum.Enum):
    SEGMENT = "segment"
    SWEEP = "sweep"


@record
class _Moments(Record):
    """Moments of a series.

    Attributes
    ----------
    mean : float
        The mean (Hz).
    count : int
        Values counted.
    """

    mean: float
    count: int


@record
class _Root(Record):
    """A root record for the tests.

    Attributes
    ----------
    f0_hz : _Moments
        The resonance (Hz).
    """

    route: _Route
    f0_hz: _Moments
    span_s: tuple[float, float]
    lines_hz: tuple[float, ...]
    verdict: bool
    q: float | None
    truth: _Moments | None = optional()

    HEADLINE = (Item("f0'", "f0_hz.mean", "Hz"),)


def _root(**changes) -> _Root:
    values = dict(route=_Route.SWEEP, f0_hz=_Moments(mean=np.float64(7e4), count=np.int64(3)), span_s=(0.0, np.inf),
                  lines_hz=np.array([1.0, 2.0]), verdict=np.bool_(True), q=None)
    return _Root(**{**values, **changes})


def test_to_json_writes_json_types_nulls_for_non_finite_and_leaves_out_absent_sections() -> None:
    data = _root().to_json()
    assert data == {"route": "sweep", "f0_hz": {"mean": 7e4, "count": 3}, "span_s": [0.0, None],
                    "lines_hz": [1.0, 2.0], "verdict": True, "q": None}
    assert type(data["f0_hz"]["count"]) is int and type(data["verdict"]) is bool
    json.dumps(data, allow_nan=False)
    assert "truth" in _root(truth=_Moments(mean=1.0, count=1)).to_json()


def test_from_json_reads_back_what_to_json_wrote() -> None:
    original = _root(truth=_Moments(mean=2.5, count=4), q=200.0)
    again = _Root.from_json(original.to_json())
    assert again.route is _Route.SWEEP and again.truth == _Moments(mean=2.5, count=4)
    assert again.span_s[0] == 0.0 and math.isnan(again.span_s[1])  # the inf went out as null, comes back NaN
    assert again.to_json() == original.to_json()


@pytest.mark.parametrize("change, message", [
    ({"route": "segment"}, "_Root.route"),  # a str, not the enum
    ({"f0_hz": {"mean": 1.0}}, "_Root.f0_hz"),
    ({"span_s": (1.0, 2.0, 3.0)}, "_Root.span_s"),
    ({"verdict": 1}, "_Root.verdict"),
    ({"lines_hz": "1, 2"}, "_Root.lines_hz"),
])
def test_to_json_refuses_a_value_of_the_wrong_type_naming_its_path(change, message) -> None:
    with pytest.raises(TypeError, match=re.escape(message)):
        _root(**change).to_json()


@pytest.mark.parametrize("edit, message", [
    (lambda d: d.update(route="hilbert"), "results.route"),
    (lambda d: d["f0_hz"].pop("count"), "results.f0_hz: no 'count'"),
    (lambda d: d.update(verdict="yes"), "results.verdict"),
    (lambda d: d.update(span_s=[1.0]), "results.span_s"),
])
def test_from_json_refuses_a_report_it_cannot_read_as_an_input_error(edit, message) -> None:
    data = _root().to_json()
    edit(data)
    with pytest.raises(InputError, match=re.escape(message)):
        _Root.from_json(data)


def test_the_generated_schema_accepts_to_json_and_refuses_unknown_keys_and_wrong_types() -> None:
    schema = _Root.json_schema()
    data = _root(truth=_Moments(mean=1.0, count=1)).to_json()
    jsonschema.validate(data, schema)
    assert schema["$defs"]["_Moments"]["properties"]["mean"]["description"] == "The mean (Hz)."
    assert schema["properties"]["f0_hz"] == {"description": "The resonance (Hz).", "$ref": "#/$defs/_Moments"}
    assert "truth" not in schema["required"] and "q" in schema["required"]
    for bad in ({**data, "extra": 1}, {**data, "route": "hilbert"}, {**data, "f0_hz": {"mean": 1.0, "count": 1.5}},
                {**data, "span_s": [1.0]}):
        with pytest.raises(jsonschema.ValidationError):
            jsonschema.validate(bad, schema)


@record
class _Extended(_Moments):
    """Moments with a spread (the fields of _Moments, and:).

    Attributes
    ----------
    spread : float
        Largest less smallest (Hz).
    """

    spread: float


def test_a_record_that_extends_another_inherits_its_field_descriptions() -> None:
    properties = _Extended.json_schema()["properties"]
    assert properties["mean"]["description"] == "The mean (Hz)."
    assert properties["spread"]["description"] == "Largest less smallest (Hz)."


def test_resolve_follows_a_dotted_path_through_records_and_tuples() -> None:
    assert resolve(_Root, "f0_hz.mean") is float
    assert resolve(_Root, "truth.count") is int
    assert resolve(_Root, "lines_hz.3") is float
    with pytest.raises(KeyError, match="no field 'median'"):
        resolve(_Root, "f0_hz.median")


@record
class _Maps(Record):
    """Fixed keys and keys the run names.

    Attributes
    ----------
    pass_ : bool
        The verdict (a keyword: its key is "pass").
    nominal : float
        The nominal value (Hz).
    per_gain : Mapping of str to _Moments
        One entry per gain, keyed "<c>_cycles".
    """

    pass_: bool
    nominal: float
    per_gain: Mapping[str, _Moments] = inline()


def test_a_keyword_field_and_an_inline_mapping_keep_the_reports_keys() -> None:
    maps = _Maps(pass_=True, nominal=7e4, per_gain={"4_cycles": _Moments(mean=1.0, count=2)})
    data = maps.to_json()
    assert data == {"pass": True, "nominal": 7e4, "4_cycles": {"mean": 1.0, "count": 2}}
    again = _Maps.from_json(data)
    assert again.pass_ is True and again.per_gain["4_cycles"] == _Moments(mean=1.0, count=2)
    schema = _Maps.json_schema()
    assert schema["required"] == ["pass", "nominal"] and schema["properties"]["pass"]["type"] == "boolean"
    assert schema["additionalProperties"] == {"$ref": "#/$defs/_Moments"}
    jsonschema.validate(data, schema)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({**data, "8_cycles": {"mean": "x", "count": 1}}, schema)
    assert resolve(_Maps, "pass") is bool and resolve(_Maps, "16_cycles.mean") is float
    assert lookup(maps, "pass") is True and lookup(maps, "4_cycles.count") == 2 and lookup(maps, "8_cycles") is None
    with pytest.raises(TypeError, match="own fields"):
        _Maps(pass_=True, nominal=1.0, per_gain={"nominal": _Moments(mean=1.0, count=1)}).to_json()


# --------------------------------------------------------------------------- every command's record

RECORDS = results()


@pytest.mark.parametrize("command", sorted(RECORDS))
def test_a_result_schema_has_no_open_object(command) -> None:
    schema = RECORDS[command].json_schema()
    jsonschema.Draft202012Validator.check_schema(schema)
    for where, obj in walk_schema_objects(schema):
        closed = obj.get("additionalProperties") is False and "properties" in obj
        typed_map = isinstance(obj.get("additionalProperties"), dict) and obj["additionalProperties"]
        assert closed or typed_map, f"{command}: an open object at {where}"


@pytest.mark.parametrize("command", sorted(RECORDS))
def test_every_headline_item_names_a_field_of_the_record(command) -> None:
    cls = RECORDS[command]
    assert cls.HEADLINE, f"{command}: its record declares no headline"
    for item in cls.HEADLINE:
        for path in item.paths():
            resolve(cls, path)  # KeyError names the part the record lacks
        for path in (u[1:] for u in (item.units, item.at_units) if u.startswith("@")):
            assert resolve(cls, path) is str, f"{command}: units at {path!r} are not text"


def test_the_result_schemas_are_current() -> None:
    # Regenerate with: python -m afmtool.config.schema
    assert write_schemas(RESULT_SCHEMA_DIR, check=True, schemas=result_schemas()) == []


def test_every_command_that_writes_a_report_has_a_record() -> None:
    assert set(RECORDS) == {s.name for s in SPECS.values() if s.kind is not Kind.TOOL}


#: ``results["f0_hz"]``, ``reep_results.get("decimate")``: a result read by its key, not its record's field.
_READ_BY_STRING = re.compile(r"""results\[["']|results\.get\(["']""")


def reads_results_by_string(source: str) -> bool:
    return bool(_READ_BY_STRING.search(source))


def test_the_rule_finds_a_result_read_by_string_and_passes_a_field() -> None:
    assert reads_results_by_string('drive_hz = float(reep_results["drive_frequency_hz"])')
    assert reads_results_by_string("check = results.get('free_air_check') or {}")
    assert not reads_results_by_string("drive_hz = reep_results.drive_frequency_hz")


def test_no_module_reads_results_by_string() -> None:
    """Outside the record definitions, results are read by field (issue 29, item 2: ``grep 'results\\["'``)."""
    found = sorted(path.relative_to(PACKAGE).as_posix() for path in PACKAGE.rglob("*.py")
                   if not path.relative_to(PACKAGE).as_posix().startswith("records/")
                   and reads_results_by_string(path.read_text(encoding="utf-8")))
    assert not found, f"read results by string: {found}"


def test_report_schema_ties_results_to_the_commands_record_and_is_current(tmp_path):
    from afmtool.config.schema import REPORT_SCHEMA, report_schema, write_report_schema

    # Regenerate with: python -m afmtool.config.schema
    assert not write_report_schema(check=True)
    schema = report_schema(json.loads(REPORT_SCHEMA.read_text()))
    jsonschema.Draft202012Validator.check_schema(schema)
    for command in RECORDS:
        name = command.replace(" ", ".")
        assert name in schema["$defs"]
        rule = {"if": {"properties": {"command": {"const": command}}, "required": ["command"]},
                "then": {"properties": {"results": {"$ref": f"#/$defs/{name}"}}}}
        assert rule in schema["allOf"]
    # a report whose results are another command's record, or carry a key their record lacks, is refused
    invols = json.loads((Path(__file__).parent / "golden" / "freeair_ltv_step.json").read_text())
    invols["command"] = "identify invols"
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({**invols, "headline": []}, schema)


@record
class _WithOptionalNumber(Record):
    """A record with an optional number."""

    bandwidth_hz: float | None = optional()


def test_an_optional_number_is_left_out_when_absent_and_written_null_when_not_finite() -> None:
    assert _WithOptionalNumber().to_json() == {}
    assert _WithOptionalNumber(bandwidth_hz=math.inf).to_json() == {"bandwidth_hz": None}
    again = _WithOptionalNumber.from_json({"bandwidth_hz": None})
    assert math.isnan(again.bandwidth_hz) and again.to_json() == {"bandwidth_hz": None}
    assert _WithOptionalNumber.from_json({}).bandwidth_hz is None
