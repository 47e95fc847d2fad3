"""The tip-sample rest separation l along a measured force curve, from the z-piezo.

A real capture has no /truth: the separation comes from the z-piezo signal,

.. math:: l(t) = s\\,(z(t) - z_c),

with s the piezo sensitivity (nm per z_piezo unit; from the channel's length
units, or given) and z_c the contact point, the z_piezo reading at which the
tip at rest would touch the surface (l = 0).  z_piezo follows afmtool's
convention (positive = sample farther from the tip, docs/conventions.md);
a piezo whose signal grows toward the sample takes a negative s.

z_c is found from the approach's amplitude curve, the way an operator reads
the snap-in or contact point off it: averaging theory (eqs. 4.6-4.8) with the
given force and the measured free amplitude predicts a(l) on approach, and
z_c is the shift that lays the measured a(z) onto it in least squares (a grid
scan over every shift that puts the approach's turn between 0 and the
interaction onset l = a_free + d, then a bounded scalar refinement).  Only
the amplitude is used, so REEP's f0′ and Q′, which ``theory compare`` then
checks, play no part in placing the curve.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from afmtool.errors import InputError
from afmtool.models.cantilever import Cantilever
from afmtool.models.forces import PiecewiseLinearForce

__all__ = ["NM_PER_LENGTH_UNIT", "SeparationEstimate", "separation_from_z", "z_sensitivity_nm"]

#: Length units a z_piezo channel may carry, nm per unit.
NM_PER_LENGTH_UNIT = {"pm": 1e-3, "nm": 1.0, "um": 1e3, "µm": 1e3, "μm": 1e3, "mm": 1e6, "m": 1e9}

#: Approach samples the alignment uses at most (evenly thinned).
_MAX_ALIGN_SAMPLES = 4000


@dataclass(frozen=True)
class SeparationEstimate:
    """l(t) (nm) with how it was placed: the contact point z_c, sensitivity s, fit residual."""

    separation_nm: np.ndarray
    contact_z: float
    nm_per_unit: float
    method: str
    amplitude_rms_residual_nm: float | None
    contact_z_std: float = 0.0


def z_sensitivity_nm(units: str, given_nm_per_unit: float) -> float:
    """s in nm per z_piezo unit: the given one, else from the channel's length units."""
    if given_nm_per_unit:
        return float(given_nm_per_unit)
    scale = NM_PER_LENGTH_UNIT.get(str(units).strip())
    if scale is None:
        raise InputError(
            f"z_piezo is in {units!r}, not a length: give its sensitivity with --z-sensitivity (nm per {units or 'unit'})"
        )
    return scale


def _approach(z: np.ndarray, nm_per_unit: float) -> np.ndarray:
    """Indices of the approach: from the start to the closest point (the turn)."""
    turn = int(np.argmin(z * np.sign(nm_per_unit)))
    return np.arange(turn + 1)


