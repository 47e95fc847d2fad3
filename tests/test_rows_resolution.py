"""Rows at the estimator's resolution (issue 33, item 1): the default density loses nothing REEP resolves.

REEP cannot resolve anything shorter than its forgetting window (400 µs by
default), so its series are written at 8 rows per window (50 µs) instead of
one per drive period.  These tests run REEP once at every capture sample
(``decimate=1``: all there is) and once at the default density, on captures of
the independent reference simulator, and check that the default rows,
linearly interpolated back to every sample, carry the same step response and
the same 1 nm topography feature within the estimator's own stated noise.
"""

from __future__ import annotations

import numpy as np
import pytest

from afmtool.analyses.reep import run_reep
from afmtool.config import resolve
from afmtool.config.params import ReepParams
from tests import reference_sim as rs
from tests.memory_sink import MemorySink
from tests.test_reep_reference import reference_reader

FS = 500e3
F0, Q, GAIN = 70_000.0, 200.0, 0.1
AMPLITUDE_NM = 25.0
STEP_S = 0.03


def _run(reader, **overrides):
    columns = MemorySink()
    result = run_reep(reader, resolve(ReepParams, overrides), columns)
    return result.results, columns


def _dense_and_default(cap: rs.Capture, **overrides):
    dense = _run(reference_reader(cap), decimate=1, **overrides)
    default = _run(reference_reader(cap), **overrides)
    return dense, default


def _interpolated(default, dense, name):
    return np.interp(dense["t"], default["t"], default[name])


def _resolved(values, fs=FS, window_s=400e-6):
    """What the estimator resolves: a moving average over half its window.

    Its step response takes about a window (its bandwidth is near
    1/(2π·window), 400 Hz at 400 µs), which a half-window average passes
    within 1 %; the per-sample ripple above it is estimator noise that no
    row density keeps (one row per drive period aliases it too).
    """
    n = int(0.5 * window_s * fs)
    return np.convolve(values, np.ones(n) / n, "same")


def _settling_10_90(t, values, start_s, before, after):
    """Time from ``start_s`` until ``values`` stays within 10 % of the step (from ``before`` to ``after``)."""
    # the moving average's last half window sees the zeros past the end
    outside = (t >= start_s) & (t < t[-1] - 1e-3) & (np.abs(values - after) > 0.1 * abs(after - before))
    return (t[np.flatnonzero(outside)[-1]] - start_s) if outside.any() else 0.0


def _three_sine(**kwargs) -> rs.Capture:
    drive = rs.three_sine(F0, 6000.0, AMPLITUDE_NM / (GAIN * Q), 0.5)
    return rs.simulate(f0_hz=F0, q=Q, gain_nm_per_v=GAIN, sample_rate_hz=FS, drive=drive, noise_nm=0.05, **kwargs)


def test_default_rows_are_eight_per_window_and_recorded():
    cap = _three_sine(duration_s=0.01, seed=1, free_air_s=0.01)
    results, columns = _run(reference_reader(cap))
    estimator = results.estimator
    assert results.rows == "resolution"
    # 23 samples (46 us): 8.7 rows per window, 3.22 drive periods apart so the rows walk through its phase
    assert estimator.row_every_samples == 23 and results.row_rate_hz == pytest.approx(FS / 23)
    assert 8 <= estimator.rows_per_window < 11
    assert np.allclose(np.diff(columns["t"]), 23 / FS)
    per_period, _ = _run(reference_reader(cap), rows="per-period")
    assert per_period.estimator.row_every_samples == 7 and per_period.rows == "per-period"
    # --decimate N still sets the spacing itself
    assert _run(reference_reader(cap), decimate=3)[0].estimator.row_every_samples == 3


