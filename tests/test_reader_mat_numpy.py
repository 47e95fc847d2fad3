"""MATLAB (.mat v5 and v7.3) and NumPy (.npz, .npy) captures, written by their own libraries.

v5 files are written by scipy.io.savemat, v7.3 files by hdf5storage (an HDF5 MAT writer that
shares no code with afmtool), .npz and .npy by numpy; every sample must come back bit for bit.
"""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from afmtool.errors import InputError
from afmtool.io.chunks import iter_chunks
from afmtool.io.registry import open_capture
from tests.conftest import run_cli

RATE = 500_000.0


@pytest.fixture(scope="module")
def signals():
    rng = np.random.default_rng(32)
    return rng.standard_normal(3001), rng.standard_normal(3001)


def _read(path, **kwargs):
    with open_capture(path, **kwargs) as reader:
        chunks = list(iter_chunks(reader, reader.info.channel_names, 700))
        return reader.info, {n: np.concatenate([c.data[n] for c in chunks]) for n in reader.info.channel_names}


def _write(kind: str, path, variables: dict):
    if kind == "v5":
        from scipy.io import savemat

        savemat(path, variables)
    elif kind == "v5-compressed":
        from scipy.io import savemat

        savemat(path, variables, do_compression=True)
    elif kind == "v7.3":
        import hdf5storage

        hdf5storage.savemat(str(path), {k: np.float64(v) if isinstance(v, float) else v for k, v in variables.items()},
                            format="7.3", matlab_compatible=True)
    elif kind == "npz":
        np.savez(path, **variables)
    else:
        np.savez_compressed(path, **variables)
    return path


KINDS = [("v5", ".mat"), ("v5-compressed", ".mat"), ("v7.3", ".mat"), ("npz", ".npz"), ("npz-compressed", ".npz")]


@pytest.mark.parametrize("kind, suffix", KINDS)
@pytest.mark.parametrize("rate_name, value", [("fs", RATE), ("Fs", RATE), ("sample_rate", RATE), ("dt", 1 / RATE)])
def test_vectors_are_channels_and_a_scalar_the_rate(tmp_path, signals, kind, suffix, rate_name, value):
    dither, deflection = signals
    path = _write(kind, tmp_path / f"capture{suffix}", {"dither": dither, "deflection": deflection, rate_name: value})
    info, data = _read(path)
    assert info.sample_rate_hz == pytest.approx(RATE, rel=1e-12)
    assert sorted(info.channel_names) == ["deflection", "dither"] and info.n_samples == 3001
    np.testing.assert_array_equal(data["dither"], dither)
    np.testing.assert_array_equal(data["deflection"], deflection)
    assert info.format == suffix[1:]


@pytest.mark.parametrize("kind, suffix", KINDS)
def test_matrix_columns_and_mapping(tmp_path, signals, kind, suffix):
    """--channel deflection=NAME:K reads column K of a matrix; only mapped variables are read."""
    dither, deflection = signals
    path = _write(kind, tmp_path / f"m{suffix}", {"data": np.column_stack([dither, deflection]), "fs": RATE,
                                                  "other": np.zeros(17)})
    info, data = _read(path, channel_map={"dither": "data:0", "deflection": "data:1"})
    assert info.channel_names == ("dither", "deflection")
    np.testing.assert_array_equal(data["deflection"], deflection)
    np.testing.assert_array_equal(data["dither"], dither)
    with pytest.raises(InputError, match="choose a column"):
        open_capture(path, channel_map={"deflection": "data"})


def test_mat_v73_streams_and_reads_unit_attributes(tmp_path, signals):
    """v7.3 is HDF5: a dataset's unit attribute, under any common name, gives the channel's units."""
    _, deflection = signals
    path = _write("v7.3", tmp_path / "u.mat", {"deflection": deflection, "z": deflection * 2, "fs": RATE})
    with h5py.File(path, "a") as f:
        f["deflection"].attrs["unit"] = "nm"
        f["z"].attrs["UNITS"] = "um"
    info, data = _read(path, channel_map={"deflection": "deflection", "z_piezo": "z"})
    assert [(c.name, c.units) for c in info.channels] == [("deflection", "nm"), ("z_piezo", "um")]
    np.testing.assert_array_equal(data["z_piezo"], deflection * 2)


@pytest.mark.parametrize("shape", ["n", "n,2", "2,n", "n,2F", "2,nF"])
def test_npy_in_every_layout_is_memory_mapped(tmp_path, signals, shape):
    dither, deflection = signals
    arrays = {"n": deflection, "n,2": np.column_stack([dither, deflection]), "2,n": np.vstack([dither, deflection])}
    array = arrays[shape.rstrip("F")]
    if shape.endswith("F"):
        array = np.asfortranarray(array)
    np.save(tmp_path / "deflection.npy", array)
    mapping = None if shape == "n" else {"deflection": "1"}
    with open_capture(tmp_path / "deflection.npy", sample_rate_hz=RATE, channel_map=mapping) as reader:
        assert reader.info.channel_names == ("deflection",)
        chunks = list(iter_chunks(reader, ["deflection"], 512))
        assert isinstance(reader.ranges().open(), np.memmap) or isinstance(reader.ranges().open().base, np.memmap)
        np.testing.assert_array_equal(reader.ranges().read(["deflection"], 100, 200)["deflection"], deflection[100:200])
    np.testing.assert_array_equal(np.concatenate([c.data["deflection"] for c in chunks]), deflection)


