"""``--help`` (issue 18): no type after flags, option panels, the terminal's width, examples, no heavy imports."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from afmtool.cli.help import EXAMPLES, PANELS

#: Every leaf command, as typed after ``afmtool``.
COMMANDS = sorted(EXAMPLES)


def _help(*words: str, columns: int = 160) -> str:
    env = {**os.environ, "COLUMNS": str(columns), "TERMINAL_WIDTH": "", "NO_COLOR": "1"}
    env.pop("TERMINAL_WIDTH")
    result = subprocess.run([sys.executable, "-m", "afmtool", *words, "--help"], capture_output=True, text=True,
                            env=env, timeout=120)
    assert result.returncode == 0, result.stderr
    return result.stdout


@pytest.fixture(scope="module")
def helps() -> dict[str, str]:
    # one interpreter for all of them: typer's CliRunner, on the command tree main() arranges
    script = (
        "import json, sys, typer, typer.testing\n"
        "from afmtool.cli.help import arrange_help\n"
        "from afmtool.cli.main import app\n"
        "command = typer.main.get_command(app)\n"
        "arrange_help(command)\n"
        "typer.testing._get_command = lambda _: command  # the tree as main() runs it\n"
        "out = {}\n"
        "for words in json.loads(sys.argv[1]):\n"
        "    r = typer.testing.CliRunner().invoke(app, [*words.split(), '--help'])\n"
        "    out[words] = r.output\n"
        "print(json.dumps(out))\n"
    )
    import json

    env = {**os.environ, "COLUMNS": "160", "NO_COLOR": "1"}
    env.pop("TERMINAL_WIDTH", None)
    result = subprocess.run([sys.executable, "-c", script, json.dumps(["", *COMMANDS])], capture_output=True,
                            text=True, env=env, timeout=300)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)


def test_no_type_metavar_after_flags(helps):
    for words, text in helps.items():
        assert "<bool>" not in text, f"afmtool {words} --help shows <bool>"
    assert "--no-bias-compensation " in helps["reep"] and "--json " in helps["reep"]


@pytest.mark.parametrize("words", ["reep", "probeloss", "decode", "kalman-bank", "identify freeair"])
def test_analysis_options_are_grouped_in_panels(helps, words):
    text = helps[words]
    positions = [text.find(f"─ {panel} ─") for panel in PANELS]
    assert all(p >= 0 for p in positions), f"{words}: panels {dict(zip(PANELS, positions))}"
    assert positions == sorted(positions)  # Input, Model, Estimator, Output, in that order
    assert "─ Options ─" not in text  # nothing left in an unnamed panel
    output = text[positions[-1]:]
    assert "--out" in output and "--help" in output and "-h" in output


def test_every_command_ends_with_examples(helps):
    for words in COMMANDS:
        text = helps[words]
        tail = text[text.rfind("Examples:"):]
        assert "Examples:" in text, words
        assert f"afmtool {words}" in tail, words
        assert "╰" not in tail  # the examples come after every panel


def test_help_uses_the_terminal_width():
    wide = _help("reep", columns=150)
    narrow = _help("reep", columns=90)
    assert max(len(line) for line in wide.splitlines()) == 150
    assert max(len(line) for line in narrow.splitlines()) == 90
    # at 150 columns a long option help (generated from its declaration) fits on one line, not wrapped at 80
    text = "Sets use_input = false: Use the recorded dither (false: output-only AR(2) tracking) (default true)."
    assert any(text in line for line in wide.splitlines())


def test_help_imports_no_scipy_numba_matplotlib():
    check = (
        "import sys\n"
        "sys.argv = ARGV\n"
        "from afmtool.cli.main import main\n"
        "try:\n    main()\nexcept SystemExit:\n    pass\n"
        "heavy = [m for m in ('scipy', 'numba', 'matplotlib') if m in sys.modules]\n"
        "print('HEAVY=' + ','.join(heavy), file=sys.stderr)\n"
    )
    for argv in (["--help"], ["reep", "--help"], ["report", "--help"], ["probeloss", "--help"]):
        script = check.replace("ARGV", repr(["afmtool", *argv]))
        result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
        marker = [line for line in result.stderr.splitlines() if line.startswith("HEAVY=")]
        assert marker == ["HEAVY="], (argv, result.stderr[-500:])


def test_a_command_does_not_import_the_help_renderer():
    """typer's rich help module (0.12-0.17 s of rich markdown, traceback, pretty) loads only for help or a usage error."""
    script = (
        "import sys\n"
        "sys.argv = ['afmtool', '--version']\n"
        "from afmtool.cli.main import main\n"
        "try:\n    main()\nexcept SystemExit:\n    pass\n"
        "print('LOADED=' + str('typer.rich_utils' in sys.modules), file=sys.stderr)\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "TERMINAL_WIDTH"}
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=120)
    assert "LOADED=False" in result.stderr.splitlines(), result.stderr[-500:]
