"""Reading afmtool's own HDF5 outputs back (``probeloss.h5``, ``decode.h5``, ``bank.h5``, ...).

:class:`ResultFile` is the one place outside the writers where an afmtool
result file is opened: it checks the columns a caller needs, reads them in
blocks, thinned, or by time window, so memory stays flat however long the
run, and, opened for appending, adds whole arrays after a run (the
force-curve tables and images REEP bins from its own series).  The readers
of each output (:func:`open_probeloss_results`, :func:`open_decode_results`,
:func:`afmtool.io.bank_results.read_bank_rms`,
:func:`afmtool.io.reep_results.open_reep_results`,
:func:`afmtool.io.gamma_results.read_gamma_ir_ts`) build on it.  Nothing is
estimated here.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path

import h5py
import numpy as np

from afmtool.errors import InputError

__all__ = [
    "FLAG_COLUMN",
    "MAX_PLOT_POINTS",
    "ResultFile",
    "open_decode_results",
    "open_probeloss_results",
    "open_result_file",
    "read_all_datasets",
]

#: Most rows drawn per line of a figure.
MAX_PLOT_POINTS = 20000
#: The per-row validity column a result may carry: bit flags, 0 = valid.
FLAG_COLUMN = "flag"
_BLOCK_ROWS = 1 << 20


class ResultFile:
    """An open afmtool result file; use as a context manager or call :meth:`close`.

    ``result[name]`` is the h5py dataset at ``name`` (sliced on demand);
    ``name in result`` says whether it exists.
    """

    def __init__(self, path: Path, handle: h5py.File) -> None:
        self.path = path
        self._file: h5py.File | None = handle

    @property
    def _h5(self) -> h5py.File:
        if self._file is None:
            raise ValueError(f"{self.path} is closed")
        return self._file

    def __contains__(self, name: str) -> bool:
        return name in self._h5

    def __getitem__(self, name: str) -> h5py.Dataset:
        item = self._h5[name]
        if not isinstance(item, h5py.Dataset):
            raise KeyError(f"{self.path}: {name} is a group, not a dataset")
        return item

    @property
    def attrs(self) -> Mapping:
        """The file's root attributes (``afmtool_command``, ...)."""
        return self._h5.attrs

    def names(self, group: str = "/") -> tuple[str, ...]:
        """Names of the datasets directly in ``group`` (empty if it does not exist)."""
        item = self._h5.get(group)
        if not isinstance(item, h5py.Group):
            return ()
        return tuple(name for name in item if isinstance(item[name], h5py.Dataset))

    def units(self, name: str) -> str:
        """The ``units`` attribute of dataset ``name`` ("" if none)."""
        return str(self[name].attrs.get("units", ""))

    def blocks(self, name: str, n: int | None = None, block_rows: int = _BLOCK_ROWS) -> Iterator[tuple[int, np.ndarray]]:
        """``(first row, values)`` of column ``name`` in blocks of ``block_rows``, the first ``n`` rows."""
        dataset = self[name]
        n = len(dataset) if n is None else n
        for start in range(0, n, block_rows):
            yield start, dataset[start : min(n, start + block_rows)]

    def trusted(self, name: str, rows) -> np.ndarray:
        """Column ``name`` at ``rows`` (a slice or index array) as float64, NaN where :data:`FLAG_COLUMN` != 0."""
        values = np.asarray(self[name][rows], dtype=np.float64)
        if FLAG_COLUMN in self:
            values = np.where(np.asarray(self[FLAG_COLUMN][rows]) == 0, values, np.nan)
        return values

    def read_rows(
        self,
        names: Sequence[str],
        *,
        time: str = "t",
        t_range: tuple[float, float] | None = None,
        max_points: int = MAX_PLOT_POINTS,
    ) -> dict[str, np.ndarray]:
        """Columns ``time`` and ``names``, evenly thinned to at most ``max_points`` rows.

        Parameters
        ----------
        names : sequence of str
            Columns wanted; absent ones (or ones of another length) are left out.
        time : str
            The time column (s), ascending.
        t_range : (float, float), optional
            Only rows with ``t_range[0] <= t < t_range[1]`` (s).
        max_points : int
            Most rows returned; every k-th row beyond that.

        Returns
        -------
        dict
            ``{name: array}`` including ``time``, plus ``"_rows"``: the row
            numbers read (int64).
        """
        t_all = self[time]
        n = len(t_all)
        start, stop = 0, n
        if t_range is not None:
            # t is ascending: find the window by bisection on the dataset, never reading all of it
            start, stop = _bisect(t_all, float(t_range[0]), n), _bisect(t_all, float(t_range[1]), n)
        step = max(1, math.ceil((stop - start) / max_points))
        out = {time: t_all[start:stop:step]}
        for name in names:
            if name in self._h5 and name != time and isinstance(self._h5[name], h5py.Dataset) and len(self[name]) == n:
                out[name] = self[name][start:stop:step]
        out["_rows"] = np.arange(start, stop, step, dtype=np.int64)
        return out

    # ---- appending (a file opened with mode="r+")

    def put(self, name: str, values, units: str = "", attrs: Mapping | None = None) -> None:
        """Store a whole array at ``name`` (may contain '/'), with its ``units`` attribute."""
        ds = self._h5.create_dataset(name, data=np.asarray(values))
        ds.attrs["units"] = units
        for key, value in (attrs or {}).items():
            ds.attrs[key] = value
        self._h5.flush()  # while ``ds`` is alive, so a full disk raises here (see io.results.ResultWriter.put)

    def create_columns(self, group: str, units: Mapping[str, str], n_rows: int) -> dict[str, h5py.Dataset]:
        """Empty float32 columns ``group/<name>`` of ``n_rows``, each with its units, to be filled in blocks.

        float32, as the series they derive from (issue 33): 7 digits are far below their uncertainty.
        """
        parent = self._h5.create_group(group)
        columns = {}
        for name, unit in units.items():
            columns[name] = parent.create_dataset(name, shape=(n_rows,), dtype="f4")
            columns[name].attrs["units"] = unit
        return columns

    def close(self, *, failed: bool = False) -> None:
        """Close the file; one written to (``r+``) is flushed first, and left unclosed if a write failed
        (:func:`afmtool.runtime.faults.close_hdf5`)."""
        if self._file is None:
            return
        handle, self._file = self._file, None
        if handle.mode == "r":
            handle.close()
            return
        from afmtool.runtime.faults import close_hdf5

        close_hdf5(handle, failed=failed)

    def __enter__(self) -> ResultFile:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close(failed=exc_type is not None)


