"""The streaming HDF5 result writer: whole-chunk appends, and the write-behind thread."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from afmtool.io.results import ResultWriter


def _write(path, blocks, **kwargs):
    with ResultWriter(path, {"x": "nm", "t": "s"}, {"afmtool_command": "test"}, **kwargs) as writer:
        for block in blocks:
            writer.append(block)
        writer.put("images/one", np.eye(3), units="nm")


def _blocks():
    rng = np.random.default_rng(0)
    start = 0
    for size in (1, 5_000, 16_384, 40_001, 3, 70_000):  # around and across the 16 384-row HDF5 chunk
        yield {"t": np.arange(start, start + size) / 1e3, "x": rng.standard_normal(size).astype(np.float32)}
        start += size


@pytest.mark.parametrize("write_behind", [False, True])
def test_series_are_the_concatenated_blocks(tmp_path, write_behind):
    path = tmp_path / "out.h5"
    _write(path, _blocks(), write_behind=write_behind)
    expected = list(_blocks())
    with h5py.File(path) as f:
        np.testing.assert_array_equal(f["t"][:], np.concatenate([b["t"] for b in expected]))
        np.testing.assert_array_equal(f["x"][:], np.concatenate([b["x"] for b in expected]))
        assert f["x"].dtype == np.float32
        assert f["x"].attrs["units"] == "nm"
        np.testing.assert_array_equal(f["images/one"][:], np.eye(3))
        assert f.attrs["afmtool_command"] == "test"


def test_write_behind_raises_the_writer_threads_error_in_the_caller(tmp_path):
    """A block the file cannot take fails in the writer thread; the caller sees it, not a silent loss."""
    writer = ResultWriter(tmp_path / "out.h5", {}, write_behind=True)
    writer.append({"x": np.zeros(10)})
    writer.append({"x": np.zeros((2, 10))})  # a 2-D block for a 1-D series
    with pytest.raises((TypeError, ValueError)):
        for _ in range(10):  # the error surfaces at a later append, at latest at close
            writer.append({"x": np.zeros(10)})
        writer.close()
    writer.close()  # a second close after the failure is harmless
