"""The Igor .ibw reader on the real Asylum MFP-3D force curve in ../shared/data/formats.

Expected values are SOURCES.md's, and the samples are checked against an
independent read of the same file with igor2 itself.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from afmtool.io.chunks import iter_chunks
from afmtool.io.registry import open_capture
from tests.conftest import run_cli

IBW = "data/formats/fmt-igor-fd_SiN_FD_plot.ibw"


def test_info_on_the_real_force_curve(shared):
    result = run_cli("info", shared / IBW, "--json")
    assert result.returncode == 0, result.stderr.decode()
    info = json.loads(result.stdout)
    assert info["format"] == "ibw"
    assert info["sample_rate_hz"] == 2000.0
    assert info["n_samples"] == 2016
    assert [(c["name"], c["units"]) for c in info["channels"]] == [("raw", "m"), ("deflection", "m"), ("z_piezo", "m")]
    defl = info["channels"][1]
    assert defl["min"] == pytest.approx(-14.1e-9, abs=0.05e-9) and defl["max"] == pytest.approx(5.2e-9, abs=0.05e-9)
    meta = info["metadata"]
    assert meta["cantilever"] == {
        "spring_constant_n_per_m": 1.1841,
        "deflection_sensitivity_nm_per_v": pytest.approx(44.99),
        "f0_hz": 23251.0,
        "q": 139.13,
    }
    assert meta["drive"] == {"frequency_hz": 23251.0, "amplitude_v": 0.11433}
    assert meta["instrument"]["scan_size_m"] == 1e-6
    # Indexes 0,1008,2015: ZSnsr peaks at sample 1008, the approach's last.
    assert [(s["name"], s["start"], s["n_samples"]) for s in info["segments"]] == [
        ("approach", 0, 1009),
        ("retract", 1009, 1007),
    ]


def test_samples_match_igor2(shared):
    from igor2 import binarywave

    wave = binarywave.load(str(shared / IBW))["wave"]["wData"]
    with open_capture(shared / IBW) as reader:
        chunks = list(iter_chunks(reader, reader.info.channel_names, 500))
    for column, name in enumerate(("raw", "deflection", "z_piezo")):
        np.testing.assert_array_equal(np.concatenate([c.data[name] for c in chunks]), wave[:, column].astype(np.float64))
    assert int(np.argmax(wave[:, 2])) == 1008


def test_segment_and_channel_options(shared):
    from igor2 import binarywave

    wave = binarywave.load(str(shared / IBW))["wave"]["wData"]
    result = run_cli("info", shared / IBW, "--json", "--segment", "retract", "--channel", "defl=deflection")
    assert result.returncode == 0, result.stderr.decode()
    info = json.loads(result.stdout)
    assert info["n_samples"] == 1007
    defl = {c["name"]: c for c in info["channels"]}["defl"]
    assert defl["mean"] == pytest.approx(float(np.mean(wave[1009:, 1].astype(np.float64))), rel=1e-12)
    assert info["metadata"]["segment"] == {"name": "retract", "index": 1, "start_sample": 1009}
    by_number = json.loads(run_cli("info", shared / IBW, "--json", "--segment", "0").stdout)
    assert by_number["n_samples"] == 1009


@pytest.mark.parametrize("segment", ["dwell", "2", "-1"])
def test_missing_segment_is_refused(shared, segment):
    result = run_cli("info", shared / IBW, "--segment", segment)
    assert result.returncode == 2
    err = result.stderr.decode()
    assert err.count("\n") == 1 and "no segment" in err and "approach" in err and "Traceback" not in err


@pytest.mark.parametrize("keep", [10, 100, 400, 5000, 30000])
def test_truncated_ibw_is_one_line_exit_2(shared, tmp_path, keep):
    path = tmp_path / "cut.ibw"
    path.write_bytes((shared / IBW).read_bytes()[:keep])
    result = run_cli("info", path)
    assert result.returncode == 2
    err = result.stderr.decode()
    assert err.count("\n") == 1 and str(path) in err and "Igor binary wave" in err, err
    assert result.stdout == b""


@pytest.mark.parametrize("command", ["reep", "probeloss", "decode"])
def test_analyses_take_segment(shared, tmp_path, command):
    result = run_cli(command, shared / IBW, "--segment", "dwell", "--out", tmp_path / "out")
    assert result.returncode == 2 and "no segment 'dwell'" in result.stderr.decode()
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------ every version (issue 32, item 1)

WAVES = "data/formats"


def _igor2(path):
    from igor2 import binarywave

    loaded = binarywave.load(str(path))
    return loaded["version"], loaded["wave"]


@pytest.mark.parametrize("name", ["win-version2.ibw", "win-double.ibw", "win-version5.ibw", "fmt-igor-fd_SiN_FD_plot.ibw"])
def test_every_version_reads_as_igor2_does(shared, name):
    """Versions 2 and 5, float32 and float64: samples bit for bit, name and version as igor2 reads them."""
    path = shared / WAVES / name
    version, wave = _igor2(path)
    with open_capture(path, sample_rate_hz=1000.0) as reader:
        chunks = list(iter_chunks(reader, reader.info.channel_names, 3))
        assert reader.info.metadata["instrument"]["igor_wave_version"] == version
        assert reader.info.metadata["instrument"]["wave"] == wave["wave_header"]["bname"].decode()
        expected = np.asarray(wave["wData"]).reshape(len(wave["wData"]), -1)
        for column, channel in enumerate(reader.info.channel_names):
            got = np.concatenate([c.data[channel] for c in chunks])
            np.testing.assert_array_equal(got, expected[:, column].astype(np.float64))
    if name.startswith("win-"):  # igor2's own tests: the waves hold 5, 4, 3, 2, 1
        np.testing.assert_array_equal(got, [5.0, 4.0, 3.0, 2.0, 1.0])


def _set_checksum(raw: bytearray, at: int, length: int) -> bytearray:
    """Igor's header check: the int16 words of the first ``length`` bytes sum to 0; the checksum is at ``at``."""
    import struct

    struct.pack_into("<h", raw, at, 0)
    words = sum(struct.unpack(f"<{length // 2}h", bytes(raw[:length])))
    struct.pack_into("<h", raw, at, ((-words + 32768) % 65536) - 32768)
    return raw


