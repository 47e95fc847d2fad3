"""The contact slope of a force curve, and the InvOLS it gives on a hard sample.

On a hard (incompressible) sample, once the tip touches, the cantilever
deflects by as much as the z piezo moves: Δd = Δz.  The detector then reads
Δd/InvOLS volts, so the slope of the detector signal against z in contact is
s = 1/InvOLS (V/nm) and InvOLS = 1/|s| (nm/V).  On a soft sample the tip
indents and |s| is smaller: the slope still describes the curve, but it is
not an InvOLS.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from afmtool.errors import InputError

__all__ = ["ContactFit", "approach_part", "fit_contact_slope"]

#: Fewest points in each part (free and contact) of the hinge fit.
_MIN_POINTS = 8


class ContactFit(NamedTuple):
    """The contact part of a force curve, fitted by a straight line.

    Attributes
    ----------
    slope, slope_std : float
        Deflection per z (deflection units per nm), and its standard error.
    intercept : float
        Of the contact line, deflection units, at z = 0.
    contact_z_nm : float
        Where the free baseline and the contact line meet (the hinge), nm.
    contact_side : int
        +1: contact for z above ``contact_z_nm``; −1: below.
    n_contact, n_fitted : int
        Points past the hinge, and those the line was fitted to (the
        first ``skip_fraction`` of the contact range left out).
    rms_residual : float
        Of the line fit, deflection units.
    z_range_nm : (float, float)
        The z range of the fitted points.
    """

    slope: float
    slope_std: float
    intercept: float
    contact_z_nm: float
    contact_side: int
    n_contact: int
    n_fitted: int
    rms_residual: float
    z_range_nm: tuple[float, float]


def approach_part(z: np.ndarray) -> slice:
    """The approach of a force curve: from the first sample to the z extreme farthest from the start."""
    z = np.asarray(z, dtype=np.float64)
    turn = int(np.argmax(np.abs(z - z[0])))
    return slice(0, turn + 1)


def _line(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float, float]:
    """Least-squares y = a + s x: (s, a, std(s), rms residual)."""
    xm, ym = x.mean(), y.mean()
    sxx = float(np.sum((x - xm) ** 2))
    if sxx <= 0:
        return math.nan, math.nan, math.nan, math.nan
    s = float(np.sum((x - xm) * (y - ym)) / sxx)
    a = ym - s * xm
    resid = y - (a + s * x)
    dof = max(x.size - 2, 1)
    sigma2 = float(resid @ resid) / dof
    return s, float(a), math.sqrt(sigma2 / sxx), math.sqrt(sigma2)


def _hinge_sse(z: np.ndarray, d: np.ndarray, zc: float, side: int) -> float:
    """SSE of d = c + s·max(0, side·(z − zc)) by linear least squares."""
    h = np.maximum(0.0, side * (z - zc))
    design = np.column_stack([np.ones_like(z), h])
    coef, *_ = np.linalg.lstsq(design, d, rcond=None)
    r = d - design @ coef
    return float(r @ r)


def fit_contact_slope(z_nm, deflection, *, skip_fraction: float = 0.1, grid: int = 200) -> ContactFit:
    """Find the contact point of a force curve and fit the contact part with a line.

    Parameters
    ----------
    z_nm : array_like
        z-piezo position, nm, along one leg (approach or retract).
    deflection : array_like
        Deflection (V, or a length unit) at the same samples.
    skip_fraction : float
        Share of the contact z range next to the contact point left out of
        the line fit (the onset, where the tip-sample force is not yet
        linear).
    grid : int
        Candidate contact points, spread over the z range.

    Returns
    -------
    ContactFit

    Notes
    -----
    *Contact point.*  A hinge d(z) = c + s·max(0, ±(z − z_c)) (flat free
    part, straight contact part) is fitted by linear least squares at each
    of ``grid`` candidate z_c and both contact sides; the least squared
    error wins.  *Slope.*  Ordinary least squares on the contact points
    beyond the first ``skip_fraction`` of the contact range:
    std(s) = σ/√Σ(z − z̄)², σ² the residual variance.  On a hard sample
    InvOLS = 1/|s| with std(InvOLS) = std(s)/s² (module docstring).
    """
    z = np.asarray(z_nm, dtype=np.float64)
    d = np.asarray(deflection, dtype=np.float64)
    if z.shape != d.shape or z.ndim != 1:
        raise InputError(f"z and deflection must be 1-D of one length, got {z.shape} and {d.shape}")
    if not (np.all(np.isfinite(z)) and np.all(np.isfinite(d))):
        raise InputError("the force curve has NaN or inf samples")
    if not 0 <= skip_fraction < 1:
        raise InputError(f"{skip_fraction=} must be in [0, 1)")
    if z.size < 3 * _MIN_POINTS or np.ptp(z) <= 0:
        raise InputError(f"a force curve needs at least {3 * _MIN_POINTS} points over a z range, got {z.size}")
    zs = np.sort(z)
    candidates = zs[_MIN_POINTS : z.size - _MIN_POINTS]
    candidates = candidates[np.linspace(0, candidates.size - 1, min(grid, candidates.size)).astype(int)]
    best = (math.inf, math.nan, 0)
    for side in (1, -1):
        for zc in candidates:
            n_contact = int(np.count_nonzero(side * (z - zc) > 0))
            if n_contact < _MIN_POINTS or z.size - n_contact < _MIN_POINTS:
                continue
            sse = _hinge_sse(z, d, float(zc), side)
            if sse < best[0]:
                best = (sse, float(zc), side)
    _, zc, side = best
    if side == 0:
        raise InputError("no contact part found in the force curve")
    beyond = side * (z - zc)
    contact = beyond > 0
    depth = float(beyond[contact].max())
    fitted = beyond > skip_fraction * depth
    if np.count_nonzero(fitted) < _MIN_POINTS:
        raise InputError(f"only {np.count_nonzero(fitted)} points in contact; at least {_MIN_POINTS} are needed")
    s, a, s_std, rms = _line(z[fitted], d[fitted])
    return ContactFit(
        slope=s,
        slope_std=s_std,
        intercept=a,
        contact_z_nm=zc,
        contact_side=side,
        n_contact=int(np.count_nonzero(contact)),
        n_fitted=int(np.count_nonzero(fitted)),
        rms_residual=rms,
        z_range_nm=(float(z[fitted].min()), float(z[fitted].max())),
    )
