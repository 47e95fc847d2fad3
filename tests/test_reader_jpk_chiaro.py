"""JPK and Optics11 Chiaro readers on the real files in ../shared/data/formats.

Expected values are SOURCES.md's; samples are checked against afmformats
(an independent reader of both formats) where it is installed, and the
Chiaro table against a plain parse of the exported text.
"""

from __future__ import annotations

import json
import zipfile

import numpy as np
import pytest

from afmtool.io.chunks import iter_chunks
from afmtool.io.registry import open_capture
from tests.conftest import run_cli

FORMATS = "data/formats"
FORCE_SAVE = f"{FORMATS}/force-save-example.jpk-force"
SPOT3 = f"{FORMATS}/fmt-jpk-fd_spot3-0192.jpk-force"
QI = f"{FORMATS}/fmt-jpk-fd_qi-data-2021.04.13.jpk-qi-series"
CHIARO = f"{FORMATS}/fmt-chiaro-txt_AEBP1_Indentation_002.zip"


def _info(path, *args):
    result = run_cli("info", path, "--json", *args)
    assert result.returncode == 0, result.stderr.decode()
    return json.loads(result.stdout)


def _read(path, **kwargs):
    with open_capture(path, **kwargs) as reader:
        chunks = list(iter_chunks(reader, reader.info.channel_names, 999))
        return reader.info, {n: np.concatenate([c.data[n] for c in chunks]) for n in reader.info.channel_names}


def test_force_save_example(shared):
    info = _info(shared / FORCE_SAVE)
    assert info["format"] == "jpk" and info["sample_rate_hz"] == 2000.0 and info["n_samples"] == 8400
    units = {c["name"]: c["units"] for c in info["channels"]}
    # the capacitive sensor's measured height is the z-piezo (issue 32: the measured height is preferred)
    assert units == {"cellhesion-height": "m", "height": "m", "deflection": "m", "z_piezo": "m"}
    assert info["metadata"]["instrument"]["z_piezo_from"] == "capacitiveSensorHeight"
    assert [(s["name"], s["start"], s["n_samples"], s["sample_rate_hz"]) for s in info["segments"]] == [
        ("extend", 0, 6000, 2000.0),
        ("retract", 6000, 2400, 2000.0),
    ]
    cantilever = info["metadata"]["cantilever"]
    assert cantilever["spring_constant_n_per_m"] == pytest.approx(0.0223007, rel=1e-5)
    assert cantilever["deflection_sensitivity_nm_per_v"] == pytest.approx(91.207, rel=1e-4)
    assert info["metadata"]["instrument"]["instrument"] == "JPK00758-CellHesion-200"


def test_old_format_spot3(shared):
    info = _info(shared / SPOT3)
    assert info["n_samples"] == 4000 and info["sample_rate_hz"] == pytest.approx(2000.0, rel=1e-12)
    assert [c["name"] for c in info["channels"]] == ["height", "deflection", "z_piezo"]  # strainGaugeHeight
    assert [(s["name"], s["n_samples"]) for s in info["segments"]] == [("extend", 2000), ("retract", 2000)]
    assert info["metadata"]["cantilever"]["spring_constant_n_per_m"] == pytest.approx(0.0434937, rel=1e-5)
    assert info["metadata"]["cantilever"]["deflection_sensitivity_nm_per_v"] == pytest.approx(70.001, rel=1e-4)
    assert info["metadata"]["instrument"]["file_format_version"] == "0.12"


