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

# name, extra info args, format, sample rate (Hz), samples, segments [(name, samples)], {channel: units}  (SOURCES.md)
RATE_GIVEN = ["--sample-rate", "1000"]  # files that record no sample rate (their readers ask for --sample-rate)
EXPECTED = [
    ("fmt-igor-fd_SiN_FD_plot.ibw", [], "ibw", 2000.0, 2016, [("approach", 1009), ("retract", 1007)],
     {"raw": "m", "deflection": "m", "z_piezo": "m"}),
    ("win-version2.ibw", RATE_GIVEN, "ibw", 1000.0, 5, [], {"version2": ""}),
    ("win-double.ibw", RATE_GIVEN, "ibw", 1000.0, 5, [], {"double": ""}),
    ("win-version5.ibw", RATE_GIVEN, "ibw", 1000.0, 5, [], {"version5": ""}),
    ("force-save-example.jpk-force", [], "jpk", 2000.0, 8400, [("extend", 6000), ("retract", 2400)],
     {"cellhesion-height": "m", "height": "m", "deflection": "m", "z_piezo": "m"}),
    ("fmt-jpk-fd_spot3-0192.jpk-force", [], "jpk", 2000.0, 4000, [("extend", 2000), ("retract", 2000)],
     {"height": "m", "deflection": "m", "z_piezo": "m"}),
    ("fmt-jpk-fd_flipsign_2015.05.22-15.31.49.352.jpk-force", [], "jpk", 2000.0, 14000,
     [("extend", 10000), ("retract", 4000)], {"height": "m", "deflection": "m", "z_piezo": "m"}),
    ("fmt-jpk-cl_calibration_force-save-2015.02.04-11.25.21.294.jpk-force", [], "jpk", 204.8, 4096,
     [("extend", 2048), ("retract", 2048)], {"height": "m", "deflection": "V", "z_piezo": "m", "measuredHeight": "m"}),
    ("force-map2x2-example.jpk-force-map", ["--curve", "0"], "jpk-map", 2005.0, 24060,
     [("extend", 12030), ("retract", 12030)],
     {"height": "m", "deflection": "m", "hDeflection": "V", "error": "V", "z_piezo": "m"}),
    ("fmt-jpk-fd_2020.02.07-16.29.05.036.jpk-qi-data", ["--curve", "0,0"], "jpk-qi", 300 / 0.028, 600,
     [("extend", 300), ("retract", 300)], {"height": "m", "deflection": "m", "z_piezo": "m", "smoothedMeasuredHeight": "m"}),
    ("fmt-chiaro-txt_AEBP1_Indentation_002.zip", [], "chiaro", 1000.0, 13827, [],
     {"Load": "uN", "Indentation": "nm", "deflection": "nm", "z_piezo": "nm", "Auxiliary": ""}),
    ("raw1.tdms", [], "tdms", 50000.0, 2000, [],
     {n: "V" for n in ("First  Channel", "Second Chan", "Third Chan", "Fourth Chan", "Fifth Chan", "Sixth Chan",
                       "Seventh Cha")}),
    ("fmt-afm-workshop-fd_single_2018-08-01_13.06.09.csv", RATE_GIVEN, "afm-workshop", 1000.0, 1140,
     [("extend", 570), ("retract", 570)], {"z_piezo": "nm", "deflection": "V"}),
    ("fmt-afm-workshop-fd_single_2021-01-15.csv", RATE_GIVEN, "afm-workshop", 1000.0, 6738,
     [("extend", 3369), ("retract", 3369)], {"z_piezo": "nm", "deflection": "V"}),
    ("fmt-ntmdt-txt-fd_2015_01_17_gel4-0,1_mQ_adh_6B_Curve_DFL_Height_51.txt", RATE_GIVEN, "ntmdt", 1000.0, 1644,
     [("approach", 822), ("retract", 822)], {"z_piezo": "nm", "deflection": "nA"}),
]
#: Files that hold several captures: info lists them (each summarised, or the curves listed).
LISTED = {
    "fmt-jpk-fd_qi-data-2021.04.13.jpk-qi-series": "segments",  # segments at 5 and 50 kHz
    "fmt-jpk-cc_pr14-polymergel-2021.06.30.jpk-force": "segments",  # the pause stores fewer channels
    "force-map2x2-example.jpk-force-map": "curves",
    "fmt-jpk-fd_2020.02.07-16.29.05.036.jpk-qi-data": "curves",
}
#: Files that are no capture at all, refused with that reason.
REFUSED = {"win-textWave.ibw": "holds text", "win-zeroPointWave.ibw": "no points"}


def test_every_file_in_the_folder_is_held_here(shared):
    """Acceptance (issue 32): every data file in ../shared/data/formats is read by a test here (or refused with its reason)."""
    names = {p.name for p in (shared / FORMATS).iterdir() if p.is_file() and p.name != "SOURCES.md"}
    held = {row[0] for row in EXPECTED} | set(LISTED) | set(REFUSED)
    assert names <= held, sorted(names - held)


