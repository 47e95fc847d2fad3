"""identify freeair: segment, sweep (chirp and stepped sines) and thermal routes, end to end."""

from __future__ import annotations

import json

import numpy as np
import pytest

from afmtool.models.free_air import load_free_air_model
from tests.conftest import run_cli, validate_report


def _identify(tmp_path, *args):
    out = tmp_path / "freeair"
    result = run_cli("identify", "freeair", *args, "--out", out, "--json", "-q")
    assert result.returncode == 0, result.stderr.decode()
    report = json.loads(result.stdout)
    validate_report(report)
    assert json.loads(json.dumps(load_free_air_model(out).to_dict())) == report["results"]["free_air_model"]
    return report["results"]


def test_thermal_route_on_the_real_spectrum(shared, tmp_path):
    results = _identify(tmp_path, "--psd", shared / "data" / "thermal_tune_acl_a.csv")
    model = results["free_air_model"]
    print("real thermal tune (ACL-A):", model["f0_hz"], model["q"], results["spring_constant_n_per_m"])
    # recorded result of the thermal route on the commercial thermal tune
    assert model["f0_hz"] == pytest.approx(179_716.5, rel=2e-3)
    assert model["q"] == pytest.approx(378.8, rel=0.10)
    assert model["source"] == "thermal"
    assert results["peak_asd_m_per_sqrt_hz"] > 5 * results["floor_asd_m_per_sqrt_hz"]


def _reference_sweep(path, drive: str):
    """The ltv scenario's sweeps (f0 70 kHz, Q 200, 25 nm at the centre) from tests/reference_sim.py."""
    from tests import reference_sim as ref

    if drive == "chirp":
        signal, duration = ref.LinearChirp(60e3, 80e3, 25.0 / 200.0), 0.2
    else:
        signal, duration = ref.SteppedSine(tuple(np.linspace(68e3, 72e3, 21)), 0.5 / 21, 25.0 / 200.0), 0.5
    capture = ref.simulate(
        f0_hz=70e3, q=200.0, gain_nm_per_v=1.0, sample_rate_hz=500e3, duration_s=duration, drive=signal,
        noise_nm=0.05, seed=11,
    )
    return ref.write_capture_h5(path, capture)


@pytest.mark.parametrize("source", ["afmtool", "reference"])
@pytest.mark.parametrize(
    "drive, settings, extra, f0_tol_hz, q_tol",
    [
        ("chirp", ["duration_s=0.2", "sweep_span_hz=20000.0"], [], 5.0, 0.05),
        ("stepped", ["duration_s=0.5", "sweep_span_hz=4000.0", "sweep_steps=21"], ["--stepped"], 1.0, 0.01),
    ],
)
def test_sweep_routes(tmp_path, source, drive, settings, extra, f0_tol_hz, q_tol):
    capture = tmp_path / f"{drive}.h5"
    if source == "reference":
        _reference_sweep(capture, drive)
    else:
        args = [a for s in ["step_time_s=10.0", f"drive={drive}", *settings] for a in ("--set", s)]
        assert run_cli("simulate", "ltv", "-o", capture, *args).returncode == 0
    model = _identify(tmp_path, capture, "--sweep", *extra)["free_air_model"]
    assert model["f0_hz"] == pytest.approx(70_000.0, abs=f0_tol_hz)
    assert model["q"] == pytest.approx(200.0, rel=q_tol)
    assert model["source"] == "sweep"


def test_segment_route_then_reep_with_model(tmp_path):
    capture = tmp_path / "ltv.h5"
    assert run_cli("simulate", "ltv", "-o", capture, "--set", "duration_s=0.04", "--set", "step_time_s=1.0").returncode == 0
    model = _identify(tmp_path, capture, "--free-air", "0:0.02")["free_air_model"]
    assert model["f0_hz"] == pytest.approx(70_000.0, abs=2.0)
    assert model["f0_std_hz"] > 0
    result = run_cli("reep", capture, "--model", tmp_path / "freeair", "--out", tmp_path / "reep", "--json", "-q")
    assert result.returncode == 0, result.stderr.decode()
    report = json.loads(result.stdout)
    assert report["results"]["free_air_model"] == model
    assert report["results"]["summary"]["f0_hz"]["mean"] == pytest.approx(70_000.0, abs=2.0)
    assert {i["role"] for i in report["inputs"]} == {"capture", "model"}


def test_bad_psd_file(tmp_path):
    psd = tmp_path / "bad.csv"
    psd.write_text("frequency_hz,asd\n1,2\n")
    result = run_cli("identify", "freeair", "--psd", psd, "--out", tmp_path / "o")
    assert result.returncode == 2
    assert "has no units" in result.stderr.decode()
    assert not (tmp_path / "o").exists()
