"""``afmtool identify invols``: the InvOLS from the contact part of a force curve (issue 16, item 3).

Acceptance: recovered within 1 % on a simulated hard-contact curve.
"""

from __future__ import annotations

import json
import math

import h5py
import numpy as np
import pytest

from afmtool.errors import InputError
from afmtool.estimators.invols import approach_part, fit_contact_slope
from tests.conftest import run_cli

INVOLS_NM_PER_V = 47.3


def _hard_contact_curve(rng, *, contact_nm=130.0, noise_v=0.002, n=4000):
    """Approach then retract over 0–200 nm; on a hard sample the deflection follows z one-for-one past contact.

    Written from the physics, not from afmtool: in contact d = z − z_c (nm), the detector reads d / InvOLS
    volts; out of contact a flat baseline with a small drift and an attractive dip before contact.
    """
    up = np.linspace(0.0, 200.0, n // 2)
    z = np.concatenate([up, up[::-1]])
    deflection_nm = np.maximum(z - contact_nm, 0.0)
    dip = -0.8 * np.exp(-np.abs(z - contact_nm) / 1.5) * (z < contact_nm)  # van der Waals snap region
    volts = 0.31 + (deflection_nm + dip) / INVOLS_NM_PER_V + 1e-5 * z + rng.normal(0, noise_v, z.size)
    return z, volts


def _write_curve(path, z_nm, volts, *, z_units="nm", z_scale=1.0, metadata=None):
    with h5py.File(path, "w") as f:
        f.attrs["sample_rate_hz"] = 2000.0
        f.attrs["metadata"] = json.dumps(metadata or {})
        f.create_dataset("channels/deflection", data=volts).attrs["units"] = "V"
        f.create_dataset("channels/z_piezo", data=z_nm * z_scale).attrs["units"] = z_units


def test_fit_contact_slope_recovers_the_invols(rng):
    z, volts = _hard_contact_curve(rng)
    part = approach_part(z)
    fit = fit_contact_slope(z[part], volts[part])
    invols = 1.0 / fit.slope
    err = invols / INVOLS_NM_PER_V - 1
    print(f"InvOLS {invols:.4f} nm/V (true {INVOLS_NM_PER_V}), error {err * 100:+.3f} %, "
          f"std {fit.slope_std / fit.slope**2:.4f}, contact {fit.contact_z_nm:.2f} nm")
    assert abs(err) < 0.01
    assert abs(fit.contact_z_nm - 130.0) < 3.0
    # the stated uncertainty is honest: within 4 sigma of the truth
    assert abs(invols - INVOLS_NM_PER_V) < 4 * fit.slope_std / fit.slope**2


def test_fit_contact_slope_either_direction(rng):
    """z decreasing towards the sample and a deflection that falls in contact work the same."""
    z, volts = _hard_contact_curve(rng)
    part = approach_part(z)
    fit = fit_contact_slope(-z[part], -volts[part])
    assert abs(1.0 / abs(fit.slope) / INVOLS_NM_PER_V - 1) < 0.01
    assert fit.contact_side == -1


def test_fit_contact_slope_refuses_a_curve_without_points():
    with pytest.raises(InputError, match="at least"):
        fit_contact_slope(np.arange(5.0), np.zeros(5))


def test_identify_invols_cli(tmp_path, rng):
    z, volts = _hard_contact_curve(rng)
    curve = tmp_path / "curve.h5"
    # z stored in µm: the units boundary turns it into nm
    _write_curve(curve, z, volts, z_units="um", z_scale=1e-3,
                 metadata={"cantilever": {"deflection_sensitivity_nm_per_v": 50.0}})
    out = tmp_path / "out"
    result = run_cli("identify", "invols", curve, "--out", out, "-q")
    assert result.returncode == 0, result.stderr.decode()
    report = json.loads((out / "report.json").read_text())
    res = report["results"]
    print("identify invols:", res["invols_nm_per_v"], "+-", res["invols_std_nm_per_v"], "capture's:",
          res["capture_invols_nm_per_v"])
    assert abs(res["invols_nm_per_v"] / INVOLS_NM_PER_V - 1) < 0.01
    assert res["capture_invols_nm_per_v"] == 50.0
    assert 0 < res["invols_std_nm_per_v"] < 0.5
    assert (out / "invols.png").stat().st_size > 1000
    assert report["inputs"][0]["unit_conversions"]["z_piezo"]["factor"] == 1000.0


def test_identify_invols_bad_channel(tmp_path, rng):
    z, volts = _hard_contact_curve(rng)
    curve = tmp_path / "curve.h5"
    _write_curve(curve, z, volts)
    result = run_cli("identify", "invols", curve, "--z-channel", "height", "--out", tmp_path / "out")
    assert result.returncode == 2 and "no channel 'height'" in result.stderr.decode()
    assert not (tmp_path / "out").exists()


def test_identify_invols_on_the_real_asylum_force_curve(tmp_path, shared):
    """The MFP-3D force curve (SOURCES.md §1): the slope beside the wave note's InvOLS, and an independent fit.

    The independent fit reads the wave with igor2 directly (column Defl against ZSnsr, m), takes the approach
    (the note's Indexes 0,1008,...) and fits a straight line with numpy.polyfit to the points in the z range the
    report says it fitted.  The sample is soft: the slope is well below 1.
    """
    igor2 = pytest.importorskip("igor2.binarywave")
    path = shared / "data" / "formats" / "fmt-igor-fd_SiN_FD_plot.ibw"
    out = tmp_path / "out"
    result = run_cli("identify", "invols", path, "--out", out, "-q")
    assert result.returncode == 0, result.stderr.decode()
    report = json.loads((out / "report.json").read_text())
    res = report["results"]
    wave = igor2.load(str(path))["wave"]
    data = np.asarray(wave["wData"], dtype=np.float64)
    labels = [x.decode() for x in wave["labels"][1] if x]
    defl_nm = data[:1009, labels.index("Defl")] * 1e9
    z_nm = data[:1009, labels.index("ZSnsr")] * 1e9
    lo, hi = res["fitted_z_range_nm"]
    chosen = (z_nm >= lo) & (z_nm <= hi)
    slope, _ = np.polyfit(z_nm[chosen], defl_nm[chosen], 1)
    print(f"real .ibw: contact slope {res['contact_slope']:.5f} nm/nm (independent polyfit {slope:.5f}, "
          f"{chosen.sum()} points), the note's InvOLS {res['capture_invols_nm_per_v']} nm/V, implied "
          f"{res['implied_invols_nm_per_v']:.2f} nm/V")
    assert chosen.sum() == res["fitted_points"]
    assert math.isclose(res["contact_slope"], slope, rel_tol=1e-6)
    assert 0.1 < res["contact_slope"] < 0.8  # soft sample: well below 1
    assert res["capture_invols_nm_per_v"] == pytest.approx(44.99)
    assert any("soft sample" in w for w in report["warnings"])
