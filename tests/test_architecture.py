"""Architecture rules checked on the source tree with ``ast`` (issue 15).

No command module has its own chunk loop: reading a capture in chunks
(``iter_chunks``) and reading ahead (``prefetch``) happen only in
:mod:`afmtool.pipeline` and in :mod:`afmtool.io`; every analysis streams
through :func:`afmtool.pipeline.run_stream`.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "afmtool"
#: The stream machinery: used by name only here.
_STREAM_NAMES = frozenset({"iter_chunks", "prefetch"})
_STREAM_MODULES = frozenset({"afmtool.io.chunks", "afmtool.io.prefetch"})  # their other names are free


def _allowed(relative: Path) -> bool:
    return relative == Path("pipeline.py") or relative.parts[0] == "io"


def _absolute(module: str | None, level: int, relative: Path) -> str:
    """The absolute module name of ``from <level dots><module> import ...`` in ``relative``."""
    if not level:
        return module or ""
    package = ["afmtool", *relative.parent.parts]
    base = package[: len(package) - (level - 1)]
    return ".".join([*base, *([module] if module else [])])


def stream_uses(source: str, relative: Path) -> list[str]:
    """Every import or use of ``iter_chunks``/``prefetch`` in ``source`` (``line: what``)."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom):
            module = _absolute(node.module, node.level, relative)
            names = {alias.name for alias in node.names} & (_STREAM_NAMES | {"*"})
            if module in _STREAM_MODULES and names:
                found.append(f"{node.lineno}: from {module} import {', '.join(sorted(names))}")
        elif isinstance(node, ast.Attribute) and node.attr in _STREAM_NAMES:
            found.append(f"{node.lineno}: .{node.attr}")
        elif isinstance(node, ast.Name) and node.id in _STREAM_NAMES:
            found.append(f"{node.lineno}: {node.id}")
    return found


def test_no_chunk_loop_outside_the_pipeline_and_io() -> None:
    offenders = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        relative = path.relative_to(PACKAGE)
        if _allowed(relative):
            continue
        uses = stream_uses(path.read_text(encoding="utf-8"), relative)
        if uses:
            offenders[str(relative)] = uses
    assert not offenders, (
        "modules with their own chunk loop (stream through afmtool.pipeline.run_stream instead): "
        + "; ".join(f"{name} ({', '.join(uses)})" for name, uses in offenders.items())
    )


@pytest.mark.parametrize(
    "source, relative",
    [
        ("from afmtool.io.chunks import iter_chunks\n", "analyses/x.py"),
        ("from afmtool.io.prefetch import prefetch as ahead\n", "analyses/x.py"),
        ("from ..io.chunks import iter_chunks, require_channels\n", "analyses/x.py"),
        ("from ...io.prefetch import *\n", "analyses/sub/x.py"),
        ("import afmtool.io.prefetch\nafmtool.io.prefetch.prefetch(it)\n", "cli/x.py"),
        ("from afmtool.io import chunks\nchunks.iter_chunks(r, ['a'])\n", "x.py"),
        ("from afmtool import io\nfor c in io.chunks.iter_chunks(r, ['a']):\n    pass\n", "x.py"),
    ],
)
def test_the_rule_finds_a_chunk_loop(source: str, relative: str) -> None:
    assert stream_uses(source, Path(relative))


def test_the_rule_passes_the_pipeline_and_plain_code() -> None:
    assert _allowed(Path("pipeline.py")) and _allowed(Path("io/chunks.py"))
    assert not _allowed(Path("analyses/reep.py"))
    assert stream_uses("from afmtool.pipeline import run_stream\nrun_stream(r, [s])\n", Path("analyses/x.py")) == []
    assert stream_uses("from afmtool.io.chunks import require_channels\n", Path("analyses/x.py")) == []


# --------------------------------------------------------------------------- repeated blocks

#: Lines shared by two places before they count as a repeated block (issue 15).
REPEAT_LINES = 6


