"""Electrostatic actuation of a cantilever over a substrate (thesis §6.4.2, §7.2).

One convention, used by ``identify electrostatic``, the EKF decoder and the
simulator alike:

* Units are SI inside this module: lengths in m, voltages in V, forces in N,
  K_esf in F·m (so K_esf·V²/ℓ² is in N).
* The deflection p is positive away from the sample (as for the tip-sample
  force in :mod:`afmtool.models.forces`); the lever-sample separation is
  ℓ_s = ℓ0 + p − z, with z the sample topography (positive = higher sample).
* The force is attractive, F_esf = −K_esf·V²/ℓ_s² (eq. 6.4), **without** the
  ½ that eqs. 7.5 and 7.7 carry and eqs. 6.4 and 7.11 do not.  Parameters
  identified with the ½ convention convert by K_esf(here) = K_esf(½)/2.
* Below the tip height the lever cannot come closer: ℓ_s is clipped at t_h
  (eq. 6.4, second case).
* The actuation voltage is V = α_R·V_R − V_sub (eq. 6.3); only V² enters.

Per unit mass (eq. 7.11): p″ + (ω0/Q)p′ + ω0²p = −ω0²·K_esf·V²/(k·ℓ_s²), since
F/m = ω0²·F/k.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from afmtool.errors import ConfigError

__all__ = [
    "ElectrostaticParams",
    "THESIS_CH7_PARAMS",
    "actuation_voltage",
    "electrostatic_force_n",
    "electrostatic_force_scalar",
    "static_deflection_polynomial",
]


@dataclass(frozen=True)
class ElectrostaticParams:
    """Static parameters of the electrostatic force (eqs. 6.3-6.7, 7.10).

    Parameters
    ----------
    spring_constant_n_per_m : float
        k, N/m.
    k_esf_f_m : float
        K_esf, F·m (no ½ convention, see the module docstring).
    alpha_r : float
        α_R, the share of V_R seen on the lever surface (eq. 6.3).
    l0_m : float
        ℓ0, the lever-sample separation at zero deflection, m.
    tip_height_m : float
        t_h, m.
    """

    spring_constant_n_per_m: float
    k_esf_f_m: float
    alpha_r: float
    l0_m: float
    tip_height_m: float

    def __post_init__(self) -> None:
        for name in ("spring_constant_n_per_m", "k_esf_f_m", "l0_m", "tip_height_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"{name}={value!r} must be a finite number > 0")
        if not math.isfinite(self.alpha_r):
            raise ConfigError(f"alpha_r={self.alpha_r!r} must be finite")


#: The thesis's identified values (eq. 7.10; f0 = 57,185 Hz, Q = 1.0148).
THESIS_CH7_PARAMS = ElectrostaticParams(
    spring_constant_n_per_m=0.1404,
    k_esf_f_m=1.66e-21,
    alpha_r=0.2549,
    l0_m=1081.8e-9,
    tip_height_m=768.3e-9,
)


def actuation_voltage(v_r, v_sub, alpha_r: float):
    """V = α_R·V_R − V_sub (eq. 6.3), V."""
    return alpha_r * np.asarray(v_r, dtype=np.float64) - np.asarray(v_sub, dtype=np.float64)


@njit(cache=True)
def electrostatic_force_scalar(p_m, voltage_v, l0_m, k_esf_f_m, z_m, tip_height_m):  # noqa: PLR0913
    """F_esf = −K_esf·V²/max(ℓ0 + p − z, t_h)² (eq. 6.4), N; for numba kernels."""
    separation = l0_m + p_m - z_m
    if separation < tip_height_m:
        separation = tip_height_m
    return -k_esf_f_m * voltage_v * voltage_v / (separation * separation)


def electrostatic_force_n(p_m, voltage_v, params: ElectrostaticParams, z_m=0.0) -> np.ndarray:
    """Vectorised F_esf (eq. 6.4), N, for deflection ``p_m`` (m) and voltage ``voltage_v`` (V)."""
    separation = params.l0_m + np.asarray(p_m, dtype=np.float64) - np.asarray(z_m, dtype=np.float64)
    separation = np.maximum(separation, params.tip_height_m)
    v = np.asarray(voltage_v, dtype=np.float64)
    return -params.k_esf_f_m * v * v / (separation * separation)


def static_deflection_polynomial(p_m, voltage_v, params: ElectrostaticParams) -> np.ndarray:
    """Residual of the static balance k·p = F_esf as the polynomial of eq. 6.6, N·m².

    k·p³ + 2ℓ0·k·p² + ℓ0²·k·p + K_esf·V² = 0 at equilibrium (before snap-in,
    ℓ_s > t_h, no tip-sample force).
    """
    p = np.asarray(p_m, dtype=np.float64)
    v = np.asarray(voltage_v, dtype=np.float64)
    k, l0 = params.spring_constant_n_per_m, params.l0_m
    return k * p**3 + 2 * l0 * k * p**2 + l0**2 * k * p + params.k_esf_f_m * v * v
