"""JSON schemas of the config sections and of each command's results, generated from their declarations.

One schema per ``[section]`` of ``defaults.toml`` (every command's parameter
model and every ``simulate.SCENARIO``), written to ``schemas/params/``, and one
per command's ``results`` (its result record, :mod:`afmtool.records`), written
to ``schemas/results/``, at the repository root.  Regenerate with::

    python -m afmtool.config.schema            # writes schemas/params/ and schemas/results/
    python -m afmtool.config.schema --check    # exit 1 if any file is stale

``schemas/report.schema.json`` is hand-written but for its ``results``, which is generated from the
same records (:func:`report_schema`).  Tests (``tests/test_params_model.py``, ``tests/test_records.py``)
check that the committed files are current.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import types
import typing
from pathlib import Path
from typing import Any

from afmtool.config import describe_bounds

__all__ = ["section_schema", "all_schemas", "result_schemas", "report_schema", "schema_filename", "write_schemas",
           "write_report_schema", "SCHEMA_DIR", "RESULT_SCHEMA_DIR", "REPORT_SCHEMA"]

#: Where the generated schemas live (beside ``capture-metadata.schema.json``).
SCHEMA_DIR = Path(__file__).resolve().parents[2] / "schemas" / "params"
#: Where the schemas of each command's ``results`` live, generated from its result record.
RESULT_SCHEMA_DIR = SCHEMA_DIR.parent / "results"

_JSON_TYPES = {float: "number", int: "integer", bool: "boolean", str: "string"}


def _json_type(kind: Any) -> dict:
    if kind in _JSON_TYPES:
        return {"type": _JSON_TYPES[kind]}
    origin = typing.get_origin(kind)
    if origin is tuple:
        (item, *_rest) = typing.get_args(kind)
        return {"type": "array", "items": _json_type(item)}
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(kind) if a is not type(None)]
        return {"anyOf": [_json_type(a) for a in args] + [{"type": "null"}]}
    raise TypeError(f"no JSON type for {kind!r}")


def _bounds(metadata: typing.Mapping) -> dict:
    bounds: dict[str, Any] = {}
    if metadata.get("minimum") is not None:
        bounds["exclusiveMinimum" if metadata.get("exclusive_minimum") else "minimum"] = metadata["minimum"]
    if metadata.get("maximum") is not None:
        bounds["exclusiveMaximum" if metadata.get("exclusive_maximum") else "maximum"] = metadata["maximum"]
    return bounds


def _property(f: dataclasses.Field, kind: Any) -> dict:
    meta = f.metadata
    if isinstance(kind, type) and dataclasses.is_dataclass(kind):  # a nested table (``[kalman-bank.reep]``)
        hints = typing.get_type_hints(kind)
        return {"description": meta.get("help", ""), "type": "object", "additionalProperties": False,
                "default": dataclasses.asdict(f.default),
                "properties": {g.name: _property(g, hints[g.name]) for g in dataclasses.fields(kind)}}
    prop: dict[str, Any] = {"description": meta.get("help", ""), **_json_type(kind)}
    default = f.default
    prop["default"] = list(default) if isinstance(default, tuple) else default
    if meta.get("units"):
        prop["x-units"] = meta["units"]
    if meta.get("choices"):
        prop["enum"] = list(meta["choices"])
    bounds = _bounds(meta)
    if bounds:
        target = prop["items"] if prop.get("type") == "array" else prop
        if meta.get("automatic") is not None:
            target["anyOf"] = [{"const": meta["automatic"]}, bounds]
        else:
            target.update(bounds)
        prop["x-range"] = describe_bounds(meta)
    if meta.get("flag"):
        prop["x-flag"] = meta["flag"]
    return prop


def section_schema(section: str, cls: type) -> dict:
    """The JSON schema (draft 2020-12) of one config section's table."""
    hints = typing.get_type_hints(cls)
    doc = (cls.__doc__ or "").strip().splitlines()
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": f"[{section}]",
        "description": doc[0] if doc else "",
        "type": "object",
        "additionalProperties": False,
        "properties": {f.name: _property(f, hints[f.name]) for f in dataclasses.fields(cls)},
    }


def schema_filename(section: str) -> str:
    return f"{section}.schema.json"


def all_schemas() -> dict[str, dict]:
    """File name -> schema, for every section of the packaged defaults."""
    from afmtool.config.defaults import parameter_sections

    return {schema_filename(name): section_schema(name, type(value)) for name, value in parameter_sections().items()}


def _text(schema: dict) -> str:
    return json.dumps(schema, indent=2, ensure_ascii=False) + "\n"


