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


# ------------------------------------------------------------------ issue 32: groups and scalings; issue 34: the index

def _signal_express_log(path):
    """A LabVIEW SignalExpress-like log: a main group at 50 kHz and a group decimated to 5 kHz."""
    from nptdms import ChannelObject, TdmsWriter

    rng = np.random.default_rng(9)
    main = {name: rng.standard_normal(5000) for name in ("dither", "deflection")}
    decimated = {name: values[::10] for name, values in main.items()}
    objects = [ChannelObject("Main", n, v, properties={"wf_increment": 2e-5, "unit_string": "Volts"}) for n, v in main.items()]
    objects += [ChannelObject("Decimated", n, v, properties={"wf_increment": 2e-4, "unit_string": "Volts"})
                for n, v in decimated.items()]
    with TdmsWriter(str(path)) as writer:
        writer.write_segment(objects)
    return main, decimated


def test_groups_at_different_rates_are_listed_and_chosen(tmp_path):
    """Before: refused with 'TDMS channels have different lengths'."""
    path = tmp_path / "log.tdms"
    main, decimated = _signal_express_log(path)
    listed = run_cli("info", path, "--json")
    assert listed.returncode == 0, listed.stderr.decode()
    groups = sorted(json.loads(listed.stdout), key=lambda g: g["metadata"]["instrument"]["group"], reverse=True)
    assert [(g["sample_rate_hz"], g["n_samples"], g["metadata"]["instrument"]["group"]) for g in groups] == [
        (pytest.approx(50000.0), 5000, "Main"), (pytest.approx(5000.0), 500, "Decimated")
    ]
    text = run_cli("info", path).stdout.decode()
    assert "50,000 Hz, 5,000 samples" in text and "5,000 Hz, 500 samples" in text
    for group, expected, rate in (("Main", main, 5e4), ("Decimated", decimated, 5e3)):
        info, data = _read(path, group=group)
        assert info.channel_names == ("dither", "deflection") and info.sample_rate_hz == pytest.approx(rate)
        np.testing.assert_array_equal(data["deflection"], expected["deflection"])
    refused = run_cli("reep", path, "--out", tmp_path / "out")
    err = refused.stderr.decode()
    assert refused.returncode == 2 and err.count("\n") == 1 and "--group" in err and "Main (2 channels" in err, err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("group", ["Other", "7"])
def test_group_that_does_not_exist(tmp_path, group):
    path = tmp_path / "log.tdms"
    _signal_express_log(path)
    result = run_cli("convert", path, tmp_path / "o.h5", "--group", group)
    err = result.stderr.decode()
    assert result.returncode == 2 and err.count("\n") == 1 and f"no group {group!r}" in err and "Decimated" in err, err
    assert not (tmp_path / "o.h5").exists()


def test_groups_that_agree_read_together_and_one_by_one(tmp_path):
    _write_tdms(tmp_path / "w.tdms", groups=("a", "b"))
    info, _ = _read(tmp_path / "w.tdms")
    assert info.channel_names == ("a.dither", "a.deflection", "b.dither", "b.deflection")
    info, _ = _read(tmp_path / "w.tdms", group="b")
    assert info.channel_names == ("dither", "deflection") and info.metadata["instrument"]["group"] == "b"


def _scaled(path, scales: dict, data=None):
    """A channel of raw values with NI scaling properties (applied by npTDMS to non-DAQmx data too)."""
    from nptdms import ChannelObject, TdmsWriter

    data = np.arange(100, dtype=np.float64) if data is None else data
    props = {"wf_increment": 1e-5, "NI_Scaling_Status": "unscaled", **scales}
    with TdmsWriter(str(path)) as writer:
        writer.write_segment([ChannelObject("g", "deflection", data, properties=props)])
    return data


def test_supported_scaling_is_applied_as_nptdms_does(tmp_path):
    from nptdms import TdmsFile

    raw = _scaled(tmp_path / "s.tdms", {"NI_Number_Of_Scales": 1, "NI_Scale[0]_Scale_Type": "Linear",
                                        "NI_Scale[0]_Linear_Slope": 2.0, "NI_Scale[0]_Linear_Y_Intercept": 1.0,
                                        "NI_Scale[0]_Linear_Input_Source": 0xFFFFFFFF})
    _, data = _read(tmp_path / "s.tdms")
    np.testing.assert_array_equal(data["deflection"], raw * 2 + 1)
    np.testing.assert_array_equal(data["deflection"], TdmsFile.read(str(tmp_path / "s.tdms"))["g"]["deflection"][:])


def test_unsupported_scaling_reads_raw_with_one_warning(tmp_path):
    """Before: refused as 'truncated or damaged'.  npTDMS reads the raw values; so does afmtool, and says so."""
    raw = _scaled(tmp_path / "s.tdms", {"NI_Number_Of_Scales": 1, "NI_Scale[0]_Scale_Type": "Reciprocal"})
    result = run_cli("convert", tmp_path / "s.tdms", tmp_path / "o.h5")
    err = result.stderr.decode()
    assert result.returncode == 0, err
    assert err.count("\n") == 1 and "Reciprocal" in err and "raw" in err and "damaged" not in err, err
    _, data = _read(tmp_path / "o.h5")
    np.testing.assert_array_equal(data["deflection"], raw)


