"""The piecewise-linear force fitted to a REEP force curve, with profile-likelihood intervals (ch. 4, ref. [38]).

Model
-----
Averaging theory (closed form of eq. 4.8) predicts, at amplitude a and rest
separation l (eq. F.1),

.. math::

    \\omega_e^2 = \\omega_0^2 - \\frac{\\omega_a^2}{\\pi}\\gamma(x) + \\frac{\\omega_b^2}{\\pi}\\gamma(y),\\qquad
    \\frac{\\omega_e}{Q_e} = \\frac{\\omega_0}{Q} + \\frac{c_a}{\\pi}\\gamma(x) + \\frac{c_b}{\\pi}\\gamma(y),

x = (d − l)/a, y = −l/a, γ(u) = π − arccos u + u√(1 − u²), and the amplitude
from the first-harmonic balance a = a_free·√D(ω0, Q)/√D(ωe, Qe),
D = (ωe² − ω²)² + ω²(ωe/Qe)² (eq. F.2).  Along the approach l = s·(z − z_c);
f0,e and Qe are passed through REEP's exponential window.  θ = (d, ω_a², ω_b²,
c_a, c_b, z_c).

Error model (eq. F.3)
---------------------
Each row's residual is divided by σ_i² = σ_R,i² + (τ·Δ_i)²: σ_R,i REEP's own
per-row std (``f0_std_hz``, ``q_std``; the free-air scatter where reep.h5 has
none; for the amplitude its free-air scatter, at least 1 % of a_free), Δ_i the
row's measured shift from free air and τ (``MODEL_FLOOR``) the share to which
averaging theory is expected to hold (``theory compare`` uses the same).

On the wall, averaging theory at the mean amplitude is ill-conditioned
(docs/conventions.md): where the fitted tip reaches it, the floor is ``WALL_FLOOR`` for
all three series, and the wall model is refitted so weighted
(:func:`_wall_weighted`).

Two models
----------
Where the tip never reaches the wall, ω_b² and c_b have no effect and d and z_c
enter only as the onset o = d + s·z_c: the *attractive* model fits
(ω_a², c_a, z_c) with ω_b² = c_b = 0 and d fixed.  The *wall* model fits all
six, from several starts (trial d, the rest by NNLS; the curve can have local
minima).  The wall model is kept when it lowers χ² by more than the 0.99
quantile of χ²₃, in the units of eq. F.4 (likelihood-ratio test).

Uncertainty: the profile likelihood (eq. F.4)
---------------------------------------------
Rows share REEP's window and, where the model misfits, runs of residuals of
one sign: the χ² is scaled by c = max(1, χ²_min/ν)·τ_int, τ_int the
residuals' integrated autocorrelation (:func:`integrated_autocorrelation`).
Each parameter's 2σ interval is where the profile, χ² minimised over the
others with θ_j held, stays within 4c of the minimum; found by secant steps
from the first-order estimate (:func:`profile_interval`).  A profile that
never rises that far on one side leaves the interval open there (0 at a
bound of 0, or +inf).

The wall's stiffness and damping (ω_b², c_b) are given as lower bounds only
where the wall model is kept: on the reference curves the fit reads stiff
walls 2-20× too soft, and averaging theory at the mean amplitude cannot tell
(docs/conventions.md: treat the repulsive regime qualitatively); the wall's place
(d, z_c) gets the fitted tip's penetration depth as a systematic error
(:func:`_wall_systematic`).

Systematic part
---------------
Averaging theory and REEP differ by 5-18 % of the shift where the theory is
well-conditioned (more at low Q), and by 30-45 % on the repulsive wall (the
reference curves; docs/conventions.md).  That error is coherent along the curve, not
noise, so it is propagated, not averaged (:func:`_systematic`): the fit is
repeated with every row's measured shift from free air scaled by (1 ± τ_i),
and with each quarter of the interacting rows left out in turn (a
jackknife); the result is added on both sides of the profile interval
(2 × systematic) and in quadrature to the std.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit

from afmtool.errors import InputError
from afmtool.jit import JIT_OPTIONS
from afmtool.models.cantilever import Cantilever
from afmtool.models.forces import PiecewiseLinearForce

__all__ = [
    "FIT_NAMES",
    "FIT_UNITS",
    "ForceFit",
    "ForceFitData",
    "JACKKNIFE_GROUPS",
    "MODEL_FLOOR",
    "SYSTEMATIC_SCALE",
    "WALL_FLOOR",
    "fit_force",
    "integrated_autocorrelation",
    "model_curves",
    "profile_interval",
]

FIT_NAMES = ("d_nm", "omega_a2", "omega_b2", "c_a", "c_b", "contact_z")
FIT_UNITS = {"d_nm": "nm", "omega_a2": "1/s^2", "omega_b2": "1/s^2", "c_a": "1/s", "c_b": "1/s",
             "contact_z": "z units"}
#: τ of eq. F.3; the scaling of the systematic refits off the wall, and on it; the jackknife's groups.
MODEL_FLOOR = 0.1
SYSTEMATIC_SCALE = 0.2
WALL_FLOOR = 0.4
JACKKNIFE_GROUPS = 4
#: Trial attractive ranges for the wall model's starts, nm.
_TRIAL_D_NM = (1.0, 2.0, 4.0, 6.0)
#: Scales below which a parameter counts as 0 for least_squares' x_scale.
_PARAMETER_SCALES = np.array([0.1, 1e8, 1e9, 1e2, 1e3, 0.1])
_LOWER = np.array([0.0, 0.0, 0.0, 0.0, 0.0, -math.inf])
_D, _WA2, _WB2, _CA, _CB, _ZC = range(6)
#: χ²₃ at 0.99: the wall model must lower the scaled χ² by this much to be kept.
_WALL_TEST = 11.34


@dataclass(frozen=True)
class ForceFitData:
    """One approach: REEP's series per output row and the per-row errors of eq. F.3.

    ``z`` in the z_piezo's units, ``f0_hz`` (Hz), ``q``, ``amplitude_nm``
    (nm); ``sigma_*`` per row in the same units; ``fit_mask`` the rows
    fitted; ``free`` REEP's free-air (f0′, Q′, amplitude) the shifts are
    measured from; ``beat`` the envelope's relative beat m (for "on the
    wall", a(1 + m) > l).
    """

    z: np.ndarray
    f0_hz: np.ndarray
    q: np.ndarray
    amplitude_nm: np.ndarray
    fit_mask: np.ndarray
    nm_per_unit: float
    drive_frequency_hz: float
    cantilever: Cantilever
    free_amplitude_nm: float
    window_lambda: float
    sigma_f0_hz: np.ndarray
    sigma_q: np.ndarray
    sigma_amplitude_nm: np.ndarray
    free: tuple[float, float, float]
    beat: float = 0.0


class Interval(NamedTuple):
    """A parameter's 2σ interval (statistical, then with the systematic part) and its std."""

    low: float
    high: float
    std: float
    systematic: float