def _code_lines(source: str) -> list[tuple[int, str]]:
    """``(line number, stripped line)`` of the code: no blank, comment, import, docstring or lone-bracket lines."""
    tree = ast.parse(source)
    skipped: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            skipped.update(range(node.lineno, node.end_lineno + 1))
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
                skipped.update(range(first.lineno, first.end_lineno + 1))
    lines = []
    for number, line in enumerate(source.splitlines(), start=1):
        text = line.strip()
        if number in skipped or not text or text.startswith("#") or text in {")", "]", "}", "),", "],", "})", "):"}:
            continue
        lines.append((number, " ".join(text.split())))
    return lines


def repeated_blocks(files: dict[str, str], size: int = REPEAT_LINES) -> list[str]:
    """Every run of ``size`` code lines that stands in two places (``a.py:10 ~ b.py:40``)."""
    first_seen: dict[tuple[str, ...], str] = {}
    repeats = []
    for name, source in sorted(files.items()):
        lines = _code_lines(source)
        for k in range(len(lines) - size + 1):
            window = tuple(text for _, text in lines[k : k + size])
            where = f"{name}:{lines[k][0]}"
            if window in first_seen and not first_seen[window].startswith(f"{name}:"):
                repeats.append(f"{first_seen[window]} ~ {where}: {window[0][:60]}")
            first_seen.setdefault(window, where)
    return repeats


def test_no_option_block_or_command_preamble_is_repeated():
    """The CLI's option blocks and the commands' runners share no run of six code lines (issue 15)."""
    files = {
        path.relative_to(PACKAGE).as_posix(): path.read_text(encoding="utf-8")
        for folder in ("cli", "analyses")
        for path in sorted((PACKAGE / folder).glob("*.py"))
    }
    assert repeated_blocks(files) == []


def test_the_repeat_check_can_fail():
    block = "\n".join(f"    value_{k} = options[{k}] + offset" for k in range(6))
    one = f"def a(options, offset):\n    '''doc'''\n{block}\n    return value_0\n"
    assert repeated_blocks({"a.py": one, "b.py": one.replace("def a", "def b")}) != []
    assert repeated_blocks({"a.py": one, "b.py": one.replace("value_3", "other")}) == []


# --------------------------------------------------------------------------- floors

#: The floors of the package, lowest first (issue 29, item 4; docs/architecture.md, "Floors").
#: A module may import from its own floor and from any floor below it, never from one above.
FLOORS: tuple[tuple[str, ...], ...] = (
    ("errors", "jit"),  # the ground: exceptions and the numba options; they import nothing of afmtool
    ("records",),  # the typed result records of each command, with their headlines (standard library only)
    ("config",),  # parameters, defaults, sample counts
    ("runtime",),  # atomic outputs, the input registry, faults, deferred signals
    ("models",),  # cantilever, forces, thermal sensor, discretisation
    ("estimators",),  # RLS, observers, Kalman filters, EKF, fits, detectors
    ("io",),  # readers and writers
    ("pipeline", "sim"),  # the stream machinery; the simulator's scenarios
    ("report",),  # JSON, headlines, figures, images, HTML
    ("analyses",),  # one module per command
    ("api",),  # the Python API
    ("cli",),  # typer wiring
)
#: The package root (``afmtool/__init__.py``, ``__main__.py``) is the façade above every floor; what
#: it defines (``__version__``) counts as the ground when a floor imports it.
_ROOT = "afmtool"
#: Arrows allowed up a floor, each with its reason.  Keep this short; every entry is a debt.
FLOOR_EXCEPTIONS: dict[tuple[str, str], str] = {
    ("config/defaults.py", "afmtool.sim"): (
        "the generator of defaults.toml and the parameter schemas lists the simulator's scenarios' "
        "parameters beside the commands'; it runs when the file is regenerated, not in a command"
    ),
}


def _floor_of(module: str) -> int | None:
    """The floor of ``afmtool.<package>...``; None for a name outside afmtool."""
    parts = module.split(".")
    if parts[0] != _ROOT:
        return None
    if len(parts) == 1 or not ((PACKAGE / parts[1]).is_dir() or (PACKAGE / f"{parts[1]}.py").is_file()):
        return 0  # the root's own names (__version__)
    for level, names in enumerate(FLOORS):
        if parts[1] in names:
            return level
    raise AssertionError(f"{module}: afmtool.{parts[1]} is on no floor; add it to FLOORS (and docs/architecture.md)")