def test_step_response_survives_the_default_rows():
    """A (−350 Hz, Q 200 → 90) step: same 10-90 % settling and the same levels as at every sample."""
    step_f0, step_q = F0 - 350.0, 90.0
    cap = _three_sine(duration_s=0.045, seed=4, free_air_s=STEP_S,
                      f0_of_t=lambda t: np.where(t < STEP_S, F0, step_f0),
                      q_of_t=lambda t: np.where(t < STEP_S, Q, step_q))
    (results, dense), (_, default) = _dense_and_default(cap, free_air="0.005:0.025")
    row_s = results.window_us * 1e-6 / 8
    for name, before, after in (("f0_hz", F0, step_f0), ("q", Q, step_q)):
        t = dense["t"]
        settle_dense = _settling_10_90(t, _resolved(dense[name]), STEP_S, before, after)
        settle_rows = _settling_10_90(t, _resolved(_interpolated(default, dense, name)), STEP_S, before, after)
        print(f"{name}: settling {settle_dense * 1e6:.0f} us at every sample, {settle_rows * 1e6:.0f} us from the rows")
        assert abs(settle_rows - settle_dense) <= row_s
        # the rows interpolated back, at what the estimator resolves: within its own stated 1 sigma
        std = np.median(dense["f0_std_hz" if name == "f0_hz" else "q_std"][dense["t"] > 0.01])
        near = (dense["t"] > STEP_S - 0.002) & (dense["t"] < STEP_S + 0.004)
        residual = (_resolved(_interpolated(default, dense, name)) - _resolved(dense[name]))[near]
        print(f"{name}: interpolated rows - every sample across the step: rms {np.sqrt(np.mean(residual ** 2)):.3g}, "
              f"stated std {std:.3g}")
        assert np.sqrt(np.mean(residual**2)) <= std


def test_one_nm_feature_survives_the_default_rows():
    """Tapping with a 1 nm bump in the sample (2 ms long): its f0′ and amplitude come through unchanged."""
    force = rs.PiecewiseLinearForce(4.0, 0.25e6**2, 2.5e6**2, 0.03e6, 0.0)
    free_s, on_nm = 0.01, 22.0
    separation = rs.SeparationSteps((0.0, free_s, 0.025, 0.027), (40.0, on_nm, on_nm - 1.0, on_nm))
    cap = _three_sine(duration_s=0.035, seed=5, force=force, separation_nm=separation, free_air_s=free_s)
    (_, dense), (_, default) = _dense_and_default(cap, free_air=f"0.001:{free_s - 0.001}")
    t = dense["t"]
    before, on_feature = (t > 0.02) & (t < 0.025), (t > 0.0255) & (t < 0.027)
    for name in ("f0_hz", "q", "amplitude"):
        rows = _interpolated(default, dense, name)
        shift_dense = dense[name][on_feature].mean() - dense[name][before].mean()
        shift_rows = rows[on_feature].mean() - rows[before].mean()
        scatter = np.std(dense[name][before])  # the series' own noise on the sample
        print(f"{name}: 1 nm feature shifts it by {shift_dense:.4g} (every sample), {shift_rows:.4g} (rows); "
              f"scatter {scatter:.3g}")
        assert abs(shift_dense) > 1.5 * scatter  # the feature is resolved at all
        assert abs(shift_rows - shift_dense) <= 0.25 * scatter
        near = (t > 0.024) & (t < 0.028)
        assert np.sqrt(np.mean((_resolved(rows) - _resolved(dense[name]))[near] ** 2)) <= 0.5 * scatter


class _Tee:
    """The run's columns both in memory (float64, as computed) and in a reep.h5 written as the command writes it."""

    def __init__(self, writer) -> None:
        self.writer, self.columns = writer, MemorySink()

    def append(self, columns):
        self.columns.append(columns)
        self.writer.append(columns)

    def put(self, *args, **kwargs):
        self.writer.put(*args, **kwargs)


def test_float32_storage_round_trips_f0_and_q(tmp_path):
    """Issue 33, item 2: float32 series keep f0′ and Q′ within 1e-6 relative; b1, b0 and t stay float64."""
    import h5py

    from afmtool.analyses.reep_outputs import FLOAT64_SERIES
    from afmtool.io.results import ResultWriter

    cap = _three_sine(duration_s=0.02, seed=2, free_air_s=0.02)
    with ResultWriter(tmp_path / "reep.h5", {}, float64=FLOAT64_SERIES) as writer:
        tee = _Tee(writer)
        run_reep(reference_reader(cap), resolve(ReepParams, {}), tee)
    with h5py.File(tmp_path / "reep.h5") as f:
        for name in ("f0_hz", "q", "f0_std_hz", "amplitude", "sigma2"):
            assert f[name].dtype == np.float32, name
        for name in FLOAT64_SERIES:
            assert f[name].dtype == np.float64, name
            np.testing.assert_array_equal(f[name][()], tee.columns[name])
        for name in ("f0_hz", "q"):
            stored, computed = f[name][()].astype(np.float64), tee.columns[name]
            finite = np.isfinite(computed)
            assert finite.sum() > 0.9 * len(computed)
            np.testing.assert_array_equal(np.isfinite(stored), finite)
            relative = np.abs(stored[finite] / computed[finite] - 1.0)
            print(f"{name}: float32 round trip, worst relative error {relative.max():.2e}")
            assert relative.max() <= 1e-6
