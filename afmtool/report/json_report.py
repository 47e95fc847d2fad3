"""The ``report.json`` every analysis writes (``schemas/report.schema.json``).

A report records what was run (command, afmtool version), on what (inputs
with their sha256), how (the effective parameters), what came out (results
and the list of output files) and what to be careful about (warnings).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import afmtool

__all__ = ["sha256_file", "input_record", "build_report", "to_jsonable", "dumps"]

_HASH_BLOCK = 1 << 22


def sha256_file(path: Path) -> str:
    """Hex sha256 of a file, or of every file in a directory (ROS2 bags), streamed."""
    digest = hashlib.sha256()
    path = Path(path)
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    for file in files:
        with open(file, "rb") as handle:
            while block := handle.read(_HASH_BLOCK):
                digest.update(block)
    return digest.hexdigest()


def input_record(path: Path | str, role: str = "capture") -> dict:
    """``{"path", "role", "sha256"}``; stdin has no hash."""
    if str(path) == "-":
        return {"path": "-", "role": role, "sha256": None}
    return {"path": str(path), "role": role, "sha256": sha256_file(Path(path))}


def to_jsonable(value: Any) -> Any:
    """Convert numpy scalars/arrays, dataclasses and paths; non-finite floats become None."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return to_jsonable(dataclasses.asdict(value))
    if isinstance(value, Mapping):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    if hasattr(value, "tolist") and callable(value.tolist):  # numpy scalar or array
        return to_jsonable(value.tolist())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def build_report(
    command: str,
    inputs: Sequence[Mapping],
    parameters: Mapping,
    results: Mapping,
    outputs: Sequence[str],
    warnings: Sequence[str] = (),
) -> dict:
    """Assemble a report dict in the order of ``schemas/report.schema.json``."""
    return {
        "afmtool_version": afmtool.__version__,
        "command": command,
        "inputs": to_jsonable(list(inputs)),
        "parameters": to_jsonable(parameters),
        "results": to_jsonable(results),
        "outputs": sorted(outputs),
        "warnings": list(warnings),
    }


def dumps(report: Mapping) -> str:
    return json.dumps(report, indent=2, allow_nan=False) + "\n"