def test_qi_segments_at_different_rates(shared, tmp_path):
    # info lists and summarises each segment; an analysis must be told which one to read
    listed = run_cli("info", shared / QI)
    assert listed.returncode == 0, listed.stderr.decode()
    text = listed.stdout.decode()
    assert "segment 0 extend" in text and "segment 1 retract" in text
    assert "5,000 Hz, 1,000 samples" in text and "50,000 Hz, 1,000 samples" in text
    both = _info(shared / QI)
    assert [(s["sample_rate_hz"], s["n_samples"]) for s in both] == [(5000.0, 1000), (50000.0, 1000)]
    refused = run_cli("reep", shared / QI, "--out", tmp_path / "out", "--no-input")
    assert refused.returncode == 2 and not (tmp_path / "out").exists()
    err = refused.stderr.decode()
    assert err.count("\n") == 1 and "different rates" in err and "extend (1000 samples, 5000 Hz)" in err
    assert "retract (1000 samples, 50000 Hz)" in err
    extend, retract = _info(shared / QI, "--segment", "extend"), _info(shared / QI, "--segment", "1")
    assert (extend["sample_rate_hz"], extend["n_samples"]) == (5000.0, 1000)
    assert (retract["sample_rate_hz"], retract["n_samples"]) == (50000.0, 1000)
    names = [c["name"] for c in retract["channels"]]
    assert len(names) == 13 and "time" in names and "seriesTime" in names and "deflection" in names
    time = {c["name"]: c for c in retract["channels"]}["time"]
    assert time["units"] == "s" and time["min"] == pytest.approx(1e-5) and time["max"] == pytest.approx(0.01999)
    assert retract["metadata"]["cantilever"]["spring_constant_n_per_m"] == pytest.approx(35.028)
    assert retract["metadata"]["cantilever"]["deflection_sensitivity_nm_per_v"] == pytest.approx(9.76)


@pytest.mark.parametrize("name", [FORCE_SAVE, SPOT3, QI])
def test_deflection_times_k_is_afmformats_force(shared, name):
    afmformats = pytest.importorskip("afmformats")
    curve = afmformats.load_data(str(shared / name))[0]
    segments = ["extend", "retract"]
    parts = []
    for segment in segments:
        info, data = _read(shared / name, segment=segment)
        parts.append(data["deflection"] * info.metadata["cantilever"]["spring_constant_n_per_m"])
    force = np.concatenate(parts)
    np.testing.assert_allclose(force, curve["force"], rtol=1e-9, atol=1e-18)
    assert int(np.sum(curve["segment"])) == len(parts[1])


def test_truncated_jpk_is_refused(shared, tmp_path):
    data = (shared / FORCE_SAVE).read_bytes()
    for keep in (100, 5000, 60000, len(data) - 100):
        path = tmp_path / f"cut{keep}.jpk-force"
        path.write_bytes(data[:keep])
        result = run_cli("info", path)
        assert result.returncode == 2, keep
        assert result.stderr.decode().count("\n") == 1 and str(path) in result.stderr.decode()


def test_damaged_member_is_refused(shared, tmp_path):
    """A .dat of the wrong size (a hand-edited archive) is refused, not read short."""
    source = zipfile.ZipFile(shared / SPOT3)
    path = tmp_path / "edited.jpk-force"
    with zipfile.ZipFile(path, "w") as target:
        for item in source.infolist():
            body = source.read(item)
            if item.filename.endswith("segments/1/channels/vDeflection.dat"):
                body = body[:-2]
            target.writestr(item, body)
    result = run_cli("info", path)
    assert result.returncode == 2 and "vDeflection.dat holds" in result.stderr.decode()


def test_chiaro_export(shared):
    info = _info(shared / CHIARO)
    assert info["format"] == "chiaro" and info["sample_rate_hz"] == pytest.approx(1000.0, rel=1e-9)
    assert info["n_samples"] == 13827 and info["duration_s"] == pytest.approx(13.827)
    assert [(c["name"], c["units"]) for c in info["channels"]] == [
        ("Load", "uN"),
        ("Indentation", "nm"),
        ("deflection", "nm"),
        ("z_piezo", "nm"),
        ("Auxiliary", ""),
    ]
    assert info["metadata"]["cantilever"] == {"spring_constant_n_per_m": 0.019}
    assert info["metadata"]["instrument"]["software_version"] == "V3.5.0"


