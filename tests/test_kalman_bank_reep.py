"""One REEP (issue 29, item 1): kalman-bank's per-sample REEP is ``reep``'s, bit for bit, the trap included.

In filterpy's manner the same estimator is run two ways and compared number
for number: ``reep``'s stage (the columns of reep.h5) and kalman-bank's pass 2,
whose adaptive observer follows REEP sample by sample (bank.h5's
``reep_f0_hz``, ``reep_q``).  Both are built by
:func:`afmtool.analyses.reep.build_reep_estimator` from one ``ReepParams``
(``[kalman-bank.reep]``), so they must agree at every row.  Before this, pass 2
ran its own REEP without the static-offset regressor and saw f0′ fall to
16.4 kHz in the attractive trap of ``sample_data/force_curve_thesis.h5``, where
pass 1 stayed at or above 64.9 kHz.

The curve is the reference simulator's (tests/reference_sim.py), into the
attractive trap and back, at 500 kHz (REEP at the capture's rate) and at
2 MHz (REEP at fs/D, its rows held for the observer).  In the trap the
adaptive observer's f0′ must lie within 10 % of averaging theory (the
first-harmonic balance by quadrature, tests/test_reep_validity.py).
"""

from __future__ import annotations

import numpy as np
import pytest

from afmtool.analyses.kalman_bank import run_kalman_bank
from afmtool.analyses.kalman_bank_reep import bank_reep_params
from afmtool.analyses.reep import run_reep
from afmtool.config import resolve
from afmtool.config.params import KalmanBankParams
from afmtool.io.registry import open_capture
from tests import reference_sim as ref
from tests.conftest import SAMPLE_DATA
from tests.test_kalman_bank import Columns
from tests.test_reep_reference import reference_reader
from tests.test_reep_validity import THESIS_ATTRACTIVE, first_harmonic_f0_hz

F0, Q = 80318.0, 168.0
#: Acceptance: |f0′/f0_e − 1| in the trap.
TRAP_TOLERANCE = 0.10


def _trap_curve(fs: float, duration_s: float) -> ref.Capture:
    """Free air at 30 nm for a fifth, down to 2 nm (the bottom of the trap) and back, as the bundled capture."""
    free_s = 0.2 * duration_s
    turn_s = duration_s / 2 + free_s / 2

    def separation(t):
        t = np.asarray(t, dtype=float)
        down = 30.0 - 28.0 * np.clip((t - free_s) / (turn_s - free_s), 0.0, 1.0)
        up = 2.0 + 28.0 * np.clip((t - turn_s) / (duration_s - turn_s), 0.0, 1.0)
        return np.where(t <= turn_s, down, up)

    return ref.simulate(
        f0_hz=F0, q=Q, gain_nm_per_v=1.0, sample_rate_hz=fs, duration_s=duration_s,
        drive=ref.three_sine(F0, 6000.0, 20.0 / Q, side_scale=0.25), noise_nm=0.05, seed=3,
        force=THESIS_ATTRACTIVE, separation_nm=separation, record_z_piezo=True, free_air_s=free_s,
    )


def _both(reader_factory):
    """(reep's columns and result, kalman-bank's columns) on one capture, with kalman-bank's REEP parameters."""
    params = resolve(KalmanBankParams, {})
    bank_columns = Columns()
    with reader_factory() as reader:
        run_kalman_bank(reader, params, bank_columns)
    reep_columns = Columns()
    with reader_factory() as reader:
        result = run_reep(reader, bank_reep_params(params), reep_columns)
    return reep_columns, result, bank_columns


class _Open:
    """A context manager around a reader factory (in-memory readers need no closing)."""

    def __init__(self, make):
        self.make = make

    def __call__(self):
        return self

    def __enter__(self):
        self.reader = self.make()
        return self.reader

    def __exit__(self, *exc):
        close = getattr(self.reader, "close", None)
        if close is not None:
            close()


@pytest.mark.parametrize(("fs", "duration_s"), [(500e3, 0.2), pytest.param(2e6, 0.2, marks=pytest.mark.long)])
def test_bank_reep_equals_reep_bit_for_bit_in_the_trap(fs, duration_s):
    cap = _trap_curve(fs, duration_s)
    reep, result, bank = _both(_Open(lambda: reference_reader(cap)))
    t_reep, t_bank = reep["t"], bank["t"]
    factor = result.results.estimator.rate_reduction
    np.testing.assert_array_equal(t_bank, t_reep)  # one row grid: REEP's
    # bit for bit: the same estimator, the same state, the same rows (NaN where not under-damped)
    np.testing.assert_array_equal(bank["reep_f0_hz"], reep["f0_hz"])
    np.testing.assert_array_equal(bank["reep_q"], reep["q"])
    # in the trap, the adaptive observer's f0' against averaging theory at the row's amplitude and separation
    index = np.round(t_reep * fs).astype(int)
    theory = first_harmonic_f0_hz(reep["amplitude"], cap.truth["separation_nm"][index], F0, THESIS_ATTRACTIVE)
    settled = (t_reep > 5 * result.results.window_us * 1e-6) & (reep["flag"] == 0)
    trap = settled & (theory < 0.85 * F0)
    error = np.abs(bank["reep_f0_hz"][trap] / theory[trap] - 1.0)
    print(f"fs {fs:g} (D = {factor}): {trap.sum()} rows in the trap, worst |f0'/f0_e - 1| = {error.max():.4f}, "
          f"least f0' there {np.nanmin(bank['reep_f0_hz'][trap]):.0f} Hz (theory {theory[trap].min():.0f})")
    # over 2.4 ms in the trap (200 rows of one drive period before issue 33's rows at REEP's resolution)
    assert trap.sum() * result.results.row_every_samples / fs > 2.4e-3
    assert error.max() <= TRAP_TOLERANCE


@pytest.mark.long
def test_bundled_force_curve_trap_is_not_read_at_16_khz():
    """The issue's capture: pass 2's REEP in the trap stays with pass 1's (≥ 60 kHz), not at 16.4 kHz."""
    path = SAMPLE_DATA / "force_curve_thesis.h5"
    reep, result, bank = _both(_Open(lambda: open_capture(path)))
    np.testing.assert_array_equal(bank["reep_f0_hz"], reep["f0_hz"])
    settled = (reep["t"] > 5 * result.results.window_us * 1e-6) & (reep["flag"] == 0)
    least = float(np.nanmin(bank["reep_f0_hz"][settled]))
    print(f"bundled force curve: least unflagged f0' in pass 2 {least:.0f} Hz")
    assert least > 60e3
