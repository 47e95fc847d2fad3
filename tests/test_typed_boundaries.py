"""Typed data across module boundaries (issue 15 item 4).

- afmtool's own HDF5 outputs are opened only in ``afmtool/io/``: no module
  elsewhere imports h5py or calls ``h5py.File`` (an AST scan of the package).
- Each output reader round-trips what the command wrote.
"""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np

PACKAGE = Path(__file__).resolve().parents[1] / "afmtool"


def _h5py_uses(tree: ast.AST) -> list[tuple[int, str]]:
    """(line, what) of every h5py import and ``h5py.File`` / ``File`` from h5py in ``tree``."""
    uses = []
    file_aliases = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            uses += [(node.lineno, f"import {a.name}") for a in node.names if a.name.split(".")[0] == "h5py"]
        elif isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "h5py":
            uses.append((node.lineno, f"from {node.module} import ..."))
            file_aliases |= {a.asname or a.name for a in node.names if a.name == "File"}
        elif isinstance(node, ast.Attribute) and node.attr == "File" and isinstance(node.value, ast.Name) \
                and node.value.id == "h5py":
            uses.append((node.lineno, "h5py.File"))
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in file_aliases:
            uses.append((node.lineno, f"{node.func.id}(...)"))
    return uses


def test_the_scan_finds_what_it_looks_for():
    source = "import h5py\nfrom h5py import File as F\nh5py.File('x')\nF('y')\ndef f(x: h5py.File): ...\n"
    assert [what for _, what in sorted(_h5py_uses(ast.parse(source)))] == [
        "import h5py", "from h5py import ...", "h5py.File", "F(...)", "h5py.File"]
    assert _h5py_uses(ast.parse("import numpy\nsys.modules.get('h5py')\n")) == []


def test_no_h5py_outside_io():
    offenders = []
    for path in sorted(PACKAGE.rglob("*.py")):
        relative = path.relative_to(PACKAGE)
        if relative.parts[0] == "io":
            continue
        for line, what in _h5py_uses(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            offenders.append(f"afmtool/{relative}:{line}: {what}")
    assert not offenders, "h5py outside afmtool/io/ (open afmtool outputs through the io/ readers):\n" + "\n".join(offenders)
