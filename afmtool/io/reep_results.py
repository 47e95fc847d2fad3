"""Reading a finished ``afmtool reep`` run back: ``reep.h5``, its ``report.json`` and ``free_air.json``.

Series are returned as open h5py datasets (sliced on demand), so a REEP
run of any length can be followed in flat memory.  Nothing is estimated
here.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import h5py

from afmtool.errors import InputError
from afmtool.models.free_air import FreeAirModel, load_free_air_model

__all__ = ["ReepResults", "open_reep_results"]

_SERIES = ("t", "b1", "b0")
_OPTIONAL_SERIES = ("z", "f0_hz", "q", "amplitude")


@dataclass
class ReepResults:
    """An open REEP output.  Close it (or use it as a context manager) when done.

    Attributes
    ----------
    path : Path
        The ``reep.h5`` file.
    series : Mapping[str, h5py.Dataset]
        ``t`` (s), ``b1``, ``b0``, and where present ``z``, ``f0_hz``, ``q``,
        ``amplitude``: the decimated per-sample series.
    report : Mapping
        ``results`` of its ``report.json`` (empty if there is none beside it).
    free_air_model : FreeAirModel or None
        ``free_air.json`` beside it, if any.
    z_units : str
    """

    path: Path
    series: Mapping[str, h5py.Dataset]
    report: Mapping
    free_air_model: FreeAirModel | None
    z_units: str = ""
    _file: h5py.File | None = field(default=None, repr=False)

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> ReepResults:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def open_reep_results(path: Path | str) -> ReepResults:
    """Open a REEP output folder or its ``reep.h5``.

    Raises
    ------
    InputError
        If the file is missing, not HDF5, or lacks ``t``, ``b1``, ``b0``.
    """
    path = Path(path)
    h5_path = path / "reep.h5" if path.is_dir() else path
    folder = h5_path.parent
    try:
        handle = h5py.File(h5_path, "r")
    except FileNotFoundError:
        raise InputError(f"--reep {path}: no reep.h5 there") from None
    except OSError as exc:
        raise InputError(f"--reep {h5_path}: not an HDF5 file ({str(exc).splitlines()[0]})") from None
    try:
        missing = [name for name in _SERIES if not isinstance(handle.get(name), h5py.Dataset)]
        if missing:
            raise InputError(f"--reep {h5_path}: not a reep output (no {', '.join(missing)})")
        series = {name: handle[name] for name in _SERIES}
        series.update({name: handle[name] for name in _OPTIONAL_SERIES if isinstance(handle.get(name), h5py.Dataset)})
        lengths = {len(ds) for ds in series.values()}
        if len(lengths) != 1 or any(ds.ndim != 1 for ds in series.values()):
            raise InputError(f"--reep {h5_path}: its series are not 1-D of one length")
        z_units = str(series["z"].attrs.get("units", "")) if "z" in series else ""
        report = {}
        if (folder / "report.json").is_file():
            try:
                report = json.loads((folder / "report.json").read_text()).get("results", {})
            except (json.JSONDecodeError, UnicodeDecodeError) as exc:
                raise InputError(f"--reep {folder / 'report.json'}: not JSON ({exc})") from None
        free_air = load_free_air_model(folder / "free_air.json") if (folder / "free_air.json").is_file() else None
    except BaseException:
        handle.close()
        raise
    return ReepResults(h5_path, series, report, free_air, z_units, handle)
