"""Interaction quantities (issue 17 item 1) against integrals of the reference force.

The truth is computed here by quadrature of tests/reference_sim.py's force along a
harmonic cycle p = a cos θ at separation l: the work −∮F dz, and the
first-harmonic integrals (1/2π)∮F cos θ dθ, (1/2π)∮F sin θ dθ.  The equivalent f0′
and Q′ such a cycle implies (the first-harmonic balance) go in; the module must
give back the integrals (Φ_c, Φ_d, E_ts, V_ts) in SI units, and k_e, k_e − k.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from afmtool.models.interaction import EV_PER_J, interaction_quantities
from tests import reference_sim as rs

F0, Q, K = 80318.0, 168.0, 2.0
W0 = 2 * math.pi * F0
MASS = K / W0**2


@pytest.mark.parametrize("l_nm", [22.0, 16.0, 12.0, 6.0])
def test_quantities_match_the_cycle_integrals_of_the_reference_force(l_nm):
    force = rs.PiecewiseLinearForce(4.0, 0.1e6**2, 0.303e6**2, 0.0092e6, 2000.0)
    a, omega = 15.0, W0 * 0.995
    theta = np.linspace(0.0, 2 * math.pi, 200_001)
    p, v = a * np.cos(theta), -a * omega * np.sin(theta)
    f = force(p, v, l_nm)  # nm/s² per unit mass
    work = np.trapezoid(f * np.gradient(p, theta), theta)  # ∮F dp, nm²/s²
    phi_c = np.trapezoid(f * np.cos(theta), theta) / (2 * math.pi)
    phi_d = np.trapezoid(f * np.sin(theta), theta) / (2 * math.pi)
    virial = np.trapezoid(f * p, theta) / (2 * math.pi)
    # the equivalent plant this cycle implies (first-harmonic balance)
    we2 = W0**2 - 2 * phi_c / a
    be = W0 / Q + 2 * phi_d / (a * omega)
    f0p, qp = math.sqrt(we2) / (2 * math.pi), math.sqrt(we2) / be
    out = interaction_quantities(f0p, qp, a, free_f0_hz=F0, free_q=Q, spring_constant_n_per_m=K,
                                 drive_frequency_hz=omega / (2 * math.pi))
    si = MASS * 1e-9  # per-mass nm/s² -> N
    energy_ev = -work * MASS * 1e-18 * EV_PER_J
    print(f"l {l_nm} nm: E_ts {float(out.energy_per_cycle_ev):.4g} eV (truth {energy_ev:.4g}), "
          f"Phi_c {float(out.phi_c_n):.4g} N (truth {phi_c * si:.4g}), Phi_d {float(out.phi_d_n):.4g} N")
    assert float(out.phi_c_n) == pytest.approx(phi_c * si, rel=1e-6, abs=1e-18)
    assert float(out.phi_d_n) == pytest.approx(phi_d * si, rel=1e-6, abs=1e-18)
    assert float(out.energy_per_cycle_ev) == pytest.approx(energy_ev, rel=1e-6, abs=1e-9)
    assert float(out.power_w) == pytest.approx(energy_ev / EV_PER_J * omega / (2 * math.pi), rel=1e-6, abs=1e-30)
    assert float(out.virial_j) == pytest.approx(virial * MASS * 1e-18, rel=1e-6, abs=1e-30)
    assert float(out.force_gradient_n_per_m) == pytest.approx(K * ((f0p / F0) ** 2 - 1), rel=1e-12, abs=1e-15)
    if l_nm > a + 4.0:  # no contact: nothing at all
        assert energy_ev == 0 and abs(float(out.energy_per_cycle_ev)) < 1e-9
    else:
        assert energy_ev > 0
    if a < l_nm < a + 4.0:  # attraction only: a negative force gradient, Φ_c > 0 (NOTES.md signs)
        assert float(out.force_gradient_n_per_m) < 0 < float(out.phi_c_n)
    if l_nm < a - 4.0:  # deep in the repulsive wall
        assert float(out.force_gradient_n_per_m) > 0
