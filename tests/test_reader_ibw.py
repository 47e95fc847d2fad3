"""The Igor .ibw reader on the real Asylum MFP-3D force curve in ../shared/data/formats.

Expected values are SOURCES.md's, and the samples are checked against an
independent read of the same file with igor2 itself.
"""

from __future__ import annotations

import json

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