def test_chiaro_samples_match_a_plain_parse(shared, tmp_path):
    with zipfile.ZipFile(shared / CHIARO) as archive:
        raw = archive.read(archive.namelist()[0])
    text = raw.decode("latin-1")
    assert "\xb5" in text and b"\r\n" in raw and b"\n\r" in raw  # the file is what SOURCES.md says
    lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    start = next(i for i, line in enumerate(lines) if line.startswith("Time (s)\t"))
    table = np.array([[float(v) for v in line.split("\t")] for line in lines[start + 1 :] if line.strip()])
    _, data = _read(shared / CHIARO)
    np.testing.assert_array_equal(data["deflection"], table[:, 3])
    np.testing.assert_array_equal(data["z_piezo"], table[:, 4])
    # The .txt itself, outside its zip, reads the same.
    (tmp_path / "export.txt").write_bytes(raw)
    _, from_text = _read(tmp_path / "export.txt")
    np.testing.assert_array_equal(from_text["Load"], table[:, 1])


def test_text_that_is_not_a_table_is_refused(tmp_path):
    """A .txt that is neither a Chiaro export nor a table of numbers: one line, exit 2."""
    (tmp_path / "notes.txt").write_text("hello\nworld\n")
    result = run_cli("info", tmp_path / "notes.txt")
    err = result.stderr.decode()
    assert result.returncode == 2 and err.count("\n") == 1 and "notes.txt" in err and result.stdout == b"", err


def test_zip_bomb_member_is_refused(shared, tmp_path):
    """A channel claiming 5 million samples that bzip2 packs into a few hundred bytes is refused before reading."""
    source = zipfile.ZipFile(shared / SPOT3)
    path = tmp_path / "bomb.jpk-force"
    n = 5_000_000
    with zipfile.ZipFile(path, "w") as target:
        for item in source.infolist():
            body = source.read(item)
            if item.filename.startswith("segments/0/"):
                if item.filename.endswith("segment-header.properties"):
                    body = body.replace(b"num-points=2000", f"num-points={n}".encode())
                    body = body.replace(b"duration=0.9999999999999998", b"duration=50000")
                elif item.filename.endswith(".dat"):
                    body = bytes(2 * n)
            target.writestr(item.filename, body, compress_type=zipfile.ZIP_BZIP2 if body[:1] == b"\0" else None)
    result = run_cli("info", path)
    assert result.returncode == 2 and "ZIP bomb" in result.stderr.decode(), result.stderr.decode()


# ------------------------------------------------------------------ issue 32: indirections, mixed segments, maps

FLIPSIGN = f"{FORMATS}/fmt-jpk-fd_flipsign_2015.05.22-15.31.49.352.jpk-force"
CREEP = f"{FORMATS}/fmt-jpk-cc_pr14-polymergel-2021.06.30.jpk-force"
CALIBRATION = f"{FORMATS}/fmt-jpk-cl_calibration_force-save-2015.02.04-11.25.21.294.jpk-force"
MAP = f"{FORMATS}/force-map2x2-example.jpk-force-map"
QI_DATA = f"{FORMATS}/fmt-jpk-fd_2020.02.07-16.29.05.036.jpk-qi-data"


def test_segment_style_through_the_shared_header(shared, tmp_path):
    """Each segment header points into the shared header (force-segment-header-info.*=N); the style
    lives there.  Before: segments 'segment0'/'segment1', and --segment retract failed."""
    info = _info(shared / FLIPSIGN)
    assert [(s["name"], s["n_samples"]) for s in info["segments"]] == [("extend", 10000), ("retract", 4000)]
    retract = _info(shared / FLIPSIGN, "--segment", "retract")
    assert retract["n_samples"] == 4000 and retract["metadata"]["segment"]["name"] == "retract"
    with zipfile.ZipFile(shared / FLIPSIGN) as archive:
        segment = archive.read("segments/1/segment-header.properties").decode("latin-1")
    assert "force-segment-header.force-segment-header-info.*=1" in segment and "settings.style" not in segment


