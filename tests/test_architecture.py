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