def result_schemas() -> dict[str, dict]:
    """File name -> schema of ``results``, for every command with a result record (:mod:`afmtool.records`)."""
    from afmtool.config.commands import results

    return {schema_filename(command.replace(" ", ".")): record.json_schema() for command, record in results().items()}


#: report.json's schema: hand-written, but for its ``results``, which :func:`report_schema` generates.
REPORT_SCHEMA = SCHEMA_DIR.parent / "report.schema.json"


def _hoisted(command: str, schema: dict) -> tuple[dict, dict]:
    """(the root, its ``$defs``) of one command's results schema, the names prefixed by the command."""
    prefix = command.replace(" ", ".")

    def rename(node):
        if isinstance(node, dict):
            out = {k: rename(v) for k, v in node.items() if k not in ("$schema", "$defs")}
            if isinstance(out.get("$ref"), str) and out["$ref"].startswith("#/$defs/"):
                out["$ref"] = f"#/$defs/{prefix}.{out['$ref'][len('#/$defs/'):]}"
            return out
        return [rename(v) for v in node] if isinstance(node, list) else node

    return rename(schema), {f"{prefix}.{name}": rename(d) for name, d in schema.get("$defs", {}).items()}


def report_schema(current: dict) -> dict:
    """``current`` (report.schema.json) with ``results`` tied to each command's result record.

    ``results`` must be one of the records (``anyOf``), and the one of the run's ``command``
    (``allOf`` of ``if``/``then``); the records' schemas sit in ``$defs`` under their command's
    name.  The rest of the file is hand-written and kept as it is.
    """
    from afmtool.config.commands import SPECS, Kind, results

    definitions: dict[str, dict] = {}
    rules = []
    for command, record in results().items():
        root, nested = _hoisted(command, record.json_schema())
        name = command.replace(" ", ".")
        definitions[name] = root
        definitions.update(nested)
        rules.append({"if": {"properties": {"command": {"const": command}}, "required": ["command"]},
                      "then": {"properties": {"results": {"$ref": f"#/$defs/{name}"}}}})
    names = [command.replace(" ", ".") for command in results()]
    described = {"description": "what the command found: its result record (afmtool.records), chosen by `command`"}
    if all(s.result is not None for s in SPECS.values() if s.kind is not Kind.TOOL):
        described["anyOf"] = [{"$ref": f"#/$defs/{name}"} for name in names]
    else:  # while some commands' results are still dicts (issue 29, item 2)
        described["type"] = "object"
    properties = {**current["properties"], "results": described}
    rest = {k: v for k, v in current.items() if k not in ("properties", "allOf", "$defs")}
    return {**rest, "properties": properties, "allOf": rules, "$defs": definitions}


def write_report_schema(path: Path = REPORT_SCHEMA, *, check: bool = False) -> bool:
    """Write (or with ``check``, compare) report.schema.json's generated part; True when it was stale."""
    current = json.loads(path.read_text(encoding="utf-8"))
    text = _text(report_schema(current))
    stale = path.read_text(encoding="utf-8") != text
    if stale and not check:
        path.write_text(text, encoding="utf-8")
    return stale


def write_schemas(directory: Path = SCHEMA_DIR, *, check: bool = False, schemas: dict | None = None) -> list[str]:
    """Write (or with ``check``, compare) every schema; returns the names that were stale."""
    schemas = all_schemas() if schemas is None else schemas
    stale = []
    for name, schema in schemas.items():
        path = directory / name
        text = _text(schema)
        if not path.is_file() or path.read_text(encoding="utf-8") != text:
            stale.append(name)
            if not check:
                directory.mkdir(parents=True, exist_ok=True)
                path.write_text(text, encoding="utf-8")
    extra = sorted(p.name for p in directory.glob("*.schema.json") if p.name not in schemas) if directory.is_dir() else []
    stale += extra
    if not check:
        for name in extra:
            (directory / name).unlink()
    return stale


if __name__ == "__main__":
    check = "--check" in sys.argv[1:]
    stale = {"params": write_schemas(check=check),
             "results": write_schemas(RESULT_SCHEMA_DIR, check=check, schemas=result_schemas()),
             "": ["report.schema.json"] if write_report_schema(check=check) else []}
    if check:
        print("\n".join(f"stale: schemas/{folder}/{name}".replace("//", "/") for folder, names in stale.items()
                        for name in names) or "schemas/params, schemas/results and report.schema.json are current")
        sys.exit(1 if any(stale.values()) else 0)
    print(f"wrote {sum(map(len, stale.values()))} schema(s) to {SCHEMA_DIR.parent}")