def separation_from_z(
    z: np.ndarray,
    amplitude_nm: np.ndarray,
    *,
    nm_per_unit: float,
    drive_frequency_hz: float,
    cantilever: Cantilever,
    force: PiecewiseLinearForce,
    free_amplitude_nm: float,
    contact_z: float | None = None,
) -> SeparationEstimate:
    """l = s (z − z_c) along the series, z_c given or aligned on the approach amplitude (module docstring).

    Parameters
    ----------
    z : numpy.ndarray
        z_piezo per output sample, its own units.
    amplitude_nm : numpy.ndarray
        Measured (lock-in) amplitude per sample, nm.
    nm_per_unit : float
        Piezo sensitivity s, nm per z unit (sign: see module docstring).
    drive_frequency_hz, cantilever, force, free_amplitude_nm
        The averaging-theory model the amplitude is aligned with.
    contact_z : float, optional
        z_c, z units; default: aligned.

    Returns
    -------
    SeparationEstimate
    """
    z = np.asarray(z, dtype=np.float64)
    amplitude = np.asarray(amplitude_nm, dtype=np.float64)
    if z.shape != amplitude.shape or z.size < 10 or not np.all(np.isfinite(z)):
        raise InputError("the z_piezo series must be finite and as long as the amplitude series")
    if contact_z is not None:
        return SeparationEstimate(nm_per_unit * (z - contact_z), float(contact_z), nm_per_unit, "given", None)

    from scipy.optimize import minimize_scalar

    from afmtool.models.averaging import SinusoidalDrive, theoretical_force_curve

    onset_nm = free_amplitude_nm + force.d_nm
    top_nm = onset_nm + max(5.0, 0.25 * free_amplitude_nm)
    grid = np.linspace(top_nm, 0.0, 301)
    drive = SinusoidalDrive.for_free_amplitude(cantilever, free_amplitude_nm, drive_frequency_hz)
    theory = theoretical_force_curve(grid, drive, cantilever, force)
    l_up, a_up = grid[::-1], theory.amplitude_nm[::-1]

    idx = _approach(z, nm_per_unit)
    idx = idx[np.isfinite(amplitude[idx])]
    idx = idx[:: max(1, math.ceil(idx.size / _MAX_ALIGN_SAMPLES))]
    z_app, a_app = z[idx], amplitude[idx]
    z_turn = float(z_app[np.argmin(z_app * np.sign(nm_per_unit))])

    def residual(z_c: float) -> np.ndarray:
        l_app = nm_per_unit * (z_app - z_c)
        return a_app - np.interp(l_app, l_up, a_up, left=a_up[0], right=free_amplitude_nm)

    def cost(z_c: float) -> float:
        return float(np.mean(residual(z_c) ** 2))

    # the turn's separation nm_per_unit·(z_turn − z_c) ranges over [0, onset]
    candidates = z_turn - np.linspace(0.0, onset_nm, 401) / nm_per_unit
    costs = np.array([cost(c) for c in candidates])
    best = int(np.argmin(costs))
    step = abs(candidates[1] - candidates[0])
    lo, hi = sorted((candidates[best] - step, candidates[best] + step))
    refined = minimize_scalar(cost, bounds=(lo, hi), method="bounded", options={"xatol": 1e-4 * step})
    z_c = float(refined.x) if refined.fun <= costs[best] else float(candidates[best])
    if np.ptp(a_app) < 0.05 * free_amplitude_nm:
        raise InputError(
            "the approach's amplitude hardly changes: no contact point to align on; give --contact-z"
        )
    return SeparationEstimate(nm_per_unit * (z - z_c), z_c, nm_per_unit, "aligned on the approach amplitude",
                              math.sqrt(cost(z_c)), _contact_std(residual, z_c, 0.05 / abs(nm_per_unit)))


def _contact_std(residual, z_c: float, step: float) -> float:
    """Standard error of the aligned z_c (z units): s²/Σ(∂r/∂z_c)², the rows counted as independent runs.

    Linearised least squares: Var(z_c) = s²·τ/Σ g_i², g = ∂r/∂z_c by central
    differences (``step``), s² the residuals' variance and τ = 1 + 2Σρ_k their
    integrated autocorrelation (summed while ρ_k > 0), which counts a run of
    correlated residuals (REEP's window, the beat, a misfit) once.
    """
    r = residual(z_c)
    g = (residual(z_c + step) - residual(z_c - step)) / (2 * step)
    information = float(g @ g)
    if r.size < 8 or information <= 0:
        return math.inf
    centred = r - r.mean()
    denominator = float(centred @ centred)
    tau = 1.0
    for k in range(1, r.size // 4):
        rho = float(centred[:-k] @ centred[k:]) / max(denominator, 1e-300)
        if rho <= 0:
            break
        tau += 2 * rho
    return math.sqrt(float(np.mean(r * r)) * tau / information)

