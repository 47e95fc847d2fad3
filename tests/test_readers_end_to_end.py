"""Acceptance: every file in ../shared/data/formats reads with the right shape, and reep and
probeloss give identical results on a capture that went through each foreign format.

sample_data/ltv_step.h5's dither and deflection are written into TDMS (npTDMS's TdmsWriter),
WAV (scipy.io.wavfile), a LabOne HDF5 scope shot (h5py, LabOne's layout) and a scope CSV
(``Time (s),CH1 (V),CH2 (nm)``); each is converted to afmtool HDF5 with ``afmtool convert``
(mapping its channels with --channel) and run through reep and probeloss, and the results
must equal the original's to the last bit (float64 all the way).  reep also runs on the
foreign files themselves.  The runs share one parameter file, so that the original's
metadata (free-air segment, drive) gives it no advantage over formats that cannot carry it.
"""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from tests.conftest import SAMPLE_DATA, run_cli

FORMATS = "data/formats"

# name, format, sample rate (Hz), samples, segments [(name, samples)], {channel: units}  (SOURCES.md)
EXPECTED = [
    ("fmt-igor-fd_SiN_FD_plot.ibw", "ibw", 2000.0, 2016, [("approach", 1009), ("retract", 1007)],
     {"raw": "m", "deflection": "m", "z_piezo": "m"}),
    ("force-save-example.jpk-force", "jpk", 2000.0, 8400, [("extend", 6000), ("retract", 2400)],
     {"cellhesion-height": "m", "height": "m", "deflection": "m", "capacitiveSensorHeight": "m"}),
    ("fmt-jpk-fd_spot3-0192.jpk-force", "jpk", 2000.0, 4000, [("extend", 2000), ("retract", 2000)],
     {"height": "m", "deflection": "m", "strainGaugeHeight": "m"}),
    ("fmt-chiaro-txt_AEBP1_Indentation_002.zip", "chiaro", 1000.0, 13827, [],
     {"Load": "uN", "Indentation": "nm", "deflection": "nm", "z_piezo": "nm", "Auxiliary": ""}),
    ("raw1.tdms", "tdms", 50000.0, 2000, [],
     {n: "V" for n in ("First  Channel", "Second Chan", "Third Chan", "Fourth Chan", "Fifth Chan", "Sixth Chan",
                       "Seventh Cha")}),
]


@pytest.mark.parametrize("row", EXPECTED, ids=[r[0] for r in EXPECTED])
def test_info_on_every_real_file(shared, row):
    name, fmt, rate, n, segments, channels = row
    result = run_cli("info", shared / FORMATS / name, "--json")
    assert result.returncode == 0, result.stderr.decode()
    info = json.loads(result.stdout)
    assert info["format"] == fmt
    assert info["sample_rate_hz"] == pytest.approx(rate, rel=1e-9)
    assert info["n_samples"] == n
    assert {c["name"]: c["units"] for c in info["channels"]} == channels
    assert [(s["name"], s["n_samples"]) for s in info["segments"]] == segments


def test_info_on_the_qi_series_segments(shared):
    path = shared / FORMATS / "fmt-jpk-fd_qi-data-2021.04.13.jpk-qi-series"
    for segment, rate in (("extend", 5000.0), ("retract", 50000.0)):
        info = json.loads(run_cli("info", path, "--json", "--segment", segment).stdout)
        assert (info["sample_rate_hz"], info["n_samples"], len(info["channels"])) == (rate, 1000, 13)
        assert [(s["name"], s["sample_rate_hz"]) for s in info["segments"]] == [("extend", 5000.0), ("retract", 50000.0)]


def test_convert_keeps_units_metadata_and_segments(shared, tmp_path):
    source = shared / FORMATS / "fmt-igor-fd_SiN_FD_plot.ibw"
    for suffix in (".h5", ".csv"):
        target = tmp_path / f"curve{suffix}"
        assert run_cli("convert", source, target).returncode == 0
        original = json.loads(run_cli("info", source, "--json", "--segment", "retract").stdout)
        converted = json.loads(run_cli("info", target, "--json", "--segment", "retract").stdout)
        assert [(s["name"], s["start"], s["n_samples"]) for s in converted["segments"]] == [
            ("approach", 0, 1009), ("retract", 1009, 1007)
        ]
        assert converted["n_samples"] == 1007
        assert [(c["name"], c["units"]) for c in converted["channels"]] == [
            (c["name"], c["units"]) for c in original["channels"]
        ]
        for a, b in zip(converted["channels"], original["channels"]):
            assert a["mean"] == pytest.approx(b["mean"], rel=1e-12)
        assert converted["metadata"]["cantilever"] == original["metadata"]["cantilever"]


