"""Habits the code keeps (issue 15 item 5, issue 19 item 3), checked on its source.

* every numba kernel compiles with the one ``JIT_OPTIONS`` constant;
* outside numba kernels no function has over 60 code lines: docstrings,
  comments and blank lines are not counted, so a function is not squeezed
  by its documentation (issue 29 item 7; ruff's C901 and PLR0915 check
  complexity and statements, in .ci/run);
* ``afmtool --help`` and every ``afmtool ... --help`` import none of numba,
  scipy, matplotlib (nor numpy and h5py, as bench/bench_io.py asked);
* the streaming commands (reep, probeloss, decode) do not import scipy.signal.
"""

from __future__ import annotations

import ast
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "afmtool"
#: Code lines of a function outside numba kernels: no docstring, comment or blank line counts.
MAX_FUNCTION_LINES = 60


def _sources() -> list[Path]:
    return sorted(PACKAGE.rglob("*.py"))


def _parsed(path: Path) -> ast.Module:
    return ast.parse(path.read_text(encoding="utf-8"), filename=str(path))


def _is_njit(decorator: ast.expr) -> bool:
    """``@njit``, ``@njit(...)``, ``@numba.njit(...)``, ``@jit(...)`` and the like."""
    target = decorator.func if isinstance(decorator, ast.Call) else decorator
    name = target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", "")
    return name in {"njit", "jit", "generated_jit", "vectorize", "guvectorize", "cfunc"}


def _shown(path: Path) -> str:
    return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else path.name


def _functions(tree: ast.Module):
    return (n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)))


# --------------------------------------------------------------------------- one JIT constant


def test_jit_options_keep_nan_and_the_cache():
    from afmtool.jit import JIT_OPTIONS

    assert JIT_OPTIONS["cache"] is True and JIT_OPTIONS["nogil"] is True
    # fastmath would let NaN vanish and reorder sums away from the plain-Python references
    assert not JIT_OPTIONS.get("fastmath", False)
    assert JIT_OPTIONS.get("error_model") == "numpy"


def _jit_misuses(path: Path) -> list[str]:
    tree = _parsed(path)
    kernels = [(f, d) for f in _functions(tree) for d in f.decorator_list if _is_njit(d)]
    if not kernels:
        return []
    found = []
    imported = any(
        isinstance(n, ast.ImportFrom) and n.module == "afmtool.jit" and any(a.name == "JIT_OPTIONS" and a.asname is None for a in n.names)
        for n in ast.walk(tree)
    )
    if not imported:
        found.append(f"{_shown(path)}: JIT_OPTIONS is not imported from afmtool.jit")
    for function, decorator in kernels:
        one_constant = (
            isinstance(decorator, ast.Call)
            and isinstance(decorator.func, ast.Name)
            and decorator.func.id == "njit"
            and not decorator.args
            and len(decorator.keywords) == 1
            and decorator.keywords[0].arg is None
            and isinstance(decorator.keywords[0].value, ast.Name)
            and decorator.keywords[0].value.id == "JIT_OPTIONS"
        )
        if not one_constant:
            found.append(f"{_shown(path)}:{function.lineno} {function.name}: @{ast.unparse(decorator)}")
    return found


def test_every_kernel_uses_the_one_jit_constant():
    misuses = [m for path in _sources() for m in _jit_misuses(path)]
    assert not misuses, "kernels must be @njit(**JIT_OPTIONS):\n" + "\n".join(misuses)


def test_the_jit_check_finds_a_kernel_with_its_own_options(tmp_path):
    own = tmp_path / "own.py"
    own.write_text("from numba import njit\n\n@njit(cache=True)\ndef k(x):\n    return x\n")
    assert len(_jit_misuses(own)) == 2  # not imported, and its own options


# --------------------------------------------------------------------------- noqa reasons

_NOQA = re.compile(r"#\s*noqa\b(?P<rest>[^\n]*)", re.IGNORECASE)
_NOQA_WITH_REASON = re.compile(r"^:\s*[A-Z]+[0-9]+(\s*,\s*[A-Z]+[0-9]+)*\s+-\s+\S")


