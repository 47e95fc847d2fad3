"""Units and the synthetic drive on captures from the independent simulator (tests/reference_sim.py).

"Truth that is not our own": the same checks as tests/test_units.py and
tests/test_synthetic_drive.py, on a continuous-drive RK4 capture written by a
simulator that shares no code with afmtool.
"""

from __future__ import annotations

import json
import math

import h5py
import pytest

from tests.conftest import run_cli

reference_sim = pytest.importorskip("tests.reference_sim")

F0_HZ, Q, FS = 71000.0, 190.0, 500e3


def _capture(path, *, deflection_units="nm", hold="continuous", drop_dither=False):
    drive = reference_sim.three_sine(F0_HZ, 6000.0, 0.13, 0.5)
    capture = reference_sim.simulate(
        f0_hz=F0_HZ, q=Q, gain_nm_per_v=1.0, sample_rate_hz=FS, duration_s=0.03, drive=drive, hold=hold,
        noise_nm=0.02, seed=16, deflection_units=deflection_units,
    )
    reference_sim.write_capture_h5(path, capture)
    if drop_dither:
        with h5py.File(path, "a") as h5:
            del h5["channels/dither"]
    return capture.metadata


def _summary(out) -> tuple[float, float]:
    s = json.loads((out / "report.json").read_text())["results"]["summary"]
    return s["f0_hz"]["mean"], s["q"]["mean"]


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    root = tmp_path_factory.mktemp("refsim")
    metadata = _capture(root / "nm.h5")
    out = root / "out_nm"
    result = run_cli("reep", root / "nm.h5", "--out", out, "-q")
    assert result.returncode == 0, result.stderr.decode()
    return metadata, _summary(out)


@pytest.mark.parametrize("units", ["m", "um"])
def test_reep_same_in_m_and_um_on_the_reference_simulator(tmp_path, recorded, units):
    _, (f0_nm, q_nm) = recorded
    _capture(tmp_path / "c.h5", deflection_units=units)
    result = run_cli("reep", tmp_path / "c.h5", "--out", tmp_path / "out", "-q")
    assert result.returncode == 0, result.stderr.decode()
    f0, q = _summary(tmp_path / "out")
    print(f"reference_sim, deflection in {units}: f0' {f0:.4f} (nm: {f0_nm:.4f}, truth {F0_HZ}), Q' {q:.3f} ({q_nm:.3f})")
    assert math.isclose(f0, f0_nm, rel_tol=1e-9) and math.isclose(q, q_nm, rel_tol=1e-9)
    assert abs(f0 / F0_HZ - 1) < 1e-3


def test_drive_on_the_reference_simulator(tmp_path, recorded):
    metadata, (f0_ref, q_ref) = recorded
    _capture(tmp_path / "c.h5", drop_dither=True)
    drive = metadata["drive"]
    text = ",".join(f"{f:g}:{a:.8g}" for f, a in zip(drive["lines_hz"], drive["lines_v"]))
    result = run_cli("reep", tmp_path / "c.h5", "--drive", text, "--out", tmp_path / "out", "-q")
    assert result.returncode == 0, result.stderr.decode()
    f0, q = _summary(tmp_path / "out")
    print(f"reference_sim, --drive: f0' {f0:.4f} vs recorded {f0_ref:.4f} ({(f0 / f0_ref - 1) * 100:+.4f} %), "
          f"Q' {q:.3f} vs {q_ref:.3f} ({(q / q_ref - 1) * 100:+.3f} %)")
    assert abs(f0 / f0_ref - 1) < 1e-3
    assert abs(q / q_ref - 1) < 1e-2