def test_indirections_resolve_as_the_format_defines():
    from afmtool.io.jpk import _shared_groups, resolve_indirections

    shared = {"lcd-info.0.type": "integer-data", "lcd-info.0.unit.unit": "V", "lcd-info.1.type": "short",
              "info.3.style": "extend", "info.3.nested.lcd-info.*": "1", "lcd-info.10.type": "float"}
    props = {"channel.h.lcd-info.*": "0", "channel.h.unit.unit": "m", "seg.info.*": "3", "channel.x.lcd-info.*": "10"}
    resolved = resolve_indirections(props, _shared_groups(shared), "test")
    assert resolved == {"channel.h.type": "integer-data", "channel.h.unit.unit": "m",  # the header's own key wins
                        "seg.style": "extend", "seg.nested.type": "short", "channel.x.type": "float"}


@pytest.mark.parametrize("shared_keys, message", [
    ({"a.1.a.*": "1"}, "cycle"),  # a group that points to itself
    ({"a.1.b.*": "2", "b.2.a.*": "1"}, "cycle"),  # two groups that point to each other
    ({**{f"m{i}.0.m{i + 1}.*": "0" for i in range(20)}}, "deep"),
    ({}, "points to no"),
])
def test_indirections_that_cannot_resolve_are_one_line(shared_keys, message):
    from afmtool.errors import InputError
    from afmtool.io.jpk import _shared_groups, resolve_indirections

    start = {"x.a.*": "1"} if "a.1.b.*" in shared_keys or "a.1.a.*" in shared_keys else {"x.m0.*": "0"} if "m0.0.m1.*" in shared_keys else {"x.q.*": "7"}
    with pytest.raises(InputError, match=message):
        resolve_indirections(start, _shared_groups(shared_keys), "test")


def test_segments_with_different_channels_are_listed_segment_by_segment(shared, tmp_path):
    """Creep compliance: the pause stores fewer channels.  Before: info and convert refused the whole file."""
    listed = run_cli("info", shared / CREEP)
    assert listed.returncode == 0, listed.stderr.decode()
    assert all(f"segment {i} {name}" in listed.stdout.decode() for i, name in enumerate(("extend", "pause", "retract")))
    summaries = _info(shared / CREEP)
    assert [len(s["channels"]) for s in summaries] == [5, 3, 5] and all(s["n_samples"] == 3000 for s in summaries)
    refused = run_cli("reep", shared / CREEP, "--out", tmp_path / "out")
    err = refused.stderr.decode()
    assert refused.returncode == 2 and err.count("\n") == 1 and "different channels" in err and "pause" in err, err
    assert not (tmp_path / "out").exists()
    for segment in ("extend", "pause", "retract"):  # every segment reads exactly, as afmformats reads it
        result = run_cli("convert", shared / CREEP, tmp_path / f"{segment}.h5", "--segment", segment)
        assert result.returncode == 0, result.stderr.decode()


def test_creep_segments_match_afmformats(shared):
    afmformats = pytest.importorskip("afmformats")
    curve = afmformats.load_data(str(shared / CREEP))[0]
    parts = {s: _read(shared / CREEP, segment=s)[1] for s in ("extend", "pause", "retract")}
    z = np.concatenate([parts[s]["z_piezo"] for s in ("extend", "pause", "retract")])
    np.testing.assert_array_equal(z, curve["height (measured)"])
    k = curve.metadata["spring constant"]
    force = np.concatenate([parts[s]["deflection"] for s in ("extend", "pause", "retract")]) * k
    np.testing.assert_allclose(force, curve["force"], rtol=1e-12, atol=0)


@pytest.mark.parametrize("name, source", [(SPOT3, "strainGaugeHeight"), (FORCE_SAVE, "capacitiveSensorHeight"),
                                          (FLIPSIGN, "capacitiveSensorHeight"), (CALIBRATION, "capacitiveSensorHeight")])