def _bisect(dataset, value: float, n: int) -> int:
    lo, hi = 0, n
    while lo < hi:
        mid = (lo + hi) // 2
        if float(dataset[mid]) < value:
            lo = mid + 1
        else:
            hi = mid
    return lo


def open_result_file(
    path: Path | str, *, required: Sequence[str] = (), what: str = "afmtool result", mode: str = "r"
) -> ResultFile:
    """Open an afmtool HDF5 output; ``mode="r+"`` to add arrays to it.

    Raises
    ------
    InputError
        If the file is missing, not HDF5, or lacks a ``required`` dataset.
    """
    if mode not in ("r", "r+"):
        raise ValueError(f"mode={mode!r} must be 'r' or 'r+'")
    path = Path(path)
    try:
        handle = h5py.File(path, mode)
    except FileNotFoundError:
        raise InputError(f"{path}: no such {what} file") from None
    except OSError as exc:
        raise InputError(f"{path}: not an HDF5 file ({str(exc).splitlines()[0]})") from None
    missing = [name for name in required if not isinstance(handle.get(name), h5py.Dataset)]
    if missing:
        handle.close()
        raise InputError(f"{path}: not a {what} (no {', '.join(missing)})")
    return ResultFile(path, handle)


def open_probeloss_results(path: Path | str) -> ResultFile:
    """``probeloss.h5`` of ``afmtool probeloss`` (or its folder): ``t``, ``index``, ``switch``, ``amplitude``, ..."""
    path = Path(path)
    return open_result_file(path / "probeloss.h5" if path.is_dir() else path, required=("t",), what="probeloss output")


def open_decode_results(path: Path | str) -> ResultFile:
    """``decode.h5`` of ``afmtool decode`` (or its folder): ``bit_times_s``, ``bits``, ``soft``, ``t_mean``, ..."""
    path = Path(path)
    return open_result_file(path / "decode.h5" if path.is_dir() else path, what="decode output")


def read_all_datasets(path: Path | str) -> list[tuple[str, np.ndarray, dict]]:
    """Every dataset of an afmtool result file, whole: ``(path inside the file, values, attrs)``, in file order.

    For converting a finished run to labelled arrays (:mod:`afmtool.report.labelled`); the
    values are read into memory.
    """
    found: list[tuple[str, np.ndarray, dict]] = []
    try:
        with h5py.File(path, "r") as f:
            def visit(name: str, obj) -> None:
                if isinstance(obj, h5py.Dataset):
                    attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in obj.attrs.items()}
                    found.append((name, obj[()], attrs))

            f.visititems(visit)
    except OSError as exc:
        raise InputError(f"{path}: not a readable afmtool result file ({exc})") from None
    return found
