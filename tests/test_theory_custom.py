"""Averaging theory for any force and any capture (issue 17 item 4).

- ``theory averaging --force d=…,wa2=…`` equals the thesis set it spells out, and a
  different custom set changes the numbers;
- ``--q 50,100,200,400`` overlays several Q, each one the single-Q run;
- ``theory compare`` on a reference-simulator force curve with /truth removed takes
  its separation from z_piezo and the aligned contact point, finds l(0) within 1 nm,
  and passes like the /truth comparison.
"""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from afmtool.errors import ConfigError
from afmtool.models.force_spec import format_force_spec, parse_force_spec
from afmtool.models.forces import THESIS_FORCE_SETS
from tests import reference_sim as rs
from tests.conftest import run_cli, validate_report
from tests.test_kalman_bank_reference import _force_curve

F0, Q, FS = 80318.0, 168.0, 500e3


def _config(tmp_path):
    path = tmp_path / "short.toml"
    path.write_text("[theory.averaging]\npoints = 121\n")
    return path


def _averaging(tmp_path, name, *args):
    out = tmp_path / name
    result = run_cli("theory", "averaging", "--out", out, "--config", _config(tmp_path), "--json", *args)
    assert result.returncode == 0, result.stderr.decode()
    report = json.loads(result.stdout)
    validate_report(report)
    return out, report


def _series(path, group):
    with h5py.File(path) as f:
        return {name: f[f"{group}/{name}"][()] for name in ("amplitude_nm", "f0_e_hz", "q_e")}


def test_force_spec_round_trip_and_refusals():
    for force in THESIS_FORCE_SETS.values():
        assert parse_force_spec(format_force_spec(force)) == force
    for bad in ("wa2=1e9", "d=3,zz=1", "d=3,d=4", "d=x", "d=-1"):
        with pytest.raises(ConfigError):
            parse_force_spec(bad)


def test_the_records_force_sets_are_the_thesis_sets_and_custom():
    from afmtool.records.theory_averaging import ForceSet

    assert {s.value for s in ForceSet} == {*THESIS_FORCE_SETS, "custom"}


def test_custom_force_equals_the_thesis_set_it_spells_out(tmp_path):
    spec = format_force_spec(THESIS_FORCE_SETS["attractive-repulsive"])
    out_set, _ = _averaging(tmp_path, "set", "--force-set", "attractive-repulsive")
    out_custom, report = _averaging(tmp_path, "custom", "--force", spec)
    assert report["results"]["force"]["name"] == "custom"
    for leg in ("approach", "retract"):
        a, b = _series(out_set / "theory.h5", leg), _series(out_custom / "theory.h5", leg)
        for name in a:
            np.testing.assert_array_equal(a[name], b[name])
    # a softer attraction of the same range shifts f0e less
    out_soft, _ = _averaging(tmp_path, "soft", "--force", "d=4,wa2=2.5e9,wb2=9.1809e10,ca=9200")
    shift = {k: F0 - np.nanmin(_series(o / "theory.h5", "approach")["f0_e_hz"]) for k, o in
             (("set", out_set), ("soft", out_soft))}
    print(f"largest f0e drop: thesis set {shift['set']:.1f} Hz, softer custom set {shift['soft']:.1f} Hz")
    assert 0 < shift["soft"] < shift["set"]
    bad = run_cli("theory", "averaging", "--out", tmp_path / "bad", "--force", "d=4,omega=3")
    assert bad.returncode == 2 and not (tmp_path / "bad").exists()
    assert len(bad.stderr.decode().strip().splitlines()) == 1


def test_q_overlay_holds_each_single_q_run(tmp_path):
    out, report = _averaging(tmp_path, "overlay", "--force-set", "attractive", "--q", "50,100,200,400")
    assert {"averaging_q.png", "averaging_q_sensitivity.png", "theory_q.h5"} <= set(report["outputs"])
    assert sorted(report["results"]["q_overlay"], key=float) == ["50", "100", "200", "400"]
    single, _ = _averaging(tmp_path, "q200", "--force-set", "attractive", "--q", "200")
    overlay = _series(out / "theory_q.h5", "q200/approach")
    alone = _series(single / "theory.h5", "approach")
    for name in overlay:
        np.testing.assert_allclose(overlay[name], alone[name], rtol=1e-12)
    with h5py.File(out / "theory_q.h5") as f:
        for q in (50, 100, 200, 400):
            assert f[f"q{q}/approach/q_e"][0] == pytest.approx(q, rel=1e-6)  # free air at the far end
    assert (out / "averaging_q.png").stat().st_size > 10_000


@pytest.fixture(scope="module")
def no_truth_reep(tmp_path_factory):
    """A reference force curve (thesis attractive set), /truth removed, analysed by reep."""
    tmp = tmp_path_factory.mktemp("no_truth")
    start_nm = 30.0
    cap = rs.simulate(
        f0_hz=F0, q=Q, gain_nm_per_v=1.0, sample_rate_hz=FS, duration_s=0.2,
        drive=rs.three_sine(F0, 6000.0, 20.0 / Q, 0.25), noise_nm=0.05, seed=5,
        force=rs.PiecewiseLinearForce(4.0, 0.31e6**2, 3.03e6**2, 0.042e6, 0.0),
        separation_nm=_force_curve(0.2, start_nm=start_nm), record_z_piezo=True,
    )
    with_truth = rs.write_capture_h5(tmp / "with_truth.h5", cap)
    bare = rs.write_capture_h5(tmp / "bare.h5", rs.Capture(cap.sample_rate_hz, cap.channels, cap.units, {},
                                                          cap.metadata))
    with h5py.File(bare) as f:
        assert "separation_nm" not in f["truth"]
    for name, path in (("reep_truth", with_truth), ("reep_bare", bare)):
        result = run_cli("reep", path, "--out", tmp / name, "-q")
        assert result.returncode == 0, result.stderr.decode()
    return tmp, start_nm


def test_compare_without_truth_uses_z_piezo_and_the_contact_point(no_truth_reep):
    tmp, start_nm = no_truth_reep
    result = run_cli("theory", "compare", tmp / "reep_bare", "--out", tmp / "cmp_bare", "--json")
    assert result.returncode == 0, result.stderr.decode()
    bare = json.loads(result.stdout)
    validate_report(bare)
    sep = bare["results"]["separation"]
    assert sep["source"] == "z-piezo" and sep["nm_per_unit"] == 1.0
    # z_piezo = l - l(0), so the contact point (l = 0) is at z = -l(0)
    contact_error = sep["contact_z"] + start_nm
    truth = json.loads(run_cli("theory", "compare", tmp / "reep_truth", "--out", tmp / "cmp_truth",
                               "--json").stdout)
    assert truth["results"]["separation"]["source"] == "truth"
    print(f"contact point error {contact_error:+.3f} nm (tol 1); without /truth: {bare['results']['verdict']}; "
          f"with: {truth['results']['verdict']}")
    assert abs(contact_error) <= 1.0
    assert bare["results"]["pass"] is True and truth["results"]["pass"] is True
    # a given contact point is used as given
    given = run_cli("theory", "compare", tmp / "reep_bare", "--out", tmp / "cmp_given", "--json",
                    "--contact-z", str(-start_nm))
    assert json.loads(given.stdout)["results"]["separation"]["contact_method"] == "given"
    # --separation truth on a capture without it is one line, exit 2
    refused = run_cli("theory", "compare", tmp / "reep_bare", "--out", tmp / "cmp_refused", "--separation", "truth")
    assert refused.returncode == 2 and not (tmp / "cmp_refused").exists()
