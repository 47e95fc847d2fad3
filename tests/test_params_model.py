"""One typed parameter model: every parameter's declaration drives its TOML, schema, --help and checks.

* Every parameter of every section refuses NaN, inf and an out-of-range value,
  from a TOML file (through :func:`afmtool.config.resolve_from`, the function every
  command resolves its section with; scenarios through :func:`afmtool.sim.simulate`)
  and from its flag (through :func:`afmtool.cli.main.main` in-process): exit 2 and
  one stderr line naming the parameter.  A few subprocess runs show the in-process
  path is the one a user meets.
* The generated ``defaults.toml``, ``schemas/params/*.schema.json`` and each flag's
  ``--help`` agree on names, defaults, bounds and units.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import signal
import sys
import tomllib
import typing

import jsonschema
import pytest
import typer.main

from afmtool import sim
from afmtool.cli.param_flags import flag_fields
from afmtool.config import check_value, describe_bounds, resolve_from, within_bounds
from afmtool.config.defaults import packaged_defaults_text, parameter_sections
from afmtool.config.params import SECTIONS, KalmanBankParams, ReepParams
from afmtool.config.schema import SCHEMA_DIR, schema_filename, section_schema, write_schemas
from afmtool.errors import ConfigError
from tests.conftest import run_cli

#: typer's own get_command, before the in-process fixture replaces it with a cached one
_GET_COMMAND = typer.main.get_command

#: Each command section's command words and the arguments a command line needs besides the flag.
COMMANDS = {
    "identify.freeair": (["identify", "freeair"], ["capture.h5"]),
    "identify.spring_constant": (["identify", "freeair"], ["--psd", "spectrum.csv"]),
    "identify.gamma": (["identify", "gamma"], ["sweep.h5", "--contact", "contact.h5"]),
    "identify.thermal": (["identify", "thermal"], ["--iv", "iv.h5"]),
    "identify.electrostatic": (["identify", "electrostatic"], ["es.h5"]),
    "identify.invols": (["identify", "invols"], ["curve.h5"]),
    "reep": (["reep"], ["capture.h5"]),
    "probeloss": (["probeloss"], ["capture.h5"]),
    "decode": (["decode"], ["capture.h5"]),
    "kalman-bank": (["kalman-bank"], ["capture.h5"]),
    "theory.averaging": (["theory", "averaging"], []),
    "theory.compare": (["theory", "compare"], ["reep_dir"]),
    "theory.controllers": (["theory", "controllers"], []),
    "theory.fit": (["theory", "fit"], ["reep_dir"]),
    "theory.observer": (["theory", "observer"], []),
    "design.excitation": (["design", "excitation"], ["--model", "free_air.json"]),
}


def _sections() -> dict[str, type]:
    return {name: type(value) for name, value in parameter_sections().items()}


def _out_of_range(f: dataclasses.Field, kind) -> object | None:
    """A value just outside the declared bounds or choices (None: the declaration has none)."""
    meta = f.metadata
    if meta.get("choices"):
        return "not-one-of-the-choices"
    scalar = kind if kind in (int, float) else (float if typing.get_origin(kind) is tuple else None)
    if scalar is None:
        return None
    low, high = meta.get("minimum"), meta.get("maximum")
    candidates = []
    if low is not None:
        candidates += [low, low - 1] if meta.get("exclusive_minimum") else [low - 1, low - 0.5]
    if high is not None:
        candidates += [high, high + 1] if meta.get("exclusive_maximum") else [high + 1, high + 0.5]
    for value in candidates:
        value = scalar(value) if scalar is int and float(value).is_integer() else value
        if isinstance(value, float) and scalar is int:
            continue
        if not within_bounds(value, meta):
            return [value] if typing.get_origin(kind) is tuple else value
    return None


def _bad_values(f: dataclasses.Field, kind) -> list:
    """NaN, inf, -inf and (where the declaration has bounds or choices) a value just outside them."""
    bad = _out_of_range(f, kind)
    return [math.nan, math.inf, -math.inf] + ([] if bad is None else [bad])


def _cases() -> list:
    return [
        pytest.param(section, f.name, id=f"{section}.{f.name}")
        for section, cls in _sections().items()
        for f in dataclasses.fields(cls)
    ]


def _resolve_from_toml(section: str, cls: type, name: str, value) -> None:
    """What a command does with ``--config FILE`` whose ``[section]`` sets ``name = value``."""
    if section.startswith("simulate."):
        sim.simulate(section.split(".", 1)[1], {name: value})  # afmtool simulate --config: refused before running
        return
    document: dict = {}
    node = document
    for part in section.split("."):
        node = node.setdefault(part, {})
    node[name] = value
    resolve_from(cls, section, document, {})


@pytest.mark.parametrize("section, name", _cases())
def test_every_parameter_refuses_nan_inf_and_out_of_range_from_toml(section, name):
    cls = _sections()[section]
    f = {f.name: f for f in dataclasses.fields(cls)}[name]
    for value in _bad_values(f, typing.get_type_hints(cls)[name]):
        with pytest.raises(ConfigError) as refused:
            _resolve_from_toml(section, cls, name, value)
        message = str(refused.value)
        assert name in message and "\n" not in message, (value, message)


@pytest.fixture
def in_process(monkeypatch, capsys):
    """``afmtool.cli.main.main(argv)`` in this process: (exit status, stderr lines)."""
    from afmtool.cli import main as cli_main

    # main() ends a failed run without interpreter teardown while a helper thread lives; pytest has some
    monkeypatch.setattr("afmtool.runtime.process.exit_now_if_teardown_unsafe", lambda code: None)
    # main() builds the same click tree from the typer app on every call; build it once here
    monkeypatch.setattr(cli_main.typer.main, "get_command", _command_tree)
    saved = (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM), sys.unraisablehook, sys.excepthook)
    import warnings

    showwarning = warnings.showwarning

    def run(argv: list[str]) -> tuple[int, list[str]]:
        capsys.readouterr()
        with pytest.raises(SystemExit) as done:
            cli_main.main([str(a) for a in argv])
        return done.value.code, capsys.readouterr().err.strip().splitlines()

    yield run
    signal.signal(signal.SIGINT, saved[0])
    signal.signal(signal.SIGTERM, saved[1])
    sys.unraisablehook, sys.excepthook = saved[2], saved[3]
    warnings.showwarning = showwarning


@functools.cache
def _command_tree(app):
    return _GET_COMMAND(app)


def _flag_cases() -> list:
    cases = []
    for section, cls in SECTIONS.items():
        hints = typing.get_type_hints(cls)
        for flag, f in flag_fields(cls).items():
            kind = hints[f.name]
            values = ["nan", "inf"] if kind in (int, float) else []
            bad = _out_of_range(f, kind)
            if bad is not None:
                values.append(str(bad))
            if values:  # a switch (bool) takes no value; a free string has no bad one
                cases.append(pytest.param(section, flag, f.name, values, id=f"{section}:{flag}"))
    return cases


@pytest.mark.parametrize("section, flag, name, values", _flag_cases())
def test_every_flag_refuses_nan_inf_and_out_of_range(in_process, tmp_path, section, flag, name, values):
    words, required = COMMANDS[section]
    for text in values:
        status, lines = in_process([*words, *required, f"{flag}={text}", "--out", tmp_path / "out"])
        assert status == 2, (text, lines)
        assert len(lines) == 1 and (name in lines[0] or flag in lines[0]), (text, lines)
        assert not (tmp_path / "out").exists()


def test_every_flagged_section_has_a_command_line():
    assert set(COMMANDS) == set(SECTIONS)


@pytest.mark.parametrize(
    "argv, toml, needle",
    [
        (["reep", "sample_data/ltv_step.h5", "--z-bin", "nan"], None, "z_bin"),
        (["kalman-bank", "sample_data/ltv_step.h5", "--n-filters", "nan"], None, "--n-filters"),
        (["reep", "sample_data/ltv_step.h5"], "[reep]\nlockin_lowpass_hz = nan\n", "lockin_lowpass_hz"),
        (["reep", "sample_data/ltv_step.h5"], "[reep]\nwarmup_windows = nan\n", "warmup_windows"),
    ],
    ids=["z-bin-flag", "n-filters-flag", "lockin_lowpass_hz-toml", "warmup_windows-toml"],
)
def test_the_in_process_path_is_the_command_line(tmp_path, in_process, argv, toml, needle):
    extra = []
    if toml is not None:
        (tmp_path / "bad.toml").write_text(toml)
        extra = ["--config", tmp_path / "bad.toml"]
    argv = [*argv, *extra, "--out", tmp_path / "out"]
    result = run_cli(*argv)
    lines = result.stderr.decode().strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1 and needle in lines[0], lines
    assert in_process(argv) == (2, lines)
    assert not (tmp_path / "out").exists()


def test_bounds_have_open_and_closed_ends_and_an_automatic_value():
    check_value(ReepParams, "lam", 0.5)
    assert check_value(ReepParams, "lam", 0.0) == 0.0  # 0 = from window_us
    for bad in (1.0, -0.1):  # (0, 1): both ends open, 0 meaning automatic
        with pytest.raises(ConfigError, match=r"lam=.* must be in \(0, 1\), or 0"):
            check_value(ReepParams, "lam", bad)
    check_value(KalmanBankParams, "adaptive_fraction", 1.0)  # (0, 1]: 1 is in
    with pytest.raises(ConfigError, match=r"must be in \(0, 1\]"):
        check_value(KalmanBankParams, "adaptive_fraction", 0.0)
    assert check_value(ReepParams, "decimate", 0) == 0  # 0 = one per drive period
    with pytest.raises(ConfigError, match=r"decimate=-1 must be in \[1, 1000000000000000\], or 0"):
        check_value(ReepParams, "decimate", -1)
    with pytest.raises(ConfigError, match=r"decimate=99999999999999999999999 must be in \[1, "):  # past int64 (issue 34)
        check_value(ReepParams, "decimate", 99999999999999999999999)
    with pytest.raises(ConfigError, match=r"must be of type int"):
        check_value(ReepParams, "decimate", 2.5)


def test_schemas_are_current():
    # Regenerate with: python -m afmtool.config.schema
    assert write_schemas(SCHEMA_DIR, check=True) == []


def _toml_comments(text: str) -> dict[tuple[str, str], str]:
    """(section, key) -> the comment line above it in the generated TOML."""
    comments, section, previous = {}, "", ""
    for line in text.splitlines():
        if line.startswith("[") and line.endswith("]"):
            section = line[1:-1]
        elif line.startswith("# ") and " = " in line and line[2:].split(" = ")[0].isidentifier() and "(unset)" in line:
            comments[(section, line[2:].split(" = ")[0])] = previous
        elif line and not line.startswith("#"):
            comments[(section, line.split(" = ")[0])] = previous
        previous = line
    return comments


def _click_options() -> dict[tuple[str, ...], dict[str, object]]:
    import typer

    from afmtool.cli.main import app

    root = typer.main.get_command(app)
    options = {}
    for _section, (words, _) in COMMANDS.items():
        command = root
        for word in words:
            command = command.commands[word]
        options[tuple(words)] = {opt: p for p in command.params for opt in getattr(p, "opts", ())}
    return options


def test_generated_toml_schema_and_help_agree():
    packaged = tomllib.loads(packaged_defaults_text())
    comments = _toml_comments(packaged_defaults_text())
    click_options = _click_options()
    for section, cls in _sections().items():
        schema = json.loads((SCHEMA_DIR / schema_filename(section)).read_text(encoding="utf-8"))
        assert schema == section_schema(section, cls)
        table = packaged
        for part in section.split("."):
            table = table[part]
        fields = {f.name: f for f in dataclasses.fields(cls)}
        assert list(schema["properties"]) == list(fields)
        assert set(table) <= set(fields)  # unset (None) values are written as comments
        validator = jsonschema.Draft202012Validator(schema)
        validator.validate(table)
        for name, f in fields.items():
            prop = schema["properties"][name]
            if dataclasses.is_dataclass(f.default):  # a nested table ([kalman-bank.reep]): its own defaults, refused extras
                assert prop["default"] == dataclasses.asdict(f.default) == table[name], (section, name)
                assert not validator.is_valid({**table, name: {**table[name], "no_such_parameter": 1}})
                continue
            default = list(f.default) if isinstance(f.default, tuple) else f.default
            assert prop["default"] == default and table.get(name, default) == default, (section, name)
            comment = comments[(section, name)]
            units = f.metadata.get("units")
            assert prop.get("x-units", "") == units
            if units:
                assert f"[{units}]" in comment, (section, name, comment)
            assert prop.get("x-range", "") == describe_bounds(f.metadata)
            if prop.get("x-range"):
                assert f"({prop['x-range']})" in comment, (section, name, comment)
            bad = _out_of_range(f, typing.get_type_hints(cls)[name])
            if bad is not None:  # the schema refuses what the check refuses
                assert not validator.is_valid({**table, name: bad}), (section, name, bad)
            flag = f.metadata.get("flag")
            assert prop.get("x-flag") == flag
            if flag and section in COMMANDS:
                words = tuple(COMMANDS[section][0])
                option = click_options[words][flag]
                text = option.help
                if f.default is True or f.default is False:
                    assert f"Sets {name} = {str(not f.default).lower()}" in text, text
                    continue
                assert option.default is None, (section, flag)  # unset: the TOML or packaged default applies
                assert f.metadata["help"] in text and f"default {_help_default(f.default)}" in text, text
                if units:
                    assert f"({units};" in text, text
                if prop.get("x-range"):
                    assert prop["x-range"] in text, text
                for choice in f.metadata.get("choices") or ():
                    assert choice in text


def _help_default(value) -> str:
    if isinstance(value, str):
        return repr(value) if not value else value
    return f"{value:g}" if isinstance(value, float) else str(value)
