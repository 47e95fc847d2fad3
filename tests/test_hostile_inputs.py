"""Inputs that point outside themselves are refused; inputs are opened read-only."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from afmtool.errors import InputError
from afmtool.io.registry import open_capture
from tests.conftest import run_cli


def _target(tmp_path):
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f.create_dataset("secret", data=np.arange(10.0))
    return other


def test_external_link_refused(tmp_path):
    other = _target(tmp_path)
    path = tmp_path / "linky.h5"
    with h5py.File(path, "w") as f:
        f.attrs["sample_rate_hz"] = 1000.0
        f["channels/deflection"] = h5py.ExternalLink(str(other), "/secret")
    with pytest.raises(InputError, match="external link"):
        open_capture(path)
    result = run_cli("info", path)
    assert result.returncode == 2 and "external link" in result.stderr.decode()


def test_external_link_group_refused(tmp_path):
    other = tmp_path / "group.h5"
    with h5py.File(other, "w") as f:
        f.create_dataset("channels/deflection", data=np.arange(10.0))
    path = tmp_path / "linky.h5"
    with h5py.File(path, "w") as f:
        f.attrs["sample_rate_hz"] = 1000.0
        f["data"] = h5py.ExternalLink(str(other), "/channels")
    with pytest.raises(InputError, match="external link"):
        open_capture(path, channel_map={"deflection": "/data/deflection"})


def test_virtual_dataset_refused(tmp_path):
    other = _target(tmp_path)
    path = tmp_path / "virtual.h5"
    layout = h5py.VirtualLayout(shape=(10,), dtype="f8")
    layout[:] = h5py.VirtualSource(str(other), "secret", shape=(10,))
    with h5py.File(path, "w") as f:
        f.attrs["sample_rate_hz"] = 1000.0
        f.create_virtual_dataset("channels/deflection", layout)
    with pytest.raises(InputError, match="virtual"):
        open_capture(path)


def test_external_storage_refused(tmp_path):
    raw = tmp_path / "raw.bin"
    np.arange(10.0).tofile(raw)
    path = tmp_path / "external.h5"
    with h5py.File(path, "w") as f:
        f.attrs["sample_rate_hz"] = 1000.0
        f.create_dataset("channels/deflection", shape=(10,), dtype="f8", external=[(str(raw), 0, 80)])
    with pytest.raises(InputError, match="external files"):
        open_capture(path)


def test_inputs_opened_read_only(tmp_path, shared):
    source = tmp_path / "ro.h5"
    source.write_bytes((shared / "fixtures" / "capture_v1.h5").read_bytes())
    source.chmod(0o444)
    result = run_cli("info", source)
    assert result.returncode == 0, result.stderr.decode()


def _corrupt_global_heap(path):
    """A capture whose global heap (where the metadata string lives) starts with a zero-size free object.

    Found by the long fuzz run (hdf5, case 6914): libhdf5 loops forever
    reading the metadata attribute, inside one C call that holds the GIL.
    """
    with h5py.File(path, "w") as f:
        f.attrs["sample_rate_hz"] = 1e6
        f.attrs["metadata"] = '{"scenario": "x"}'
        f.create_dataset("channels/deflection", data=np.zeros(16))
    data = bytearray(path.read_bytes())
    heap = data.find(b"GCOL")
    assert heap > 0
    data[heap + 16 : heap + 32] = bytes(16)  # the first object's index, reference count and size
    path.write_bytes(bytes(data))
    return path


def test_attribute_reading_that_never_ends_is_refused(tmp_path):
    from afmtool.io.hdf5 import check_attributes_terminate

    path = _corrupt_global_heap(tmp_path / "heap.h5")
    with pytest.raises(InputError, match="did not finish in 0.5 s"):
        check_attributes_terminate(path, timeout_s=0.5)
    check_attributes_terminate(_good(tmp_path), timeout_s=5.0)  # a sound file passes


def _good(tmp_path):
    path = tmp_path / "good.h5"
    with h5py.File(path, "w") as f:
        f.attrs["sample_rate_hz"] = 1e6
        f.attrs["metadata"] = '{"scenario": "x"}'
        f.create_dataset("channels/deflection", data=np.zeros(16)).attrs["units"] = "nm"
    return path


def test_cli_refuses_a_file_whose_attributes_hang(tmp_path):
    path = _corrupt_global_heap(tmp_path / "heap.h5")
    result = run_cli("info", path)
    assert result.returncode == 2
    lines = result.stderr.decode().strip().splitlines()
    assert len(lines) == 1 and "did not finish" in lines[0] and "Traceback" not in lines[0]