@pytest.mark.parametrize("row", EXPECTED, ids=[r[0] for r in EXPECTED])
def test_info_on_every_real_file(shared, row):
    name, args, fmt, rate, n, segments, channels = row
    result = run_cli("info", shared / FORMATS / name, "--json", *args)
    assert result.returncode == 0, result.stderr.decode()
    info = json.loads(result.stdout)
    assert info["format"] == fmt
    assert info["sample_rate_hz"] == pytest.approx(rate, rel=1e-9)
    assert info["n_samples"] == n
    assert {c["name"]: c["units"] for c in info["channels"]} == channels
    assert [(s["name"], s["n_samples"]) for s in info["segments"]] == segments


@pytest.mark.parametrize("name", sorted(LISTED))
def test_info_lists_what_a_file_holds(shared, name):
    result = run_cli("info", shared / FORMATS / name, "--json")
    assert result.returncode == 0, result.stderr.decode()
    info = json.loads(result.stdout)
    if LISTED[name] == "curves":
        assert len(info["curves"]) == 4 and all(c["grid_index"] is not None for c in info["curves"])
    else:
        assert isinstance(info, list) and len(info) in (2, 3) and all(s["n_samples"] > 0 for s in info)


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
    if fmt == "ibw":  # no library writes Igor binary waves: a minimal version-5 wave packed here
        path = folder / "ltv.ibw"
        _write_ibw(path, [dither, deflection], [b"dither", b"deflection"], fs)
        return path, ["--units", "dither=V", "--units", "deflection=nm"]
    if fmt == "jpk":  # a JPK force file (format 0.x, float64 channels) in one extend segment
        path = folder / "ltv.jpk-force"
        _write_jpk(path, {"dither": (dither, "V"), "vDeflection": (deflection, "nm")}, fs)
        return path, []
    if fmt == "chiaro":  # an Optics11 Chiaro text export: the real file's header lines, this capture's table
        path = folder / "ltv_chiaro.txt"
        t = np.arange(len(dither)) / fs
        # no Piezo (nm) column: a z_piezo would make reep bin force curves, which the original has not
        table = np.column_stack([t, np.zeros_like(t), np.zeros_like(t), deflection, dither])
        with open(path, "w", encoding="latin-1", newline="") as handle:
            handle.write("Date\t02/12/2026\tTime\t06:00:00\tStatus\tOK\r\nltv\r\n\r\n"
                         "Device:\tChiaro\r\nSoftware version: V3.5.0\r\n\r\n"
                         "Time (s)\tLoad (uN)\tIndentation (nm)\tCantilever (nm)\tAuxiliary\r\n")
            np.savetxt(handle, table, delimiter="\t", fmt="%.17g", newline="\r\n")
        return path, ["--channel", "dither=Auxiliary", "--units", "dither=V"]
    if fmt in _ARRAY_AND_TEXT:
        return _write_array_or_text(fmt, folder, fs, dither, deflection)
    if fmt == "scope-csv":
        path = folder / "ltv_scope.csv"
        t = np.arange(len(dither)) / fs
        with open(path, "w", newline="") as handle:
            handle.write("Time (s),CH1 (V),CH2 (nm)\r\n")
            np.savetxt(handle, np.column_stack([t, dither, deflection]), delimiter=",", fmt="%.17g", newline="\r\n")
        return path, ["--channel", "dither=CH1", "--channel", "deflection=CH2"]
    raise AssertionError(fmt)


_ARRAY_AND_TEXT = ("mat-v5", "mat-v7.3", "npz", "npy", "text")


def _write_array_or_text(fmt: str, folder, fs: float, dither, deflection):
    """The issue-32 formats: MATLAB (scipy.io, hdf5storage), NumPy, and a vendor-style text export."""
    if fmt in ("mat-v5", "mat-v7.3", "npz"):  # a DAQ script's save(): the signals and fs, by their own libraries
        variables = {"dither": dither, "deflection": deflection, "fs": np.float64(fs)}
        path = folder / ("ltv.npz" if fmt == "npz" else "ltv.mat")
        if fmt == "mat-v5":
            from scipy.io import savemat

            savemat(path, variables)
        elif fmt == "mat-v7.3":
            import hdf5storage

            hdf5storage.savemat(str(path), variables, format="7.3", matlab_compatible=True)
        else:
            np.savez(path, **variables)
        return path, []
    if fmt == "npy":  # one (n, 2) array; numpy records no rate
        path = folder / "ltv.npy"
        np.save(path, np.column_stack([dither, deflection]))
        return path, ["--channel", "dither=0", "--channel", "deflection=1", "--sample-rate", repr(fs)]
    if fmt == "text":  # a vendor text export: a preamble, units in the header, ';' and decimal commas
        path = folder / "ltv_export.txt"
        with open(path, "w", encoding="latin-1", newline="") as handle:
            handle.write(f"AFM export\r\nSampling rate, Hz: {fs!r}\r\nOperator = x\r\n\r\n"
                         "dither (V);deflection (nm)\r\n")
            for a, b in zip(dither, deflection):
                handle.write(f"{float(a)!r};{float(b)!r}\r\n".replace(".", ","))
        return path, []
    raise AssertionError(fmt)


