"""Parameters: packaged defaults, then the user's TOML file, then flags.

Each command's parameters are one frozen dataclass (:mod:`afmtool.config.params`)
whose fields are declared once with :func:`field`: default, help, units,
choices, bounds (open or closed ends, and a value meaning "automatic") and
the command-line flag.  That one declaration generates the packaged
``defaults.toml`` (:mod:`afmtool.config.defaults`, ``afmtool config init``),
the JSON schema of each section (:mod:`afmtool.config.schema`), the flags
and their ``--help`` (:mod:`afmtool.cli.param_flags`), and the check every
value goes through, from a flag or a file (:func:`check_value`), so none of
them can drift.  A class's ``validate()`` keeps only what no single bound
says: checks across fields and of formatted strings.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import numbers
import os
import stat
import tomllib
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

from afmtool.errors import ConfigError

__all__ = [
    "field",
    "check_value",
    "coerce_value",
    "nested_section",
    "describe_bounds",
    "describe_field",
    "parse_bounds",
    "within_bounds",
    "load_toml",
    "packaged_defaults",
    "resolve",
    "resolve_from",
    "section_to_toml",
    "parameters_dict",
]

P = TypeVar("P")


def field(
    default: Any,
    help: str,
    units: str = "",
    choices: tuple[str, ...] | None = None,
    *,
    minimum: float | None = None,
    maximum: float | None = None,
    exclusive_minimum: bool = False,
    exclusive_maximum: bool = False,
    automatic: float | None = None,
    flag: str | None = None,
    bounds: str | None = None,
):
    """The one declaration of a parameter: default, help, units, bounds and CLI flag.

    Parameters
    ----------
    default
        The packaged default (``defaults.toml`` is generated from it).
    help, units : str
        Shown in ``--help``, in ``defaults.toml`` comments and in the JSON schema.
    choices : tuple of str, optional
        The values a string parameter may take.
    minimum, maximum : float, optional
        Bounds of a number, closed unless ``exclusive_minimum`` /
        ``exclusive_maximum``.  Every float must also be finite.
    bounds : str, optional
        The same bounds in interval notation, as the help and errors write them:
        ``"(0, 1)"``, ``"[0, 1)"``, ``"> 0"``, ``">= 16"``, ``"<= 6"``.
    automatic : float, optional
        A value outside the bounds that means "automatic" (``0 = ...`` in the help).
    flag : str, optional
        The command-line flag that sets it (``"--z-bin"``); a boolean whose
        default is true gets a ``--no-...`` flag that sets it false.  The flag's
        help, and the flag -> field mapping, are generated from this declaration
        (:mod:`afmtool.cli.param_flags`).
    """
    if bounds is not None:
        minimum, maximum, exclusive_minimum, exclusive_maximum = parse_bounds(bounds)
    metadata = {
        "help": help,
        "units": units,
        "choices": choices,
        "minimum": minimum,
        "maximum": maximum,
        "exclusive_minimum": exclusive_minimum,
        "exclusive_maximum": exclusive_maximum,
        "automatic": automatic,
        "flag": flag,
    }
    return dataclasses.field(default=default, metadata=types.MappingProxyType(metadata))


def parse_bounds(text: str) -> tuple[float | None, float | None, bool, bool]:
    """``"(0, 1]"`` -> (0, 1, True, False); ``"> 0"`` -> (0, None, True, False): minimum, maximum, exclusive ends."""
    text = text.strip()
    for op, exclusive in ((">=", False), ("<=", False), (">", True), ("<", True)):
        if text.startswith(op):
            value = _bound_value(text[len(op):])
            return (value, None, exclusive, False) if op[0] == ">" else (None, value, False, exclusive)
    if len(text) < 5 or text[0] not in "([" or text[-1] not in ")]" or "," not in text:
        raise ValueError(f"bounds {text!r} must look like (a, b), [a, b), > a, >= a, < b or <= b")
    low, high = text[1:-1].split(",")
    return _bound_value(low), _bound_value(high), text[0] == "(", text[-1] == ")"


def _bound_value(text: str) -> int | float:
    text = text.strip()
    return int(text) if text.lstrip("-").isdigit() else float(text)


def _number(value: float) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)


def describe_bounds(metadata: Mapping) -> str:
    """The range a declaration allows, in words: ``"in (0, 1)"``, ``"> 0"``, ``">= 16, or 0"``.

    The one wording used by the error messages, ``--help``, ``defaults.toml`` and the JSON schema.
    """
    low, high = metadata.get("minimum"), metadata.get("maximum")
    if low is not None and high is not None:
        text = (f"in {'(' if metadata.get('exclusive_minimum') else '['}{_number(low)}, {_number(high)}"
                f"{')' if metadata.get('exclusive_maximum') else ']'}")
    elif low is not None:
        text = f"{'>' if metadata.get('exclusive_minimum') else '>='} {_number(low)}"
    elif high is not None:
        text = f"{'<' if metadata.get('exclusive_maximum') else '<='} {_number(high)}"
    else:
        return ""
    if metadata.get("automatic") is not None:
        text += f", or {_number(metadata['automatic'])}"  # what that value means, the help says
    return text


def within_bounds(value: Any, metadata: Mapping) -> bool:
    """Whether a number (or every element of a tuple of numbers) satisfies the declared bounds."""
    if isinstance(value, (tuple, list)):
        return all(within_bounds(v, metadata) for v in value)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return True
    if metadata.get("automatic") is not None and value == metadata["automatic"]:
        return True
    low, high = metadata.get("minimum"), metadata.get("maximum")
    if low is not None and not (value > low if metadata.get("exclusive_minimum") else value >= low):
        return False
    if high is not None and not (value < high if metadata.get("exclusive_maximum") else value <= high):
        return False
    return True


def describe_field(f: dataclasses.Field) -> str:
    """A declaration in one line: ``help (units; default D; range R; one of: ...)``."""
    meta = f.metadata
    # units in the parentheses, not in [brackets]: rich reads "[s]" in --help as markup
    notes = [meta["units"]] if meta.get("units") else []
    notes.append(f"default {_default_text(f.default)}")
    if describe_bounds(meta):
        notes.append(describe_bounds(meta))
    if meta.get("choices"):
        notes.append("one of: " + ", ".join(repr(c) if not c else c for c in meta["choices"]))
    return f"{meta.get('help', '')} ({'; '.join(notes)})"


def _default_text(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return repr(value) if not value else value
    return _number(value)


#: Largest config file read, bytes, and its deepest nesting of tables and arrays.
MAX_CONFIG_BYTES = 1 << 20
MAX_CONFIG_DEPTH = 16


def _read_regular_file(path: Path) -> bytes:
    """The bytes of ``path`` if it is a regular file of at most MAX_CONFIG_BYTES.

    Opened non-blocking and checked with fstat before reading, so a FIFO or
    a device is refused at once instead of hanging the run.
    """
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise ConfigError(f"--config {path}: not a regular file")
        if info.st_size > MAX_CONFIG_BYTES:
            raise ConfigError(f"--config {path}: {info.st_size:,} bytes; a config file is at most {MAX_CONFIG_BYTES:,}")
        with os.fdopen(fd, "rb", closefd=False) as handle:
            return handle.read(MAX_CONFIG_BYTES + 1)
    finally:
        os.close(fd)


def _depth(document: Any) -> int:
    """Deepest nesting of tables and arrays in a parsed document (iterative)."""
    deepest, stack = 0, [(document, 0)]
    while stack:
        node, depth = stack.pop()
        deepest = max(deepest, depth)
        if isinstance(node, Mapping):
            stack.extend((v, depth + 1) for v in node.values())
        elif isinstance(node, list):
            stack.extend((v, depth + 1) for v in node)
    return deepest


def load_toml(path: Path) -> dict:
    """Read a user config file; errors become :class:`ConfigError`."""
    try:
        document = tomllib.loads(_read_regular_file(path).decode("utf-8"))
    except RecursionError:
        raise ConfigError(f"--config {path}: nested too deeply") from None
    except FileNotFoundError:
        raise ConfigError(f"--config {path}: no such file") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"--config {path}: not valid TOML ({exc})") from None
    except UnicodeDecodeError:
        raise ConfigError(f"--config {path}: not UTF-8 text") from None
    except OSError as exc:
        raise ConfigError(f"--config {path}: cannot read ({exc.strerror})") from None
    if _depth(document) > MAX_CONFIG_DEPTH:
        raise ConfigError(f"--config {path}: nested more than {MAX_CONFIG_DEPTH} deep")
    return document


def _section(document: Mapping, dotted: str) -> Mapping:
    node: Any = document
    for part in dotted.split("."):
        node = node.get(part, {}) if isinstance(node, Mapping) else {}
    if not isinstance(node, Mapping):
        raise ConfigError(f"config section [{dotted}] must be a table")
    return node


def _is_real(value: Any) -> bool:
    """A real number that is not a bool (numpy's numbers included; numpy's bool is not a Real)."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _is_bool(value: Any) -> bool:
    return isinstance(value, bool) or type(value).__name__ == "bool_"  # numpy's bool, without importing numpy


