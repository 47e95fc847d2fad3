"""REEP in the attractive trap (issue 14, item 6): the static-offset regressor and the validity flags.

Acceptance: along a force curve into the attractive trap every unflagged f0′ lies within
10 % of averaging theory at that separation, on afmtool's bundled capture
(``sample_data/force_curve_thesis.h5``) and on a capture of the independent
``tests/reference_sim.py``; the bundled capture no longer reports an f0′ range below 50 kHz.

The theory here is the first-harmonic balance of docs/conventions.md (ch. 4) by direct quadrature of
the reference simulator's own force, so the truth shares nothing with afmtool; it is also
checked against afmtool's closed forms (``afmtool.models.averaging``).
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest

from afmtool.estimators.reep_validity import (
    FLAG_LOW_AMPLITUDE,
    FLAG_NOT_CONVERGED,
    FLAG_NOT_UNDERDAMPED,
    FLAG_OFFSET_DRIFT,
    FreeAirLevels,
    OffsetDrift,
    ValidityLimits,
    validity_flags,
)
from tests import reference_sim as ref
from tests.conftest import run_cli, validate_report

SAMPLE = Path(__file__).resolve().parents[1] / "sample_data" / "force_curve_thesis.h5"
#: Acceptance tolerance: |f0′/f0_e − 1| of every unflagged sample after the warm-up.
F0_TOLERANCE = 0.10
#: Acceptance: the bundled capture's force-curve f0′ range stays above this, Hz.
F0_FLOOR_HZ = 50e3
#: Warm-up left out: REEP's 5 windows (1000 samples at 500 kHz), as the report's summary.
WARMUP_S = 2e-3


def first_harmonic_f0_hz(amplitude_nm, separation_nm, f0_hz, force: ref.PiecewiseLinearForce, n_theta=720):
    """f_e from ωe² = ω0² − (1/(πa))∫₀^{2π} F(a cosθ, −aω sinθ) cosθ dθ (docs/conventions.md, ch. 4), by quadrature.

    The dissipative terms are odd in sinθ and drop out of the cosθ integral, so ω does not enter.
    """
    a = np.asarray(amplitude_nm, dtype=float)[:, None]
    l = np.asarray(separation_nm, dtype=float)[:, None]
    theta = (np.arange(n_theta) + 0.5) * (2 * np.pi / n_theta)
    conservative = force(a * np.cos(theta), 0.0 * theta, l)
    integral = conservative @ np.cos(theta) * (2 * np.pi / n_theta)
    w0 = 2 * np.pi * f0_hz
    we2 = w0 * w0 - integral / (np.pi * a[:, 0])
    return np.sqrt(we2) / (2 * np.pi)


def _unflagged_errors(reep_dir: Path, capture: Path, force: ref.PiecewiseLinearForce):
    """|f0′/f0_e − 1| at every unflagged sample after the warm-up, and the counts."""
    with h5py.File(capture, "r") as h5:
        separation = h5["truth/separation_nm"][()]
        fs = float(h5.attrs["sample_rate_hz"])
        f0_free = json.loads(h5.attrs["metadata"])["cantilever"]["f0_hz"]
    with h5py.File(reep_dir / "reep.h5", "r") as h5:
        t, f0, amplitude, flag = (h5[name][()] for name in ("t", "f0_hz", "amplitude", "flag"))
    index = np.round(t * fs).astype(int)
    theory = first_harmonic_f0_hz(amplitude, separation[index], f0_free, force)
    judged = (t > WARMUP_S) & (flag == 0)
    error = np.abs(f0[judged] / theory[judged] - 1.0)
    in_trap = judged & (theory < 0.85 * f0_free)  # the tip oscillates inside the attractive zone
    return error, int(np.count_nonzero(in_trap)), int(np.count_nonzero(flag[t > WARMUP_S])), theory, t


#: The force of the bundled capture (its metadata), as the reference simulator takes it.
THESIS_ATTRACTIVE = ref.PiecewiseLinearForce(4.0, 9.61e10, 9.1809e12, 42000.0, 0.0)


def test_quadrature_theory_matches_afmtool_closed_form():
    # the truth of this file against afmtool's averaging theory: the same first-harmonic balance
    from afmtool.models.averaging import equivalent_parameters_closed_form
    from afmtool.models.cantilever import Cantilever
    from afmtool.models.forces import THESIS_FORCE_SETS

    amplitude = np.array([0.3, 0.3, 2.0, 8.0, 19.5, 0.5])
    separation = np.array([2.0, 3.5, 5.0, 11.0, 23.0, 4.2])
    ours = first_harmonic_f0_hz(amplitude, separation, 80318.0, THESIS_ATTRACTIVE, n_theta=20000)
    theirs = equivalent_parameters_closed_form(
        amplitude, separation, 2 * np.pi * 80318.0, Cantilever(80318.0, 168.0), THESIS_FORCE_SETS["attractive"]
    ).f0_e_hz
    print("quadrature/closed-form − 1:", ours / theirs - 1)
    np.testing.assert_allclose(ours, theirs, rtol=1e-6)
    assert abs(ours[0] - 63378.0) < 5.0  # inside the trap: sqrt(ω0² − ωa²)/2π


def test_thesis_force_curve_unflagged_f0_within_10_percent(tmp_path):
    out = tmp_path / "reep"
    result = run_cli("reep", SAMPLE, "--out", out, "--json", "-q")
    assert result.returncode == 0, result.stderr.decode()
    report = json.loads(result.stdout)
    validate_report(report)
    for leg, curve in report["results"]["force_curve"].items():
        print(leg, "f0' range", curve["f0_hz_range"])
        assert curve["f0_hz_range"][0] > F0_FLOOR_HZ
    assert report["results"]["summary"]["f0_hz"]["min"] > F0_FLOOR_HZ
    error, in_trap, flagged, theory, _ = _unflagged_errors(out, SAMPLE, THESIS_ATTRACTIVE)
    print(f"bundled capture: worst unflagged |f0'/f0_e - 1| = {error.max():.4f} over {error.size} samples "
          f"({in_trap} in the trap, {flagged} flagged); tolerance {F0_TOLERANCE}")
    assert theory.min() < 64e3  # the curve reaches the bottom of the trap (f0_e = 63.4 kHz)
    # and REEP reports there, unflagged, for 10 ms of the curve (rows at REEP's resolution, issue 33)
    assert in_trap / report["results"]["row_rate_hz"] > 0.010
    assert error.max() <= F0_TOLERANCE


def test_without_offset_regressor_the_trap_reads_far_low(tmp_path):
    # negative control: eq. 3.40 without the constant term is what the issue reported (13 kHz)
    out = tmp_path / "plain"
    result = run_cli("reep", SAMPLE, "--out", out, "--json", "-q", "--no-static-offset")
    assert result.returncode == 0, result.stderr.decode()
    with h5py.File(out / "reep.h5", "r") as h5:
        t, f0 = h5["t"][()], h5["f0_hz"][()]
        assert "flag" in h5 and "offset" not in h5
    assert np.nanmin(f0[(t > WARMUP_S)]) < 30e3


def _reference_force_curve(path: Path, hold: str) -> Path:
    # Free air 80,318 Hz, Q 168, three-sine drive for a 20 nm free amplitude (side lines at a quarter:
    # at Q 168 their beating would otherwise modulate the interaction, docs/conventions.md); 0.08 s in free air
    # at 30 nm, then in 0.14 s down to 2 nm (the bottom of the trap), and back, as the bundled capture.
    fs, duration = 500e3, 0.4
    top, bottom, t_free = 30.0, 2.0, 0.08
    t_turn = duration / 2 + t_free / 2

    def separation(t):
        t = np.asarray(t, dtype=float)
        down = top - (top - bottom) * np.clip((t - t_free) / (t_turn - t_free), 0.0, 1.0)
        up = bottom + (top - bottom) * np.clip((t - t_turn) / (duration - t_turn), 0.0, 1.0)
        return np.where(t <= t_turn, down, up)

    capture = ref.simulate(
        f0_hz=80318.0, q=168.0, gain_nm_per_v=1.0, sample_rate_hz=fs, duration_s=duration,
        drive=ref.three_sine(80318.0, 6000.0, 20.0 / 168.0, side_scale=0.25), hold=hold, noise_nm=0.05, seed=3,
        force=THESIS_ATTRACTIVE, separation_nm=separation, record_z_piezo=True, free_air_s=t_free,
    )
    return ref.write_capture_h5(path, capture)


@pytest.mark.parametrize("hold", ["continuous", "zoh"])
def test_reference_force_curve_unflagged_f0_within_10_percent(tmp_path, hold):
    capture = _reference_force_curve(tmp_path / f"fc_{hold}.h5", hold)
    out = tmp_path / "reep"
    result = run_cli("reep", capture, "--out", out, "--json", "-q")
    assert result.returncode == 0, result.stderr.decode()
    report = json.loads(result.stdout)
    error, in_trap, flagged, theory, _ = _unflagged_errors(out, capture, THESIS_ATTRACTIVE)
    print(f"reference capture ({hold} drive): worst unflagged |f0'/f0_e - 1| = {error.max():.4f} over "
          f"{error.size} samples ({in_trap} in the trap, {flagged} flagged); tolerance {F0_TOLERANCE}; "
          f"f0' ranges {[c['f0_hz_range'] for c in report['results']['force_curve'].values()]}")
    assert theory.min() < 64e3
    assert in_trap / report["results"]["row_rate_hz"] > 0.010  # 10 ms unflagged in the trap
    assert error.max() <= F0_TOLERANCE


# ---------------------------------------------------------------------------
# the flags themselves
# ---------------------------------------------------------------------------


def test_each_flag_fires_on_its_own_condition():
    levels = FreeAirLevels(amplitude=20.0, sigma2=0.0025, source="free-air segment")
    limits = ValidityLimits(min_amplitude_fraction=0.01, max_offset_drift=0.1)
    underdamped = np.array([True, True, False, True, True, True, True])
    amplitude = np.array([5.0, 5.0, 5.0, 0.19, 5.0, 1.0, 1.0])
    # σ̂² far above its free-air level (0.11 = 44x) is no reason: only NaN (undefined) is
    sigma2 = np.array([0.0025, 0.0025, 0.0025, 0.0025, 0.11, np.nan, 0.0025])
    drift = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.049, 0.051])  # against 0.1 · A²/2 = 0.05
    flags = validity_flags(underdamped, amplitude, sigma2, levels, limits, drift, settled_from=1)
    np.testing.assert_array_equal(
        flags, [FLAG_NOT_CONVERGED, 0, FLAG_NOT_UNDERDAMPED, FLAG_LOW_AMPLITUDE, 0, FLAG_NOT_CONVERGED,
                FLAG_OFFSET_DRIFT]
    )
    # unknown free-air levels or zero limits switch the checks off, never the under-damped or convergence ones
    converging = np.where(np.isnan(sigma2), FLAG_NOT_CONVERGED, 0)
    off = validity_flags(underdamped, amplitude, sigma2, FreeAirLevels(None, None, "none"), limits)
    np.testing.assert_array_equal(off, np.where(underdamped, 0, FLAG_NOT_UNDERDAMPED) | converging)
    off = validity_flags(underdamped, amplitude, sigma2, levels, ValidityLimits(0.0, 0.0), drift)
    np.testing.assert_array_equal(off, np.where(underdamped, 0, FLAG_NOT_UNDERDAMPED) | converging)


def test_offset_drift_is_chunk_independent_and_measures_the_window_variance(rng):
    # a ramp of slope s per output sample: the EW variance tends to s²λ/(1−λ)²
    lam, keep = 0.995, 6
    ramp = 0.01 * np.arange(20_000) + 0.001 * rng.standard_normal(20_000)
    ramp[100] = np.nan  # skipped, not propagated
    whole = OffsetDrift(lam, keep)(ramp)
    drift = OffsetDrift(lam, keep)
    parts = np.concatenate([drift(ramp[a:b]) for a, b in ((0, 1), (1, 777), (777, 5000), (5000, 20_000))])
    np.testing.assert_array_equal(parts, whole)
    lam_out = lam**keep
    expected = 0.01**2 * lam_out / (1 - lam_out) ** 2
    assert np.all(np.isfinite(whole))
    assert abs(whole[-1] / expected - 1) < 0.01


@pytest.mark.parametrize("with_offset", [True, False])
@pytest.mark.parametrize("levels_known", [True, False])
def test_reep_rows_equals_the_steps_one_after_the_other(rng, with_offset, levels_known):
    """The fused pass against eq. 3.48, c/(1 + b1 + b0), OffsetDrift and validity_flags, bit for bit."""
    from afmtool.estimators.reep_validity import reep_rows
    from afmtool.models.discretisation import resonance_from_denominator

    fs, lam, keep, n = 500e3, 0.995, 6, 5000
    b0 = 0.998 + 0.003 * rng.standard_normal(n)  # some above 1: not under-damped
    b1 = -2.0 * np.sqrt(np.abs(b0)) * np.cos(2 * np.pi * 70e3 / fs) + 0.002 * rng.standard_normal(n)
    b1[17], b0[18] = np.nan, np.nan
    c = 0.3 * (1.0 + b1 + b0) + 0.02 * np.cumsum(rng.standard_normal(n)) * (1.0 + b1 + b0)
    c[40] = np.nan
    sigma2 = 0.0025 * np.exp(rng.standard_normal(n))
    sigma2[:5] = np.nan
    amplitude = 5.0 * np.exp(0.5 * rng.standard_normal(n))
    levels = FreeAirLevels(5.0, 0.0025, "free-air segment") if levels_known else FreeAirLevels(None, None, "none")
    limits = ValidityLimits(0.3, 0.01)
    settled = 700

    f0, q, valid = resonance_from_denominator(b1, b0, fs)
    offset = c / (1.0 + b1 + b0) if with_offset else None
    variance = OffsetDrift(lam, keep)(offset) if with_offset else None
    flags = validity_flags(valid, amplitude, sigma2, levels, limits, variance, settled_from=settled)

    drift = OffsetDrift(lam, keep) if with_offset else None
    cuts = (0, 1, 999, 2500, n)
    parts = [
        reep_rows(b1[a:b], b0[a:b], c[a:b] if with_offset else None, sigma2[a:b], amplitude[a:b], fs, levels, limits,
                  drift, settled_from=max(0, min(settled, b) - a))
        for a, b in zip(cuts[:-1], cuts[1:])
    ]
    np.testing.assert_array_equal(np.concatenate([p.f0_hz for p in parts]), f0)
    np.testing.assert_array_equal(np.concatenate([p.q for p in parts]), q)
    np.testing.assert_array_equal(np.concatenate([p.flags for p in parts]), flags)
    if with_offset:
        np.testing.assert_array_equal(np.concatenate([p.offset for p in parts]), offset)
    else:
        assert all(p.offset is None for p in parts)
    # the case exercises every check that is on
    expected_bits = FLAG_NOT_UNDERDAMPED | FLAG_NOT_CONVERGED | (FLAG_LOW_AMPLITUDE if levels_known else 0)
    assert np.bitwise_or.reduce(flags) == expected_bits | (FLAG_OFFSET_DRIFT if with_offset else 0)


def test_flag_counter_counts_each_bit(rng):
    from afmtool.estimators.reep_validity import FlagCounter

    flags = (rng.integers(0, 16, 1000) & ~4 | 16 * rng.integers(0, 2, 1000)).astype(np.uint8)
    counter = FlagCounter()
    counter.add(flags[:300])
    counter.add(flags[300:])
    assert counter.total == 1000 and counter.flagged == np.count_nonzero(flags)
    for bit in (FLAG_NOT_UNDERDAMPED, FLAG_LOW_AMPLITUDE, FLAG_NOT_CONVERGED, FLAG_OFFSET_DRIFT):
        assert counter.by_bit[bit] == np.count_nonzero(flags & bit)