@pytest.mark.parametrize("sources, reason", [
    ({1: 1}, "cycle"),  # a scale that reads itself
    ({0: 1, 1: 0}, "cycle"),  # two scales that read each other
    ({1: 5}, "does not exist"),
])
def test_scaling_chains_that_do_not_end_are_one_line(tmp_path, sources, reason):
    """Issue 34: a scaling that refers to itself, or two that refer to each other, gave RecursionError."""
    scales = {"NI_Number_Of_Scales": 2}
    for k in (0, 1):
        scales |= {f"NI_Scale[{k}]_Scale_Type": "Linear", f"NI_Scale[{k}]_Linear_Slope": 1.0,
                   f"NI_Scale[{k}]_Linear_Y_Intercept": 0.0, f"NI_Scale[{k}]_Linear_Input_Source": sources.get(k, 0xFFFFFFFF)}
    _scaled(tmp_path / "s.tdms", scales)
    result = run_cli("info", tmp_path / "s.tdms")
    err = result.stderr.decode()
    assert result.returncode == 2 and err.count("\n") == 1 and reason in err and "Recursion" not in err, err


def test_one_bit_flip_in_raw1_that_made_a_scale_read_itself(shared, tmp_path):
    """Issue 34: one bit flip in raw1.tdms gave RecursionError: NI_Scale[1]_Linear_Input_Source 0 -> 1 (byte 424)."""
    data = bytearray((shared / TDMS).read_bytes())
    key = b"NI_Scale[1]_Linear_Input_Source"
    at = data.index(key) + len(key) + 4  # after the uint32 type code: the value
    assert at == 424 and data[at] == 0
    data[at] ^= 1
    path = tmp_path / "flipped.tdms"
    path.write_bytes(bytes(data))
    result = run_cli("info", path)
    err = result.stderr.decode()
    assert result.returncode == 2 and err.count("\n") == 1 and "cycle" in err and "Recursion" not in err, err


def test_huge_scale_count_is_refused_before_allocating(tmp_path):
    _scaled(tmp_path / "s.tdms", {"NI_Number_Of_Scales": 10**12, "NI_Scale[0]_Scale_Type": "Linear"})
    result = run_cli("info", tmp_path / "s.tdms")
    assert result.returncode == 2 and "scales" in result.stderr.decode() and "Memory" not in result.stderr.decode()


def test_an_index_file_never_rewrites_its_capture(tmp_path):
    """Issue 34: a .tdms_index beside the file replaced its channel names, rate and units (15 cases)."""
    from nptdms import ChannelObject, TdmsWriter

    capture = tmp_path / "run.tdms"
    _write_tdms(capture)
    liar = tmp_path / "liar.tdms"  # another file's index, planted beside the capture under its name
    with TdmsWriter(str(liar), index_file=True) as writer:
        writer.write_segment([ChannelObject("x", "planted", np.zeros(3000), properties={"wf_increment": 1.0,
                                                                                        "unit_string": "A"})])
    (tmp_path / "run.tdms_index").write_bytes((tmp_path / "liar.tdms_index").read_bytes())
    info = json.loads(run_cli("info", capture, "--json").stdout)
    assert [(c["name"], c["units"]) for c in info["channels"]] == [("dither", "V"), ("deflection", "nm")]
    assert info["sample_rate_hz"] == pytest.approx(500000.0)
    _, data = _read(capture)
    objects = _write_tdms(tmp_path / "again.tdms")  # the same seeded data
    np.testing.assert_array_equal(data["deflection"], objects[1].data)


def test_nul_and_utf16_units_convert(tmp_path):
    """Issue 34: a unit string holding a NUL (or UTF-16 text) ended convert in 'VLEN strings do not support
    embedded NULLs'."""
    from nptdms import ChannelObject, TdmsWriter

    with TdmsWriter(str(tmp_path / "u.tdms")) as writer:
        writer.write_segment([
            ChannelObject("g", "dither", np.zeros(10), properties={"wf_increment": 1e-3, "unit_string": "V\x00olts"}),
            ChannelObject("g", "deflection", np.ones(10), properties={"wf_increment": 1e-3,
                                                                      "unit_string": "n\x00m\x00"}),
        ])
    for target in ("o.h5", "o.csv", "o.bag"):
        result = run_cli("convert", tmp_path / "u.tdms", tmp_path / target)
        assert result.returncode == 0, result.stderr.decode()
        info = json.loads(run_cli("info", tmp_path / target, "--json").stdout)
        assert [c["units"] for c in info["channels"]] == ["V", "nm"]  # NI's "Volts", its NUL removed


# ------------------------------------------------------------------ issue 34: WAV with two data chunks

def test_wav_with_two_data_chunks_is_refused(tmp_path):
    """Issue 34: a WAV with two data chunks read as 10 samples (scipy reads the first)."""
    import struct

    from scipy.io import wavfile

    wavfile.write(tmp_path / "one.wav", 1000, np.arange(10, dtype=np.int16))
    raw = (tmp_path / "one.wav").read_bytes()
    data_at = raw.index(b"data")
    chunk = raw[data_at:]
    doubled = raw[:data_at] + chunk + chunk
    doubled = doubled[:4] + struct.pack("<I", len(doubled) - 8) + doubled[8:]
    (tmp_path / "two.wav").write_bytes(doubled)
    result = run_cli("info", tmp_path / "two.wav")
    err = result.stderr.decode()
    assert result.returncode == 2 and err.count("\n") == 1 and "data chunks" in err, err