def test_measured_height_is_z_piezo(shared, name, source):
    """The sensor height (afmformats' 'height (measured)') is z_piezo; the piezo's own 'height' keeps its name."""
    afmformats = pytest.importorskip("afmformats")
    info, data = _read(shared / name)
    assert info.metadata["instrument"]["z_piezo_from"] == source
    if name != CALIBRATION:  # no spring constant: afmformats refuses it
        curve = afmformats.load_data(str(shared / name))[0]
        np.testing.assert_array_equal(data["z_piezo"], curve["height (measured)"])
        np.testing.assert_array_equal(data["height"], curve["height (piezo)"])
    chosen = _read(shared / name, channel_map={"z_piezo": "height"})[1]  # --channel z_piezo=height
    np.testing.assert_array_equal(chosen["z_piezo"], data["height"])


def test_invols_without_z_channel_on_a_jpk_curve(shared, tmp_path):
    """Before: identify invols on a JPK curve needed --z-channel height."""
    result = run_cli("identify", "invols", shared / SPOT3, "--segment", "extend", "--out", tmp_path / "inv", "--json")
    assert result.returncode == 0, result.stderr.decode()


def test_map_lists_its_curves_and_grid_cells(shared):
    """afmformats' own test of this map numbers the curves' grid x 0, 9, 9, 0."""
    listing = _info(shared / MAP)
    assert listing["format"] == "jpk-map" and listing["grid_shape"] == [10, 10]
    assert [(c["curve"], tuple(c["grid_index"])) for c in listing["curves"]] == [(0, (0, 0)), (1, (9, 0)), (2, (9, 9)),
                                                                                 (3, (0, 9))]
    text = run_cli("info", shared / MAP).stdout.decode()
    assert "4 curves on a 10 x 10 grid" in text and "--curve" in text


def test_qi_data_matches_afmformats(shared):
    """afmformats' test_fmt_jpk_qi.py: force[0], height[0], grid x 0..3 (y 0), instrument and software of curve 3."""
    afmformats = pytest.importorskip("afmformats")
    listing = _info(shared / QI_DATA)
    assert [tuple(c["grid_index"]) for c in listing["curves"]] == [(0, 0), (1, 0), (2, 0), (3, 0)]
    info, data = _read(shared / QI_DATA, curve="0")
    k = info.metadata["cantilever"]["spring_constant_n_per_m"]
    assert data["deflection"][0] * k == pytest.approx(-1.269014596090597e-10, rel=1e-12)
    assert data["z_piezo"][0] == pytest.approx(4.716154783699957e-06, rel=1e-12)
    last = _info(shared / QI_DATA, "--curve", "3,0")
    assert last["metadata"]["instrument"]["instrument"] == "JPK01496-H-18-0132"
    assert last["metadata"]["instrument"]["software_version"] == "6.1.157"
    assert last["metadata"]["curve"]["curve"] == 3
    curves = afmformats.load_data(str(shared / QI_DATA))
    for index, curve in enumerate(curves):
        _, data = _read(shared / QI_DATA, curve=str(index))
        np.testing.assert_array_equal(data["z_piezo"], curve["height (measured)"])


def test_map_curves_match_afmformats(shared):
    afmformats = pytest.importorskip("afmformats")
    curves = afmformats.load_data(str(shared / MAP))
    for index, curve in enumerate(curves):
        cell = f"{curve.metadata['grid index x']},{curve.metadata['grid index y']}"
        info, data = _read(shared / MAP, curve=cell)  # by grid cell, as afmformats numbers it
        assert info.metadata["curve"]["curve"] == index
        np.testing.assert_array_equal(data["z_piezo"], curve["height (measured)"])
        k = info.metadata["cantilever"]["spring_constant_n_per_m"]
        np.testing.assert_allclose(data["deflection"] * k, curve["force"], rtol=1e-12, atol=0)


@pytest.mark.parametrize("choice", ["4", "5,5", "x", "-1"])
def test_curve_that_does_not_exist(shared, tmp_path, choice):
    for command in (["info", shared / MAP, "--curve", choice], ["convert", shared / MAP, tmp_path / "c.h5", "--curve", choice]):
        result = run_cli(*command)
        err = result.stderr.decode()
        assert result.returncode == 2 and err.count("\n") == 1 and "no curve" in err and "0 (0,0)" in err, err
    assert not (tmp_path / "c.h5").exists()


