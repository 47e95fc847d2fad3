"""REEP against averaging theory on reference-simulator force curves (issue 14, item 2).

tests/test_reep_theory.py's comparison and tolerance (25 % of the theory's change
along the curve) on force curves integrated by tests/reference_sim.py: the §3.4.3
force sets written out here from the thesis (eq. 4.1 magnitudes), a continuous
three-sine drive, 20 nm free amplitude, 30 → 2 nm and back in 0.4 s.
"""

from __future__ import annotations

import numpy as np
import pytest

from afmtool.analyses.reep import run_reep
from afmtool.analyses.theory import compare_with_theory
from afmtool.config import resolve
from afmtool.config.params import ReepParams
from afmtool.models.cantilever import Cantilever
from afmtool.models.forces import THESIS_FORCE_SETS
from tests import reference_sim as rs
from tests.test_kalman_bank_reference import _force_curve
from tests.test_reep import _Columns
from tests.test_reep_reference import reference_reader

F0, Q, FS = 80318.0, 168.0, 500e3
FREE_AMPLITUDE_NM = 20.0
TOLERANCE = 0.25
#: §3.4.3 (Figs. 3.11-3.13): d (nm), ω_a², ω_b² (1/s²), c_a, c_b (1/s).
REFERENCE_FORCES = {
    "attractive": rs.PiecewiseLinearForce(4.0, 0.31e6**2, 3.03e6**2, 0.042e6, 0.0),
    "attractive-repulsive": rs.PiecewiseLinearForce(4.0, 0.1e6**2, 0.303e6**2, 0.0092e6, 0.0),
    "repulsive": rs.PiecewiseLinearForce(5.0, 0.11e6**2, 0.63e6**2, 0.0042e6, 0.0),
}


@pytest.mark.long
@pytest.mark.parametrize("force_set", sorted(REFERENCE_FORCES))
def test_reep_agrees_with_averaging_theory_on_the_reference(force_set):
    cap = rs.simulate(
        f0_hz=F0, q=Q, gain_nm_per_v=1.0, sample_rate_hz=FS, duration_s=0.4,
        drive=rs.three_sine(F0, 6000.0, FREE_AMPLITUDE_NM / Q, 0.25), noise_nm=0.05, seed=1,
        force=REFERENCE_FORCES[force_set], separation_nm=_force_curve(), record_z_piezo=True,
    )
    params = resolve(ReepParams, {"decimate": 1})
    columns = _Columns()
    result = run_reep(reference_reader(cap), params, columns)
    t = columns["t"]
    index = np.round(t * FS).astype(int)
    comparison = compare_with_theory(
        t, columns["f0_hz"], columns["q"], columns["amplitude"], cap.truth["separation_nm"][index],
        drive_frequency_hz=result.results["drive_frequency_hz"], cantilever=Cantilever(F0, Q),
        force=THESIS_FORCE_SETS[force_set], forgetting_factor=params.lam, free_amplitude_nm=FREE_AMPLITUDE_NM,
    )
    print(force_set, comparison.summary())
    assert comparison.f0_theory_change_hz > 100.0
    assert comparison.excluded_near_jumps < 0.02 * comparison.mask.sum()
    assert comparison.f0_error_fraction <= TOLERANCE
    assert comparison.q_error_fraction <= TOLERANCE