def _retyped(raw: bytes, version: int) -> bytes:
    """win-version2.ibw rewritten as a version-1 or version-3 wave (TN003 headers), checksum fixed."""
    import struct

    wfm, note, pict, _ = struct.unpack_from("<iiih", raw, 2)
    wave = raw[16 : 16 + wfm]
    if version == 1:  # BinHeader1: version, wfmSize, checksum; no note
        head = bytearray(struct.pack("<hih", 1, wfm, 0) + wave)
        return bytes(_set_checksum(head, 6, 8 + 126))
    head = bytearray(struct.pack("<hiiiih", 3, wfm, note, 0, pict, 0) + wave)  # BinHeader3 adds formulaSize
    return bytes(_set_checksum(head, 18, 20 + 126)) + raw[16 + wfm : 16 + wfm + note]


@pytest.mark.parametrize("version", [1, 3])
def test_versions_1_and_3(shared, tmp_path, version):
    """No real v1 or v3 wave is at hand: win-version2's wave under a v1 and a v3 header, held to igor2."""
    path = tmp_path / f"v{version}.ibw"
    path.write_bytes(_retyped((shared / WAVES / "win-version2.ibw").read_bytes(), version))
    got_version, wave = _igor2(path)
    assert got_version == version
    info = _cli_info(path, "--sample-rate", "10")
    assert info["n_samples"] == 5 and info["channels"][0]["name"] == "version2"
    assert info["channels"][0]["mean"] == pytest.approx(float(np.mean(wave["wData"])))
    assert info["metadata"]["instrument"]["igor_wave_version"] == version


def _cli_info(path, *args):
    result = run_cli("info", path, "--json", *args)
    assert result.returncode == 0, result.stderr.decode()
    return json.loads(result.stdout)


def _patched_v2(shared, tmp_path, x_units: bytes, step: float):
    """win-version2.ibw with x units and the x step hsA set, its checksum fixed."""
    import struct

    raw = bytearray((shared / WAVES / "win-version2.ibw").read_bytes())
    raw[16 + 38 : 16 + 42] = x_units.ljust(4, b"\0")
    struct.pack_into("<d", raw, 16 + 48, step)
    path = tmp_path / "timed.ibw"
    path.write_bytes(bytes(_set_checksum(raw, 14, 142)))
    return path


def test_version_2_rate_from_hsA_in_seconds(shared, tmp_path):
    """Versions 1-3 carry hsA and xUnits (not sfA and dimUnits): the rate is 1/hsA when x is in s."""
    info = _cli_info(_patched_v2(shared, tmp_path, b"s", 2e-6))
    assert info["sample_rate_hz"] == pytest.approx(5e5, rel=1e-12)
    info = _cli_info(_patched_v2(shared, tmp_path, b"ms", 0.5))
    assert info["sample_rate_hz"] == pytest.approx(2000.0, rel=1e-12)
    refused = run_cli("info", _patched_v2(shared, tmp_path, b"nm", 2e-6))
    err = refused.stderr.decode()
    assert refused.returncode == 2 and err.count("\n") == 1 and "give --sample-rate" in err and "'nm'" in err


def test_version_2_with_a_damaged_checksum_is_refused(shared, tmp_path):
    path = _patched_v2(shared, tmp_path, b"s", 2e-6)
    raw = bytearray(path.read_bytes())
    raw[16 + 48] ^= 0x01  # hsA changed, checksum not
    path.write_bytes(bytes(raw))
    result = run_cli("info", path)
    assert result.returncode == 2 and "checksum" in result.stderr.decode() and result.stdout == b""