def test_convert_of_segments_at_different_rates_needs_segment(shared, tmp_path):
    source = shared / FORMATS / "fmt-jpk-fd_qi-data-2021.04.13.jpk-qi-series"
    refused = run_cli("convert", source, tmp_path / "qi.h5")
    assert refused.returncode == 2 and not (tmp_path / "qi.h5").exists()
    assert run_cli("convert", source, tmp_path / "qi.h5", "--segment", "retract").returncode == 0
    info = json.loads(run_cli("info", tmp_path / "qi.h5", "--json").stdout)
    assert (info["sample_rate_hz"], info["n_samples"]) == (50000.0, 1000)
    assert info["metadata"]["segment"]["name"] == "retract"


# ------------------------------------------------------------------ end to end through every format

PARAMETERS = """\
[reep]
free_air = "0:0.03"
drive_frequency_hz = 70000.0
lockin_lowpass_hz = 3000.0
[probeloss]
free_air = "0:0.03"
drive_frequency_hz = 70000.0
lockin_lowpass_hz = 3000.0
amplitude_upper = 20.0
"""


def _original():
    with h5py.File(SAMPLE_DATA / "ltv_step.h5") as f:
        return float(f.attrs["sample_rate_hz"]), f["channels/dither"][()], f["channels/deflection"][()]


def _write_foreign(fmt: str, folder):
    """ltv_step's channels in ``fmt``, written by that format's own library; returns (path, --channel args)."""
    fs, dither, deflection = _original()
    if fmt == "tdms":
        from nptdms import ChannelObject, TdmsWriter

        path = folder / "ltv.tdms"
        props = {"wf_increment": 1.0 / fs}
        with TdmsWriter(str(path)) as writer:
            writer.write_segment([
                ChannelObject("afm", "dither", dither, properties={**props, "unit_string": "Volts"}),
                ChannelObject("afm", "deflection", deflection, properties={**props, "unit_string": "nm"}),
            ])
        return path, []
    if fmt == "wav":
        from scipy.io import wavfile

        path = folder / "ltv.wav"
        wavfile.write(path, int(fs), np.column_stack([dither, deflection]))
        return path, ["--channel", "dither=ch1", "--channel", "deflection=ch2"]
    if fmt == "labone":
        path = folder / "ltv_labone.h5"
        with h5py.File(path, "w") as f:
            wave = f.create_group("000/dev1234/scopes/0/wave")
            wave["wave"] = np.vstack([dither, deflection])
            wave.attrs["dt"] = 1.0 / fs
        return path, ["--channel", "dither=ch1", "--channel", "deflection=ch2"]
    if fmt == "csv":  # a plain CSV with units in the header, as numpy writes it
        path = folder / "ltv_plain.csv"
        t = np.arange(len(dither)) / fs
        np.savetxt(path, np.column_stack([t, dither, deflection]), delimiter=",", fmt="%.17g",
                   header="t (s),dither (V),deflection (nm)", comments="")
        return path, []
    if fmt in ("ros1", "ros2-mcap"):  # bags, written by rosbags (through afmtool's writer)
        path = folder / ("ltv.bag" if fmt == "ros1" else "ltv_mcap")
        result = run_cli("convert", SAMPLE_DATA / "ltv_step.h5", path, "--format", fmt)
        assert result.returncode == 0, result.stderr.decode()
        return path, []
    if fmt == "scope-csv":
        path = folder / "ltv_scope.csv"
        t = np.arange(len(dither)) / fs
        with open(path, "w", newline="") as handle:
            handle.write("Time (s),CH1 (V),CH2 (nm)\r\n")
            np.savetxt(handle, np.column_stack([t, dither, deflection]), delimiter=",", fmt="%.17g", newline="\r\n")
        return path, ["--channel", "dither=CH1", "--channel", "deflection=CH2"]
    raise AssertionError(fmt)


def _units_flags(command: str) -> list[str]:
    """WAV and LabOne scope channels carry no nm: once ``--units`` exists (issue 16 item 2), say what they hold."""
    help_text = run_cli(command, "--help").stdout.decode()
    return ["--units", "deflection=nm", "--units", "dither=V"] if "--units" in help_text else []