def _type_checking_lines(tree: ast.Module) -> set[int]:
    """Lines under ``if TYPE_CHECKING:``: annotations only, nothing is imported at run time."""
    lines: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and getattr(node.test, "id", getattr(node.test, "attr", None)) == "TYPE_CHECKING":
            for child in node.body:
                lines.update(range(child.lineno, child.end_lineno + 1))
    return lines


def upward_imports(source: str, relative: Path) -> list[tuple[str, str]]:
    """Every import in ``source`` (module ``relative``) that runs up a floor: ``(line: statement, target)``.

    Imports inside functions count (a lazy import is still an arrow); those under
    ``if TYPE_CHECKING:`` do not (they load nothing).
    """
    if relative.parts[0] in ("__init__.py", "__main__.py"):
        return []
    own = _floor_of(".".join([_ROOT, relative.parts[0].removesuffix(".py")]))
    tree = ast.parse(source)
    annotations = _type_checking_lines(tree)
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            module = _absolute(node.module, node.level, relative)
            targets = [f"{module}.{alias.name}" if module == _ROOT else module for alias in node.names]
        elif isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        else:
            continue
        if node.lineno in annotations:
            continue
        for target in targets:
            floor = _floor_of(target)
            if floor is not None and floor > own:
                found.append((f"{node.lineno}: {ast.unparse(node)}", ".".join(target.split(".")[:2])))
    return found


def test_no_import_runs_up_a_floor() -> None:
    offenders = []
    excused = set()
    for path in sorted(PACKAGE.rglob("*.py")):
        relative = path.relative_to(PACKAGE)
        for where, target in upward_imports(path.read_text(encoding="utf-8"), relative):
            if (relative.as_posix(), target) in FLOOR_EXCEPTIONS:
                excused.add((relative.as_posix(), target))
            else:
                offenders.append(f"{relative}:{where}")
    assert not offenders, "imports that run up a floor (docs/architecture.md, 'Floors'):\n" + "\n".join(offenders)
    assert excused == set(FLOOR_EXCEPTIONS), f"exceptions no longer needed: {set(FLOOR_EXCEPTIONS) - excused}"


def test_every_package_is_on_a_floor_and_the_docs_draw_them() -> None:
    packages = {p.name for p in PACKAGE.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    packages |= {p.stem for p in PACKAGE.glob("*.py") if p.stem not in ("__init__", "__main__")}
    placed = {name for floor in FLOORS for name in floor}
    assert packages == placed
    architecture = (PACKAGE.parent / "docs" / "architecture.md").read_text(encoding="utf-8")
    for floor in FLOORS:
        assert " · ".join(floor) in architecture, f"docs/architecture.md does not draw the floor {floor}"


@pytest.mark.parametrize(
    "source, relative",
    [
        ("from afmtool.report.images import write_png\n", "io/x.py"),  # io/ -> report/
        ("from afmtool.estimators.rls import run\n", "models/x.py"),  # models/ -> estimators/
        ("def f():\n    from afmtool.analyses.reep import run_reep\n", "estimators/x.py"),  # lazily, still up
        ("from ..report import headline\n", "io/x.py"),  # relative
        ("import afmtool.cli.main\n", "report/x.py"),
        ("from afmtool import sim\n", "config/x.py"),
        ("from afmtool.io.capture import Chunk\n", "runtime/x.py"),
    ],
)
def test_the_floor_rule_finds_an_upward_import(source: str, relative: str) -> None:
    assert upward_imports(source, Path(relative))


def test_the_floor_rule_passes_downward_sideways_and_annotation_imports() -> None:
    assert upward_imports("from afmtool.runtime.atomic import write_text_atomic\n", Path("io/x.py")) == []
    assert upward_imports("from afmtool.estimators.rls import run\n", Path("estimators/x.py")) == []
    assert upward_imports("from afmtool.sim import simulate\n", Path("pipeline.py")) == []
    assert upward_imports("from afmtool import __version__\n", Path("report/x.py")) == []
    assert upward_imports("import numpy as np\nfrom typing import TYPE_CHECKING\n", Path("models/x.py")) == []
    typed = "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from afmtool.io.capture import Chunk\n"
    assert upward_imports(typed, Path("estimators/x.py")) == []
