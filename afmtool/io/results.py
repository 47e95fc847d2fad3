"""HDF5 result files (``reep.h5``, ``probeloss.h5``, ...), written as they stream.

Columns are appended chunk by chunk to resizable datasets, each with a
``units`` attribute, so a result of any length is written in flat memory.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Collection, Mapping
from pathlib import Path

import h5py
import numpy as np

__all__ = ["ResultWriter", "row_attrs"]

_CHUNK = 1 << 14


class ResultWriter:
    """Append-only writer of named 1-D series plus whole arrays and attributes."""

    def __init__(
        self, path: Path, units: Mapping[str, str], attrs: Mapping | None = None, *, write_behind: bool = False,
        float64: Collection[str] | None = None,
    ) -> None:
        """Open ``path`` for writing.

        With ``float64`` (names), every other float64 series is stored as
        float32 (issue 33: f0′ at 70 kHz resolves 0.008 Hz in float32, far
        below any estimator's noise), while the named ones (time, REEP's b1 and
        b0, whose poles sit 1e-4 from the unit circle) keep float64.  The
        caller computes in float64 either way; HDF5 converts as it writes.

        With ``write_behind``, :meth:`append` hands its blocks to a writer
        thread and returns at once, so the file is written while the caller
        computes the next chunk (HDF5 releases the GIL while it writes).
        The caller must then not modify a block after appending it.
        """
        # No raw-data chunk cache: with it, HDF5 keeps growing while series are
        # appended (about 15 % of what is written); without it memory is flat
        # and appends are no slower.
        self._file = h5py.File(path, "w", track_order=True, rdcc_nbytes=0)
        self._units = dict(units)
        self._float64 = None if float64 is None else frozenset(float64)
        self._series: dict[str, h5py.Dataset] = {}
        self._pending: dict[str, np.ndarray] = {}  # per series, less than one chunk not yet written
        self._behind = None
        try:
            for key, value in (attrs or {}).items():
                self._file.attrs[key] = value
        except BaseException:
            self.close(failed=True)
            raise
        self._behind = _WriteBehind(self._append_now) if write_behind else None

    def append(self, columns: Mapping[str, np.ndarray]) -> None:
        """Append equal-length blocks to the series named in ``columns``."""
        if self._behind is not None:
            self._behind.submit(columns)
        else:
            self._append_now(columns)

    def _append_now(self, columns: Mapping[str, np.ndarray]) -> None:
        for name, values in columns.items():
            values = np.asarray(values)
            ds = self._series.get(name)
            if ds is None:
                ds = self._create(name, values)
                ds.attrs["units"] = self._units.get(name, "")
                self._series[name] = ds
            self._extend(name, ds, values)

    def _create(self, name: str, values: np.ndarray) -> h5py.Dataset:
        """A resizable dataset for the series ``name``, from its first block."""
        return self._file.create_dataset(name, shape=(0,), maxshape=(None,), dtype=self._stored_dtype(name, values),
                                         chunks=(_CHUNK,))

    def _stored_dtype(self, name: str, values: np.ndarray) -> np.dtype:
        """float32 for a float64 series not kept in float64 (``float64`` given), else the values' own."""
        if self._float64 is not None and values.dtype == np.float64 and name not in self._float64:
            return np.dtype(np.float32)
        return values.dtype

    def _extend(self, name: str, ds: h5py.Dataset, values: np.ndarray) -> None:
        """Append along the last axis in whole HDF5 chunks; the rest (< 1 chunk) waits for the next block.

        With no chunk cache, writing a part chunk and later the rest of it
        makes HDF5 read the chunk back and write it again; that cost as much
        as the REEP kernel.  Whole-chunk writes never touch a chunk twice.
        """
        pending = self._pending.get(name)
        if pending is not None and pending.shape[-1]:
            values = np.concatenate([pending, values.astype(ds.dtype, copy=False)], axis=-1)
        step = ds.chunks[-1]
        whole = values.shape[-1] // step * step
        if whole:
            _write_at_end(ds, values[..., :whole])
        self._pending[name] = values[..., whole:].copy()

    def set_attrs(self, attrs: Mapping) -> None:
        """Set attributes of the file's root (e.g. the series' row rate, once the run knows it)."""
        if self._behind is not None:
            self._behind.drain()
        for key, value in attrs.items():
            self._file.attrs[key] = value

    def put(self, name: str, values, units: str = "", attrs: Mapping | None = None) -> None:
        """Store a whole array (an image, a table column) at ``name`` (may contain '/')."""
        if self._behind is not None:
            self._behind.drain()
        ds = self._file.create_dataset(name, data=np.asarray(values))
        ds.attrs["units"] = units
        for key, value in (attrs or {}).items():
            ds.attrs[key] = value
        # written to disk while ``ds`` is alive: h5py writes a small dataset's data when it drops the
        # object, where a full disk's error is only printed, and the next flush then crashed libhdf5
        self._file.flush()

    def close(self, *, failed: bool = False) -> None:
        """Write what is still pending and close the file.

        ``failed``: the run failed while writing (the file is thrown away);
        it is left unclosed, out of reach of every finaliser
        (:func:`afmtool.runtime.faults.close_hdf5`).
        """
        from afmtool.runtime.faults import close_hdf5

        if self._file is None:
            return
        try:
            if self._behind is not None:
                self._behind.stop()
            if not failed:
                for name, rest in self._pending.items():
                    if rest.shape[-1]:
                        _write_at_end(self._series[name], rest)
            self._pending.clear()
        except BaseException:
            failed = True
            raise
        finally:
            handle, self._file = self._file, None
            close_hdf5(handle, self._series, failed=failed)

    def __enter__(self) -> ResultWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close(failed=exc_type is not None)


