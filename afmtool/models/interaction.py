"""Tip-sample interaction quantities from REEP's f0′, Q′ and amplitude (issue 17 item 1).

The cantilever is one mode of mass m = k/ω0² (k the spring constant, N/m;
ω0 = 2πf0 the free-air resonance).  REEP gives the equivalent plant
p̈ + (ωe/Qe)ṗ + ωe²p = ω0²g (eq. 3.1 with the interaction folded in), and
averaging theory (eqs. 4.6-4.8, closed form in
:mod:`afmtool.models.averaging`) reads it as the first-harmonic balance of the
tip-sample force F over one cycle p = a cos θ:

.. math::

    \\omega_e^2 = \\omega_0^2 - \\frac{2\\Phi_c}{a},\\qquad
    \\frac{\\omega_e}{Q_e} = \\frac{\\omega_0}{Q} + \\frac{2\\Phi_d}{a\\omega},

Φ_c = (1/2π)∮F cos θ dθ and Φ_d = (1/2π)∮F sin θ dθ (per unit mass; the
docs/conventions.md sign convention, force positive away from the sample, so that
attraction gives Φ_c > 0 and dissipation Φ_d > 0; eq. 4.8 writes Φ_d with the
opposite sign).  Inverting with the measured a, f0′ = ωe/2π and Q′ = Qe:

- equivalent stiffness k_e = k(f0′/f0)² and force gradient k_e − k
  (eqs. 1.2-1.4; k_e − k = −∂F/∂z for a small oscillation);
- equivalent damping c_e = m ωe/Qe (N·s/m) and its tip-sample part
  c_ts = c_e − m ω0/Q;
- Φ_c·m = k a (1 − (f0′/f0)²)/2 and Φ_d·m = a ω c_ts/2, in N: the average
  conservative force and the average dissipative force per cycle
  (eqs. 4.6-4.7);
- the energy the tip-sample force dissipates per cycle,
  E_ts = −∮F dz = π c_ts ω a² = 2π a Φ_d m (J, reported in eV), the
  mean dissipated power P_ts = E_ts ω/2π (W), and the virial
  V_ts = ⟨F p⟩ over a cycle = a Φ_c m (J; the definition of San Paulo &
  García, Phys. Rev. B 64, 193411 (2001), here with the docs/conventions.md signs, so
  attraction gives V_ts > 0).

All are per sample, broadcast over the inputs; nm in, SI out.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from afmtool.errors import ConfigError

__all__ = ["EV_PER_J", "InteractionQuantities", "interaction_quantities"]

#: 1 J in eV (exact, SI 2019).
EV_PER_J = 1.0 / 1.602176634e-19
_M_PER_NM = 1e-9


class InteractionQuantities(NamedTuple):
    """Per-sample interaction quantities, SI units (module docstring)."""

    k_e_n_per_m: np.ndarray
    force_gradient_n_per_m: np.ndarray
    damping_n_s_per_m: np.ndarray
    damping_ts_n_s_per_m: np.ndarray
    phi_c_n: np.ndarray
    phi_d_n: np.ndarray
    energy_per_cycle_ev: np.ndarray
    power_w: np.ndarray
    virial_j: np.ndarray

    #: units per field, for writers
    @staticmethod
    def units() -> dict[str, str]:
        return {"k_e_n_per_m": "N/m", "force_gradient_n_per_m": "N/m", "damping_n_s_per_m": "N*s/m",
                "damping_ts_n_s_per_m": "N*s/m", "phi_c_n": "N", "phi_d_n": "N", "energy_per_cycle_ev": "eV",
                "power_w": "W", "virial_j": "J"}


def interaction_quantities(
    f0_hz,
    q,
    amplitude_nm,
    *,
    free_f0_hz: float,
    free_q: float,
    spring_constant_n_per_m: float,
    drive_frequency_hz: float,
) -> InteractionQuantities:
    """k_e, k_e − k, c_e, c_ts, Φ_c, Φ_d, E_ts (eV), P_ts, V_ts from f0′, Q′ and a (module docstring).

    Parameters
    ----------
    f0_hz, q : array_like
        REEP's f0′ (Hz) and Q′.
    amplitude_nm : array_like
        Oscillation amplitude a, nm.
    free_f0_hz, free_q : float
        Free-air f0 (Hz) and Q.
    spring_constant_n_per_m : float
        k, N/m.
    drive_frequency_hz : float
        Oscillation frequency ω/2π, Hz.

    Returns
    -------
    InteractionQuantities
    """
    for name, value in (("free_f0_hz", free_f0_hz), ("free_q", free_q),
                        ("spring_constant_n_per_m", spring_constant_n_per_m),
                        ("drive_frequency_hz", drive_frequency_hz)):
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise ConfigError(f"{name}={value!r} must be a finite number > 0")
    f0, qe, a_nm = np.broadcast_arrays(*(np.asarray(v, dtype=np.float64) for v in (f0_hz, q, amplitude_nm)))
    k = float(spring_constant_n_per_m)
    w0 = 2.0 * math.pi * free_f0_hz
    mass = k / (w0 * w0)
    we = 2.0 * math.pi * f0
    omega = 2.0 * math.pi * drive_frequency_hz
    a = a_nm * _M_PER_NM
    ratio2 = (f0 / free_f0_hz) ** 2
    k_e = k * ratio2  # eqs. 1.2-1.4
    damping = mass * we / qe
    damping_ts = damping - mass * w0 / free_q
    phi_c = 0.5 * k * a * (1.0 - ratio2)  # Φ_c·m: ωe² = ω0² − 2Φ_c/a (eq. 4.6)
    phi_d = 0.5 * a * omega * damping_ts  # Φ_d·m: ωe/Qe = ω0/Q + 2Φ_d/(aω) (eq. 4.7)
    energy = math.pi * damping_ts * omega * a * a  # −∮F dz for p = a cos ωt
    return InteractionQuantities(
        k_e, k_e - k, damping, damping_ts, phi_c, phi_d, energy * EV_PER_J, energy * omega / (2.0 * math.pi),
        a * phi_c,
    )