def _results(folder, name: str):
    report = json.loads((folder / "report.json").read_text())
    with h5py.File(folder / f"{name}.h5") as f:
        arrays = {}
        f.visititems(lambda key, obj: arrays.__setitem__(key, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    return report["results"], arrays


def _rounded(value):
    """Floats to 12 significant digits: the drive-hold phase is a sum over chunks whose edges differ by format."""
    if isinstance(value, float):
        return float(f"{value:.12g}")
    if isinstance(value, dict):
        return {k: _rounded(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_rounded(v) for v in value]
    return value


def _assert_same(a, b):
    results_a, arrays_a = a
    results_b, arrays_b = b
    # only afmtool's HDF5 carries /truth, so only the original run can score against it
    results_a, results_b = ({k: _rounded(v) for k, v in r.items() if k != "truth_tracking"} for r in (results_a, results_b))
    differing = {k: (results_a.get(k), results_b.get(k)) for k in results_a.keys() | results_b.keys()
                 if results_a.get(k) != results_b.get(k)}
    assert not differing, "\n".join(f"{k}:\n  {va}\n  {vb}" for k, (va, vb) in differing.items())
    assert arrays_a.keys() == arrays_b.keys()
    for key in arrays_a:
        np.testing.assert_array_equal(arrays_a[key], arrays_b[key], err_msg=key)


@pytest.fixture(scope="module")
def reference_runs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("reference")
    (folder / "p.toml").write_text(PARAMETERS)
    runs = {}
    for command in ("reep", "probeloss"):
        result = run_cli(command, SAMPLE_DATA / "ltv_step.h5", "--config", folder / "p.toml", "--out", folder / command, "-q")
        assert result.returncode == 0, result.stderr.decode()
        runs[command] = _results(folder / command, command)
    return runs


@pytest.mark.slow  # 13 CLI runs, about 15 s of CPU
@pytest.mark.parametrize("fmt", ["tdms", "wav", "labone", "scope-csv", "csv", "ros1", "ros2-mcap"])
def test_reep_and_probeloss_identical_through_each_format(tmp_path, reference_runs, fmt):
    (tmp_path / "p.toml").write_text(PARAMETERS)
    foreign, mapping = _write_foreign(fmt, tmp_path)
    converted = tmp_path / "converted.h5"
    result = run_cli("convert", foreign, converted, *mapping)
    assert result.returncode == 0, result.stderr.decode()
    for command in ("reep", "probeloss"):
        out = tmp_path / command
        result = run_cli(command, converted, "--config", tmp_path / "p.toml", "--out", out, "-q", *_units_flags(command))
        assert result.returncode == 0, result.stderr.decode()
        _assert_same(_results(out, command), reference_runs[command])
    direct = tmp_path / "direct"
    result = run_cli("reep", foreign, "--config", tmp_path / "p.toml", "--out", direct, "-q", *mapping, *_units_flags("reep"))
    assert result.returncode == 0, result.stderr.decode()
    _assert_same(_results(direct, "reep"), reference_runs["reep"])


@pytest.mark.parametrize("suffix", [".ibw", ".jpk-force", ".jpk-qi-series", ".tdms", ".wav", ".txt", ".zip", ".h5", ".csv"])
@pytest.mark.parametrize("content", [b"\x00\x01garbage\xff" * 50, b"PK\x03\x04" + bytes(300)])
def test_unparsable_file_with_a_supported_suffix(tmp_path, suffix, content):
    from afmtool.errors import InputError
    from afmtool.io.chunks import iter_chunks
    from afmtool.io.registry import open_capture

    path = tmp_path / f"junk{suffix}"
    path.write_bytes(content)
    with pytest.raises(InputError) as caught:
        with open_capture(path) as reader:
            list(iter_chunks(reader, reader.info.channel_names, 100))
    assert str(path) in str(caught.value) and "\n" not in str(caught.value)


def test_unparsable_file_through_the_cli(tmp_path):
    path = tmp_path / "junk.tdms"
    path.write_bytes(b"TDSm" + bytes(100))
    for command in (["info", path], ["convert", path, tmp_path / "out.h5"]):
        result = run_cli(*command)
        err = result.stderr.decode()
        assert result.returncode == 2 and err.count("\n") == 1 and str(path) in err and "Traceback" not in err, err
    assert not (tmp_path / "out.h5").exists()


@pytest.mark.parametrize("name", [r[0] for r in EXPECTED] + ["fmt-jpk-fd_qi-data-2021.04.13.jpk-qi-series"])
def test_vendor_metadata_follows_the_schema(shared, name):
    import jsonschema

    from afmtool.io.metadata import validate_metadata
    from afmtool.io.registry import open_capture
    from tests.conftest import load_schema

    segment = "retract" if "qi-series" in name else None
    with open_capture(shared / FORMATS / name, segment=segment) as reader:
        metadata = json.loads(json.dumps(dict(reader.info.metadata)))
    jsonschema.validate(metadata, load_schema("capture-metadata.schema.json"))
    validate_metadata(metadata)