def row_attrs(rows: str, row_every_samples: int | None, row_rate_hz: float | None, sample_rate_hz: float) -> dict:
    """A series file's root attributes: the rows' spacing, their rate and what set them (issue 33).

    ``rows`` is what set them (``"resolution"``, ``"per-period"``, ``"decimate 24"``); a spacing or
    rate that is None is left out.
    """
    attrs = {"sample_rate_hz": float(sample_rate_hz), "rows": rows,
             "row_every_samples": row_every_samples, "row_rate_hz": row_rate_hz}
    return {key: value for key, value in attrs.items() if value is not None}


def _write_at_end(ds: h5py.Dataset, block: np.ndarray) -> None:
    """Grow ``ds`` along its last axis and write ``block`` there."""
    start = ds.shape[-1]
    ds.resize(start + block.shape[-1], axis=ds.ndim - 1)
    ds[..., start:] = block


class _WriteBehind:
    """Calls ``write(block)`` in a daemon thread, in order, holding at most ``depth`` blocks.

    The first exception ``write`` raises is re-raised in the caller's thread
    at its next :meth:`submit`, :meth:`drain` or :meth:`stop`; later blocks
    are dropped, as the file is no good anyway.
    """

    def __init__(self, write: Callable[[Mapping[str, np.ndarray]], None], depth: int = 2) -> None:
        self._write = write
        self._queue: queue.Queue = queue.Queue(maxsize=depth)
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="afmtool-writer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            block = self._queue.get()
            try:
                if block is None:
                    return
                if self._error is None:
                    self._write(block)
            except BaseException as exc:  # noqa: BLE001 - re-raised in the caller's thread by _check
                self._error = exc
            finally:
                self._queue.task_done()

    def _check(self) -> None:
        if self._error is not None:
            error, self._error = self._error, None
            raise error

    def submit(self, block: Mapping[str, np.ndarray]) -> None:
        self._check()
        self._queue.put(block)

    def drain(self) -> None:
        """Wait until every submitted block is written."""
        self._queue.join()
        self._check()

    def stop(self) -> None:
        """Write what was submitted, end the thread."""
        if self._thread.is_alive():
            self._queue.put(None)
            self._thread.join()
        self._check()
