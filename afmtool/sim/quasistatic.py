"""Quasi-static equilibrium of the lever under electrostatic and tip-sample forces, with snap-in and snap-off.

For slow inputs (a ramp of V_sub or of the sample position z at a few Hz,
far below f0), the lever sits at a stable equilibrium of the static balance
(eq. 6.1 with p̈ = ṗ = 0)

.. math:: r(p) = k\\,p - F_{esf}(p; V, z) - F_{ts}(p; z) = 0,

with F_esf of eq. 6.4 (:func:`~afmtool.models.electrostatic.electrostatic_force_scalar`)
and F_ts of eq. 6.2 (:func:`~afmtool.models.forces.force_per_mass` with
"unit mass", see :meth:`afmtool.sim.probe.ProbeParams.tip_sample_force`).
Lengths are in m and forces in N; p is positive away from the sample and the
tip-sample separation is t_s = ℓ0 + p − t_h − z.

Which equilibrium: the lever follows the overdamped flow ṗ = −r(p) from
where it was.  At each new input the previous p is moved in the direction
−sign r(p) until r changes sign; that first root is stable (r increases
through it).  While the branch exists this is the continuation of the
branch; when it ends at a fold (∂r/∂p = 0) the search runs on to the next
stable branch: a snap-in toward the sample or a snap-off away from it.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from afmtool.jit import JIT_OPTIONS
from afmtool.models.electrostatic import electrostatic_force_scalar
from afmtool.models.forces import force_per_mass

__all__ = ["track_equilibrium"]

#: First trial step of the root search, m (grows ×2 per step up to the cap).
_FIRST_STEP_M = 1e-13
#: Largest step of the root search, m: smaller than any feature of r(p)
#: (the attractive range d, tens of nm), so no pair of roots is stepped over.
_MAX_STEP_M = 0.25e-9
#: Cap on search steps per sample (10 µm at the largest step).
_MAX_STEPS = 40000


@njit(**JIT_OPTIONS)
def _residual(p, voltage, z, k, kesf, l0, th, d, ka, kr):
    """r(p) = k·p − F_esf − F_ts, N."""
    f_esf = electrostatic_force_scalar(p, voltage, l0, kesf, z, th)
    # t_s = p + l with l = ℓ0 − t_h − z (forces module convention); "unit mass": ω² = stiffness
    f_ts = force_per_mass(p, 0.0, l0 - th - z, d, ka, kr, 0.0, 0.0)
    return k * p - f_esf - f_ts


@njit(**JIT_OPTIONS)
def _track_kernel(voltage, z, p_start, k, kesf, l0, th, d, ka, kr, out):
    p = p_start
    for n in range(voltage.shape[0]):
        v = voltage[n]
        zn = z[n]
        ra = _residual(p, v, zn, k, kesf, l0, th, d, ka, kr)
        if ra != 0.0:
            direction = -1.0 if ra > 0.0 else 1.0
            a = p
            h = _FIRST_STEP_M
            b = a + direction * h
            rb = _residual(b, v, zn, k, kesf, l0, th, d, ka, kr)
            steps = 0
            while (rb > 0.0) == (ra > 0.0) and rb != 0.0 and steps < _MAX_STEPS:
                a = b
                ra = rb
                h = min(2.0 * h, _MAX_STEP_M)
                b = a + direction * h
                rb = _residual(b, v, zn, k, kesf, l0, th, d, ka, kr)
                steps += 1
            # bisection on [a, b] (a on the side of the old sign)
            for _ in range(200):
                mid = 0.5 * (a + b)
                rm = _residual(mid, v, zn, k, kesf, l0, th, d, ka, kr)
                if rm == 0.0:
                    a = mid
                    b = mid
                    break
                if (rm > 0.0) == (ra > 0.0):
                    a = mid
                    ra = rm
                else:
                    b = mid
                if abs(b - a) <= 1e-18:
                    break
            p = 0.5 * (a + b)
        out[n] = p
    return out


def track_equilibrium(
    voltage_v: np.ndarray,
    z_m: np.ndarray,
    *,
    spring_constant_n_per_m: float,
    k_esf_f_m: float,
    l0_m: float,
    tip_height_m: float,
    attractive_range_m: float,
    attractive_stiffness_n_per_m: float,
    repulsive_stiffness_n_per_m: float,
    p_start_m: float = 0.0,
) -> np.ndarray:
    """Deflection p(n) (m) following the stable equilibrium through V(n) and z(n).

    Parameters
    ----------
    voltage_v : numpy.ndarray
        V = α_R·V_R − V_sub per sample, V.
    z_m : numpy.ndarray
        Sample position per sample (toward the lever), m; same length.
    spring_constant_n_per_m, k_esf_f_m, l0_m, tip_height_m : float
        k (N/m), K_esf (F·m), ℓ0 (m) and t_h (m).
    attractive_range_m, attractive_stiffness_n_per_m, repulsive_stiffness_n_per_m : float
        d (m), |k_a| and |k_r| (N/m) of eq. 6.2.
    p_start_m : float, optional
        Where the search for the first equilibrium starts, m (the rest
        position 0: the first sample is then the equilibrium reached from
        rest).

    Returns
    -------
    numpy.ndarray
        p, m.
    """
    voltage = np.ascontiguousarray(voltage_v, dtype=np.float64)
    z = np.ascontiguousarray(np.broadcast_to(np.asarray(z_m, dtype=np.float64), voltage.shape))
    return _track_kernel(
        voltage,
        z,
        float(p_start_m),
        float(spring_constant_n_per_m),
        float(k_esf_f_m),
        float(l0_m),
        float(tip_height_m),
        float(attractive_range_m),
        float(attractive_stiffness_n_per_m),
        float(repulsive_stiffness_n_per_m),
        np.empty_like(voltage),
    )
