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
import threading
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import afmtool

__all__ = ["sha256_file", "input_record", "PendingInputRecord", "build_report", "to_jsonable", "dumps"]

_HASH_BLOCK = 1 << 20


def sha256_file(path: Path) -> str:
    """Hex sha256 of a file, or of every file in a directory (ROS2 bags), streamed."""
    digest = hashlib.sha256()
    path = Path(path)
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    # One reused buffer that stays in cache: a fresh bytes object per read
    # costs a page fault per 4 KiB, a fifth of the hashing time on a large capture.
    buffer = bytearray(_HASH_BLOCK)
    view = memoryview(buffer)
    for file in files:
        with open(file, "rb", buffering=0) as handle:
            while n := handle.readinto(buffer):
                digest.update(view[:n])
    return digest.hexdigest()


def input_record(path: Path | str, role: str = "capture") -> dict:
    """``{"path", "role", "sha256"}``; stdin has no hash."""
    if str(path) == "-":
        return {"path": "-", "role": role, "sha256": None}
    from afmtool.report.input_guard import register_input

    register_input(path)  # no output of this run may overwrite what it hashed
    return {"path": str(path), "role": role, "sha256": sha256_file(Path(path))}


class PendingInputRecord:
    """:func:`input_record` computed in a daemon thread, started at construction.

    Hashing a 1.6 GB capture takes about 2 s of CPU; hashlib releases the GIL
    on large blocks, so started before the analysis imports its modules the
    hash overlaps the imports and the pass instead of following them.  An
    interrupted run never waits for it (the thread is a daemon).
    """

    def __init__(self, path: Path | str, role: str = "capture") -> None:
        self._value: dict | None = None
        self._error: BaseException | None = None

        def run() -> None:
            try:
                self._value = input_record(path, role)
            except BaseException as exc:  # noqa: BLE001 - re-raised by result() in the caller's thread
                self._error = exc

        self._thread = threading.Thread(target=run, name="afmtool-sha256", daemon=True)
        self._thread.start()

    def result(self) -> dict:
        """The record; re-raises whatever hashing raised."""
        self._thread.join()
        if self._error is not None:
            raise self._error
        return self._value


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
    """Assemble a report dict in the order of ``schemas/report.schema.json``.

    ``headline`` is :func:`afmtool.report.headline.headline` of the results:
    the few numbers with units and uncertainties that the HTML page shows first.
    """
    from afmtool.report.headline import headline

    jsonable_results = to_jsonable(results)
    return {
        "afmtool_version": afmtool.__version__,
        "command": command,
        "headline": headline(command, jsonable_results),
        "inputs": to_jsonable(list(inputs)),
        "parameters": to_jsonable(parameters),
        "results": jsonable_results,
        "outputs": sorted(outputs),
        "warnings": list(warnings),
    }


def dumps(report: Mapping) -> str:
    return json.dumps(report, indent=2, allow_nan=False) + "\n"
