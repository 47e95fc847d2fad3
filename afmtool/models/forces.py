"""Piecewise-linear tip-sample force (eqs. 4.1 and 6.2), one sign convention.

Convention (``docs/conventions.md``, chapter 4)
----------------------------------------------
* The deflection p (nm) and the force are positive **upward**, away from
  the sample.
* The sample surface is at p = −l, where l (nm) is the rest separation
  between the tip and the sample; the tip-sample separation is
  t_s = p + l (nm).
* Forces are per unit mass (nm/s²), as in eq. 3.1 written as
  p̈ + (ω0/Q)ṗ + ω0²p = ω0²g + F(p, ṗ; l).
* Attraction is a negative force for 0 ≤ t_s < d; repulsion is added for
  t_s < 0; the dissipative terms always oppose the velocity v = ṗ.

With ω_a², ω_b² in 1/s² and c_a, c_b in 1/s:

.. math::

    F(p, v; l) = \\begin{cases}
        0 & t_s \\ge d \\\\
        -\\omega_a^2 (d - t_s) - c_a v & 0 \\le t_s < d \\\\
        -\\omega_a^2 (d - t_s) - \\omega_b^2 t_s - (c_a + c_b) v & t_s < 0
    \\end{cases}

The conservative part is continuous (−ω_a²d at contact); the slope in
the repulsive region is ω_a² − ω_b², repulsive when ω_b² > ω_a², and the
attractive term continues into t_s < 0 exactly as in eqs. 4.1 and 6.2.

How the thesis's signs map to this one
--------------------------------------
* Eq. 6.2, F = k_a(t_s − d) for 0 ≤ t_s ≤ d and k_r t_s + k_a(t_s − d)
  for t_s ≤ 0, has the right attractive sign here for k_a > 0, but its
  k_r t_s term pulls the tip into the sample for k_r > 0.  The fitted
  values of §6.6 (k_a = −0.29 N/m, k_r = 3.4 N/m) fit eq. 6.2 read as a
  force positive *toward* the sample.  Either way this module takes the
  magnitudes: ω_a² = |k_a|/m, ω_b² = |k_r|/m.
* Eq. 4.1, F = −ω_a²(p + l − d) + c_a ṗ and
  F = ω_b²(p + l) − ω_a²(p + l − d) + (c_a + c_b)ṗ, is the **negative**
  of the force above, term by term: inserted literally into eq. 3.1/4.2
  its attractive part would push the tip away, its repulsive part would
  pull it into the sample and a positive c_a would reduce the damping.
  This module uses F = −F_4.1 with the same (positive) parameter
  values, so the §3.4.3 and chapter-4 sets keep their published numbers.
* Averaging theory (chapter 4) must then use this F in the
  first-harmonic balance of docs/conventions.md; attraction lowers ωe, dissipation
  lowers Qe.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np
from numba import njit

from afmtool.errors import ConfigError
from afmtool.jit import JIT_OPTIONS

__all__ = [
    "PiecewiseLinearForce",
    "force_per_mass",
    "force_per_mass_array",
    "ATTRACTIVE_F80K_Q168",
    "ATTRACTIVE_REPULSIVE_F80K_Q168",
    "REPULSIVE_F80K_Q168",
    "REPULSIVE_F80K_Q38",
    "CH4_DEFAULT",
    "THESIS_FORCE_SETS",
    "THESIS_FORCE_SET_CANTILEVERS",
]


@njit(**JIT_OPTIONS)
def force_per_mass(p, v, l, d, wa2, wb2, ca, cb):  # the model's own parameters
    """Piecewise-linear tip-sample force per unit mass (module docstring).

    Parameters
    ----------
    p : float
        Deflection, nm, positive away from the sample.
    v : float
        Velocity ṗ, nm/s.
    l : float
        Rest tip-sample separation, nm; the surface is at p = −l.
    d : float
        Range of the attractive zone, nm (d ≥ 0).
    wa2, wb2 : float
        Attractive and repulsive stiffness per unit mass ω_a², ω_b², 1/s².
    ca, cb : float
        Attractive and repulsive damping per unit mass, 1/s.

    Returns
    -------
    float
        F/m in nm/s², positive upward (away from the sample).
    """
    ts = p + l
    if ts >= d:
        return 0.0
    force = -wa2 * (d - ts) - ca * v
    if ts < 0.0:
        force += -wb2 * ts - cb * v
    return force


def force_per_mass_array(p, v, l, d, wa2, wb2, ca, cb) -> np.ndarray:
    """Vectorised :func:`force_per_mass` over broadcast arrays (nm/s²)."""
    p, v, l = np.broadcast_arrays(
        np.asarray(p, dtype=np.float64), np.asarray(v, dtype=np.float64), np.asarray(l, dtype=np.float64)
    )
    ts = p + l
    attract = np.where(ts < d, -wa2 * (d - ts) - ca * v, 0.0)
    repel = np.where(ts < 0.0, -wb2 * ts - cb * v, 0.0)
    return attract + repel


@dataclass(frozen=True)
class PiecewiseLinearForce:
    """Parameters of the piecewise-linear force (eq. 4.1/6.2, module convention).

    Parameters
    ----------
    d_nm : float
        Range of the attractive zone d, nm (onset of attraction at t_s = d).
    omega_a2 : float
        Attractive stiffness per unit mass ω_a², 1/s².
    omega_b2 : float
        Repulsive stiffness per unit mass ω_b², 1/s².
    c_a : float
        Damping per unit mass in the attractive zone (and below), 1/s.
    c_b : float
        Additional damping per unit mass in the repulsive zone, 1/s.

    Raises
    ------
    ConfigError
        If a parameter is negative or not finite.
    """

    d_nm: float
    omega_a2: float
    omega_b2: float
    c_a: float
    c_b: float

    def __post_init__(self) -> None:
        for name in ("d_nm", "omega_a2", "omega_b2", "c_a", "c_b"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise ConfigError(f"{name}={value!r} must be a finite number >= 0")

    def as_args(self) -> tuple[float, float, float, float, float]:
        """``(d, wa2, wb2, ca, cb)`` in the order :func:`force_per_mass` takes them."""
        return (float(self.d_nm), float(self.omega_a2), float(self.omega_b2), float(self.c_a), float(self.c_b))

    def __call__(self, p, v, l) -> np.ndarray:
        """F/m (nm/s²) at deflection ``p`` (nm), velocity ``v`` (nm/s), separation ``l`` (nm)."""
        return force_per_mass_array(p, v, l, *self.as_args())

    def to_metadata(self) -> dict[str, float]:
        """The force parameters as a JSON-ready mapping (units in the keys' docs)."""
        return {
            "d_nm": float(self.d_nm),
            "omega_a2_per_s2": float(self.omega_a2),
            "omega_b2_per_s2": float(self.omega_b2),
            "c_a_per_s": float(self.c_a),
            "c_b_per_s": float(self.c_b),
            "convention": "F/m in nm/s^2, positive away from sample, t_s = p + l, F = -F_eq4.1",
        }


#: §3.4.3, "predominant attractive interaction" (Fig. 3.11); f0 = 80,318 Hz, Q = 168.
ATTRACTIVE_F80K_Q168 = PiecewiseLinearForce(4.0, (0.31e6) ** 2, (3.03e6) ** 2, 0.042e6, 0.0)
#: §3.4.3, "attractive/repulsive interaction" (Fig. 3.12); f0 = 80,318 Hz, Q = 168.
ATTRACTIVE_REPULSIVE_F80K_Q168 = PiecewiseLinearForce(4.0, (0.1e6) ** 2, (0.303e6) ** 2, 0.0092e6, 0.0)
#: §3.4.3, "predominant repulsive interaction", bistable (Fig. 3.13); f0 = 80,318 Hz, Q = 168.
REPULSIVE_F80K_Q168 = PiecewiseLinearForce(5.0, (0.11e6) ** 2, (0.63e6) ** 2, 0.0042e6, 0.0)
#: §3.4.3, low-Q case (Fig. 3.14); Q = 38 (f0 not restated; 80,318 Hz assumed).
REPULSIVE_F80K_Q38 = PiecewiseLinearForce(5.0, (0.11e6) ** 2, (1.83e6) ** 2, 0.0012e6, 0.0)
#: §4.2, the parameters of the chapter-4 simulations (cantilever not stated).
CH4_DEFAULT = PiecewiseLinearForce(1.65, (0.18e6) ** 2, (4.03e6) ** 2, 0.042e6, 1.45e6)

#: The thesis's force sets by name.
THESIS_FORCE_SETS: Mapping[str, PiecewiseLinearForce] = MappingProxyType(
    {
        "attractive": ATTRACTIVE_F80K_Q168,
        "attractive-repulsive": ATTRACTIVE_REPULSIVE_F80K_Q168,
        "repulsive": REPULSIVE_F80K_Q168,
        "repulsive-q38": REPULSIVE_F80K_Q38,
        "ch4-default": CH4_DEFAULT,
    }
)

#: Free-air (f0_hz, q) the thesis used with each set (§3.4.3).  The Q = 38
#: set's f0 and the chapter-4 cantilever are not given; 80,318 Hz and
#: Q = 168 are assumed.
THESIS_FORCE_SET_CANTILEVERS: Mapping[str, tuple[float, float]] = MappingProxyType(
    {
        "attractive": (80318.0, 168.0),
        "attractive-repulsive": (80318.0, 168.0),
        "repulsive": (80318.0, 168.0),
        "repulsive-q38": (80318.0, 38.0),
        "ch4-default": (80318.0, 168.0),
    }
)
