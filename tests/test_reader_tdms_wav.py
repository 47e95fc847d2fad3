"""TDMS and WAV readers: the real DAQmx file, and files from npTDMS's and scipy's own writers."""

from __future__ import annotations

import json

import numpy as np
import pytest

from afmtool.io.chunks import iter_chunks
from afmtool.io.registry import open_capture
from tests.conftest import run_cli

TDMS = "data/formats/raw1.tdms"


def _read(path, **kwargs):
    with open_capture(path, **kwargs) as reader:
        chunks = list(iter_chunks(reader, reader.info.channel_names, 777))
        return reader.info, {n: np.concatenate([c.data[n] for c in chunks]) for n in reader.info.channel_names}


def test_info_on_the_real_daqmx_file(shared):
    result = run_cli("info", shared / TDMS, "--json")
    assert result.returncode == 0, result.stderr.decode()
    info = json.loads(result.stdout)
    names = ["First  Channel", "Second Chan", "Third Chan", "Fourth Chan", "Fifth Chan", "Sixth Chan", "Seventh Cha"]
    assert [c["name"] for c in info["channels"]] == names
    assert {c["units"] for c in info["channels"]} == {"V"}  # unit_string "Volts"
    assert info["sample_rate_hz"] == pytest.approx(50000.0, rel=1e-12)
    assert info["n_samples"] == 2000
    means = [c["mean"] for c in info["channels"]]
    assert means[0] == pytest.approx(0.07, abs=0.02) and means[-1] == pytest.approx(4.90, abs=0.02)


def test_samples_are_the_daqmx_scaled_values(shared):
    from nptdms import TdmsFile

    info, data = _read(shared / TDMS)
    independent = TdmsFile.read(str(shared / TDMS))
    for channel in independent["Layer Data"].channels():
        np.testing.assert_array_equal(data[channel.name], channel[:])
    raw = independent["Layer Data"]["First  Channel"].read_data(scaled=False)
    raw = raw[0] if isinstance(raw, dict) else raw
    assert list(raw[:4]) == [-603, 485, -803, -974]
    np.testing.assert_allclose(data["First  Channel"][:4], np.array([-603, 485, -803, -974]) * 3.0518509e-4, rtol=1e-7)


def _write_tdms(path, *, increment=2e-6, groups=("g",), n=3000, with_unit=True):
    from nptdms import ChannelObject, TdmsWriter

    rng = np.random.default_rng(5)
    objects = []
    for group in groups:
        for name in ("dither", "deflection"):
            props = {"wf_increment": increment} if increment is not None else {}
            if with_unit:
                props["unit_string"] = "Volts" if name == "dither" else "nm"
            objects.append(ChannelObject(group, name, rng.standard_normal(n), properties=props))
    with TdmsWriter(str(path)) as writer:
        writer.write_segment(objects[: len(objects)])
    return objects


def test_file_from_nptdms_writer(tmp_path):
    objects = _write_tdms(tmp_path / "w.tdms")
    info, data = _read(tmp_path / "w.tdms")
    assert info.sample_rate_hz == pytest.approx(500000.0, rel=1e-12)
    assert [(c.name, c.units) for c in info.channels] == [("dither", "V"), ("deflection", "nm")]
    np.testing.assert_array_equal(data["deflection"], objects[1].data)


def test_two_groups_are_named_group_dot_channel(tmp_path):
    _write_tdms(tmp_path / "w.tdms", groups=("a", "b"))
    info, _ = _read(tmp_path / "w.tdms", channel_map={"deflection": "b.deflection"})
    assert "deflection" in info.channel_names and "a.dither" in info.channel_names


def test_channel_without_sample_interval_is_refused(tmp_path):
    _write_tdms(tmp_path / "w.tdms", increment=None)
    result = run_cli("info", tmp_path / "w.tdms")
    assert result.returncode == 2
    err = result.stderr.decode()
    assert err.count("\n") == 1 and "no sample interval (wf_increment)" in err and "'dither'" in err
    assert run_cli("info", tmp_path / "w.tdms", "--sample-rate", "1e5").returncode == 0


@pytest.mark.parametrize("keep", [20, 500, 3000, 20000, 34000])
def test_truncated_tdms_is_one_line_exit_2(shared, tmp_path, keep):
    path = tmp_path / "cut.tdms"
    path.write_bytes((shared / TDMS).read_bytes()[:keep])
    result = run_cli("info", path)
    assert result.returncode == 2
    err = result.stderr.decode()
    assert err.count("\n") == 1 and str(path) in err and "Traceback" not in err, err
    assert result.stdout == b""


@pytest.mark.parametrize("dtype", ["float64", "float32", "int16", "int32"])
def test_wav_from_scipy_writer(tmp_path, dtype):
    from scipy.io import wavfile

    rng = np.random.default_rng(3)
    samples = (rng.standard_normal((2500, 3)) * (1000 if dtype.startswith("int") else 1)).astype(dtype)
    wavfile.write(tmp_path / "s.wav", 192000, samples)
    info, data = _read(tmp_path / "s.wav", channel_map={"deflection": "ch2"})
    assert info.sample_rate_hz == 192000 and info.n_samples == 2500
    assert info.channel_names == ("ch1", "deflection", "ch3")
    assert all(c.units == "" for c in info.channels)
    np.testing.assert_array_equal(data["deflection"], samples[:, 1].astype(np.float64))


def test_truncated_wav_is_refused(tmp_path):
    from scipy.io import wavfile

    wavfile.write(tmp_path / "s.wav", 1000, np.zeros((1000, 2)))
    (tmp_path / "cut.wav").write_bytes((tmp_path / "s.wav").read_bytes()[:5000])
    (tmp_path / "junk.wav").write_bytes(b"RIFX" + bytes(100))
    for name in ("cut.wav", "junk.wav"):
        result = run_cli("info", tmp_path / name)
        assert result.returncode == 2 and result.stderr.decode().count("\n") == 1, result.stderr
