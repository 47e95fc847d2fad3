"""``afmtool kalman-bank`` end to end: files, report, routes, golden report on the bundled force curves."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from tests.conftest import SAMPLE_DATA, run_cli, validate_report
from tests.golden import assert_matches_golden

#: The thesis-rate force curve (§3.4.3 attractive set, 0.4 s): the verdict passes.
CAPTURE = SAMPLE_DATA / "force_curve_thesis.h5"
#: The short REEP sample (28 nm in 24 ms): REEP's window spans about a bin of z.
FAST_CAPTURE = SAMPLE_DATA / "tapping_force_curve.h5"


@pytest.fixture(scope="module")
def internal(tmp_path_factory):
    out = tmp_path_factory.mktemp("kb") / "bank"
    result = run_cli("kalman-bank", CAPTURE, "--out", out, "--json", "--quiet")
    assert result.returncode == 0, result.stderr.decode()
    return out, json.loads(result.stdout)


def test_golden_report(internal):
    out, report = internal
    validate_report(report)
    assert json.loads((out / "report.json").read_text()) == report
    assert_matches_golden(report, "kalman_bank_force_curve_thesis")
    assert report["results"]["verdict"]["pass"] is True
    assert report["results"]["adaptive"]["fraction_lowest"] >= 0.9


def test_outputs(internal):
    out, report = internal
    assert set(report["outputs"]) == {"bank.h5", "bank_rms_vs_time.png", "bank_rms_vs_z.png", "config.toml", "report.json"}
    assert (out / "bank_rms_vs_z.png").stat().st_size > 20_000
    n_filters = len(report["results"]["filters"])
    with h5py.File(out / "bank.h5") as f:
        n = f["t"].shape[0]
        assert f["rms"].shape == (n_filters, n)
        for name in ("z", "adaptive_rms", "reep_f0_hz", "reep_q"):
            assert f[name].shape == (n,)
        assert f["z"].attrs["units"] == "nm" and f["rms"].attrs["units"] == "nm"
        assert f["models/f0_hz"].shape == (n_filters,)
        assert f["force_curve/approach/rms"].shape[0] == n_filters
        np.testing.assert_allclose(f["models/design_z"][()], [g["design_z"] for g in report["results"]["filters"]])
        assert n == report["results"]["n_samples"] // report["results"]["decimate"]


def test_fast_ramp_fails_and_says_why(tmp_path):
    # tapping_force_curve.h5 ramps 28 nm in 24 ms: REEP's 200-sample window spans about a bin of z,
    # the adaptive observer misses the 90 % criterion, and the report says why
    result = run_cli("kalman-bank", FAST_CAPTURE, "--out", tmp_path / "kb", "--json", "-q")
    assert result.returncode == 0, result.stderr.decode()
    report = json.loads(result.stdout)
    assert report["results"]["adaptive"]["pass"] is False
    assert report["results"]["verdict"]["pass"] is False
    assert any("spans" in r and "bins" in r for r in report["results"]["verdict"]["reasons"])


def test_reep_file_route_matches_internal(internal, tmp_path):
    _, inner = internal
    assert run_cli("reep", CAPTURE, "--out", tmp_path / "reep", "-q").returncode == 0
    result = run_cli("kalman-bank", CAPTURE, "--reep", tmp_path / "reep", "--out", tmp_path / "kb", "--json", "-q")
    assert result.returncode == 0, result.stderr.decode()
    report = json.loads(result.stdout)
    validate_report(report)
    # the same REEP estimates and the same binning give the same design points and models
    for a, b in zip(report["results"]["filters"], inner["results"]["filters"], strict=True):
        assert a["design_z"] == b["design_z"]
        # reep.h5 stores f0' and Q' as float32 (issue 33): the binned model agrees to float32's 6e-8
        assert a["f0_hz"] == pytest.approx(b["f0_hz"], rel=1e-6)
    assert report["results"]["reep"]["coefficients"].startswith("held")
    # holding the decimated estimates changes the adaptive observer's RMS only a little
    assert report["results"]["adaptive"]["fraction_lowest"] == pytest.approx(
        inner["results"]["adaptive"]["fraction_lowest"], abs=0.05
    )
    assert {"capture", "reep series"} <= {i["role"] for i in report["inputs"]}


def test_negative_control_fails_with_reasons(tmp_path):
    result = run_cli("kalman-bank", CAPTURE, "--out", tmp_path / "kb", "--json", "-q", "--f0-scale", "1.02")
    assert result.returncode == 0, result.stderr.decode()
    report = json.loads(result.stdout)
    verdict = report["results"]["verdict"]
    assert verdict["pass"] is False
    assert report["results"]["design"]["f0_scale"] == 1.02
    assert any(w.startswith("verdict FAIL") for w in report["warnings"])
    assert all("design bin" in r for r in verdict["reasons"][:5])


def test_stdin_runs_the_bank_as_the_file_does(tmp_path):
    # the capture is read once (pass 2 reads a spill of it), so a stream needs no --reep
    csv = tmp_path / "curve.csv"
    converted = run_cli("convert", FAST_CAPTURE, csv, "--format", "csv")
    assert converted.returncode == 0, converted.stderr.decode()
    from_file = run_cli("kalman-bank", csv, "--out", tmp_path / "file", "--json", "-q")
    from_stdin = run_cli("kalman-bank", "-", "--out", tmp_path / "stdin", "--json", "-q", input=csv.read_bytes())
    assert from_file.returncode == 0, from_file.stderr.decode()
    assert from_stdin.returncode == 0, from_stdin.stderr.decode()
    assert json.loads(from_stdin.stdout)["results"] == json.loads(from_file.stdout)["results"]
    assert sorted(p.name for p in (tmp_path / "stdin").iterdir()) == sorted(p.name for p in (tmp_path / "file").iterdir())


def test_a_capture_whose_z_never_moves_is_refused(tmp_path):
    # REEP's model against z (pass 1) has no leg to bin: one line, exit 2, nothing written
    still = tmp_path / "still.h5"
    still.write_bytes(FAST_CAPTURE.read_bytes())
    with h5py.File(still, "r+") as f:
        z = f["channels/z_piezo"]
        z[...] = np.full(z.shape, z[0])
    result = run_cli("kalman-bank", still, "--out", tmp_path / "kb", "-q")
    assert result.returncode == 2
    assert "REEP found no force curve" in result.stderr.decode() and len(result.stderr.decode().splitlines()) == 1
    assert not (tmp_path / "kb").exists()
