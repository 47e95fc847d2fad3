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