#: Files whose noqa comments are not checked (none: every branch has merged).
_NOQA_PENDING: set[str] = set()


def _noqa_without_reason(path: Path) -> list[str]:
    found = []
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        for match in _NOQA.finditer(line):
            if not _NOQA_WITH_REASON.match(match.group("rest")):
                found.append(f"{_shown(path)}:{number}: {line.strip()[:100]}")
    return found


def test_every_noqa_names_its_rules_and_says_why():
    # a bare noqa silences every rule; one without a reason leaves the next reader guessing
    this_file = Path(__file__).resolve()
    paths = [p for folder in ("afmtool", "tests", "bench") for p in sorted((ROOT / folder).rglob("*.py"))
             if p != this_file and p.relative_to(ROOT).as_posix() not in _NOQA_PENDING]
    missing = [m for path in paths for m in _noqa_without_reason(path)]
    assert not missing, "write '# noqa: CODE - why':\n" + "\n".join(missing)


def test_the_noqa_check_finds_a_bare_noqa(tmp_path):
    source = tmp_path / "bare.py"
    source.write_text("import os  # noqa\nimport re  # noqa: F401\nimport io  # noqa: F401 - re-exported\n")
    assert [m.split(":")[1] for m in _noqa_without_reason(source)] == ["1", "2"]


# --------------------------------------------------------------------------- short functions


def _docstring_lines(function: ast.AST) -> set[int]:
    """Lines of the docstrings of ``function`` and of the functions and classes inside it."""
    lines: set[int] = set()
    for node in ast.walk(function):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
                lines.update(range(first.lineno, first.end_lineno + 1))
    return lines


def code_lines(function: ast.AST, source_lines: list[str]) -> int:
    """Lines of ``function`` from its ``def`` on that are code: not docstring, comment or blank."""
    documentation = _docstring_lines(function)
    return sum(
        1 for number in range(function.lineno, function.end_lineno + 1)
        if number not in documentation and source_lines[number - 1].strip()
        and not source_lines[number - 1].strip().startswith("#")
    )


def _long_functions(path: Path) -> list[str]:
    found = []
    source_lines = path.read_text(encoding="utf-8").splitlines()
    for function in _functions(_parsed(path)):
        if any(_is_njit(d) for d in function.decorator_list):
            continue  # a numba kernel is one scalar recursion; ruff's noqa on it says so
        length = code_lines(function, source_lines)
        if length > MAX_FUNCTION_LINES:
            found.append(f"{_shown(path)}:{function.lineno} {function.name}: {length} code lines")
    return found


def _folders() -> list[str]:
    return sorted({p.relative_to(PACKAGE).parts[0] if len(p.relative_to(PACKAGE).parts) > 1 else "." for p in _sources()})


@pytest.mark.parametrize("folder", _folders())
def test_functions_outside_kernels_are_at_most_60_code_lines(folder):
    paths = [p for p in _sources() if (p.parent == PACKAGE if folder == "." else p.is_relative_to(PACKAGE / folder))]
    too_long = [f for path in paths for f in _long_functions(path)]
    assert not too_long, f"split these into helpers of at most {MAX_FUNCTION_LINES} code lines:\n" + "\n".join(too_long)


def test_the_length_check_counts_code_not_documentation_and_leaves_kernels_out(tmp_path):
    body = "".join(f"    x = {i}\n" for i in range(MAX_FUNCTION_LINES))  # with its def line: one too many
    short = "".join(f"    x = {i}\n" for i in range(MAX_FUNCTION_LINES - 1))  # with its def line: allowed
    documented = '    """' + "\n".join(["A long docstring."] * 40) + '"""\n' + "    # why\n\n" * 10 + short
    nested = '    def inner():\n        """doc"""\n' + "".join(f"        y = {i}\n" for i in range(MAX_FUNCTION_LINES))
    source = tmp_path / "long.py"
    source.write_text(f"def long():\n{body}\n@njit(**JIT_OPTIONS)\ndef kernel():\n{body}\ndef short():\n{short}"
                      f"def documented():\n{documented}def outer():\n{nested}")
    found = sorted(f.split(" ", 1)[1] for f in _long_functions(source))
    assert found == sorted([f"long: {MAX_FUNCTION_LINES + 1} code lines", f"outer: {MAX_FUNCTION_LINES + 2} code lines",
                            f"inner: {MAX_FUNCTION_LINES + 1} code lines"])


