"""The spring constant of a rectangular cantilever from its thermal spectrum: equipartition and Sader.

Both use the first flexural mode fitted by
:func:`afmtool.estimators.thermal_noise.fit_thermal_spectrum` (f0, Q and the
peak's area ⟨p²⟩).

*Thermal (equipartition) with the optical-lever correction.*  Each mode n of
a clamped-free Euler–Bernoulli beam holds k_B·T/2, so its end deflection has
⟨z_n²⟩ = 12·k_B·T/(k·(α_n L)⁴), α_1 L = 1.8751 (mode 1: 0.9707·k_B·T/k).  An
optical lever reads the slope at the end, and its sensitivity (InvOLS) is
calibrated by a static force curve, whose end-loaded shape has
slope·(2L/3) = deflection.  Mode 1's shape has slope·(2L/3) = deflection/χ,
χ = 1.0897, so the spectrum shows ⟨z*²⟩ = ⟨z_1²⟩/χ², and

    k = (12/(α_1 L)⁴)·(1/χ²)·k_B·T/⟨z*²⟩ = 0.8174·k_B·T/⟨z*²⟩

(Butt & Jaschke [1]_, eq. 17; the 1/χ² is their optical-lever factor).  A
spectrum of the tip's actual displacement (an interferometer) needs only the
mode-1 share: k = 0.9707·k_B·T/⟨z²⟩.

*Sader.*  From the plan-view length L and width b, the fluid's density ρ_f
and viscosity η, and the resonance in that fluid (ω_f = 2π f_f, Q_f) [2]_:

    k = 0.1906·ρ_f·b²·L·Q_f·Γ_i(Re)·ω_f²,   Re = ρ_f·ω_f·b²/(4η),

with Γ_i the imaginary part of the hydrodynamic function of a rectangular
beam, Γ_rect = Ω(Re)·Γ_circ(Re), Γ_circ = 1 + 4i·K_1(−i√(iRe))/(√(iRe)·K_0(−i√(iRe)))
and Ω the rational fit in τ = log10 Re of Sader (1998) [3]_.  Valid for
L/b ≳ 3 and Q_f ≫ 1.

References
----------
.. [1] H.-J. Butt and M. Jaschke, "Calculation of thermal noise in atomic
   force microscopy", Nanotechnology 6, 1–7 (1995).
.. [2] J. E. Sader, J. W. M. Chon and P. Mulvaney, "Calibration of
   rectangular atomic force microscope cantilevers", Rev. Sci. Instrum. 70,
   3967–3969 (1999).
.. [3] J. E. Sader, "Frequency response of cantilever beams immersed in
   viscous fluids with applications to the atomic force microscope",
   J. Appl. Phys. 84, 64–76 (1998).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from types import MappingProxyType
from typing import NamedTuple

import numpy as np

from afmtool.errors import ConfigError

__all__ = [
    "MODE1_SHARE",
    "OPTICAL_LEVER_FACTOR",
    "FLUIDS",
    "thermal_factor",
    "thermal_spring_constant",
    "SaderResult",
    "hydrodynamic_function_rectangular",
    "sader_spring_constant",
]

#: α_1 L of a clamped-free beam (first root of cos x·cosh x = −1).
_ALPHA1_L = 1.8751040687119611
#: ⟨z_1²⟩·k/(k_B·T) = 12/(α_1 L)⁴: mode 1's share of the thermal deflection.
MODE1_SHARE = 12.0 / _ALPHA1_L**4
#: χ = deflection/(slope·2L/3) of mode 1; the optical lever, calibrated statically, reads z_1/χ.
_CHI = 1.0897159631418622
#: k·⟨z*²⟩/(k_B·T) for an optical-lever spectrum calibrated by a static force curve: 0.8174 [1]_.
OPTICAL_LEVER_FACTOR = MODE1_SHARE / _CHI**2

#: (density kg/m³, dynamic viscosity Pa·s) at 25 °C, 1 atm.
FLUIDS: Mapping[str, tuple[float, float]] = MappingProxyType({"air": (1.184, 1.849e-5), "water": (997.05, 8.90e-4)})


def thermal_factor(detection: str) -> float:
    """The equipartition factor: 0.8174 for ``"optical-lever"``, 0.9707 for ``"displacement"``."""
    if detection == "optical-lever":
        return OPTICAL_LEVER_FACTOR
    if detection == "displacement":
        return MODE1_SHARE
    raise ConfigError(f"detection={detection!r} must be 'optical-lever' or 'displacement'")


def thermal_spring_constant(plain_n_per_m: float, detection: str = "optical-lever") -> float:
    """k = factor·k_B·T/⟨p²⟩ (N/m) from the plain one-mode equipartition value k_B·T/⟨p²⟩ (module docstring)."""
    return thermal_factor(detection) * plain_n_per_m


def _omega_correction(reynolds: float) -> complex:
    """Ω(Re) of Sader (1998), eq. 21: Γ_rect = Ω·Γ_circ."""
    tau = math.log10(reynolds)
    real = np.polyval([0.00069085, -0.0035117, 0.044055, -0.12886, 0.46842, -0.48274, 0.91324], tau) / np.polyval(
        [0.00069085, -0.0035862, 0.045155, -0.13444, 0.48690, -0.56964, 1.0], tau
    )
    imag = np.polyval([-0.000044510, 0.000064577, -0.00010961, 0.016294, -0.029256, -0.024134], tau) / np.polyval(
        [0.0028361, -0.014369, 0.079156, -0.18357, 0.55182, -0.59702, 1.0], tau
    )
    return complex(real, imag)


def hydrodynamic_function_rectangular(reynolds: float) -> complex:
    """Γ_rect(Re) = Ω(Re)·[1 + 4i·K_1(−i√(iRe))/(√(iRe)·K_0(−i√(iRe)))] (Sader 1998, eqs. 20, 21)."""
    from scipy.special import kv

    if not (math.isfinite(reynolds) and reynolds > 0):
        raise ConfigError(f"Reynolds number {reynolds!r} must be > 0")
    root = np.sqrt(1j * reynolds)
    circular = 1.0 + 4j * kv(1, -1j * root) / (root * kv(0, -1j * root))
    return complex(_omega_correction(reynolds) * circular)


class SaderResult(NamedTuple):
    """The Sader spring constant and what went into it.

    Attributes
    ----------
    spring_constant_n_per_m, spring_constant_std : float
        k (N/m) and its standard deviation from those of f0 and Q.
    reynolds : float
        Re = ρ_f·ω_f·b²/(4η).
    gamma_imag : float
        Γ_i(Re).
    """

    spring_constant_n_per_m: float
    spring_constant_std: float
    reynolds: float
    gamma_imag: float


def _sader(f0_hz: float, q: float, length_m: float, width_m: float, density: float, viscosity: float):
    omega = 2.0 * math.pi * f0_hz
    reynolds = density * omega * width_m**2 / (4.0 * viscosity)
    gamma_i = hydrodynamic_function_rectangular(reynolds).imag
    return 0.1906 * density * width_m**2 * length_m * q * gamma_i * omega**2, reynolds, gamma_i


def sader_spring_constant(
    f0_hz: float,
    q: float,
    length_m: float,
    width_m: float,
    *,
    fluid: str = "air",
    density_kg_per_m3: float | None = None,
    viscosity_pa_s: float | None = None,
    f0_std_hz: float = 0.0,
    q_std: float = 0.0,
) -> SaderResult:
    """Spring constant of a rectangular cantilever by the Sader method (module docstring, [2]_).

    Parameters
    ----------
    f0_hz, q : float
        Resonant frequency (Hz) and quality factor in the fluid.
    length_m, width_m : float
        Plan-view length L and width b, m.
    fluid : {"air", "water"}
        Supplies ρ_f and η (at 25 °C) unless given.
    density_kg_per_m3, viscosity_pa_s : float, optional
        ρ_f (kg/m³) and η (Pa·s).
    f0_std_hz, q_std : float
        Standard deviations, propagated to k by finite differences.

    Returns
    -------
    SaderResult

    Notes
    -----
    k = 0.1906·ρ_f·b²·L·Q_f·Γ_i(Re)·ω_f², Re = ρ_f·ω_f·b²/(4η).
    """
    if fluid not in FLUIDS:
        raise ConfigError(f"fluid={fluid!r} must be one of {', '.join(FLUIDS)}")
    density = density_kg_per_m3 or FLUIDS[fluid][0]
    viscosity = viscosity_pa_s or FLUIDS[fluid][1]
    for name, value in (("f0_hz", f0_hz), ("q", q), ("length_m", length_m), ("width_m", width_m),
                        ("density", density), ("viscosity", viscosity)):
        if not (math.isfinite(value) and value > 0):
            raise ConfigError(f"{name}={value!r} must be a finite number > 0")
    k, reynolds, gamma_i = _sader(f0_hz, q, length_m, width_m, density, viscosity)
    # k ∝ Q exactly; f0 enters through ω² and Γ_i(Re(ω)): a central difference
    h = 1e-6 * f0_hz
    dk_df = (_sader(f0_hz + h, q, length_m, width_m, density, viscosity)[0]
             - _sader(f0_hz - h, q, length_m, width_m, density, viscosity)[0]) / (2 * h)
    k_std = math.hypot(dk_df * f0_std_hz, k / q * q_std)
    return SaderResult(float(k), float(k_std), float(reynolds), float(gamma_i))