@dataclass(frozen=True)
class ForceFit:
    """The fitted force, its intervals and which model the curve supports."""

    theta: np.ndarray
    intervals: tuple[Interval, ...]
    model: str  # "wall" or "attractive"
    free: tuple[bool, ...]  # which parameters were fitted (not fixed)
    cost: float
    chi2_scale: float
    wall_test: float
    rms: tuple[float, float, float]
    prediction: tuple[np.ndarray, np.ndarray, np.ndarray]
    repulsive_share: float
    onset: Interval

    @property
    def force(self) -> PiecewiseLinearForce:
        return PiecewiseLinearForce(*(max(0.0, float(v)) for v in self.theta[:5]))

    @property
    def std(self) -> np.ndarray:
        return np.array([i.std for i in self.intervals])


def _gamma(u: np.ndarray) -> np.ndarray:
    """γ(u) = π − arccos u + u√(1 − u²), u clipped to [−1, 1] (closed form of eq. 4.8)."""
    u = np.clip(u, -1.0, 1.0)
    return math.pi - np.arccos(u) + u * np.sqrt(1.0 - u * u)


@njit(**JIT_OPTIONS)
def _gamma_scalar(u: float) -> float:
    """γ(u) of :func:`_gamma` for one u."""
    if u <= -1.0:
        return 0.0
    if u >= 1.0:
        return math.pi
    return math.pi - math.acos(u) + u * math.sqrt(1.0 - u * u)


