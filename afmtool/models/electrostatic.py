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

Static balance before snap-in (eqs. 6.5-6.7)
--------------------------------------------
With no tip-sample force, k·p = −K_esf·V²/(ℓ0 + p)² (eq. 6.5, z = 0).  Only
the ratio ρ = K_esf/k (m³/V²) enters: p(ℓ0 + p)² = −ρV².  On the stable
branch −ℓ0/3 < p ≤ 0 the left side increases with p, so there is one
root while ρV² ≤ 4ℓ0³/27 and none beyond, the electrostatic pull-in
(:func:`stable_deflection_m`).  Eq. 6.7 is the same balance written in the
tip-sample separation, t_s = ℓ0 + p − t_h.

Small-signal actuation (eqs. 6.13, 6.14)
----------------------------------------
Linearising F_esf about (V0, ℓ_s0) gives ∂F/∂p = 2K_esf·V0²/ℓ_s0³ and
∂F/∂V = −2K_esf·V0/ℓ_s0², hence, with κ = 2K_esf·V0²/(k·ℓ_s0³),

    Γ_p,V(s) = L·ω′²/(s² + (ω′/Q′)s + ω′²),  ω′ = ω0√(1 − κ),
    Q′ = Q0√(1 − κ),  L = −2K_esf·V0/(k·ℓ_s0²)/(1 − κ)   (m/V),

the thesis's eq. 6.14 with its denominator corrected (docs/conventions.md) and the
1/k that eq. 6.13 leaves implicit (it writes the force per unit stiffness)
made explicit.  The input is V = α_R·V_R − V_sub, so Δt_s/ΔV_sub = −Γ_p,V
at constant V_R and sample position.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit

from afmtool.errors import ConfigError
from afmtool.jit import JIT_OPTIONS