def _kind_name(kind: Any) -> str:
    return getattr(kind, "__name__", None) if typing.get_origin(kind) is None else repr(kind).replace("typing.", "")


def coerce_value(name: str, kind: Any, value: Any, where: str = "", choices: tuple[str, ...] | None = None) -> Any:
    """``value`` for a parameter ``name`` of type ``kind``, checked and normalised: the one coercer.

    Parameter models (:func:`check_value`, TOML, flags) and the simulator's
    scenarios (:mod:`afmtool.sim`) both go through it, so a value means the
    same wherever it is given:

    * ``bool``: a bool (numpy's too);
    * ``int``: an integer, or a float with an integer value (``4.0`` is 4; ``2.5`` is refused);
    * ``float``: any finite real (an int becomes a float);
    * ``str``: a string, one of ``choices`` when there are any;
    * ``tuple[float, ...]``: a list, tuple or array of finite reals;
    * ``X | None``: None, or an ``X``.

    Raises
    ------
    ConfigError
        ``{where}{name}={value!r} must be ...``.
    """
    if kind is bool and _is_bool(value):
        return bool(value)
    if kind is int and _is_real(value) and math.isfinite(value) and float(value).is_integer():
        return value if isinstance(value, int) else int(value)  # a Python int past 2**53 stays exact
    if kind is float and _is_real(value):
        if not math.isfinite(value):
            raise ConfigError(f"{where}{name}={value!r} must be a finite number")
        return float(value)
    if kind is str and isinstance(value, str):
        if choices and value not in choices:
            raise ConfigError(f"{where}{name}={value!r} must be one of {', '.join(choices)}")
        return value
    origin = typing.get_origin(kind)
    if origin is tuple and typing.get_args(kind) == (float, ...):
        if (isinstance(value, (list, tuple)) or hasattr(value, "__array__")) and all(
            _is_real(v) and math.isfinite(v) for v in value
        ):
            return tuple(float(v) for v in value)
        raise ConfigError(f"{where}{name}={value!r} must be a list of finite numbers")
    if origin in (typing.Union, types.UnionType):
        if value is None:
            return None
        for arg in (a for a in typing.get_args(kind) if a is not type(None)):
            try:
                return coerce_value(name, arg, value, where, choices)
            except ConfigError:
                continue
    raise ConfigError(f"{where}{name}={value!r} must be of type {_kind_name(kind)}")


