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