@njit(**JIT_OPTIONS)
def _model_kernel(z, measured_amplitude, nm_per_unit, theta, w0, q0, om2, free_amplitude, lam, f0_out, q_out, a_out):
    """Eqs. F.1, F.2 row by row, f0,e and Qe through REEP's window y[n] = λ·y[n−1] + (1 − λ)·x[n], y[0] = x[0]."""
    d, wa2, wb2, ca, cb, z_c = theta[0], theta[1], theta[2], theta[3], theta[4], theta[5]
    d0 = (w0 * w0 - om2) ** 2 + om2 * (w0 / q0) ** 2
    f_prev = 0.0
    q_prev = 0.0
    for i in range(z.size):
        a = max(measured_amplitude[i], 1e-6)
        l = nm_per_unit * (z[i] - z_c)
        gx = _gamma_scalar((d - l) / a)
        gy = _gamma_scalar(-l / a)
        # eq. F.1: ωe² and ωe/Qe
        w = w0 * w0 - (wa2 / math.pi) * gx + (wb2 / math.pi) * gy
        b = w0 / q0 + (ca / math.pi) * gx + (cb / math.pi) * gy
        omega_e = math.sqrt(max(w, 1.0))
        f0e = omega_e / (2.0 * math.pi)
        qe = omega_e / max(b, 1e-9)
        # eq. F.2: the first-harmonic balance's amplitude
        a_out[i] = free_amplitude * math.sqrt(d0 / ((w - om2) ** 2 + om2 * b * b))
        if i == 0:
            f_prev, q_prev = f0e, qe
        else:
            f_prev = lam * f_prev + (1.0 - lam) * f0e
            q_prev = lam * q_prev + (1.0 - lam) * qe
        f0_out[i] = f_prev
        q_out[i] = q_prev


def model_curves(theta: np.ndarray, data: ForceFitData) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(f0,e windowed, Qe windowed, amplitude) along the approach for θ (eqs. F.1, F.2; :func:`_model_kernel`)."""
    n = data.z.size
    f0e, qe, amplitude = np.empty(n), np.empty(n), np.empty(n)
    _model_kernel(np.ascontiguousarray(data.z, dtype=np.float64),
                  np.ascontiguousarray(data.amplitude_nm, dtype=np.float64), float(data.nm_per_unit),
                  np.asarray(theta, dtype=np.float64), data.cantilever.omega0_rad_s, float(data.cantilever.q),
                  (2 * math.pi * data.drive_frequency_hz) ** 2, float(data.free_amplitude_nm),
                  float(data.window_lambda), f0e, qe, amplitude)
    return f0e, qe, amplitude


def _residual(theta: np.ndarray, data: ForceFitData, targets) -> np.ndarray:
    """Eq. F.3 residuals of the fitted rows: model minus (possibly scaled) data, over σ_i."""
    f0e, qe, amplitude = model_curves(theta, data)
    m = data.fit_mask
    f_target, q_target, a_target = targets
    return np.concatenate([(f0e[m] - f_target) / data.sigma_f0_hz[m], (qe[m] - q_target) / data.sigma_q[m],
                           (amplitude[m] - a_target) / data.sigma_amplitude_nm[m]])


def _targets(data: ForceFitData, scale: np.ndarray | None = None):
    """The fitted rows' data; with ``scale`` (per row), each shift from free air multiplied by it."""
    m = data.fit_mask
    out = []
    for values, free in ((data.f0_hz, data.free[0]), (data.q, data.free[1]), (data.amplitude_nm, data.free[2])):
        v = values[m]
        out.append(v if scale is None else free + (v - free) * scale)
    return tuple(out)


def _solve(data: ForceFitData, theta0: np.ndarray, free: np.ndarray, targets, max_nfev: int = 400):
    """Least squares over the ``free`` parameters (trust-region reflective, bounds of θ), the rest held."""
    from scipy.optimize import least_squares

    index = np.flatnonzero(free)
    scale = np.maximum(np.abs(theta0[index]), _PARAMETER_SCALES[index])
    lower = _LOWER[index]
    start = np.maximum(theta0[index], lower + 1e-9 * scale)
    theta = theta0.copy()

    def residual(x):
        theta[index] = x
        return _residual(theta, data, targets)

    solution = least_squares(residual, start, bounds=(lower, np.full(index.size, np.inf)), x_scale=scale,
                             method="trf", max_nfev=max_nfev)
    out = theta0.copy()
    out[index] = solution.x
    return out, float(2.0 * solution.cost), solution