def test_curve_on_a_single_curve_file_and_group_on_jpk_are_refused(shared):
    result = run_cli("info", shared / SPOT3, "--curve", "0")
    assert result.returncode == 2 and "not a map" in result.stderr.decode()
    result = run_cli("info", shared / SPOT3, "--group", "a")
    assert result.returncode == 2 and "--group selects a group of a TDMS file" in result.stderr.decode()


@pytest.mark.parametrize("name, curve", [(MAP, "2"), (QI_DATA, "1,0")])
def test_identify_invols_on_a_map_curve(shared, tmp_path, name, curve):
    """Acceptance: identify invols on a JPK force-map curve and on a QI curve."""
    out = tmp_path / "invols"
    result = run_cli("identify", "invols", shared / name, "--curve", curve, "--segment", "extend", "--out", out, "--json")
    assert result.returncode == 0, result.stderr.decode()
    report = json.loads(result.stdout)
    results = report["results"]
    assert np.isfinite(results["contact_slope"]) and results["points"] > 100, results  # a cell or a gel: no slope of 1
    assert report["inputs"][0]["path"].endswith(name.split("/")[-1])
    convert = run_cli("convert", shared / name, tmp_path / "curve.h5", "--curve", curve)
    assert convert.returncode == 0, convert.stderr.decode()
    assert _info(tmp_path / "curve.h5")["metadata"]["curve"]["curve"] in (1, 2)


def test_header_declaring_30000_channels_is_refused_at_once(shared, tmp_path):
    """Issue 34: a 565 KB JPK file declaring 30,000 channels took 418 s (quadratic in the channel count)."""
    import time

    path = tmp_path / "many.jpk-force"
    names = [f"c{i}" for i in range(30000)]
    lines = ["force-segment-header.num-points=10", "force-segment-header.duration=0.01", f"channels.list={' '.join(names)}"]
    lines += [f"channel.{n}.data.type=short\nchannel.{n}.data.num-points=10" for n in names]
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("header.properties", "file-format-version=0.12\n")
        archive.writestr("segments/0/segment-header.properties", "\n".join(lines) + "\n")
    start = time.monotonic()
    result = run_cli("info", path)
    assert result.returncode == 2 and "30000 channels" in result.stderr.decode()
    assert time.monotonic() - start < 5 + 3  # the CLI's own start-up is about 1-2 s of it


def test_opening_is_linear_in_the_channel_count(tmp_path):
    """Channels declared up to the limit: doubling them at most about doubles the time to open."""

    from afmtool.io.jpk import MAX_CHANNELS, JpkReader

    def build(count):
        path = tmp_path / f"c{count}.jpk-force"
        names = [f"c{i}" for i in range(count)]
        lines = ["force-segment-header.num-points=4", "force-segment-header.duration=0.004",
                 f"channels.list={' '.join(names)}"]
        lines += [f"channel.{n}.data.type=short\nchannel.{n}.data.num-points=4\n"
                  f"channel.{n}.conversion-set.conversions.base=volts" for n in names]
        with zipfile.ZipFile(path, "w") as archive:
            archive.writestr("header.properties", "file-format-version=0.12\n")
            archive.writestr("segments/0/segment-header.properties", "\n".join(lines) + "\n")
            for n in names:
                archive.writestr(f"segments/0/channels/{n}.dat", bytes(8))
        return path

    times = {}
    for count in (MAX_CHANNELS // 4, MAX_CHANNELS):
        path = build(count)
        best = min(_timed(JpkReader, path) for _ in range(3))
        times[count] = best
    assert times[MAX_CHANNELS] < 4 * times[MAX_CHANNELS // 4] * 2.5, times  # linear (x4), with room for noise


def _timed(reader_class, path):
    import time

    start = time.perf_counter()
    reader_class(path).close()
    return time.perf_counter() - start