# --------------------------------------------------------------------------- import guarantees

#: Runs every command's --help in one interpreter (in-process, as the
#: console script does) and prints, per command, which heavy modules had been
#: imported by then.  The list is cumulative, so the first command that
#: imports one is the one named.
_HELP_PROBE = """
import json, sys
import typer.main
from afmtool.cli.main import app, main

def paths(command, prefix=()):
    found = [list(prefix)]
    for name, sub in sorted(getattr(command, "commands", {}).items()):
        found += paths(sub, (*prefix, name))
    return found

seen = {}
for path in paths(typer.main.get_command(app)):
    sys.argv = ["afmtool", *path, "--help"]
    try:
        main()
    except SystemExit:
        pass
    seen[" ".join(path)] = [m for m in HEAVY if m in sys.modules]
print("PROBE=" + json.dumps(seen), file=sys.stderr)
"""

#: numba, scipy and matplotlib (issue 19), numpy and h5py (bench/bench_io.py's check), and pydantic
#: (issue 33: typer is pinned below 0.29, whose option parsing loads it).
HEAVY = ("numba", "scipy", "matplotlib", "numpy", "h5py", "pydantic")


def _probe(script: str) -> dict:
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300, cwd=ROOT,
                            stdin=subprocess.DEVNULL)
    marker = [line for line in result.stderr.splitlines() if line.startswith("PROBE=")]
    assert len(marker) == 1, result.stderr[-2000:]
    return json.loads(marker[0].removeprefix("PROBE="))


def test_help_of_every_command_imports_no_heavy_module():
    seen = _probe(_HELP_PROBE.replace("HEAVY", repr(HEAVY)))
    # the probe found the commands (a probe that finds none cannot fail)
    assert {"", "reep", "probeloss", "decode", "identify freeair", "theory compare", "config init"} <= set(seen)
    heavy = {command or "(afmtool --help)": modules for command, modules in seen.items() if modules}
    assert not heavy, f"--help imported heavy modules (first command to do so): {heavy}"


_STREAM_PROBE = """
import json, sys
from afmtool.cli.main import main

commands = {
    "reep": ["reep", "sample_data/ltv_step.h5"],
    "probeloss": ["probeloss", "sample_data/raster_grating.h5"],
    "decode": ["decode", "sample_data/bits_30khz.h5", "--bit-rate", "30000"],
}
seen = {}
for name, argv in commands.items():
    status = None
    sys.argv = ["afmtool", *argv, "--stream", "--quiet"]
    try:
        main()
    except SystemExit as exit:
        status = exit.code
    seen[name] = {"status": status, "imported": [m for m in ("scipy.signal",) if m in sys.modules]}
print("PROBE=" + json.dumps(seen), file=sys.stderr)
"""


@pytest.mark.parametrize("command", ["reep", "probeloss", "decode"])
def test_streaming_commands_do_not_import_scipy_signal(command, _stream_probe):
    # README "Development": at 0.6-1 s, scipy.signal's import cost more than analysing 1e7 samples
    assert _stream_probe[command]["status"] in (0, None)
    assert _stream_probe[command]["imported"] == [], f"afmtool {command} --stream imported scipy.signal"


@pytest.fixture(scope="module")
def _stream_probe() -> dict:
    """The three streaming commands on the bundled captures, in one interpreter (about 2 s of CPU)."""
    return _probe(_STREAM_PROBE)
