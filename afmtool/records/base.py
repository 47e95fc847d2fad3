"""Typed result records: what a command found, as a frozen tree (issue 29, item 2).

Each command returns one root :class:`Record` (``ReepResults``, ``InvolsResults``,
...), a frozen dataclass whose fields are numbers, text, :class:`enum.Enum`
members, tuples and other records.  From those declarations alone this module
generates

* :meth:`Record.to_json`: the ``results`` section of ``report.json`` (numpy
  scalars and arrays to JSON numbers and lists, non-finite floats to null,
  an enum to its value, an :func:`optional` section left out when it is None);
* :meth:`Record.from_json`: the record back from ``report.json``, for a later
  command that reads an earlier run (``theory compare`` reads reep's);
* :meth:`Record.json_schema`: the JSON schema of ``results``, with no open
  object: every object lists its properties and refuses others
  (``schemas/results/<command>.schema.json``, written by ``python -m
  afmtool.records.schema``).

A field named like a Python keyword takes a trailing underscore, which its key in
``results`` drops (``pass_`` is ``"pass"``, :func:`json_key`).  An object whose keys are
partly fixed and partly named by the run keeps the run's keys in one :func:`inline` field.

A root record also declares its headline: :attr:`Record.HEADLINE`, the
:class:`Item` s a reader sees first (label, dotted path into the record,
units), and :attr:`Record.STATES`, the rules that put the run's state before
its numbers where the run undermines them (issue 28).  ``report.json``, the
terminal summary, batch's ``summary.csv`` and the HTML page all read that
one declaration (:mod:`afmtool.report.headline`).

The module uses the standard library only: the command table
(:mod:`afmtool.config.commands`) names each command's record, and
``afmtool --help`` stays light.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import inspect
import math
import re
import types
import typing
from collections.abc import Callable, Mapping
from typing import Any, ClassVar, NamedTuple

from afmtool.errors import InputError

__all__ = ["Record", "record", "optional", "inline", "json_key", "Item", "State", "StateRule", "resolve", "lookup",
           "walk_schema_objects"]

_T = typing.TypeVar("_T", bound="Record")


# --------------------------------------------------------------------------- the headline's declarations


@dataclasses.dataclass(frozen=True)
class Item:
    """One headline number, as a root record declares it.

    Attributes
    ----------
    label : str
        What the number is, for a reader ("f0' in the free-air segment").
    path : str
        Dotted path of the value in the record ("segments.free_air.f0_hz.mean"); a number
        indexes a tuple ("worst_bins.0.f0_z").
    units : str
        Its units ("" when dimensionless); ``"@path"`` reads them from the record.
    std : str, optional
        Dotted path of its standard deviation.
    at : str, optional
        Dotted path of where it occurs (the z of a force curve's largest shift).
    at_label : str
        The name of that coordinate ("z", "separation").
    at_units : str
        Its units, or ``"@path"``.
    note : str, optional
        Dotted path of a word on its standing ("identified", "not identifiable").
    text : bool
        The value may be text or a yes/no (a verdict), not only a number.
    scores : bool
        A score that a failed premise undermines: left out when a :class:`State` says so.
    needs : str, optional
        Dotted path of a flag in the record: the item is left out when it is False
        (Q′ items need ``q_identifiable``).
    """

    label: str
    path: str
    units: str = ""
    std: str | None = None
    at: str | None = None
    at_label: str = "z"
    at_units: str = ""
    note: str | None = None
    text: bool = False
    scores: bool = False
    needs: str | None = None

    def paths(self) -> tuple[str, ...]:
        """Every dotted path the item reads (value, std, where, note, flag, units read from the record)."""
        units = tuple(u[1:] for u in (self.units, self.at_units) if u.startswith("@"))
        return tuple(p for p in (self.path, self.std, self.at, self.note, self.needs) if p) + units


class State(NamedTuple):
    """The run's state where it undermines its own numbers: said first, and maybe the scores left out.

    Attributes
    ----------
    text : str
        What a reader is told.
    source : str
        The dotted path of the number that says so.
    hides_scores : bool
        The items declared ``scores`` are left out.
    """

    text: str
    source: str
    hides_scores: bool = True


#: A state rule: the root record and whether an earlier state already hides the scores -> a state or None.
StateRule = Callable[[Any, bool], "State | None"]


# --------------------------------------------------------------------------- declaring records


def optional(default: Any = None) -> Any:
    """A field that may be absent: left out of ``results`` (and not required by the schema) while None.

    For a section a run writes only in some modes (``truth`` with a ``/truth`` group, ``step`` in
    decode's step mode).  Declare it ``X | None``.  A number that may be unknown is typed
    ``float | None`` and written as null; an optional number written as null (present, but not
    finite) reads back as NaN, so it is written as null again rather than left out.
    """
    return dataclasses.field(default=default, metadata={"omit_none": True})


def inline() -> Any:
    """A ``Mapping[str, X]`` field whose entries sit beside the record's own keys in ``results``.

    For an object whose keys are partly fixed and partly named by the run (``theory observer``'s
    ``maps``: ``nominal``, ``f_k_hz_range``, ... and one ``"<c>_cycles"`` entry per gain).  The
    schema lists the fixed keys and types every other key as ``X``.
    """
    return dataclasses.field(default_factory=lambda: types.MappingProxyType({}), metadata={"inline": True})


def json_key(field: dataclasses.Field) -> str:
    """A field's key in ``results``: its name, less a trailing underscore (``pass_`` is ``"pass"``)."""
    return field.name[:-1] if field.name.endswith("_") else field.name


def _inline(field: dataclasses.Field) -> bool:
    return bool(field.metadata.get("inline"))


def _field_at(cls: type, part: str) -> dataclasses.Field | None:
    """The field of record class ``cls`` whose key is ``part``, else its :func:`inline` field (or None)."""
    fields = dataclasses.fields(cls)
    own = next((f for f in fields if json_key(f) == part and not _inline(f)), None)
    return own or next((f for f in fields if _inline(f)), None)


def record(cls: type[_T]) -> type[_T]:
    """Declare a result record: ``cls`` becomes a frozen, keyword-only dataclass."""
    if not issubclass(cls, Record):
        raise TypeError(f"{cls.__name__} must subclass Record")
    return dataclasses.dataclass(frozen=True, kw_only=True)(cls)


class Record:
    """Base of every result record; subclasses are declared with :func:`record`."""

    #: The headline a root record declares: its items, in reading order.
    HEADLINE: ClassVar[tuple[Item, ...]] = ()
    #: The state rules of a root record, checked in order before its items.
    STATES: ClassVar[tuple[StateRule, ...]] = ()

    def to_json(self) -> dict:
        """The record as ``report.json`` holds it: JSON types only, non-finite floats as null."""
        return _encode_record(self, type(self).__name__)

    @classmethod
    def from_json(cls: type[_T], data: Any) -> _T:
        """The record that :meth:`to_json` wrote; unknown keys are ignored (a later afmtool may add some).

        Raises
        ------
        InputError
            A value of the wrong type or a required key missing, named by its path.
        """
        return _decode(cls, data, "results")

    @classmethod
    def json_schema(cls) -> dict:
        """The JSON schema (draft 2020-12) of the record, nested records under ``$defs``."""
        definitions: dict[str, dict] = {}
        root = _record_schema(cls, definitions)
        names = _definition_names(definitions)
        schema = {"$schema": "https://json-schema.org/draft/2020-12/schema", **root}
        if len(definitions) > 1:
            schema["$defs"] = {names[c]: s for c, s in definitions.items() if c is not cls}
        return _rename_refs(schema, names)

    def replace(self: _T, **changes: Any) -> _T:
        """A copy with ``changes`` (the record is frozen)."""
        return dataclasses.replace(self, **changes)


# --------------------------------------------------------------------------- types


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


def _is_record(kind: Any) -> bool:
    return isinstance(kind, type) and issubclass(kind, Record)


def _is_enum(kind: Any) -> bool:
    return isinstance(kind, type) and issubclass(kind, enum.Enum)


def _optional_of(kind: Any) -> Any | None:
    """``X`` of ``X | None``; None for any other type."""
    if typing.get_origin(kind) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(kind) if a is not type(None)]
        if len(args) != 1 or len(typing.get_args(kind)) != 2:
            raise TypeError(f"{kind!r}: a result field is one type or that type | None")
        return args[0]
    return None


def _items_of(kind: Any) -> tuple[Any, ...] | None:
    """The element types of a tuple type: ``(X, Ellipsis)`` for ``tuple[X, ...]``; None if not a tuple."""
    if typing.get_origin(kind) is tuple:
        return typing.get_args(kind)
    return None


def _values_of(kind: Any) -> Any | None:
    """``X`` of ``Mapping[str, X]``; None for any other type."""
    if typing.get_origin(kind) in (Mapping, dict, typing.Mapping):
        key, value = typing.get_args(kind)
        if key is not str:
            raise TypeError(f"{kind!r}: a result mapping is keyed by str")
        return value
    return None


# --------------------------------------------------------------------------- to JSON


def _wrong(where: str, kind: Any, value: Any) -> TypeError:
    return TypeError(f"{where}: {type(value).__name__} {value!r:.60} is not {getattr(kind, '__name__', kind)}")


def _encode_record(value: Record, where: str) -> dict:
    out = {}
    for f in dataclasses.fields(value):
        item = getattr(value, f.name)
        if item is None and f.metadata.get("omit_none"):
            continue
        encoded = _encode(_hints(type(value))[f.name], item, f"{where}.{json_key(f)}")
        if not _inline(f):
            out[json_key(f)] = encoded
        elif clash := sorted(set(encoded) & {json_key(g) for g in dataclasses.fields(value) if not _inline(g)}):
            raise TypeError(f"{where}.{f.name}: keys {clash} are the record's own fields")
        else:
            out.update(encoded)
    return out


def _number(value: Any) -> bool:
    return not isinstance(value, bool) and type(value).__name__ not in ("bool_", "bool") and (
        isinstance(value, (int, float)) or hasattr(value, "dtype"))


def _encode(kind: Any, value: Any, where: str) -> Any:
    inner = _optional_of(kind)
    if inner is not None:
        return None if value is None else _encode(inner, value, where)
    if kind is float:
        if not _number(value):
            raise _wrong(where, kind, value)
        number = float(value)
        return number if math.isfinite(number) else None
    if kind is int:
        if not _number(value) or float(value) != int(value):
            raise _wrong(where, kind, value)
        return int(value)
    if kind is bool or kind is str:
        value = value.item() if hasattr(value, "item") and kind is bool else value
        if not isinstance(value, kind):
            raise _wrong(where, kind, value)
        return value
    if _is_enum(kind):
        if not isinstance(value, kind):
            raise _wrong(where, kind, value)
        return value.value
    if _is_record(kind):
        if not isinstance(value, kind):
            raise _wrong(where, kind, value)
        return _encode_record(value, where)
    items = _items_of(kind)
    if items is not None:
        return _encode_items(items, value, where)
    values = _values_of(kind)
    if values is not None:
        if not isinstance(value, Mapping):
            raise _wrong(where, kind, value)
        return {str(k): _encode(values, v, f"{where}.{k}") for k, v in value.items()}
    raise TypeError(f"{where}: {kind!r} is not a result type")


def _encode_items(items: tuple[Any, ...], value: Any, where: str) -> list:
    if isinstance(value, (str, bytes, Mapping)) or not hasattr(value, "__len__"):
        raise _wrong(where, tuple, value)
    sequence = list(value)
    if len(items) == 2 and items[1] is Ellipsis:
        return [_encode(items[0], v, f"{where}.{i}") for i, v in enumerate(sequence)]
    if len(sequence) != len(items):
        raise TypeError(f"{where}: {len(sequence)} values for a tuple of {len(items)}")
    return [_encode(k, v, f"{where}.{i}") for i, (k, v) in enumerate(zip(items, sequence, strict=True))]


# --------------------------------------------------------------------------- from JSON


def _bad(where: str, message: str) -> InputError:
    return InputError(f"{where}: {message} (a report.json of another afmtool version, or edited?)")


def _decode(kind: Any, data: Any, where: str) -> Any:
    inner = _optional_of(kind)
    if inner is not None:
        return None if data is None else _decode(inner, data, where)
    if kind is float:
        if data is None:
            return math.nan  # to_json wrote a non-finite float as null
        if isinstance(data, bool) or not isinstance(data, (int, float)):
            raise _bad(where, f"{data!r:.40} is not a number")
        return float(data)
    if kind in (int, bool, str):
        if not isinstance(data, kind) or (kind is int and isinstance(data, bool)):
            raise _bad(where, f"{data!r:.40} is not {kind.__name__}")
        return data
    if _is_enum(kind):
        try:
            return kind(data)
        except ValueError:
            raise _bad(where, f"{data!r:.40} is none of {', '.join(repr(m.value) for m in kind)}") from None
    if _is_record(kind):
        return _decode_record(kind, data, where)
    items = _items_of(kind)
    if items is not None:
        if not isinstance(data, list):
            raise _bad(where, "not a list")
        if len(items) == 2 and items[1] is Ellipsis:
            return tuple(_decode(items[0], v, f"{where}.{i}") for i, v in enumerate(data))
        if len(data) != len(items):
            raise _bad(where, f"{len(data)} values, not {len(items)}")
        return tuple(_decode(k, v, f"{where}.{i}") for i, (k, v) in enumerate(zip(items, data, strict=True)))
    values = _values_of(kind)
    if values is not None and isinstance(data, Mapping):
        return {k: _decode(values, v, f"{where}.{k}") for k, v in data.items()}
    raise _bad(where, f"{data!r:.40} is not {kind!r}")


def _decode_record(kind: type[Record], data: Any, where: str) -> Record:
    if not isinstance(data, Mapping):
        raise _bad(where, "not an object")
    hints = _hints(kind)
    values = {}
    own = {json_key(f) for f in dataclasses.fields(kind) if not _inline(f)}
    for f in dataclasses.fields(kind):
        if _inline(f):
            values[f.name] = _decode(hints[f.name], {k: v for k, v in data.items() if k not in own}, where)
        elif json_key(f) in data:
            raw = data[json_key(f)]
            if raw is None and f.metadata.get("omit_none") and (_optional_of(hints[f.name]) or hints[f.name]) is float:
                # present and null: a number the run could not give (non-finite), not an absent one (None)
                values[f.name] = math.nan
            else:
                values[f.name] = _decode(hints[f.name], raw, f"{where}.{json_key(f)}")
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise _bad(where, f"no {json_key(f)!r}")
    return kind(**values)


# --------------------------------------------------------------------------- the schema

_NUMPYDOC_ATTRIBUTE = re.compile(r"^(\w+) : [^\n]*\n((?:[ \t]+\S[^\n]*\n?)+)", re.MULTILINE)


@functools.cache
def _descriptions(cls: type) -> dict[str, str]:
    """Each field's description from the numpydoc ``Attributes`` sections of the class and its bases.

    A record that extends another documents only the fields it adds; its own word wins.
    """
    inherited: dict[str, str] = {}
    for base in reversed(cls.__mro__[1:]):
        if base is not Record and isinstance(base, type) and issubclass(base, Record):
            inherited.update(_descriptions(base))
    doc = inspect.getdoc(cls) if "__doc__" in vars(cls) else ""
    section = (doc or "").split("Attributes\n----------\n", 1)
    if len(section) < 2:
        return inherited
    own = {m.group(1): " ".join(m.group(2).split()) for m in _NUMPYDOC_ATTRIBUTE.finditer(section[1] + "\n")}
    return {**inherited, **own}


def _record_schema(cls: type[Record], definitions: dict[type, dict]) -> dict:
    if cls in definitions:
        return definitions[cls]
    schema: dict[str, Any] = {"title": cls.__name__}
    definitions[cls] = schema
    summary = (inspect.getdoc(cls) or "").split("\n\n", 1)[0]
    if summary:
        schema["description"] = " ".join(summary.split())
    descriptions = _descriptions(cls)
    properties: dict[str, Any] = {}
    others: Any = False
    for f in dataclasses.fields(cls):
        prop = _type_schema(_hints(cls)[f.name], definitions)
        if _inline(f):
            others = prop["additionalProperties"]
            continue
        description = descriptions.get(f.name, descriptions.get(json_key(f)))
        properties[json_key(f)] = {"description": description, **prop} if description else prop
    required = [json_key(f) for f in dataclasses.fields(cls) if not f.metadata.get("omit_none") and not _inline(f)]
    schema.update({"type": "object", "properties": properties, "required": required, "additionalProperties": others})
    return schema


def _type_schema(kind: Any, definitions: dict[type, dict]) -> dict:
    inner = _optional_of(kind)
    if inner is not None:
        return {"anyOf": [_type_schema(inner, definitions), {"type": "null"}]}
    if kind is float:
        return {"type": ["number", "null"]}  # null: a non-finite value
    if kind in (int, bool, str):
        return {"type": {int: "integer", bool: "boolean", str: "string"}[kind]}
    if _is_enum(kind):
        return {"enum": [m.value for m in kind]}
    if _is_record(kind):
        _record_schema(kind, definitions)
        return {"$ref": kind}  # renamed to "#/$defs/<name>" once every name is known
    items = _items_of(kind)
    if items is not None:
        if len(items) == 2 and items[1] is Ellipsis:
            return {"type": "array", "items": _type_schema(items[0], definitions)}
        return {"type": "array", "prefixItems": [_type_schema(k, definitions) for k in items], "items": False,
                "minItems": len(items), "maxItems": len(items)}
    values = _values_of(kind)
    if values is not None:
        return {"type": "object", "additionalProperties": _type_schema(values, definitions)}
    raise TypeError(f"{kind!r} is not a result type")


def _definition_names(definitions: Mapping[type, dict]) -> dict[type, str]:
    """A ``$defs`` name per record: its class name, with its module's where two classes share one."""
    names: dict[type, str] = {}
    taken = [c.__name__ for c in definitions]
    for cls in definitions:
        clash = taken.count(cls.__name__) > 1
        names[cls] = f"{cls.__module__.rsplit('.', 1)[-1]}.{cls.__name__}" if clash else cls.__name__
    return names


def _rename_refs(schema: Any, names: Mapping[type, str]) -> Any:
    if isinstance(schema, dict):
        if "$ref" in schema and isinstance(schema["$ref"], type):
            return {**schema, "$ref": f"#/$defs/{names[schema['$ref']]}"}
        return {k: _rename_refs(v, names) for k, v in schema.items()}
    if isinstance(schema, list):
        return [_rename_refs(v, names) for v in schema]
    return schema


def walk_schema_objects(schema: Any, where: str = "results") -> typing.Iterator[tuple[str, dict]]:
    """Every object schema in ``schema`` (``type`` "object"), with where it is: to check none is open."""
    if isinstance(schema, dict):
        kind = schema.get("type")
        if kind == "object" or (isinstance(kind, list) and "object" in kind):
            yield where, schema
        for key, value in schema.items():
            yield from walk_schema_objects(value, f"{where}/{key}")
    elif isinstance(schema, list):
        for i, value in enumerate(schema):
            yield from walk_schema_objects(value, f"{where}/{i}")


# --------------------------------------------------------------------------- dotted paths


def resolve(cls: type[Record], path: str) -> Any:
    """The type at the dotted ``path`` of records of ``cls``.

    Raises
    ------
    KeyError
        A part of the path that the record does not declare.
    """
    kind: Any = cls
    for part in path.split("."):
        kind = _optional_of(kind) or kind
        if _is_record(kind):
            field = _field_at(kind, part)
            if field is None:
                raise KeyError(f"{cls.__name__}: {path!r}: {kind.__name__} has no field {part!r}")
            kind = _hints(kind)[field.name]
            kind = _values_of(kind) if _inline(field) else kind
            continue
        items = _items_of(kind)
        if items is not None and part.isdigit():
            kind = items[0] if items[1:] == (Ellipsis,) else items[int(part)]
            continue
        values = _values_of(kind)
        if values is not None:
            kind = values
            continue
        raise KeyError(f"{cls.__name__}: {path!r}: {part!r} indexes {kind!r}")
    return _optional_of(kind) or kind


def lookup(value: Any, path: str) -> Any:
    """The value at the dotted ``path`` of a record (or None where a part is absent or out of range)."""
    for part in path.split("."):
        if value is None:
            return None
        if isinstance(value, Record):
            field = _field_at(type(value), part)
            value = None if field is None else getattr(value, field.name)
            value = value.get(part) if field is not None and _inline(field) else value
        elif isinstance(value, Mapping):
            value = value.get(part)
        elif isinstance(value, tuple) and part.isdigit():
            value = value[int(part)] if int(part) < len(value) else None
        else:
            return None
    return value

