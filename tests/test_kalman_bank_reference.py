"""The Kalman-bank acceptance (tests/test_kalman_bank.py) on a force curve from the independent reference simulator.

Same settings as the afmtool ``tapping`` captures there (the thesis's
§3.4.3 attractive set, f0 80,318 Hz, Q 168, 20 nm free amplitude, 30 → 2 nm
and back in 0.4 s, side lines at a quarter of the main line), integrated by
tests/reference_sim.py with a continuous drive; same tolerances: every
filter's RMS minimum in its design bin, the adaptive observer least ≥ 90 %
of the time, and a bank 2 % high in f0 fails.
"""

from __future__ import annotations

import numpy as np
import pytest

from afmtool.analyses.kalman_bank import run_kalman_bank
from afmtool.config import resolve
from afmtool.config.params import KalmanBankParams
from afmtool.records.common import DriveHold
from tests import reference_sim as rs
from tests.test_kalman_bank import ADAPTIVE_FRACTION, Columns
from tests.test_reep_reference import reference_reader

F0, Q, GAIN, FS = 80318.0, 168.0, 1.0, 500e3


def _force_curve(duration_s=0.4, start_nm=30.0, turn_nm=2.0, free_fraction=0.2):
    free_s = free_fraction * duration_s
    ramp_s = (duration_s - free_s) / 2

    def separation(t):
        t = np.asarray(t, dtype=np.float64)
        down = start_nm - (start_nm - turn_nm) * (t - free_s) / ramp_s
        up = turn_nm + (start_nm - turn_nm) * (t - free_s - ramp_s) / ramp_s
        return np.where(t < free_s, start_nm, np.where(t < free_s + ramp_s, down, np.minimum(up, start_nm)))

    return separation


@pytest.fixture(scope="module")
def reference_curve():
    amplitude_v = 20.0 / (GAIN * Q)  # 20 nm free amplitude of the main line at f0
    cap = rs.simulate(
        f0_hz=F0, q=Q, gain_nm_per_v=GAIN, sample_rate_hz=FS, duration_s=0.4,
        drive=rs.three_sine(F0, 6000.0, amplitude_v, 0.25), noise_nm=0.05, seed=1,
        force=rs.ATTRACTIVE_SET, separation_nm=_force_curve(), record_z_piezo=True,
    )
    return cap


def _run(cap, **overrides):
    columns = Columns()
    return run_kalman_bank(reference_reader(cap), resolve(KalmanBankParams, overrides), columns)


def test_bank_verdict_on_a_reference_force_curve(reference_curve):
    res = _run(reference_curve).results
    adaptive = res.adaptive
    print(
        f"reference attractive: design z {[f.design_z for f in res.filters]}, least-RMS offsets "
        f"{[f.min_bin_offset for f in res.filters]}, adaptive least {adaptive.fraction_lowest:.1%}; "
        f"hold {res.free_air_route.drive_hold.value}"
    )
    assert res.free_air_route.drive_hold is DriveHold.CONTINUOUS
    assert len(res.filters) == 5
    for f in res.filters:
        assert f.min_bin_offset == 0, f
    assert abs(res.filters[0].f0_hz - res.filters[-1].f0_hz) > 300.0
    assert adaptive.fraction_lowest >= ADAPTIVE_FRACTION
    assert res.verdict.pass_, res.verdict.reasons


def test_bank_two_percent_high_fails_on_the_reference(reference_curve):
    verdict = _run(reference_curve, f0_scale=1.02).results.verdict
    assert not verdict.pass_
    assert len(verdict.reasons) >= 5
