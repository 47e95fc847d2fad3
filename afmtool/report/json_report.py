"""The ``report.json`` every analysis writes (``schemas/report.schema.json``).

A report records what was run (command, afmtool version), on what (inputs
with their hash: sha256 of a file, or the XXH3-128 of the samples a
streaming command read, :mod:`afmtool.io.provenance`), how (the effective parameters), what came out (results
and the list of output files) and what to be careful about (warnings).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import afmtool

if TYPE_CHECKING:
    from afmtool.records import Record

__all__ = ["sha256_file", "file_hash", "input_record", "SampleInputRecord", "build_report", "to_jsonable", "dumps"]

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


def file_hash(path: Path | str) -> dict:
    """``{"algorithm": "sha256", "value", "over": "file"}``: the hash of a (small) input file's bytes."""
    return {"algorithm": "sha256", "value": sha256_file(Path(path)), "over": "file"}


def input_record(path: Path | str, role: str = "capture") -> dict:
    """``{"path", "role", "hash"}`` with the sha256 of the file's bytes; stdin has no hash."""
    if str(path) == "-":
        return {"path": "-", "role": role, "hash": None}
    from afmtool.runtime.input_guard import register_input

    register_input(path)  # no output of this run may overwrite what it hashed
    return {"path": str(path), "role": role, "hash": file_hash(path)}


class SampleInputRecord:
    """The input record of a capture that a streaming command hashes in its own read pass.

    Parameters
    ----------
    path : path or "-"
        The capture as given (stdin too: its samples are hashed like a file's).
    reader : HashedReader or None
        The view the analysis reads through; None records no hash (``--no-hash``).
    role : str
        The input's role in the report.
    """

    def __init__(self, path: Path | str, reader=None, role: str = "capture") -> None:
        self._path, self._reader, self._role = str(path), reader, role
        if self._path != "-":
            from afmtool.runtime.input_guard import register_input

            register_input(path)  # no output of this run may overwrite what it read

    def result(self) -> dict:
        """``{"path", "role", "hash"}``, the hash being :meth:`afmtool.io.provenance.HashedReader.record`."""
        record = self._reader.record() if self._reader is not None else None
        return {"path": self._path, "role": self._role, "hash": record}


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
    results: Record | Mapping,
    outputs: Sequence[str],
    warnings: Sequence[str] = (),
) -> dict:
    """Assemble a report dict in the order of ``schemas/report.schema.json``.

    ``headline`` is :func:`afmtool.report.headline.headline` of the results:
    the few numbers with units and uncertainties that the terminal, the HTML
    page and batch's summary show.  ``warning_shares`` gives each warning's
    share of the samples (:class:`afmtool.errors.SampleShareWarning`), or None.
    """
    from afmtool.records import Record
    from afmtool.report.headline import headline

    jsonable_results = results.to_json() if isinstance(results, Record) else to_jsonable(results)
    return {
        "afmtool_version": afmtool.__version__,
        "command": command,
        "headline": headline(command, results if isinstance(results, Record) else jsonable_results),
        "inputs": to_jsonable(list(inputs)),
        "parameters": to_jsonable(parameters),
        "results": jsonable_results,
        "outputs": sorted(outputs),
        "warnings": [str(w) for w in warnings],
        "warning_shares": [getattr(w, "share", None) for w in warnings],
    }


def dumps(report: Mapping) -> str:
    return json.dumps(report, indent=2, allow_nan=False) + "\n"
