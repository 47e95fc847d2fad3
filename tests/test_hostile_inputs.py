"""Inputs that point outside themselves are refused; inputs are opened read-only."""

from __future__ import annotations

import json

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


# ------------------------------------------------------------------ issue 34, the readers' side

def _one_line_exit_2(result, *words):
    err = result.stderr.decode()
    assert result.returncode == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert all(word in err for word in words), err
    assert result.stdout == b""


@pytest.mark.parametrize("reader", ["ros1", "ros2-sqlite3", "ros2-mcap"])
def test_deep_json_in_bag_metadata_is_one_line(tmp_path, reader):
    """Bag metadata nesting JSON arrays deeply gave RecursionError in ROS1, ROS2-db3 and ROS2-mcap."""
    from tests.fuzz_harness import _bag_hostile

    path, must_refuse = _bag_hostile(reader, tmp_path, np.random.default_rng([34, 5000]))
    assert must_refuse
    for command in (["info", path], ["reep", path, "--out", tmp_path / "out"]):
        _one_line_exit_2(run_cli(*command), "nested", "deep")
    assert not (tmp_path / "out").exists()


def test_json_depth_and_size_are_bounded_for_every_source():
    from afmtool.io.metadata import MAX_JSON_CHARS, load_json

    for text in ("[" * 100_000 + "]" * 100_000, '{"a":' * 5000 + "1" + "}" * 5000):
        with pytest.raises(InputError, match="nested"):
            load_json(text, "x.bag", "/afm/metadata")
    with pytest.raises(InputError, match="characters"):
        load_json(" " * (MAX_JSON_CHARS + 1), "x.h5")
    assert load_json('{"a": [[[1]]]}', "x.h5") == {"a": [[[1]]]}


@pytest.mark.serial
def test_hdf5_metadata_of_100000_keys_reads_within_5_s(tmp_path):
    """'info' on an HDF5 capture whose metadata holds very many keys hung past 120 s."""
    import json
    import time

    path = tmp_path / "keys.h5"
    with h5py.File(path, "w") as f:
        f.attrs["sample_rate_hz"] = 1e3
        f.attrs["metadata"] = json.dumps({"instrument": {f"k{i}": i for i in range(100_000)}})
        f["channels/deflection"] = np.zeros(100)
    start = time.monotonic()
    with open_capture(path) as reader:
        assert len(reader.info.metadata["instrument"]) == 100_000
    assert time.monotonic() - start < 5
    start = time.monotonic()
    result = run_cli("info", path, "--json")
    assert result.returncode == 0 and time.monotonic() - start < 5 + 5  # the CLI's start-up on a loaded machine


def test_a_root_of_very_many_attributes_is_refused_by_its_count(tmp_path, monkeypatch):
    """100,000 root attributes took longer to read than the heap check allows, which called the file damaged;
    the count is read first (the limit is lowered here: writing 10,000 attributes takes minutes)."""
    import afmtool.io.hdf5 as hdf5

    monkeypatch.setattr(hdf5, "MAX_ROOT_ATTRIBUTES", 50)
    path = tmp_path / "attrs.h5"
    with h5py.File(path, "w") as f:
        f.attrs["sample_rate_hz"] = 1e3
        for i in range(60):
            f.attrs[f"k{i}"] = i
        f["channels/deflection"] = np.zeros(10)
    with pytest.raises(InputError, match="61 attributes"):
        open_capture(path)


@pytest.mark.parametrize("order", ["rising", "falling"])
def test_labone_timestamp_at_the_uint64_maximum(tmp_path, order):
    """A LabOne HDF5 export with a timestamp at the uint64 maximum gave OverflowError."""
    path = tmp_path / "labone.h5"
    with h5py.File(path, "w") as f:
        group = f.create_group("000/dev1234/demods/0/sample")
        stamps = np.arange(100, dtype=np.uint64) * 3000
        stamps[-1 if order == "rising" else 0] = np.iinfo(np.uint64).max
        group["timestamp"] = stamps
        group["x"] = np.zeros(100)
        group.attrs["clockbase"] = 60e6
    for command in (["info", path], ["convert", path, tmp_path / "o.h5"]):
        _one_line_exit_2(run_cli(*command))
    assert not (tmp_path / "o.h5").exists()


def test_labone_csv_with_a_huge_declared_size(tmp_path):
    """A LabOne CSV export whose header file declares a huge size gave MemoryError; the size is not trusted."""
    path = tmp_path / "dev1234_demods_0_sample_00000.csv"
    lines = ["chunk;timestamp;x;y"] + [f"0;{10**9 + 3000 * i};{0.1 * i};{0.2 * i}" for i in range(300)]
    path.write_text("\n".join(lines) + "\n")
    (tmp_path / "dev1234_demods_0_sample_header_00000.csv").write_text(
        "chunk;history_name;clockbase;size;createdtimestamp\n0;sample;60000000;1000000000000000000000;1\n")
    result = run_cli("info", path, "--json")
    assert result.returncode == 0, result.stderr.decode()
    assert b"Memory" not in result.stderr


def test_jpk_unit_strings_with_nul_and_utf16_convert(tmp_path):
    """convert of a JPK file whose unit strings hold a NUL or UTF-16 text gave 'VLEN strings do not support
    embedded NULLs'."""
    from tests.test_readers_end_to_end import _write_jpk

    path = tmp_path / "units.jpk-force"
    _write_jpk(path, {"dither": (np.zeros(100), "V\\u0000"), "vDeflection": (np.ones(100), "n\\u0000m")}, 1000.0)
    for target in ("o.h5", "o.csv", "o.mcap"):
        result = run_cli("convert", path, tmp_path / target)
        assert result.returncode == 0, result.stderr.decode()
        info = json.loads(run_cli("info", tmp_path / target, "--json").stdout)
        assert [c["units"] for c in info["channels"]] == ["V", "nm"]
