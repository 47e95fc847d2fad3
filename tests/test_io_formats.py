"""HDF5 and CSV readers/writers: round trips, streaming, fixtures, bad input."""

from __future__ import annotations

import io

import h5py
import numpy as np
import pytest

from afmtool.errors import InputError
from afmtool.io.capture import ChannelSpec
from afmtool.io.chunks import iter_chunks
from afmtool.io.csv import CsvReader, CsvWriter
from afmtool.io.hdf5 import Hdf5Reader, Hdf5Writer
from afmtool.io.registry import open_capture

CHANNELS = (ChannelSpec("dither", "V"), ChannelSpec("deflection", "nm"))
META = {"cantilever": {"f0_hz": 70000.0, "q": 200.0}, "note": "test"}


def _data(rng, n=2503):
    return {"dither": rng.standard_normal(n), "deflection": 25 * rng.standard_normal(n)}


def _read_all(reader, chunk):
    parts = list(iter_chunks(reader, reader.info.channel_names, chunk))
    return {name: np.concatenate([p.data[name] for p in parts]) for name in reader.info.channel_names}


@pytest.mark.parametrize("chunk", [1, 777, 1 << 20])
def test_hdf5_round_trip_exact(tmp_path, rng, chunk):
    data = _data(rng)
    path = tmp_path / "c.h5"
    writer = Hdf5Writer(path, 5e5, CHANNELS, META)
    writer.write({k: v[:1000] for k, v in data.items()})
    writer.write({k: v[1000:] for k, v in data.items()})
    writer.write_truth({"separation_nm": np.arange(2503.0)})
    writer.close()
    with open_capture(path) as reader:
        assert reader.info.sample_rate_hz == 5e5
        assert dict(reader.info.metadata) == META
        assert [(c.name, c.units) for c in reader.info.channels] == [("dither", "V"), ("deflection", "nm")]
        assert reader.info.truth_names == ("separation_nm",)
        back = _read_all(reader, chunk)
    for name in data:
        np.testing.assert_array_equal(back[name], data[name])


def test_hdf5_gzip_readable(tmp_path, rng):
    data = _data(rng)
    path = tmp_path / "c.h5"
    writer = Hdf5Writer(path, 5e5, CHANNELS, META, compression="gzip")
    writer.write(data)
    writer.close()
    with h5py.File(path) as f:
        assert f["channels/deflection"].compression == "gzip"
        assert f["channels/deflection"].shuffle
    with open_capture(path) as reader:
        np.testing.assert_array_equal(_read_all(reader, 1000)["deflection"], data["deflection"])


@pytest.mark.parametrize("chunk", [1, 999, 1 << 20])
def test_csv_round_trip_exact(tmp_path, rng, chunk):
    data = _data(rng)
    stream = io.StringIO()
    writer = CsvWriter(stream, 5e5, CHANNELS, META)
    writer.write(data)
    writer.close()
    reader = CsvReader("mem.csv", stream=io.StringIO(stream.getvalue()))
    assert reader.info.sample_rate_hz == 5e5
    assert dict(reader.info.metadata) == META
    assert reader.info.units("deflection") == "nm"
    back = _read_all(reader, chunk)
    for name in data:
        np.testing.assert_array_equal(back[name], data[name])


def test_fixture_hdf5_and_csv(shared):
    expected = np.load(shared / "fixtures" / "capture_v1_expected.npy")
    names = ("dither", "deflection", "z_piezo")
    with open_capture(shared / "fixtures" / "capture_v1.h5") as reader:
        back = _read_all(reader, 1500)
        assert reader.info.sample_rate_hz == 500000.0
        assert reader.info.metadata["cantilever"]["f0_hz"] == 71000
    for i, name in enumerate(names):
        np.testing.assert_array_equal(back[name], expected[i].astype(np.float64))
    with open_capture(shared / "fixtures" / "capture_v1.csv") as reader:
        back = _read_all(reader, 1500)
        assert reader.info.sample_rate_hz == 500000.0
        assert reader.info.units("deflection") == "nm"
    for i, name in enumerate(names):
        np.testing.assert_allclose(back[name], expected[i], rtol=1e-6, atol=1e-12)


def test_foreign_hdf5_mapping(shared):
    path = shared / "data" / "fm_kpfm_displacement.h5"
    with open_capture(path, channel_map={"deflection": "/s"}, sample_rate_hz=1.15e6) as reader:
        assert reader.info.n_samples == 762_375
        assert reader.info.sample_rate_hz == 1.15e6


def test_csv_sample_rate_from_t_column():
    text = "t,deflection\n" + "".join(f"{i * 2e-6!r},{i}\n" for i in range(100))
    reader = CsvReader("x.csv", stream=io.StringIO(text))
    assert reader.info.sample_rate_hz == pytest.approx(5e5, rel=1e-9)


@pytest.mark.parametrize(
    "text, message",
    [
        ("# sample_rate_hz: 1000\na,b\n1,2\n3\n", "columns"),
        ("# sample_rate_hz: 1000\na,b\n1,2\n3,x\n", "x"),
        ("t,a\n0,1\n0.001,2\n0.0025,3\n0.003,4\n", "non-uniform"),
        ("", "empty"),
        ("a,b\n1,2\n", "sample rate"),
        ("# sample_rate_hz: -5\na\n1\n", "positive"),
        ('# sample_rate_hz: 10\n# metadata: {"free_air": 3}\na\n1\n', "free_air"),
    ],
)
def test_csv_bad_input(text, message):
    with pytest.raises(InputError, match=message):
        reader = CsvReader("bad.csv", stream=io.StringIO(text))
        list(iter_chunks(reader, reader.info.channel_names, 2))


def test_hdf5_bad_input(tmp_path, rng):
    no_rate = tmp_path / "norate.h5"
    with h5py.File(no_rate, "w") as f:
        f.create_dataset("channels/deflection", data=np.zeros(10))
    with pytest.raises(InputError, match="sample_rate_hz"):
        Hdf5Reader(no_rate)
    good = tmp_path / "good.h5"
    writer = Hdf5Writer(good, 5e5, CHANNELS, META)
    writer.write(_data(rng, 100_000))
    writer.close()
    truncated = tmp_path / "trunc.h5"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(InputError, match="HDF5|cannot read"):
        with open_capture(truncated) as reader:
            _read_all(reader, 1 << 20)


def test_nan_refused(tmp_path):
    path = tmp_path / "nan.h5"
    writer = Hdf5Writer(path, 1e3, CHANNELS[:1])
    values = np.zeros(50)
    values[17] = np.nan
    writer.write({"dither": values})
    writer.close()
    with open_capture(path) as reader, pytest.raises(InputError, match="sample 17"):
        _read_all(reader, 10)


def test_missing_channel(shared):
    with open_capture(shared / "fixtures" / "capture_v1.h5") as reader, pytest.raises(InputError, match="thermal"):
        list(iter_chunks(reader, ["thermal_current"], 100))
