"""One command table (issue 29, item 3): every per-command table is derived from the specs.

:mod:`afmtool.config.commands` declares each command once (:class:`CommandSpec`);
the config sections, the help's examples, the headlines, the HTML page's main
figures, batch's commands, the capture commands' channels and the runners are
read from it.  These tests check that every command of the CLI has a whole
spec and every spec a command, that each derived table holds exactly the
commands whose spec has that part, and that a spec lacking a part fails.
"""

from __future__ import annotations

import dataclasses

import pytest
import typer.main

from afmtool.config.commands import (
    REQUIRED,
    SPECS,
    CommandSpec,
    Kind,
    Lazy,
    Section,
    check_specs,
    missing_parts,
)


def _cli_commands() -> list[str]:
    """Every command of the click tree, by its words (as test_habits' help probe walks it)."""
    from afmtool.cli.main import app

    def walk(command, prefix: tuple[str, ...]) -> list[str]:
        subcommands = getattr(command, "commands", None)
        if subcommands is None:
            return [" ".join(prefix)]
        return [path for name, sub in subcommands.items() for path in walk(sub, (*prefix, name))]

    return walk(typer.main.get_command(app), ())


def _with(kind: Kind) -> set[str]:
    return {name for name, spec in SPECS.items() if spec.kind is kind}


def test_every_command_has_a_whole_spec_and_every_spec_a_command():
    commands = _cli_commands()
    assert {"reep", "identify freeair", "theory compare", "config init", "batch"} <= set(commands)
    assert check_specs(SPECS, commands) == []


def test_each_derived_table_holds_the_commands_whose_spec_has_that_part():
    from afmtool.api.run import CAPTURE_COMMANDS
    from afmtool.cli.batch_cmd import _COMMANDS
    from afmtool.cli.help import EXAMPLES
    from afmtool.config.params import SECTIONS
    from afmtool.report.headline import HEADLINES
    from afmtool.report.html import MAIN_FIGURES

    specs = SPECS.values()
    assert EXAMPLES == {s.name: s.examples for s in specs} and set(EXAMPLES) == set(SPECS)
    assert HEADLINES == {s.name: s.result.load().HEADLINE for s in specs if s.kind is not Kind.TOOL}
    assert set(HEADLINES) == set(SPECS) - _with(Kind.TOOL)
    assert MAIN_FIGURES == {s.name: s.main_figures for s in specs if s.main_figures is not None}
    assert SECTIONS == {name: model for s in specs for name, model in s.sections()}
    assert {s.section for s in specs if s.params} <= set(SECTIONS)
    assert _COMMANDS == {s.batch: tuple(s.name.split()) for s in specs if s.batch is not None}
    assert CAPTURE_COMMANDS == {s.name: (s.channels, s.synthesised_drive) for s in specs if s.kind is Kind.CAPTURE}
    assert set(CAPTURE_COMMANDS) == {"reep", "probeloss", "decode", "kalman-bank"}


def test_every_section_and_batch_name_is_given_once():
    named = [name for s in SPECS.values() for name, _ in s.sections()]
    assert len(named) == len(set(named))
    batch = [s.batch for s in SPECS.values() if s.batch is not None]
    assert len(batch) == len(set(batch)) and {"reep", "freeair", "invols"} <= set(batch)


def test_every_runner_and_stream_loads():
    """Each Lazy names a function (or the stream's units table) that exists: a typo fails here, not in a run."""
    for spec in SPECS.values():
        for part in ("runner", "stream"):
            lazy = getattr(spec, part)
            if lazy is not None:
                assert callable(lazy.load()), (spec.name, part, lazy)
        if spec.stream_units is not None:
            assert dict(spec.stream_units.load()), spec.name


def test_the_api_and_the_cli_bind_the_specs_runners():
    """No command module is imported by a name outside the specs: api/run keeps no runner table."""
    import afmtool.api.run as run

    assert not hasattr(run, "_RUNNERS") and not hasattr(run, "_FOLDER_RUNNERS") and not hasattr(run, "_function")
    assert run._runner("theory compare") is SPECS["theory compare"].runner.load()


# --------------------------------------------------------------------------- a spec that lacks a part

_CAPTURE = dict(
    params=(Section(dict),), runner=Lazy("afmtool.analyses.reep_outputs", "run_reep_command"),
    examples=("afmtool x capture.h5 --out results/x",), main_figures=(), result=Lazy("afmtool.records.invols", "InvolsResults"),
    channels=("deflection",),
)


def test_a_whole_spec_is_built():
    spec = CommandSpec("x", Kind.CAPTURE, **_CAPTURE)
    assert missing_parts(spec) == [] and spec.section == "x"


@pytest.mark.parametrize("kind", list(Kind))
def test_a_spec_lacking_a_required_part_is_refused_as_it_is_built(kind):
    for part in REQUIRED[kind]:
        parts = {key: value for key, value in _CAPTURE.items() if key in REQUIRED[kind] and key != part}
        with pytest.raises(ValueError, match=part):
            CommandSpec("x", kind, **parts)


@pytest.mark.parametrize(
    "kind, extra, needle",
    [
        (Kind.ANALYSIS, {"channels": ("deflection",)}, "channels"),
        (Kind.ANALYSIS, {"synthesised_drive": True}, "synthesised_drive"),
        (Kind.TOOL, {"result": Lazy("afmtool.records.invols", "InvolsResults")}, "result"),
        (Kind.CAPTURE, {"stream": Lazy("m", "f")}, "stream_units"),
        (Kind.CAPTURE, {"examples": ()}, "examples"),
    ],
)
def test_a_spec_with_a_part_it_must_not_have_is_refused(kind, extra, needle):
    parts = {key: value for key, value in _CAPTURE.items() if key in REQUIRED[kind]}
    with pytest.raises(ValueError, match=needle):
        CommandSpec("x", kind, **{**parts, **extra})


def test_the_check_fails_a_spec_that_lost_a_part_and_a_table_out_of_step_with_the_cli():
    whole = CommandSpec("x", Kind.CAPTURE, **_CAPTURE)
    broken = dataclasses.replace(whole)
    object.__setattr__(broken, "result", None)  # past the constructor's check: the check function finds it
    assert missing_parts(broken) == ["result"]
    assert check_specs({"x": broken}, ["x"]) == ["x: lacks result"]
    assert check_specs({"x": whole}, ["x", "y"]) == ["y: a command without a spec"]
    assert check_specs({"x": whole}, []) == ["x: a spec without a command"]
    assert check_specs({"z": whole}, ["z"]) == ["z: its spec is named 'x'"]
    twice = {"x": dataclasses.replace(whole, batch="b"), "y": dataclasses.replace(whole, name="y", batch="b")}
    assert check_specs(twice, ["x", "y"]) == ["batch name 'b' given twice"]
