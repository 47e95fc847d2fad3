"""The synthetic drive (``--drive``) against the recorded dither, on reference captures (issue 27 item 6).

tests/reference_sim.py (no code shared with afmtool) drives the thesis's three-line design (side
lines ±6 kHz, B/A = 0.5) continuously; 50 ms of free air, then the resonance steps down by 0.4 %
and Q by 20 % (what a tip does). REEP runs once with the recorded dither and once with the dither
dropped and synthesised from the lines' frequencies and amplitudes:

* with f0 and Q in the metadata, the phases are fitted against them: f0′ within 0.01 % and Q′
  within 1 % of the recorded-dither run (or within three of the carried uncertainty where the
  side lines stand too little above the noise: Q 400 with 0.1 nm, 1.6 % on 50 ms of free air;
  on 0.2 s it is 0.8 % and 1 % holds, test below);
* from the lines alone, f0, Q and the phases come from the lines' complex amplitudes with one
  phase origin (the thesis's lines start together; eq. D.4), with a stated uncertainty that REEP's
  per-row std carries (eq. D.3): f0′ within 0.05 % and Q′ within 3 %, in every cell.  The
  magnitudes alone could not do it at Q 400 (tests/test_synthetic_drive_information.py): the
  closure phase ∠D₊ + ∠D₋ − 2∠D₀ is what pins the main line's phase.

The comparison is of the mean over the free-air rows and over the on-sample rows.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

from afmtool.analyses.reep import run_reep
from afmtool.config import resolve
from afmtool.config.params import ReepParams
from afmtool.estimators.drive_lines import DriveLine, drive_phase_std, drive_std_rows
from afmtool.io.capture import ChannelSpec
from afmtool.io.memory import ArrayReader
from afmtool.io.synthetic_drive import SyntheticDriveReader
from tests import reference_sim as rs
from tests.memory_sink import MemorySink

FREE_S, STEP_S, DURATION_S = 0.05, 0.06, 0.12


def _runs(fs: float, f0: float, q: float, noise: float, seed: int, with_metadata: bool, free_s: float = FREE_S):
    """(recorded columns, synthetic columns, the phase fit) on one capture with ``free_s`` of free air."""
    step_s = free_s + STEP_S - FREE_S
    cap = rs.simulate(
        f0_hz=f0, q=q, gain_nm_per_v=1.0, sample_rate_hz=fs, duration_s=free_s + DURATION_S - FREE_S,
        drive=rs.three_sine(f0, 6000.0, 20.0 / q, 0.5), noise_nm=noise, seed=seed, free_air_s=free_s,
        f0_of_t=lambda t: np.where(t < step_s, f0, 0.996 * f0), q_of_t=lambda t: np.where(t < step_s, q, 0.8 * q),
    )
    specs = tuple(ChannelSpec(k, cap.units[k]) for k in cap.channels)
    recorded = MemorySink()
    run_reep(ArrayReader(fs, specs, cap.channels, cap.metadata, cap.truth, "recorded"), resolve(ReepParams, {}),
             recorded)
    meta = copy.deepcopy(cap.metadata)
    if not with_metadata:
        meta.pop("cantilever")
    meta["drive"] = {"hold": meta["drive"]["hold"]}  # what an instrument that did not record its dither says
    channels = {k: v for k, v in cap.channels.items() if k != "dither"}
    lines = tuple(DriveLine(f, a) for f, a in zip(cap.metadata["drive"]["lines_hz"], cap.metadata["drive"]["lines_v"]))
    reader = SyntheticDriveReader(ArrayReader(fs, tuple(s for s in specs if s.name != "dither"), channels, meta,
                                              cap.truth, "synthetic"), lines)
    synthetic = MemorySink()
    result = run_reep(reader, resolve(ReepParams, {}), synthetic)
    return recorded, synthetic, reader.fit, float(result.results.drive_frequency_hz)


def _compare(fs, f0, q, noise, with_metadata, seed=1, free_s=FREE_S):
    recorded, synthetic, fit, drive_hz = _runs(fs, f0, q, noise, seed, with_metadata, free_s)
    phase_std = drive_phase_std(fit, drive_hz)
    rows = []
    later = free_s - FREE_S
    for segment, (lo, hi) in (("free air", (0.01, free_s)), ("on sample", (STEP_S + later + 0.01, DURATION_S + later))):
        a = (recorded["t"] > lo) & (recorded["t"] < hi)
        b = (synthetic["t"] > lo) & (synthetic["t"] < hi)
        f_rec, f_syn = np.nanmean(recorded["f0_hz"][a]), np.nanmean(synthetic["f0_hz"][b])
        q_rec, q_syn = np.nanmean(recorded["q"][a]), np.nanmean(synthetic["q"][b])
        f_std, q_std = drive_std_rows(np.array([f_syn]), np.array([q_syn]), drive_hz, phase_std)
        rows.append((segment, f_syn / f_rec - 1.0, q_syn / q_rec - 1.0, float(f_std[0] / f_rec), float(q_std[0] / q_rec)))
    print(f"\n{fs / 1e6:g} MHz f0 {f0:g} Q {q:g} noise {noise} nm, {'metadata f0/Q' if with_metadata else 'lines alone'}: "
          f"fit f0 {fit.f0_hz:.2f} ± {fit.f0_std_hz:.2f} Hz, Q {fit.q:.2f} ± {fit.q_std:.2f} ({fit.response_source})")
    for segment, df, dq, sf, sq in rows:
        print(f"   {segment}: f0' {100 * df:+.4f} %, Q' {100 * dq:+.3f} % (carried std: f0' {100 * sf:.4f} %, "
              f"Q' {100 * sq:.3f} %)")
    return rows


def _check(rows, with_metadata):
    for segment, df, dq, _sf, sq in rows:
        if with_metadata:
            assert abs(df) <= 1e-4, segment
            assert abs(dq) <= max(0.01, 3 * sq), segment
        else:
            assert abs(df) <= 5e-4, segment
            assert abs(dq) <= 0.03, segment


#: (fs, f0, Q, noise nm): 0.5-2 MHz, Q 100-600, f0 70-250 kHz, 0.02-0.1 nm.
CELLS = [
    (500e3, 70e3, 100.0, 0.1),
    (500e3, 70e3, 200.0, 0.02),
    (500e3, 70e3, 400.0, 0.02),
    (500e3, 70e3, 400.0, 0.1),
    (1e6, 120e3, 250.0, 0.05),
    (2e6, 75e3, 100.0, 0.05),
    (2e6, 75e3, 200.0, 0.05),
    (2e6, 75e3, 400.0, 0.05),
    (2e6, 150e3, 300.0, 0.05),
    (2e6, 250e3, 600.0, 0.02),
]


@pytest.mark.slow
@pytest.mark.parametrize("with_metadata", [True, False], ids=["metadata", "lines-alone"])
@pytest.mark.parametrize(("fs", "f0", "q", "noise"), CELLS)
def test_synthetic_drive_grid(fs, f0, q, noise, with_metadata):
    _check(_compare(fs, f0, q, noise, with_metadata), with_metadata)


@pytest.mark.parametrize("with_metadata", [True, False], ids=["metadata", "lines-alone"])
def test_synthetic_drive_matches_the_recorded_dither(with_metadata):
    _check(_compare(500e3, 70e3, 200.0, 0.05, with_metadata), with_metadata)


def test_with_metadata_at_q_400_and_0_1_nm_a_longer_free_air_segment_meets_1_percent():
    """The one cell where the metadata route's Q′ may miss 1 % (three carried std allowed: 1.6 % each) is short
    of information, not method: the side lines stand 0.15 nm above 0.1 nm of noise for 50 ms, and their phase
    difference (the envelope's timing, which Q′ on a detuned tip reads) is uncertain by that much.  Four times the
    free air halves it, and the same route then lands within 1 % on every seed."""
    for seed in (1, 2, 3):
        rows = _compare(500e3, 70e3, 400.0, 0.1, True, seed=seed, free_s=0.2)
        for segment, df, dq, _sf, sq in rows:
            assert abs(df) <= 1e-4 and abs(dq) <= 0.01 and sq < 0.01, segment


def test_synthetic_drive_at_2_mhz_and_q_400():
    """REEP decimates at 2 MHz (D = 5 at 75 kHz): the synthesised dither passes the same anti-alias filter."""
    _check(_compare(2e6, 75e3, 400.0, 0.05, True), True)


def test_reep_drive_takes_f0_q_from_the_model_and_widens_its_std(tmp_path):
    """From the command line: --drive with --model fits the phases against the model's f0 and Q; from the
    lines alone the fitted f0, Q and their std are in the report, and reep.h5's f0_std_hz, q_std carry them."""
    import json

    import h5py

    from afmtool.models.free_air import FreeAirModel
    from tests.conftest import run_cli

    f0, q, fs = 70e3, 200.0, 500e3
    cap = rs.simulate(f0_hz=f0, q=q, gain_nm_per_v=1.0, sample_rate_hz=fs, duration_s=0.06,
                      drive=rs.three_sine(f0, 6000.0, 20.0 / q, 0.5), noise_nm=0.05, seed=4, free_air_s=0.03)
    meta = {k: v for k, v in cap.metadata.items() if k != "cantilever"}
    meta["drive"] = {"hold": "continuous"}
    channels = {k: v for k, v in cap.channels.items() if k != "dither"}
    path = rs.write_capture_h5(tmp_path / "no_dither.h5", rs.Capture(fs, channels, {"deflection": "nm"}, {}, meta))
    drive = ",".join(f"{a:g}:{b:.8g}" for a, b in zip(cap.metadata["drive"]["lines_hz"], cap.metadata["drive"]["lines_v"]))
    FreeAirModel(f0, q, 1.0, f0_std_hz=0.5, q_std=1.0, source="given").save(tmp_path / "free_air.json")
    reports = {}
    for name, extra in (("model", ["--model", tmp_path / "free_air.json"]), ("lines", [])):
        result = run_cli("reep", path, "--drive", drive, *extra, "--out", tmp_path / name, "--json", "-q")
        assert result.returncode == 0, result.stderr.decode()
        reports[name] = json.loads(result.stdout)
    response = reports["model"]["inputs"][0]["synthetic_drive"]["response"]
    assert response["from"].startswith("--model") and response["f0_hz"] == f0 and response["f0_std_hz"] == 0.5
    fitted = reports["lines"]["inputs"][0]["synthetic_drive"]["response"]
    assert fitted["from"] == "line magnitudes and common phase origin" and fitted["line_phases"] == "common"
    assert fitted["f0_std_hz"] > 0 and fitted["q_std"] > 0 and 0 <= fitted["closure_chi2"] < 11
    assert abs(fitted["f0_hz"] - f0) <= 4 * fitted["f0_std_hz"]
    widened = reports["lines"]["results"]["synthetic_drive_uncertainty"]
    assert widened["main_line_phase_std_deg"] > 0 and widened["largest_f0_std_added_hz"] > 0
    with h5py.File(tmp_path / "lines" / "reep.h5") as f:
        f0_rows, f0_std = f["f0_hz"][()], f["f0_std_hz"][()]
    # the main line's phase std, δf0' = f0'·δφ/(2Q') per row, is now part of REEP's stated std
    floor = f0 * np.radians(widened["main_line_phase_std_deg"]) / (2 * q)
    settled = np.isfinite(f0_rows) & (np.arange(f0_rows.size) > f0_rows.size // 4)
    assert np.all(f0_std[settled] >= 0.9 * floor)


def _independent_capture(q: float, noise: float, seed: int = 3):
    """A three-line capture whose side lines were phased apart (+0.7 and −0.2 rad): no common origin."""
    f0, fs = 70e3, 500e3
    drive = rs.MultiSine((rs.Sine(f0, 20.0 / q), rs.Sine(f0 - 6000.0, 10.0 / q, 0.7), rs.Sine(f0 + 6000.0, 10.0 / q, -0.2)))
    cap = rs.simulate(f0_hz=f0, q=q, gain_nm_per_v=1.0, sample_rate_hz=fs, duration_s=0.05, drive=drive,
                      noise_nm=noise, seed=seed, free_air_s=0.05)
    lines = tuple(DriveLine(f, a) for f, a in zip(cap.metadata["drive"]["lines_hz"], cap.metadata["drive"]["lines_v"]))
    return cap, lines


@pytest.mark.parametrize(("q", "noise"), [(38.0, 0.1), (100.0, 0.05), (200.0, 0.02)])
def test_lines_phased_apart_fail_the_closure_test_and_fall_back_to_the_magnitudes(q, noise):
    """Where the closure phase stands above the noise, lines that did not start together fail eq. D.4's χ²:
    the fit keeps the magnitudes alone (their phases are then right) and the report warns."""
    from afmtool.estimators.drive_lines import MAGNITUDES, drive_fit_warnings, fit_drive_phases

    cap, lines = _independent_capture(q, noise)
    fit = fit_drive_phases(cap.channels["deflection"], cap.sample_rate_hz, 0, lines)
    print(f"\nQ {q:g}, {noise} nm: closure chi2 {fit.closure_chi2:.1f}; phases {[round(l.phase_rad, 3) for l in fit.lines]}")
    assert fit.response_source == MAGNITUDES and fit.closure_chi2 > 11.0
    true_phases = np.array([0.0, 0.7, -0.2])
    error = np.angle(np.exp(1j * (np.array([line.phase_rad for line in fit.lines]) - true_phases)))
    assert np.all(np.abs(error) <= 4 * np.array(fit.phase_std_rad) + 1e-3)
    assert "do not share one phase origin" in drive_fit_warnings(fit)[0]
    # told so, the fit does not try the common origin at all
    told = fit_drive_phases(cap.channels["deflection"], cap.sample_rate_hz, 0, lines, common_origin=False)
    assert told.response_source == MAGNITUDES and np.isnan(told.closure_chi2) and not drive_fit_warnings(told)


def test_common_origin_chi2_follows_its_distribution_on_lines_that_started_together():
    """On 30 seeded captures whose lines did start together, eq. D.4's χ² (1 degree of freedom) has mean
    about 1 and passes its 99.9 % test every time; the main line's phase error lies within 2σ in ≥ 85 %."""
    from afmtool.estimators.drive_lines import COMMON_ORIGIN, fit_drive_phases

    chi2, within = [], []
    for seed in range(30):
        fs, f0, q, noise = ((500e3, 70e3, 400.0, 0.02), (2e6, 75e3, 100.0, 0.05), (1e6, 120e3, 250.0, 0.1))[seed % 3]
        cap = rs.simulate(f0_hz=f0, q=q, gain_nm_per_v=1.0, sample_rate_hz=fs, duration_s=0.03,
                          drive=rs.three_sine(f0, 6000.0, 20.0 / q, 0.5), noise_nm=noise, seed=seed, free_air_s=0.03)
        lines = tuple(DriveLine(f, a) for f, a in zip(cap.metadata["drive"]["lines_hz"], cap.metadata["drive"]["lines_v"]))
        fit = fit_drive_phases(cap.channels["deflection"], fs, 0, lines)
        assert fit.response_source == COMMON_ORIGIN
        chi2.append(fit.closure_chi2)
        within.append(abs(np.angle(np.exp(1j * fit.lines[0].phase_rad))) <= 2 * fit.phase_std_rad[0])
    print(f"\nchi2 mean {np.mean(chi2):.2f}, main phase within 2 sigma {np.mean(within):.0%}")
    assert 0.4 <= np.mean(chi2) <= 2.0
    assert np.mean(within) >= 0.85


def test_reep_drive_phases_independent_from_the_command_line(tmp_path):
    """``--drive-phases independent`` fits f0 and Q from the magnitudes alone and says so; a bad value is one line."""
    import json

    from tests.conftest import run_cli

    cap = rs.simulate(f0_hz=70e3, q=200.0, gain_nm_per_v=1.0, sample_rate_hz=500e3, duration_s=0.03,
                      drive=rs.three_sine(70e3, 6000.0, 0.1, 0.5), noise_nm=0.05, seed=2, free_air_s=0.02)
    meta = {k: v for k, v in cap.metadata.items() if k != "cantilever"}
    meta["drive"] = {"hold": "continuous"}
    channels = {k: v for k, v in cap.channels.items() if k != "dither"}
    path = rs.write_capture_h5(tmp_path / "no_dither.h5", rs.Capture(500e3, channels, {"deflection": "nm"}, {}, meta))
    drive = ",".join(f"{a:g}:{b:.8g}" for a, b in zip(cap.metadata["drive"]["lines_hz"], cap.metadata["drive"]["lines_v"]))
    result = run_cli("reep", path, "--drive", drive, "--drive-phases", "independent", "--out", tmp_path / "r",
                     "--json", "-q")
    assert result.returncode == 0, result.stderr.decode()
    response = json.loads(result.stdout)["inputs"][0]["synthetic_drive"]["response"]
    assert response["from"] == "line magnitudes" and response["line_phases"] == "independent"
    assert "closure_chi2" not in response
    for extra in (["--drive", drive], []):  # refused whether or not a drive is synthesised
        bad = run_cli("reep", path, *extra, "--drive-phases", "apart", "--out", tmp_path / "bad")
        assert bad.returncode == 2 and len(bad.stderr.decode().strip().splitlines()) == 1
        assert "--drive-phases" in bad.stderr.decode() and not (tmp_path / "bad").exists()


def test_reep_drive_takes_a_designed_loop_and_fits_its_origin(tmp_path):
    """``afmtool design excitation`` phases its side lines apart (in quadrature with the main line's response);
    ``--drive lines.json`` keeps those offsets and fits only the loop's origin in the capture (eq. D.4): Q′ within
    3 % of the recorded-dither run at Q 400 from the lines alone.  The same lines given as a string (no phases)
    fail the closure test, and the report says so."""
    import json
    import math

    import h5py

    from afmtool.models.free_air import FreeAirModel
    from tests.conftest import run_cli

    fs, f0, q, step = 500e3, 70e3, 400.0, 0.06
    FreeAirModel(f0, q, 1.0, source="given").save(tmp_path / "free_air.json")
    designed = run_cli("design", "excitation", "--model", tmp_path / "free_air.json", "--out", tmp_path / "exc", "-q")
    assert designed.returncode == 0, designed.stderr.decode()
    lines = json.loads((tmp_path / "exc" / "lines.json").read_text())["lines"]
    loop_start = 0.0123456  # the capture starts part-way through the loop
    drive = rs.MultiSine(tuple(
        rs.Sine(line["frequency_hz"], line["amplitude_v"],
                math.radians(line["phase_deg"]) - math.pi / 2 + 2 * math.pi * line["frequency_hz"] * loop_start)
        for line in lines))
    cap = rs.simulate(f0_hz=f0, q=q, gain_nm_per_v=1.0, sample_rate_hz=fs, duration_s=0.12, drive=drive,
                      noise_nm=0.02, seed=1, free_air_s=0.05,
                      f0_of_t=lambda t: np.where(t < step, f0, 0.996 * f0), q_of_t=lambda t: np.where(t < step, q, 0.8 * q))
    recorded = rs.write_capture_h5(tmp_path / "recorded.h5", cap)
    meta = {k: v for k, v in cap.metadata.items() if k != "cantilever"}
    meta["drive"] = {"hold": "continuous"}
    channels = {k: v for k, v in cap.channels.items() if k != "dither"}
    no_dither = rs.write_capture_h5(tmp_path / "no_dither.h5", rs.Capture(fs, channels, {"deflection": "nm"}, {}, meta))

    def on_sample(out):
        with h5py.File(out / "reep.h5") as f:
            t, f0_rows, q_rows = f["t"][()], f["f0_hz"][()], f["q"][()]
        rows = t > step + 0.01
        return np.nanmean(f0_rows[rows]), np.nanmean(q_rows[rows])

    runs = {}
    as_string = ",".join(f"{line['frequency_hz']!r}:{line['amplitude_v']!r}" for line in lines)
    for name, path, extra in (("recorded", recorded, []), ("designed", no_dither, ["--drive", tmp_path / "exc" / "lines.json"]),
                              ("string", no_dither, ["--drive", as_string])):
        result = run_cli("reep", path, *extra, "--out", tmp_path / name, "--json", "-q")
        assert result.returncode == 0, result.stderr.decode()
        runs[name] = (json.loads(result.stdout), on_sample(tmp_path / name))
    (f_rec, q_rec), (f_des, q_des) = runs["recorded"][1], runs["designed"][1]
    print(f"\ndesigned loop from lines.json: f0' {f_des / f_rec - 1:+.5%}, Q' {q_des / q_rec - 1:+.3%}; "
          f"as a string: Q' {runs['string'][1][1] / q_rec - 1:+.3%}")
    assert abs(f_des / f_rec - 1) <= 5e-4 and abs(q_des / q_rec - 1) <= 0.03
    response = runs["designed"][0]["inputs"][0]["synthetic_drive"]["response"]
    assert response["from"] == "line magnitudes and common phase origin" and response["closure_chi2"] < 11
    string_report = runs["string"][0]
    assert string_report["inputs"][0]["synthetic_drive"]["response"]["from"] == "line magnitudes"
    assert any("do not share one phase origin" in w for w in string_report["warnings"])


def test_a_drive_file_that_is_not_a_design_is_one_line(tmp_path):
    from tests.conftest import run_cli

    (tmp_path / "lines.json").write_text('{"not": "a design"}')
    result = run_cli("reep", "sample_data/ltv_step.h5", "--drive", tmp_path / "lines.json", "--out", tmp_path / "r")
    assert result.returncode == 2 and len(result.stderr.decode().strip().splitlines()) == 1
    assert "not a lines.json" in result.stderr.decode() and not (tmp_path / "r").exists()


def test_a_common_origin_fit_that_does_not_converge_is_a_failed_test(monkeypatch):
    """No silent fallback: where the common-origin fit does not converge, the magnitudes give f0 and Q and the
    report says why, as when its χ² is too large."""
    import afmtool.estimators.drive_lines as dl

    cap = rs.simulate(f0_hz=70e3, q=200.0, gain_nm_per_v=1.0, sample_rate_hz=500e3, duration_s=0.02,
                      drive=rs.three_sine(70e3, 6000.0, 0.1, 0.5), noise_nm=0.05, seed=2, free_air_s=0.02)
    lines = tuple(DriveLine(f, a) for f, a in zip(cap.metadata["drive"]["lines_hz"], cap.metadata["drive"]["lines_v"]))
    monkeypatch.setattr(dl, "_common_origin_fit", lambda *args, **kwargs: None)
    fit = dl.fit_drive_phases(cap.channels["deflection"], 500e3, 0, lines)
    assert fit.response_source == dl.MAGNITUDES and fit.closure_chi2 == np.inf
    assert "common-origin fit does not converge" in dl.drive_fit_warnings(fit)[0]
    # two lines: the test does not apply, and nothing is said
    two = dl.fit_drive_phases(cap.channels["deflection"], 500e3, 0, lines[:2], f0_hz=70e3, q=200.0)
    assert np.isnan(two.closure_chi2) and not dl.drive_fit_warnings(two)
