"""Command-line flags generated from the parameter declarations (``afmtool.config.field(flag=...)``).

Each field of a parameter model that declares a ``flag`` becomes one typer
option whose help is generated from the declaration (help, units, default,
range, choices: :func:`flag_help`), and the command receives the flag ->
field mapping as one dict, ``{field: value or None}`` (None: not given), the
``flags`` that ``run_*_command(reader, capture, out, config, flags, ...)`` take.

A boolean whose default is true gets a flag that sets it false (``--no-input``
sets ``use_input = false``); one whose default is false, a flag that sets it
true (``--recommend``).  Every value given is checked at once with
:func:`afmtool.config.check_value` (type, finite, declared bounds), so a bad
flag is a one-line error naming the flag and the parameter.
"""

from __future__ import annotations

import dataclasses
import typing
from typing import Annotated, Any, Optional

import typer

from afmtool.cli.groups import OptionGroup, option
from afmtool.config import check_value, describe_field

__all__ = ["param_flags", "flag_fields", "flag_help"]


def flag_fields(cls: type) -> dict[str, dataclasses.Field]:
    """Flag -> field, for every field of ``cls`` that declares a flag."""
    return {f.metadata["flag"]: f for f in dataclasses.fields(cls) if f.metadata.get("flag")}


def _switch_value(f: dataclasses.Field) -> bool:
    """The value a boolean field's flag sets: the opposite of its default."""
    return not f.default


def flag_help(f: dataclasses.Field) -> str:
    """A flag's ``--help`` text: the declaration's help, units, default, range and choices."""
    if f.default is True or f.default is False:
        state = "false" if f.default else "true"
        return f"Sets {f.name} = {state}: {f.metadata['help']} (default {str(f.default).lower()})."
    return describe_field(f) + "."


def param_flags(cls: type, keyword: str = "flags", *, section: str | None = None) -> OptionGroup:
    """The options of every flag ``cls`` declares, collected into ``{field: value or None}``.

    ``section`` names the config section in error messages (default: from
    :data:`afmtool.config.params.SECTIONS`).
    """
    from afmtool.config.params import SECTIONS

    section = section or next((name for name, model in SECTIONS.items() if model is cls), cls.__name__)
    hints = typing.get_type_hints(cls)
    parameters = []
    for flag, f in flag_fields(cls).items():
        if hints[f.name] is bool:
            annotation: Any = Annotated[bool, typer.Option(flag, help=flag_help(f))]
            parameters.append(option(f.name, annotation, False))
        else:
            annotation = Annotated[Optional[hints[f.name]], typer.Option(flag, help=flag_help(f))]
            parameters.append(option(f.name, annotation, None))
    fields = {f.name: (flag, f) for flag, f in flag_fields(cls).items()}

    def collect(values: dict) -> dict:
        flags = {}
        for name, value in values.items():
            flag, f = fields[name]
            if hints[name] is bool:
                flags[name] = _switch_value(f) if value else None
            elif value is None:
                flags[name] = None
            else:
                flags[name] = check_value(cls, name, value, f"{flag}: [{section}] ", hints)
        return flags

    return OptionGroup(keyword, tuple(parameters), collect)