__all__ = [
    "ElectrostaticParams",
    "THESIS_CH7_PARAMS",
    "actuation_voltage",
    "LeverVoltages",
    "electrostatic_force_n",
    "electrostatic_force_scalar",
    "static_deflection_polynomial",
    "thermal_separation_polynomial",
    "stable_deflection_m",
    "pull_in_voltage_v",
    "ActuationSmallSignal",
    "linearise_actuation",
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
        t_h, m; 0 when not known (the separation is then not clamped: it
        matters only with the lever within t_h of the sample).
    """

    spring_constant_n_per_m: float
    k_esf_f_m: float
    alpha_r: float
    l0_m: float
    tip_height_m: float

    def __post_init__(self) -> None:
        for name in ("spring_constant_n_per_m", "k_esf_f_m", "l0_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"{name}={value!r} must be a finite number > 0")
        if not (math.isfinite(self.tip_height_m) and self.tip_height_m >= 0):
            raise ConfigError(f"tip_height_m={self.tip_height_m!r} must be a finite number >= 0 (0: not known)")
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


class LeverVoltages(NamedTuple):
    """The read-heater and substrate voltages V_R, V_sub (V) and α_R that form V (eq. 6.3).

    Handed to a kernel as they are, which forms V = α_R·V_R − V_sub per
    sample, rather than as a V series: at MHz rates that array costs more
    to build than the filter spends on it.
    """

    v_r: np.ndarray
    v_sub: np.ndarray
    alpha_r: float


@njit(**JIT_OPTIONS)
def electrostatic_force_scalar(p_m, voltage_v, l0_m, k_esf_f_m, z_m, tip_height_m):
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


def thermal_separation_polynomial(separation_m, voltage_v, params: ElectrostaticParams) -> np.ndarray:
    """Residual of eq. 6.7, k(t_s + t_h − ℓ0)(t_s + t_h)² + K_esf·V², N·m².

    Zero at equilibrium before snap-in, with t_s the tip-sample separation
    (m) measured by the thermal sensor; the deflection is p = t_s + t_h − ℓ0.
    """
    lever = np.asarray(separation_m, dtype=np.float64) + params.tip_height_m
    v = np.asarray(voltage_v, dtype=np.float64)
    k = params.spring_constant_n_per_m
    return k * (lever - params.l0_m) * lever**2 + params.k_esf_f_m * v * v


def stable_deflection_m(voltage_v, ratio_m3_per_v2: float, l0_m: float) -> np.ndarray:
    """The stable root p of p(ℓ0 + p)² = −ρV² (eq. 6.6 divided by k), m.

    Parameters
    ----------
    voltage_v : array_like
        V = α_R·V_R − V_sub, V.
    ratio_m3_per_v2 : float
        ρ = K_esf/k, m³/V² (> 0).
    l0_m : float
        ℓ0, m (> 0).

    Returns
    -------
    numpy.ndarray
        p in (−ℓ0/3, 0], m; NaN beyond pull-in (ρV² > 4ℓ0³/27).

    Notes
    -----
    In x = p/ℓ0 and c = ρV²/ℓ0³ the balance is f(x) = x(1 + x)² + c = 0.
    On −1/3 ≤ x ≤ 0, f increases (f′ = (1 + x)(1 + 3x) ≥ 0) and is convex
    (f″ = 6x + 4 > 0), and f(0) = c ≥ 0, so Newton's method from x = 0
    decreases monotonically onto the root without overshooting it.
    """
    if not (math.isfinite(ratio_m3_per_v2) and ratio_m3_per_v2 > 0):
        raise ConfigError(f"ratio_m3_per_v2={ratio_m3_per_v2!r} must be a finite number > 0")
    if not (math.isfinite(l0_m) and l0_m > 0):
        raise ConfigError(f"l0_m={l0_m!r} must be a finite number > 0")
    v = np.asarray(voltage_v, dtype=np.float64)
    c = ratio_m3_per_v2 * v * v / l0_m**3
    x = np.zeros_like(c)
    for _ in range(200):
        f = x * (1.0 + x) ** 2 + c
        df = (1.0 + x) * (1.0 + 3.0 * x)
        with np.errstate(divide="ignore", invalid="ignore"):
            step = np.where(df > 0, f / df, 0.0)
        x = np.maximum(x - step, -1.0 / 3.0)
        if np.all(np.abs(step) <= 1e-15):
            break
    return np.where(c <= 4.0 / 27.0, x * l0_m, np.nan)


def pull_in_voltage_v(ratio_m3_per_v2: float, l0_m: float) -> float:
    """|V| at which the stable branch of eq. 6.6 ends: √(4ℓ0³/(27ρ)), V."""
    return math.sqrt(4.0 * l0_m**3 / (27.0 * ratio_m3_per_v2))


class ActuationSmallSignal(NamedTuple):
    """Γ_p,V of eq. 6.14 (corrected): ω′/2π (Hz), Q′, L (m/V) and κ."""

    f0_hz: float
    q: float
    gain_m_per_v: float
    stiffness_ratio: float

    def response(self, frequency_hz) -> np.ndarray:
        """Γ_p,V(j2πf) = L·ω′²/(s² + (ω′/Q′)s + ω′²), m/V (input V = α_R·V_R − V_sub)."""
        s = 2j * np.pi * np.asarray(frequency_hz, dtype=np.float64)
        w = 2 * np.pi * self.f0_hz
        return self.gain_m_per_v * w * w / (s * s + (w / self.q) * s + w * w)

    def tf(self) -> tuple[np.ndarray, np.ndarray]:
        """(numerator, denominator) of Γ_p,V in descending powers of s (rad/s)."""
        w = 2 * np.pi * self.f0_hz
        return np.array([self.gain_m_per_v * w * w]), np.array([1.0, w / self.q, w * w])


def linearise_actuation(
    params: ElectrostaticParams, f0_hz: float, q: float, voltage_v: float, separation_m: float
) -> ActuationSmallSignal:
    """Linearise the electrostatically forced lever about (V0, ℓ_s0) (eqs. 6.13, 6.14).

    Parameters
    ----------
    params : ElectrostaticParams
        k and K_esf are used.
    f0_hz, q : float
        Free-air f0 (Hz) and Q0 of eq. 6.1.
    voltage_v : float
        V0 = α_R·V_R0 − V_sub0, V.
    separation_m : float
        ℓ_s0 = ℓ0 + p0 − z, the lever-sample separation at equilibrium, m
        (> t_h: the lever is off the sample).

    Returns
    -------
    ActuationSmallSignal

    Raises
    ------
    ConfigError
        For bad arguments, or κ ≥ 1 (no stable equilibrium: snap-in).
    """
    for name, value in (("f0_hz", f0_hz), ("q", q), ("separation_m", separation_m)):
        if not (math.isfinite(value) and value > 0):
            raise ConfigError(f"{name}={value!r} must be a finite number > 0")
    if not math.isfinite(voltage_v):
        raise ConfigError(f"voltage_v={voltage_v!r} must be finite")
    if separation_m <= params.tip_height_m:
        raise ConfigError(f"separation_m={separation_m!r} must exceed the tip height {params.tip_height_m!r}")
    k, kesf = params.spring_constant_n_per_m, params.k_esf_f_m
    # κ = (∂F/∂p)/k = 2K_esf·V0²/(k·ℓ_s0³)
    kappa = 2.0 * kesf * voltage_v**2 / (k * separation_m**3)
    if kappa >= 1.0:
        raise ConfigError(
            f"voltage_v={voltage_v!r} at separation_m={separation_m!r} is past snap-in (κ = {kappa:.3g} >= 1)"
        )
    root = math.sqrt(1.0 - kappa)
    # L = (∂F/∂V)/(k(1 − κ)) = −2K_esf·V0/(k·ℓ_s0²(1 − κ))
    gain = -2.0 * kesf * voltage_v / (k * separation_m**2) / (1.0 - kappa)
    return ActuationSmallSignal(f0_hz * root, q * root, gain, kappa)