def integrated_autocorrelation(r: np.ndarray) -> float:
    """τ_int = 1 + 2Σρ_k of a residual series, summed while ρ_k > 0 (at least 1).

    A run of correlated residuals (REEP's window, the beat, a systematic
    misfit) then counts as one independent piece of evidence, not as many.
    """
    centred = np.asarray(r, dtype=np.float64) - float(np.mean(r))
    denominator = float(centred @ centred)
    tau = 1.0
    if denominator <= 0:
        return tau
    for k in range(1, centred.size // 4):
        rho = float(centred[:-k] @ centred[k:]) / denominator
        if rho <= 0:
            break
        tau += 2.0 * rho
    return tau


def _chi2_scale(residual: np.ndarray, n_free: int) -> float:
    """c of eq. F.4: max(1, χ²/ν) times the largest τ_int of the three series' residuals."""
    nu = max(1, residual.size - n_free)
    dispersion = max(1.0, float(residual @ residual) / nu)
    return dispersion * max(integrated_autocorrelation(part) for part in np.split(residual, 3))


def _linear_start(d: float, z_c: float, data: ForceFitData) -> np.ndarray:
    """(ω_a², ω_b², c_a, c_b) ≥ 0 by NNLS of the unwindowed ωe², ωe/Qe of eq. F.1 for fixed (d, z_c)."""
    from scipy.optimize import nnls

    m = data.fit_mask
    a = np.maximum(data.amplitude_nm[m], 1e-6)
    l = data.nm_per_unit * (data.z[m] - z_c)
    gx, gy = _gamma((d - l) / a) / math.pi, _gamma(-l / a) / math.pi
    w0 = data.cantilever.omega0_rad_s
    w_meas = (2 * math.pi * data.f0_hz[m]) ** 2 - w0 * w0
    b_meas = 2 * math.pi * data.f0_hz[m] / data.q[m] - w0 / data.cantilever.q
    sw, sb = max(np.std(w_meas), 1.0), max(np.std(b_meas), 1e-6)
    zeros = np.zeros_like(gx)
    matrix = np.vstack([np.column_stack([-gx, gy, zeros, zeros]) / sw, np.column_stack([zeros, zeros, gx, gy]) / sb])
    solution, _ = nnls(matrix, np.concatenate([w_meas / sw, b_meas / sb]))
    return solution


def _onset_z(data: ForceFitData, drop: float) -> float:
    """First approach z where the amplitude falls below (1 − drop)·a_free."""
    below = np.flatnonzero(data.amplitude_nm < (1.0 - drop) * data.free_amplitude_nm)
    if below.size == 0:
        raise InputError("the approach amplitude never drops: the curve does not reach the interaction")
    return float(data.z[below[0]])


def _start(d: float, z_on: float, data: ForceFitData, wall: bool) -> np.ndarray:
    """θ for a trial d: z_c puts the onset at z_on, the stiffnesses and dampings by NNLS."""
    z_c = z_on - (data.free_amplitude_nm + d) / data.nm_per_unit
    linear = _linear_start(d, z_c, data)
    if not wall:
        linear[[1, 3]] = 0.0
    return np.concatenate([[d], linear, [z_c]])


def _fit_model(data: ForceFitData, z_on: float, wall: bool) -> list:
    """[(θ, χ², solution)] of the attractive (d fixed) or the wall model, one per start, in the starts' order."""
    targets = _targets(data)
    free = np.array([wall, True, wall, True, wall, True])
    return [_solve(data, _start(d, z_on, data, wall), free, targets) for d in (_TRIAL_D_NM if wall else (2.0,))]


def _canonical(found: list, scale: float):
    """The first start's solution whose χ² is within c of the lowest: a choice that tiny changes of the data do not flip.

    Starts that end within c of each other (a short d with a stiff wall
    mimics a long soft one) are equally good; taking the lowest χ² would
    pick between them by rounding.
    """
    best = min(cost for _, cost, _ in found)
    return next(item for item in found if item[1] - best <= scale)


def _first_order_std(solution, free: np.ndarray, scale: float) -> np.ndarray:
    """√diag(c·(JᵀJ)⁻¹) of the free parameters (NaN for the held ones): the profile's first step only."""
    jac = np.asarray(solution.jac)
    std = np.full(free.size, np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        cov = scale * np.linalg.pinv(jac.T @ jac)
    std[np.flatnonzero(free)] = np.sqrt(np.abs(np.diag(cov)))
    return std


def _profile_side(data, theta_hat, free, j, chi2_min, threshold, step, sign, targets) -> float:
    """The distance from θ̂_j, on one side, where the profile χ² rises by ``threshold`` (inf: it never does).

    Secant steps on √Δχ², which is nearly linear in the distance for a
    quadratic profile; each point refits the other free parameters, warm
    started from the previous one.
    """
    held = free.copy()
    held[j] = False
    theta = theta_hat.copy()
    delta = step
    ceiling = 1e3 * max(abs(theta_hat[j]), _PARAMETER_SCALES[j])
    for _ in range(8):
        if sign < 0 and _LOWER[j] == 0.0 and theta_hat[j] - delta <= 0.0:
            delta = theta_hat[j]  # try the bound itself
        trial = theta.copy()
        trial[j] = theta_hat[j] + sign * delta
        theta, cost, _ = _solve(data, trial, held, targets, max_nfev=120) if held.any() else (
            trial, float(np.sum(_residual(trial, data, targets) ** 2)), None)
        rise = cost - chi2_min
        if abs(rise / threshold - 1.0) < 0.15:
            return delta
        if sign < 0 and _LOWER[j] == 0.0 and delta >= theta_hat[j] and rise < threshold:
            return theta_hat[j]  # the interval reaches the bound 0
        factor = math.sqrt(threshold / rise) if rise > 0 else 4.0
        delta *= min(max(factor, 0.25), 4.0)
        if delta > ceiling:
            return math.inf
    return delta


def profile_interval(data, theta_hat, free, j, chi2_min, threshold, first_std, targets,
                     upper: bool = True) -> tuple[float, float]:
    """θ_j's interval where the profile χ² stays within ``threshold`` of its minimum (eq. F.4).

    ``upper=False`` profiles the lower side only (the upper end is then inf).
    """
    scale = max(abs(theta_hat[j]), _PARAMETER_SCALES[j])
    step = 2.0 * first_std if math.isfinite(first_std) and first_std > 0 else 0.3 * scale
    step = min(max(step, 1e-4 * scale), 10.0 * scale)
    low = _profile_side(data, theta_hat, free, j, chi2_min, threshold, step, -1, targets)
    high = _profile_side(data, theta_hat, free, j, chi2_min, threshold, step, +1, targets) if upper else math.inf
    return theta_hat[j] - low, theta_hat[j] + high


def _on_wall(theta: np.ndarray, data: ForceFitData) -> np.ndarray:
    """Rows (fitted) where the tip reaches the wall at the top of the beating envelope, a(1 + m) > l."""
    l = data.nm_per_unit * (data.z - theta[_ZC])
    return (data.amplitude_nm * (1.0 + data.beat) > l)[data.fit_mask]


def _systematic(data: ForceFitData, theta_hat: np.ndarray, free: np.ndarray, wall: bool) -> np.ndarray:
    """√(scaling move² + jackknife variance) per parameter (module docstring: the systematic part).

    Scaling: every shift from free air multiplied by 1 ± τ_i (``SYSTEMATIC_SCALE``
    off the wall, ``WALL_FLOOR`` on it), the largest move.  Jackknife: the
    rows where the curve shows the interaction (a shift of f0′ over three
    times its σ_R) cut into ``JACKKNIFE_GROUPS`` contiguous groups, each left
    out in turn; Var = (g − 1)/g·Σ(θ_(i) − θ̄)².  A misfit that varies along the
    curve pulls the groups apart, which no scaling shows.
    """
    tau = np.full(int(data.fit_mask.sum()), SYSTEMATIC_SCALE)
    if wall:
        tau[_on_wall(theta_hat, data)] = WALL_FLOOR
    moves = np.zeros(theta_hat.size)
    for sign in (-1.0, 1.0):
        theta, _, _ = _solve(data, theta_hat, free, _targets(data, 1.0 + sign * tau), max_nfev=200)
        moves = np.maximum(moves, np.abs(theta - theta_hat))
    return np.where(free, np.hypot(moves, _jackknife_std(data, theta_hat, free)), np.nan)


def _jackknife_std(data: ForceFitData, theta_hat: np.ndarray, free: np.ndarray) -> np.ndarray:
    """Delete-a-group jackknife std over contiguous groups of the interacting fitted rows."""
    import dataclasses

    shift = np.abs(data.f0_hz - data.free[0]) > 3.0 * data.sigma_f0_hz
    rows = np.flatnonzero(data.fit_mask & shift)
    g = JACKKNIFE_GROUPS
    if rows.size < 4 * g:
        return np.zeros(theta_hat.size)
    estimates = []
    for k in range(g):
        mask = data.fit_mask.copy()
        mask[rows[k * rows.size // g : (k + 1) * rows.size // g]] = False
        part = dataclasses.replace(data, fit_mask=mask)
        estimates.append(_solve(part, theta_hat, free, _targets(part), max_nfev=200)[0])
    estimates = np.array(estimates)
    return np.sqrt((g - 1) / g * np.sum((estimates - estimates.mean(axis=0)) ** 2, axis=0))


def _wall_systematic(systematic: np.ndarray, theta: np.ndarray, data: ForceFitData) -> np.ndarray:
    """The wall's place is known only to within the fitted tip's penetration max(a(1 + m) − l): add it to d and z_c.

    A wall averaging theory cannot follow trades its stiffness against where
    it stands: a softer fitted wall sits farther away by about the depth the
    fitted tip enters it.
    """
    l = data.nm_per_unit * (data.z - theta[_ZC])
    penetration = max(0.0, float(np.max((data.amplitude_nm * (1.0 + data.beat) - l)[data.fit_mask])))
    out = systematic.copy()
    out[_D] = math.hypot(out[_D], penetration)
    out[_ZC] = math.hypot(out[_ZC], penetration / abs(data.nm_per_unit))
    return out


def _interval(low: float, high: float, systematic: float, bounded_below: bool) -> Interval:
    """The statistical 2σ interval widened by 2 × systematic on each side, and its std."""
    low_total = low - 2.0 * systematic
    if bounded_below:
        low_total = max(low_total, 0.0)
    high_total = high + 2.0 * systematic
    stat = (high - low) / 4.0 if math.isfinite(high - low) else math.inf
    return Interval(low_total, high_total, math.sqrt(stat * stat + systematic * systematic), systematic)


def _select_model(data: ForceFitData, z_on: float):
    """(θ, χ², solution, free mask, 'wall' or 'attractive', test statistic, the wall model's solutions).

    The likelihood-ratio choice between the models (module docstring).
    """
    (theta_a, chi2_a, sol_a), = _fit_model(data, z_on, wall=False)
    found = _fit_model(data, z_on, wall=True)
    best_w = min(found, key=lambda item: item[1])
    scale = _chi2_scale(best_w[2].fun, 6)
    statistic = (chi2_a - best_w[1]) / scale
    if statistic > _WALL_TEST:
        theta_w, chi2_w, sol_w = _canonical(found, scale)
        return theta_w, chi2_w, sol_w, np.ones(6, dtype=bool), "wall", statistic, found
    return theta_a, chi2_a, sol_a, np.array([False, True, False, True, False, True]), "attractive", statistic, []


def _with_modes(interval: Interval, j: int, modes: list, chi2_min: float, threshold: float) -> Interval:
    """The interval stretched over every other start's solution within ``threshold`` of the minimum (an equally good mode)."""
    values = [theta[j] for theta, cost, _ in modes if cost - chi2_min <= threshold]
    if not values:
        return interval
    low, high = min(interval.low, *values), max(interval.high, *values)
    stat = (high - low) / 4.0 if math.isfinite(high - low) else math.inf
    return Interval(low, high, max(interval.std, stat), interval.systematic)


def _wall_weighted(data: ForceFitData, theta: np.ndarray) -> ForceFitData:
    """The data with eq. F.3's floor raised from ``MODEL_FLOOR`` to ``WALL_FLOOR`` on the rows where θ's tip reaches the wall.

    Averaging theory at the mean amplitude is ill-conditioned there
    (docs/conventions.md): f0′, Q′ and the amplitude on the wall weigh as little as the
    theory can be trusted, so the wall's parameters come out as uncertain as
    they are.
    """
    import dataclasses

    on_wall = np.zeros(data.z.size, dtype=bool)
    on_wall[np.flatnonzero(data.fit_mask)[_on_wall(theta, data)]] = True
    extra = WALL_FLOOR**2 - MODEL_FLOOR**2
    sigmas = []
    for sigma, values, free in ((data.sigma_f0_hz, data.f0_hz, data.free[0]), (data.sigma_q, data.q, data.free[1]),
                                (data.sigma_amplitude_nm, data.amplitude_nm, data.free[2])):
        sigmas.append(np.where(on_wall, np.sqrt(sigma * sigma + extra * (values - free) ** 2), sigma))
    return dataclasses.replace(data, sigma_f0_hz=sigmas[0], sigma_q=sigmas[1], sigma_amplitude_nm=sigmas[2])


def fit_force(data: ForceFitData, *, onset_drop: float = 0.02) -> ForceFit:
    """Fit θ = (d, ω_a², ω_b², c_a, c_b, z_c) with profile-likelihood intervals (module docstring).

    Parameters
    ----------
    data : ForceFitData
        The approach and its per-row errors.
    onset_drop : float
        The interaction's onset is where the amplitude first falls by this
        share of a_free; it places the starts.

    Returns
    -------
    ForceFit
    """
    theta, chi2_min, solution, free, model, statistic, modes = _select_model(data, _onset_z(data, onset_drop))
    if model == "wall":
        data = _wall_weighted(data, theta)
        theta, chi2_min, solution = _solve(data, theta, free, _targets(data))
        modes = [(t, float(np.sum(_residual(t, data, _targets(data)) ** 2)), None) for t, _, _ in modes]
    n_free = int(free.sum())
    scale = _chi2_scale(solution.fun, n_free)
    threshold = 4.0 * scale  # 2σ of eq. F.4
    first = _first_order_std(solution, free, scale)
    targets = _targets(data)
    base = _systematic(data, theta, free, model == "wall")
    systematic = _wall_systematic(base, theta, data) if model == "wall" else base
    intervals = []
    for j in range(6):
        if not free[j]:
            intervals.append(Interval(math.nan, math.nan, math.nan, math.nan))
            continue
        if model == "wall" and j in (_WB2, _CB):
            # a wall averaging theory cannot follow: its stiffness and damping are bounded below only
            low, _ = profile_interval(data, theta, free, j, chi2_min, threshold, first[j], targets, upper=False)
            intervals.append(_interval(low, math.inf, float(systematic[j]), True))
            continue
        low, high = profile_interval(data, theta, free, j, chi2_min, threshold, first[j], targets)
        intervals.append(_with_modes(_interval(low, high, float(systematic[j]), _LOWER[j] == 0.0), j, modes,
                                     chi2_min, threshold))
    s = data.nm_per_unit
    zc = intervals[_ZC]
    onset = Interval(theta[_D] + s * zc.low if s > 0 else theta[_D] + s * zc.high,
                     theta[_D] + s * zc.high if s > 0 else theta[_D] + s * zc.low,
                     abs(s) * zc.std, abs(s) * zc.systematic)
    if model == "attractive":
        # without a wall z_c is only the onset's other half (d is held): no interval of its own
        intervals[_ZC] = Interval(math.nan, math.nan, math.nan, math.nan)
    if model == "wall":
        # the onset keeps the base systematic of d and z_c and the penetration once (not once each)
        penetration = abs(s) * math.sqrt(max(systematic[_ZC] ** 2 - base[_ZC] ** 2, 0.0))
        onset = _wall_onset(theta, solution, scale, base, s, penetration)
    residual = solution.fun
    rms = tuple(float(np.sqrt(np.mean((r * sig[data.fit_mask]) ** 2))) for r, sig in
                zip(np.split(residual, 3), (data.sigma_f0_hz, data.sigma_q, data.sigma_amplitude_nm)))
    reach = float(np.mean(_on_wall(theta, data))) if model == "wall" else 0.0
    return ForceFit(theta, tuple(intervals), model, tuple(bool(f) for f in free), chi2_min, scale, statistic, rms,
                    model_curves(theta, data), reach, onset)


def _wall_onset(theta, solution, scale, systematic, s, penetration: float) -> Interval:
    """The onset d + s·z_c of the wall model: first-order std from the (d, z_c) covariance, with the systematic part."""
    jac = np.asarray(solution.jac)
    cov = scale * np.linalg.pinv(jac.T @ jac)
    gradient = np.array([1.0, 0, 0, 0, 0, s])
    stat = math.sqrt(max(float(gradient @ cov @ gradient), 0.0))
    sys_ = abs(systematic[_D]) + abs(s) * abs(systematic[_ZC]) + penetration
    value = theta[_D] + s * theta[_ZC]
    return Interval(value - 2 * (stat + sys_), value + 2 * (stat + sys_), math.hypot(stat, sys_), sys_)
