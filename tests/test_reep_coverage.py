"""REEP's per-row standard deviations cover the truth as often as they claim (issue 27, item 3).

``f0_std_hz`` and ``q_std`` in reep.h5 come from the RLS covariance and σ̂²
(``afmtool.estimators.rls._edge_covariance_2``).  On seeded captures of the
independent reference simulator the true f0 and Q must lie within ±2σ in
90–99 % of the rows after the warm-up (a Gaussian's ±2σ holds 95.4 %).
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

#: Coverage of ±2σ required of every cell.
COVERAGE = (0.90, 0.99)


def _free_air_rows(fs, f0, q, noise_nm, amplitude_nm, seed, duration_s=0.06):
    gain = 0.1
    cap = rs.simulate(f0_hz=f0, q=q, gain_nm_per_v=gain, sample_rate_hz=fs, duration_s=duration_s,
                      drive=rs.three_sine(f0, 6000.0, amplitude_nm / (gain * q), 0.5), noise_nm=noise_nm, seed=seed)
    columns = MemorySink()
    run_reep(reference_reader(cap), resolve(ReepParams, {}), columns)
    settled = columns["t"] > duration_s / 4
    return {name: columns[name][settled] for name in ("f0_hz", "q", "f0_std_hz", "q_std", "flag")}


def coverage(values, truth, std) -> float:
    """Share of rows whose value lies within ±2 std of the truth."""
    return float(np.mean(np.abs(values - truth) <= 2.0 * std))


#: (fs, f0, Q, noise nm, amplitude nm): the thesis's point, a stiff high-Q lever, a liquid-like Q.
FREE_AIR_CELLS = [
    (500e3, 70e3, 200.0, 0.05, 25.0),
    (1e6, 100e3, 600.0, 0.02, 10.0),
    (500e3, 70e3, 20.0, 0.05, 10.0),
]


@pytest.mark.parametrize(("fs", "f0", "q", "noise", "amplitude"), FREE_AIR_CELLS)
def test_free_air_coverage(fs, f0, q, noise, amplitude):
    rows = _free_air_rows(fs, f0, q, noise, amplitude, seed=11)
    assert not rows["flag"].any()
    f0_cov = coverage(rows["f0_hz"], f0, rows["f0_std_hz"])
    q_cov = coverage(rows["q"], q, rows["q_std"])
    print(f"fs {fs:g} f0 {f0:g} Q {q:g}: f0' ±2σ coverage {f0_cov:.3f} (std {np.median(rows['f0_std_hz']):.3g} Hz, "
          f"scatter {np.std(rows['f0_hz']):.3g}); Q' {q_cov:.3f}")
    assert COVERAGE[0] <= f0_cov <= COVERAGE[1]
    assert COVERAGE[0] <= q_cov <= COVERAGE[1]