def nested_section(kind: Any) -> bool:
    """Whether a field's type is a parameter model of its own: a sub-table (``[kalman-bank.reep]``)."""
    return isinstance(kind, type) and dataclasses.is_dataclass(kind)


def check_value(cls: type, name: str, value: Any, where: str = "", hints: Mapping | None = None) -> Any:
    """``value`` for parameter ``name`` of ``cls``, type-checked, finite and within its declared bounds.

    The one check every layer goes through (TOML file, flags, :func:`resolve`);
    its :class:`ConfigError` names the parameter and the value.  A nested
    parameter model takes a table (resolved over its own defaults) or an
    instance of itself.
    """
    hints = typing.get_type_hints(cls) if hints is None else hints
    if nested_section(hints[name]):
        if isinstance(value, hints[name]):
            return value
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where}{name}={value!r} must be a table of {hints[name].__name__} parameters")
        return resolve(hints[name], value, where=f"{where}{name}.")
    choices = {f.name: f for f in dataclasses.fields(cls)}[name].metadata.get("choices")
    coerced = coerce_value(name, hints[name], value, where, choices)
    metadata = {f.name: f for f in dataclasses.fields(cls)}[name].metadata
    if not within_bounds(coerced, metadata):
        raise ConfigError(f"{where}{name}={value!r} must be {describe_bounds(metadata)}")
    return coerced


