"""The one-mode cantilever model.

The first flexural mode of the cantilever is the second-order system of
eq. 3.1 with the tip-sample force removed ("sample-free" or "free-air"
model),

.. math:: \\ddot p + (\\omega_0/Q)\\dot p + \\omega_0^2 p = \\omega_0^2 g(t),

so that its transfer function from the dither forcing ``g`` (nm) to the
deflection ``p`` (nm) is

.. math:: G(s) = \\frac{\\omega_0^2}{s^2 + (\\omega_0/Q)s + \\omega_0^2},

with unit DC gain and ``|G(j\\omega_0)| = Q``.  Its sampled (discrete-time)
forms are in :mod:`afmtool.models.discretisation`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from afmtool.errors import ConfigError

__all__ = ["Cantilever", "DEFAULT_SPRING_CONSTANT_N_PER_M"]

#: Spring constant used when none is given: the AC240 lever of §3.5
#: (f0 = 71.5 kHz, Q = 206, k = 2 N/m), N/m.
DEFAULT_SPRING_CONSTANT_N_PER_M = 2.0


def _check_positive(name: str, value: float) -> None:
    if not (isinstance(value, (int, float, np.floating, np.integer)) and math.isfinite(value) and value > 0):
        raise ConfigError(f"{name}={value!r} must be a finite number > 0")


@dataclass(frozen=True)
class Cantilever:
    """Free-air first mode of a cantilever (eq. 3.1 with Φ = 0).

    Parameters
    ----------
    f0_hz : float
        Resonant frequency f0 = ω0/2π of the first mode, Hz.
    q : float
        Quality factor Q (dimensionless).
    spring_constant_n_per_m : float, optional
        Spring constant k, N/m.  It does not enter the per-unit-mass
        dynamics; it sets the thermal-noise level (k⟨p²⟩ = k_B·T) and is
        recorded in capture metadata.

    Raises
    ------
    ConfigError
        If any parameter is not a finite number > 0.
    """

    f0_hz: float
    q: float
    spring_constant_n_per_m: float = DEFAULT_SPRING_CONSTANT_N_PER_M

    def __post_init__(self) -> None:
        _check_positive("f0_hz", self.f0_hz)
        _check_positive("q", self.q)
        _check_positive("spring_constant_n_per_m", self.spring_constant_n_per_m)

    @property
    def omega0_rad_s(self) -> float:
        """Angular resonant frequency ω0 = 2π·f0, rad/s."""
        return 2.0 * math.pi * float(self.f0_hz)

    @property
    def damping_rate_per_s(self) -> float:
        """Damping coefficient per unit mass ω0/Q, 1/s (the ṗ term of eq. 3.1)."""
        return self.omega0_rad_s / float(self.q)

    @property
    def time_constant_s(self) -> float:
        """Amplitude decay time constant 2Q/ω0, s."""
        return 2.0 * float(self.q) / self.omega0_rad_s

    def transfer_function(self, s: np.ndarray | complex) -> np.ndarray:
        """Evaluate G(s) = ω0² / (s² + (ω0/Q)s + ω0²) (eq. 3.1).

        Parameters
        ----------
        s : array_like of complex
            Laplace variable, rad/s.

        Returns
        -------
        numpy.ndarray of complex128
            G(s), dimensionless (nm of deflection per nm of dither forcing).
        """
        s = np.asarray(s, dtype=np.complex128)
        w0 = self.omega0_rad_s
        return w0 * w0 / (s * s + (w0 / self.q) * s + w0 * w0)

    def frequency_response(self, f_hz: np.ndarray | float) -> np.ndarray:
        """Analytic frequency response G(j2πf).

        Parameters
        ----------
        f_hz : array_like of float
            Frequency, Hz.

        Returns
        -------
        numpy.ndarray of complex128
            G(j2πf).  ``abs`` is the amplitude ratio deflection/forcing;
            ``np.angle`` is the phase of the deflection relative to the
            forcing, rad (−π/2 at f0, lagging).
        """
        f = np.asarray(f_hz, dtype=np.float64)
        return self.transfer_function(2j * math.pi * f)

    def tf_coefficients(self) -> tuple[np.ndarray, np.ndarray]:
        """Numerator and denominator of G(s) in descending powers of s.

        Returns
        -------
        num, den : numpy.ndarray
            ``[ω0²]`` and ``[1, ω0/Q, ω0²]``, as used by ``scipy.signal``.
        """
        w0 = self.omega0_rad_s
        return np.array([w0 * w0]), np.array([1.0, w0 / self.q, w0 * w0])

    def to_metadata(self) -> dict[str, float]:
        """The ``cantilever`` object of capture metadata."""
        return {
            "f0_hz": float(self.f0_hz),
            "q": float(self.q),
            "spring_constant_n_per_m": float(self.spring_constant_n_per_m),
        }