def test_npy_needs_a_rate_and_numbers(tmp_path):
    np.save(tmp_path / "x.npy", np.zeros(10))
    with pytest.raises(InputError, match="give --sample-rate"):
        open_capture(tmp_path / "x.npy")
    np.save(tmp_path / "o.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(InputError, match="objects"):
        open_capture(tmp_path / "o.npy", sample_rate_hz=1.0)
    np.save(tmp_path / "t.npy", np.zeros((3, 4, 5)))
    with pytest.raises(InputError, match="3-D"):
        open_capture(tmp_path / "t.npy", sample_rate_hz=1.0)
    (tmp_path / "cut.npy").write_bytes((tmp_path / "x.npy").read_bytes()[:-8])
    with pytest.raises(InputError, match="truncated"):
        open_capture(tmp_path / "cut.npy", sample_rate_hz=1.0)


def _bad_inputs(tmp_path, signals):
    dither, deflection = signals
    return {
        "mat without the named variable": (
            _write("v5", tmp_path / "a.mat", {"defl": deflection, "fs": RATE}), ["--channel", "deflection=missing"],
            "no variable 'missing'"),
        "mat without a rate": (_write("v5", tmp_path / "b.mat", {"deflection": deflection}), [], "no sample rate"),
        "v7.3 with a non-numeric variable": (
            _write("v7.3", tmp_path / "c.mat", {"deflection": deflection, "label": "tip 3", "fs": RATE}),
            ["--channel", "deflection=label"], "holds char, not numbers"),
        "npz with arrays of different lengths": (
            _write("npz", tmp_path / "d.npz", {"dither": dither, "deflection": deflection[:-5], "fs": RATE}), [],
            "arrays of different lengths"),
        "mat with a rate that is not a number": (
            _write("v5", tmp_path / "e.mat", {"deflection": deflection, "fs": -1.0}), [], "fs = -1.0"),
    }


@pytest.mark.parametrize("case", ["mat without the named variable", "mat without a rate", "v7.3 with a non-numeric variable",
                                  "npz with arrays of different lengths", "mat with a rate that is not a number"])
def test_bad_input_is_one_line_exit_2_no_output(tmp_path, signals, case):
    path, args, message = _bad_inputs(tmp_path, signals)[case]
    result = run_cli("convert", path, tmp_path / "out.h5", *args)
    err = result.stderr.decode()
    assert result.returncode == 2 and err.count("\n") == 1 and message in err and str(path) in err, err
    assert "Traceback" not in err and not (tmp_path / "out.h5").exists()


def test_mat_cli_with_channel_and_sample_rate(tmp_path, signals):
    _, deflection = signals
    path = _write("v5", tmp_path / "daq.mat", {"ai1": deflection})
    result = run_cli("info", path, "--channel", "deflection=ai1", "--sample-rate", "1e6", "--units", "deflection=nm", "--json")
    assert result.returncode == 0, result.stderr.decode()
    info = json.loads(result.stdout)
    assert info["sample_rate_hz"] == 1e6 and [(c["name"], c["units"]) for c in info["channels"]] == [("deflection", "nm")]
    assert info["channels"][0]["mean"] == pytest.approx(float(np.mean(deflection)), rel=1e-12)


def test_npz_member_claiming_more_than_it_holds_is_refused(tmp_path):
    """A header claiming 10^12 values in a small member: refused from the header, nothing allocated."""
    import zipfile

    np.savez(tmp_path / "ok.npz", deflection=np.zeros(100), fs=1.0)
    with zipfile.ZipFile(tmp_path / "ok.npz") as source, zipfile.ZipFile(tmp_path / "lie.npz", "w") as target:
        for item in source.infolist():
            body = source.read(item)
            if item.filename == "deflection.npy":
                body = body.replace(b"(100,)", b"(1000000000000,)".ljust(6))
            target.writestr(item, body)
    with pytest.raises(InputError, match="claims"):
        open_capture(tmp_path / "lie.npz")


def test_afmformats_hdf5_export_units_from_its_unit_attribute(shared, tmp_path):
    """afmformats' own HDF5 export stores units in a 'unit' attribute, which afmtool now reads."""
    afmformats = pytest.importorskip("afmformats")
    curve = afmformats.load_data(str(shared / "data/formats/fmt-jpk-fd_spot3-0192.jpk-force"))[0]
    curve.export_data(tmp_path / "afmformats.h5", fmt="hdf5")
    with h5py.File(tmp_path / "afmformats.h5") as f:
        assert f["0/force"].attrs["unit"] == "N" and "units" not in f["0/force"].attrs
    info, data = _read(tmp_path / "afmformats.h5", sample_rate_hz=2000.0,
                       channel_map={"z_piezo": "/0/height (measured)", "force": "/0/force", "t": "/0/time"})
    assert [(c.name, c.units) for c in info.channels] == [("z_piezo", "m"), ("force", "N"), ("t", "s")]
    np.testing.assert_array_equal(data["force"], curve["force"])
