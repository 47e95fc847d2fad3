"""Reading a finished ``afmtool reep`` run back: ``reep.h5``, its ``report.json`` and ``free_air.json``.

Series are returned as open h5py datasets (sliced on demand), so a REEP
run of any length can be followed in flat memory.  Nothing is estimated
here.  The same reader, opened with ``mode="r+"``, lets ``reep`` add what it
derives from its own finished series (``/interaction``, the binned tables
and images) to the staged reep.h5.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import h5py

from afmtool.errors import InputError
from afmtool.io.result_files import FLAG_COLUMN, ResultFile, open_result_file
from afmtool.models.free_air import FreeAirModel, load_free_air_model
from afmtool.records.reep import ReepResults as ReepRecord

__all__ = ["ReepResults", "open_reep_results"]

_SERIES = ("t", "b1", "b0")
_OPTIONAL_SERIES = ("z", "f0_hz", "q", "f0_std_hz", "q_std", "sigma2", "amplitude", "phase_deg", FLAG_COLUMN)


@dataclass
class ReepResults:
    """An open REEP output.  Close it (or use it as a context manager) when done.

    Attributes
    ----------
    path : Path
        The ``reep.h5`` file.
    series : Mapping[str, h5py.Dataset]
        ``t`` (s), ``b1``, ``b0``, and where present ``z``, ``f0_hz``, ``q``,
        ``amplitude``, ``phase_deg``, ``flag`` (0 = valid): the decimated
        per-sample series.
    report : Mapping
        ``results`` of its ``report.json`` as JSON (empty if there is none beside it); read
        as reep's record by :attr:`results`.
    free_air_model : FreeAirModel or None
        ``free_air.json`` beside it, if any.
    z_units : str
        Units of ``z``; where the series has none, those of the force-curve
        tables' ``z``.
    file : ResultFile or None
        The open file itself: blocks, thinned rows, ``/interaction``, and
        (opened with ``mode="r+"``) adding arrays.
    inputs : tuple of Mapping
        ``inputs`` of its ``report.json``: the capture REEP read first.
    """

    path: Path
    series: Mapping[str, h5py.Dataset]
    report: Mapping
    free_air_model: FreeAirModel | None
    z_units: str = ""
    file: ResultFile | None = field(default=None, repr=False)
    inputs: tuple[Mapping, ...] = ()

    @functools.cached_property
    def results(self) -> ReepRecord | None:
        """``results`` of its ``report.json`` as reep's record (:class:`afmtool.records.reep.ReepResults`).

        None when there is no report.json beside it.

        Raises
        ------
        InputError
            A report.json that is not a reep run's (of another command, or another afmtool version).
        """
        if not self.report:
            return None
        try:
            return ReepRecord.from_json(self.report)
        except InputError as exc:
            raise InputError(f"{self.path.parent / 'report.json'}: not the report of a reep run ({exc})") from None

    def close(self) -> None:
        if self.file is not None:
            self.file.close()
            self.file = None

    def __enter__(self) -> ReepResults:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def open_reep_results(path: Path | str, *, mode: str = "r", where: str = "--reep") -> ReepResults:
    """Open a REEP output folder or its ``reep.h5``.

    Parameters
    ----------
    path : Path or str
        The folder or the file.
    mode : {"r", "r+"}
        ``"r+"`` to add arrays to it (a staged output of this run).
    where : str
        What the path was given as, to begin error messages with.

    Raises
    ------
    InputError
        If the file is missing, not HDF5, or lacks ``t``, ``b1``, ``b0``.
    """
    path = Path(path)
    h5_path = path / "reep.h5" if path.is_dir() else path
    folder = h5_path.parent
    if not h5_path.exists():
        raise InputError(f"{where} {path}: no reep.h5 there")
    try:
        handle = open_result_file(h5_path, mode=mode, what="reep output")
    except InputError as exc:
        raise InputError(f"{where} {exc}") from None
    try:
        missing = [name for name in _SERIES if name not in handle.names()]
        if missing:
            raise InputError(f"{where} {h5_path}: not a reep output (no {', '.join(missing)})")
        series = {name: handle[name] for name in _SERIES + _OPTIONAL_SERIES if name in handle.names()}
        lengths = {len(ds) for ds in series.values()}
        if len(lengths) != 1 or any(ds.ndim != 1 for ds in series.values()):
            raise InputError(f"{where} {h5_path}: its series are not 1-D of one length")
        report, inputs = _report(folder / "report.json", where)
        free_air = load_free_air_model(folder / "free_air.json") if (folder / "free_air.json").is_file() else None
    except BaseException:
        handle.close()
        raise
    return ReepResults(h5_path, series, report, free_air, _z_units(handle), handle, inputs)


def _report(path: Path, where: str) -> tuple[Mapping, tuple[Mapping, ...]]:
    """``results`` and ``inputs`` of the report.json at ``path`` (empty when there is none)."""
    if not path.is_file():
        return {}, ()
    try:
        report = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{where} {path}: not JSON ({exc})") from None
    if not isinstance(report, Mapping):
        raise InputError(f"{where} {path}: not an afmtool report (not a JSON object)")
    results, inputs = report.get("results", {}), report.get("inputs", [])
    if not isinstance(results, Mapping) or not isinstance(inputs, list):
        raise InputError(f"{where} {path}: not an afmtool report (results or inputs of the wrong type)")
    return results, tuple(item for item in inputs if isinstance(item, Mapping))


def _z_units(handle: ResultFile) -> str:
    """Units of reep.h5's z; the force-curve tables carry them where the series does not."""
    units = handle.units("z") if "z" in handle.names() else ""
    for leg in ("approach", "retract"):
        if not units and "z" in handle.names(f"force_curve/{leg}"):
            units = handle.units(f"force_curve/{leg}/z")
    return units