def _write_ibw(path, columns, labels, sample_rate_hz):
    """A minimal Igor binary wave, version 5 (Igor Technical Note 003): one 2-D float64 wave, x in s.

    Header fields not listed are zero; the dimension labels name the columns.  igor2 reads
    what it checks: the version, the checksum (the 16-bit words of both headers sum to 0),
    the section sizes and the wave header.
    """
    import struct

    data = np.column_stack(columns).astype("<f8")
    n, m = data.shape
    body = data.tobytes(order="F")  # Igor stores the rows (samples) fastest
    wave_header = b"".join([
        struct.pack("<iIIihh", 0, 0, 0, n * m, 4, 0),  # next, creationDate, modDate, npnts, type (NT_FP64), dLock
        bytes(6), struct.pack("<h", 1), b"capture".ljust(32, b"\0"), bytes(8),  # whpad1, whVersion, bname, whpad2, dFolder
        struct.pack("<4i", n, m, 0, 0), struct.pack("<4d", 1.0 / sample_rate_hz, 1, 1, 1), bytes(32),  # nDim, sfA, sfB
        bytes(4), b"s".ljust(16, b"\0"), bytes(4 + 16 + 4 + 16 + 16 + 4 + 64 + 8 + 8 + 2 + 2 + 8),  # units, rest
    ])
    labels_block = b"".join(label.ljust(32, b"\0") for label in [b"", *labels])
    sizes = struct.pack("<iiii4i4iiii", 320 + len(body), 0, 0, 0, 0, 0, 0, 0, 0, len(labels_block), 0, 0, 0, 0, 0)
    head = struct.pack("<hh", 5, 0) + sizes + wave_header
    assert len(head) == 384
    checksum = (-sum(struct.unpack("<192h", head))) % 65536
    head = struct.pack("<hH", 5, checksum) + head[4:]
    path.write_bytes(head + body + labels_block)


def _write_jpk(path, channels: dict, sample_rate_hz: float) -> None:
    """A JPK force file in the 0.x layout: one segment, each channel float64 with its unit and no scaling."""
    import zipfile

    n = len(next(iter(channels.values()))[0])
    lines = [f"force-segment-header.num-points={n}", f"force-segment-header.duration={n / sample_rate_hz!r}",
             "force-segment-header.settings.style=extend", f"channels.list={' '.join(channels)}"]
    for name, (_, unit) in channels.items():
        lines += [f"channel.{name}.data.type=double", f"channel.{name}.data.file.name=channels/{name}.dat",
                  f"channel.{name}.data.num-points={n}", f"channel.{name}.unit.unit={unit}"]
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("header.properties", "file-format-version=0.12\n")
        archive.writestr("segments/0/segment-header.properties", "\n".join(lines) + "\n")
        for name, (values, _) in channels.items():
            archive.writestr(f"segments/0/channels/{name}.dat", np.asarray(values, dtype=">f8").tobytes())


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
    # the free-air f0' is held against the worst of the model's f0 and the metadata's, and only afmtool's
    # HDF5 carries the lever's metadata: the measured f0' must agree, the reference it was held against need not
    for r in (results_a, results_b):
        if "free_air_check" in r:
            r["free_air_check"] = {k: r["free_air_check"][k] for k in ("f0_hz", "f0_std_hz")}
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


@pytest.mark.long  # 13 CLI runs, about 15 s of CPU
@pytest.mark.parametrize("fmt", ["tdms", "wav", "labone", "scope-csv", "csv", "ros1", "ros2-mcap", "ibw", "jpk", "chiaro",
                                 "mat-v5", "mat-v7.3", "npz", "npy", "text"])
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
    row = next((r for r in EXPECTED if r[0] == name), None)
    args = dict(zip(row[1][::2], row[1][1::2])) if row else {}
    curve = args.get("--curve")
    rate = float(args["--sample-rate"]) if "--sample-rate" in args else None
    with open_capture(shared / FORMATS / name, segment=segment, curve=curve, sample_rate_hz=rate) as reader:
        metadata = json.loads(json.dumps(dict(reader.info.metadata)))
    jsonschema.validate(metadata, load_schema("capture-metadata.schema.json"))
    validate_metadata(metadata)