def resolve(cls: type[P], *layers: Mapping | None, where: str = "") -> P:
    """Merge layers (lowest priority first) over ``cls``'s defaults, with validation.

    ``None`` values in a layer mean "not given" (an unset flag).
    """
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    values: dict[str, Any] = {}
    nested: dict[str, list] = {}
    for layer in layers:
        for key, value in (layer or {}).items():
            if key not in names:
                raise ConfigError(f"{where}unknown parameter {key!r} (known: {', '.join(sorted(names))})")
            if value is None:
                continue
            if nested_section(hints[key]) and isinstance(value, Mapping):
                nested.setdefault(key, []).append(value)  # the layers of a sub-table merge key by key
            else:
                values[key] = check_value(cls, key, value, where, hints)
    for key, tables in nested.items():
        values[key] = resolve(hints[key], *tables, where=f"{where}{key}.")
    instance = cls(**values)
    check = getattr(instance, "validate", None)
    if callable(check):
        check()
    return instance


def packaged_defaults() -> dict:
    """The ``defaults.toml`` shipped with afmtool (generated from the parameter models); a fresh copy."""
    import copy

    return copy.deepcopy(_parsed_packaged_defaults())


@functools.cache
def _parsed_packaged_defaults() -> dict:
    # parsed once per process: batch and the tests resolve many sections
    from importlib import resources

    text = resources.files("afmtool.config").joinpath("defaults.toml").read_text(encoding="utf-8")
    return tomllib.loads(text)


def resolve_from(cls: type[P], section: str, user_config: Mapping | None, flags: Mapping) -> P:
    """Packaged defaults, then ``[section]`` of the user's config, then flags."""
    packaged = _section(packaged_defaults(), section)
    from_file = _section(user_config or {}, section)
    return resolve(cls, packaged, from_file, flags, where=f"[{section}] ")


def parameters_dict(instance: Any) -> dict:
    return dataclasses.asdict(instance)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return str(value)


def section_to_toml(section: str, instance: Any, *, comments: bool = True) -> str:
    """One ``[section]`` table, then one ``[section.name]`` table per nested model; ``None`` values are comments."""
    lines = [f"[{section}]"]
    tables = []
    for f in dataclasses.fields(instance):
        value = getattr(instance, f.name)
        if dataclasses.is_dataclass(value):
            tables.append((f, value))
            continue
        if comments and f.metadata.get("help"):
            units = f" [{f.metadata['units']}]" if f.metadata.get("units") else ""
            choices = f" (one of: {', '.join(f.metadata['choices'])})" if f.metadata.get("choices") else ""
            bounds = f" ({describe_bounds(f.metadata)})" if describe_bounds(f.metadata) else ""
            lines.append(f"# {f.metadata['help']}{units}{choices}{bounds}")
        lines.append(f"# {f.name} = (unset)" if value is None else f"{f.name} = {_toml_value(value)}")
    text = "\n".join(lines) + "\n"
    for f, value in tables:
        heading = f"# {f.metadata['help']}\n" if comments and f.metadata.get("help") else ""
        text += "\n" + heading + section_to_toml(f"{section}.{f.name}", value, comments=comments)
    return text