@pytest.mark.parametrize("name, reason", [("win-textWave.ibw", "holds text"), ("win-zeroPointWave.ibw", "no points")])
def test_text_and_empty_waves_are_refused_clearly(shared, tmp_path, name, reason):
    result = run_cli("convert", shared / WAVES / name, tmp_path / "out.h5")
    err = result.stderr.decode()
    assert result.returncode == 2 and err.count("\n") == 1 and reason in err and name in err, err
    assert not (tmp_path / "out.h5").exists()


# ------------------------------------------------------------------ hostile notes and strings (issue 34)

def _with_note(shared, tmp_path, note: bytes, units: bytes | None = None) -> Path:
    """The real MFP-3D force curve with its note replaced (and its data units), sizes and checksum fixed."""
    import struct

    raw = (shared / IBW).read_bytes()
    sizes = list(struct.unpack_from("<hhiiii4i4iiii", raw, 0))
    wfm, formula, note_size, units_size = sizes[2], sizes[3], sizes[4], sizes[5]
    data_end = 64 + wfm
    old_note_at = data_end + formula
    rest = raw[old_note_at + note_size + units_size :]
    new_units = b"" if units is None else units
    sizes[4], sizes[5] = len(note), len(new_units)
    head = _set_checksum(bytearray(struct.pack("<hhiiii4i4iiii", *sizes) + raw[64:384]), 2, 384)
    path = tmp_path / "noted.ibw"
    path.write_bytes(bytes(head) + raw[384:old_note_at] + note + new_units + rest)
    return path


@pytest.mark.parametrize("indexes", [b"0,inf,2015", b"0,1e400,2015", b"0,nan,2015", b"0,10.5,2015"])
@pytest.mark.parametrize("command", ["info", "convert", "invols"])
def test_note_with_infinite_indexes_is_one_line(shared, tmp_path, indexes, command):
    """Issue 34: Indexes 'inf' gave OverflowError on info, convert and identify invols."""
    path = _with_note(shared, tmp_path, b"SpringConstant: 1.2\rIndexes: " + indexes + b"\rDirection: inf,1,-1\r")
    args = {"info": ["info", path], "convert": ["convert", path, tmp_path / "o.h5"],
            "invols": ["identify", "invols", path, "--out", tmp_path / "inv"]}[command]
    result = run_cli(*args)
    err = result.stderr.decode()
    assert result.returncode == 2 and err.count("\n") == 1 and "Indexes" in err and "Traceback" not in err, err
    assert result.stdout == b"" and not (tmp_path / "o.h5").exists() and not (tmp_path / "inv").exists()


@pytest.mark.serial
def test_a_64_mb_note_is_read_in_bounded_time_and_memory(shared, tmp_path):
    """Issue 34: a 64 MB note took igor2 35 s and more than 6 GB; only the first MiB is parsed now."""
    import subprocess
    import sys
    import time

    from tests.conftest import REPO

    note = b"".join(b"Key%d: %d\r" % (i, i) for i in range(4_200_000))[: 64 << 20] + b"\rSpringConstant: 2.5\r"
    path = _with_note(shared, tmp_path, b"SpringConstant: 1.5\r" + note)
    # a wrapper process whose only child is the run, so that its children's peak RSS is the run's own
    wrapper = ("import resource, subprocess, sys; r = subprocess.run(sys.argv[1:], capture_output=True); "
               "sys.stdout.write(r.stdout.decode() + chr(10) + str(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)); "
               "sys.stderr.write(r.stderr.decode()); sys.exit(r.returncode)")
    start = time.monotonic()
    result = subprocess.run([sys.executable, "-c", wrapper, sys.executable, "-m", "afmtool", "info", str(path), "--json"],
                            cwd=REPO, capture_output=True, timeout=120)
    elapsed = time.monotonic() - start
    output, _, peak_kb = result.stdout.decode().rpartition("\n")
    assert result.returncode == 0, result.stderr.decode()
    assert json.loads(output)["metadata"]["cantilever"]["spring_constant_n_per_m"] == 1.5
    assert "note is" in result.stderr.decode()  # said once, as a warning
    assert elapsed < 20 and int(peak_kb) < 500_000, (elapsed, peak_kb)  # igor2: 35 s and more than 6 GB


@pytest.mark.parametrize("units", [b"m\x00V", b"\xff\xfem\x00\x00\x00", b"n\x00m\x00", b"\xb5m"])
def test_units_with_nul_or_utf16_convert(shared, tmp_path, units):
    """Issue 34: a NUL in a unit string ended convert in 'VLEN strings do not support embedded NULLs'."""
    path = _with_note(shared, tmp_path, b"SpringConstant: 1.5\r", units=units)
    for target in (tmp_path / "o.h5", tmp_path / "o.csv"):
        result = run_cli("convert", path, target)
        assert result.returncode == 0, result.stderr.decode()
        info = _cli_info(target)
        assert all(c["units"] in ("mV", "m", "nm", "µm") and c["units"].isprintable() for c in info["channels"])
