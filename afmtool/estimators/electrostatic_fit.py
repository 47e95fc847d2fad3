"""Electrostatic parameters from a quasi-static approach curve (thesis §6.5.1 eq. 6.6, §6.5.2 eq. 6.7).

Before snap-in, with no tip-sample force, the static balance is

* optical (deflection p measured): k·p(ℓ0 + p)² = −K_esf·V² (eq. 6.6);
* thermal (separation t_s from the sensor): k(t_s + t_h − ℓ0)(t_s + t_h)² = −K_esf·V² (eq. 6.7),

with V = α_R·V_R − V_sub.  The fit is nonlinear least squares on the
*output error*: the measured p (or t_s) against the stable root predicted
from V_sub (:func:`afmtool.models.electrostatic.stable_deflection_m`), in
log-parameters (α_R linear), with :func:`scipy.optimize.least_squares`.

Identifiability, stated rather than hidden: k and K_esf enter both
relations only through ρ = K_esf/k, so a static curve cannot separate them;
the SVD of the relative Jacobian finds that null direction (and any other)
numerically (:mod:`afmtool.estimators.identifiability`).  One parameter per
null direction is then held fixed (k first: at the user's value when
given, since the spring constant is often known from a thermal-noise fit;
otherwise at a placeholder and reported as not identifiable), the rest is
fitted, and the report gives the identifiable combination (ρ) with its
uncertainty.  Parameters determined worse than ``max_relative_std`` are
flagged as poorly identifiable.  (The thesis's Table 6.1 quotes k and K_esf
separately from such curves; that is only possible with k from elsewhere.)
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import scipy.optimize

from afmtool.errors import ConfigError, InputError
from afmtool.estimators.identifiability import (
    Identifiability,
    analyse_identifiability,
    relative_covariance,
    relative_jacobian,
)
from afmtool.models.electrostatic import stable_deflection_m

__all__ = [
    "SENSORS",
    "PARAMETERS",
    "ApproachRegion",
    "select_before_snap_in",
    "predict",
    "ParameterEstimate",
    "ElectrostaticFit",
    "fit_electrostatic",
]

SENSORS = ("optical", "thermal")
#: Fitted parameters per sensor (SI units in the names).
PARAMETERS: Mapping[str, tuple[str, ...]] = {
    "optical": ("spring_constant_n_per_m", "l0_m", "k_esf_f_m", "alpha_r"),
    "thermal": ("spring_constant_n_per_m", "l0_m", "k_esf_f_m", "alpha_r", "tip_height_m"),
}
#: Which parameter to hold fixed first in a null direction.
_FIX_PRIORITY = ("spring_constant_n_per_m", "k_esf_f_m", "alpha_r", "tip_height_m", "l0_m")
#: Placeholder spring constant when none is given (its value cannot matter: only K_esf/k is fitted), N/m.
_REFERENCE_K = 1.0


# --------------------------------------------------------------------------- region


class ApproachRegion(NamedTuple):
    """Samples [start, stop) of the approach leg before snap-in.

    snap_index : int or None
        Last sample before the snap-in jump (None: no snap-in found).
    snap_v_sub_v : float
        V_sub there (NaN without a snap-in).
    jump : float
        Size of the jump, units of the curve (0 without one).
    turn_index : int
        End of the approach leg (largest |V_sub − V_sub[0]|).
    """

    start: int
    stop: int
    snap_index: int | None
    snap_v_sub_v: float
    jump: float
    turn_index: int


def select_before_snap_in(
    v_sub, y, *, margin_fraction: float = 0.05, min_jump_sigmas: float = 10.0
) -> ApproachRegion:
    """The part of the approach where only the electrostatic force acts (Fig. 6.25(b), a-b).

    Parameters
    ----------
    v_sub : array_like
        V_sub per sample, V (ramped away from its first value, then back).
    y : array_like
        Deflection or separation per sample (any length unit); NaN allowed
        (samples outside a thermal calibration).
    margin_fraction : float
        The last ``margin_fraction`` of the V_sub range before snap-in is
        dropped (close to the fold the curve is steepest and any tip-sample
        force acts first).
    min_jump_sigmas : float
        A snap-in is the largest one-sample jump of y on the approach leg
        if it exceeds this many robust standard deviations of the
        sample-to-sample differences (1.4826·MAD).  A curve that turns NaN
        for the rest of the approach (a thermal curve leaving its K_TP
        table in contact) snaps in at its last finite sample.

    Returns
    -------
    ApproachRegion
    """
    v = np.asarray(v_sub, dtype=np.float64)
    ya = np.asarray(y, dtype=np.float64)
    if v.shape != ya.shape or v.ndim != 1 or v.size < 8:
        raise InputError(f"v_sub and the curve must be 1-D of equal length >= 8, got {v.shape} and {ya.shape}")
    if not 0 <= margin_fraction < 1:
        raise ConfigError(f"margin_fraction={margin_fraction!r} must be in [0, 1)")
    turn = int(np.argmax(np.abs(v - v[0])))
    if turn < 8:
        raise InputError("V_sub does not ramp away from its first value: no approach leg")
    leg = ya[: turn + 1]
    # jumps between consecutive finite samples (a thermal curve may have NaN gaps where K_TP leaves its table)
    finite_index = np.flatnonzero(np.isfinite(leg))
    if finite_index.size < 8:
        raise InputError("the approach leg has fewer than 8 finite samples")
    steps = np.abs(np.diff(leg[finite_index]))
    robust = 1.4826 * float(np.median(np.abs(steps - np.median(steps)))) + float(np.median(steps))
    j = int(np.argmax(steps))
    k = int(finite_index[j])
    found = steps[j] > min_jump_sigmas * max(robust, np.finfo(float).tiny)
    jump = float(leg[finite_index[j + 1]] - leg[k]) if found else 0.0
    # a thermal curve leaves its calibration at snap-in (K_TP in contact is off the table): a NaN tail
    last_finite = int(finite_index[-1])
    if last_finite < turn and (not found or last_finite < k):
        k, found, jump = last_finite, True, math.nan
    end = k if found else turn
    span = v[end] - v[0]
    limit = v[end] - margin_fraction * span
    inside = np.flatnonzero((v[: end + 1] - limit) * np.sign(span) <= 0)
    stop = int(inside[-1]) + 1 if inside.size else 1
    return ApproachRegion(
        start=0,
        stop=stop,
        snap_index=k if found else None,
        snap_v_sub_v=float(v[k]) if found else math.nan,
        jump=jump,
        turn_index=turn,
    )


# --------------------------------------------------------------------------- model


def _unpack(theta: np.ndarray, names: tuple[str, ...]) -> dict[str, float]:
    return dict(zip(names, (float(t) for t in theta)))


def predict(theta: Mapping[str, float], v_sub, v_r_v: float, sensor: str) -> np.ndarray:
    """Predicted deflection p (optical) or separation t_s (thermal), m, before snap-in.

    Where the model has no stable root (past its pull-in) the fold value
    p = −ℓ0/3 is returned, so that a least-squares step past pull-in costs
    a finite, continuous residual.
    """
    if sensor not in SENSORS:
        raise ConfigError(f"sensor={sensor!r} must be one of {', '.join(SENSORS)}")
    voltage = theta["alpha_r"] * v_r_v - np.asarray(v_sub, dtype=np.float64)
    ratio = theta["k_esf_f_m"] / theta["spring_constant_n_per_m"]
    p = stable_deflection_m(voltage, ratio, theta["l0_m"])
    p = np.where(np.isfinite(p), p, -theta["l0_m"] / 3.0)
    if sensor == "optical":
        return p
    # eq. 6.7: p = t_s + t_h − ℓ0
    return p + theta["l0_m"] - theta["tip_height_m"]


def _initial_guess(v_sub: np.ndarray, y: np.ndarray, v_r_v: float, sensor: str, k_value: float) -> list[dict]:
    """Start points: the offset from a parabola, ℓ0 from the deepest point, ρ through it (several ℓ0)."""
    order = np.argsort(np.abs(v_sub - v_sub[0]))
    first = order[: max(8, order.size // 3)]
    c2, c1, _ = np.polyfit(v_sub[first], y[first], 2)
    v_off = -c1 / (2 * c2) if c2 != 0 else 0.0
    alpha = v_off / v_r_v if v_r_v != 0 and math.isfinite(v_off) else 0.0
    if abs(alpha) > 2:
        alpha = 0.0
    gap = 0.0
    p = y
    if sensor == "thermal":
        gap = float(np.nanmax(y))  # the rest gap ℓ0 − t_h ≈ the separation at the smallest force
        p = y - gap
    deepest = int(np.argmin(p))
    p_end = min(float(p[deepest]), -1e-12)
    v_end = alpha * v_r_v - v_sub[deepest]
    starts = []
    for factor in (1.1, 1.5, 2.5, 5.0):
        l0 = 3.0 * abs(p_end) * factor
        ratio = -p_end * (l0 + p_end) ** 2 / max(v_end**2, 1e-12)
        guess = {"spring_constant_n_per_m": k_value, "l0_m": l0, "k_esf_f_m": ratio * k_value, "alpha_r": alpha}
        if sensor == "thermal":
            guess["tip_height_m"] = max(l0 - gap, 0.1 * l0)
        starts.append(guess)
    return starts


# --------------------------------------------------------------------------- fit


class ParameterEstimate(NamedTuple):
    """One parameter of the fit.

    value, std : float or None
        SI units (None when the data cannot determine it).
    status : str
        ``"identified"``, ``"fixed"`` (given by the user), ``"poorly identifiable"``
        (relative std above the threshold) or ``"not identifiable"`` (a
        structural null direction, no value).
    """

    value: float | None
    std: float | None
    status: str

    @property
    def relative_std(self) -> float | None:
        if self.value is None or self.std is None or self.value == 0:
            return None
        return abs(self.std / self.value)


@dataclass(frozen=True, eq=False)
class ElectrostaticFit:
    """Result of :func:`fit_electrostatic`.

    Attributes
    ----------
    sensor : str
    estimates : dict
        Parameter name → :class:`ParameterEstimate`, plus
        ``"k_esf_over_k_m3_per_v2"``: ρ = K_esf/k, m³/V², always identifiable.
    identifiability : Identifiability
        SVD of the relative Jacobian of all parameters at the solution
        (residuals in noise units).
    fixed : tuple of str
        Parameters held fixed (one per null direction, and k if given).
    correlation : dict
        Correlations between the fitted parameters.
    rms_residual_m : float
        √(mean residual²), m.
    n_points : int
    theta : dict
        The full parameter vector of the solution (fixed ones included, at
        the placeholder when not given).
    cost_starts : tuple of float
        Final cost of each start point (several ℓ0).
    residual_autocorrelation : float
        Lag-1 autocorrelation of the residuals in V_sub order: near 0 for a
        model that fits to the noise, near 1 for a systematic misfit (a
        region reaching into the tip-sample force or into contact).
    """

    sensor: str
    estimates: dict
    identifiability: Identifiability
    fixed: tuple[str, ...]
    correlation: dict
    rms_residual_m: float
    n_points: int
    theta: dict
    cost_starts: tuple[float, ...]
    residual_autocorrelation: float

    def predict(self, v_sub, v_r_v: float) -> np.ndarray:
        """The fitted curve at ``v_sub`` (V), m."""
        return predict(self.theta, v_sub, v_r_v, self.sensor)


def _residual_fn(v_sub, y, v_r_v, sensor, names, free, theta_fixed, log_mask):
    """r(x) in nm for the free parameters x (log where log-scaled)."""

    def full(x: np.ndarray) -> np.ndarray:
        theta = theta_fixed.copy()
        values = np.where(log_mask[free], np.exp(x), x)
        theta[free] = values
        return theta

    def residual(x: np.ndarray) -> np.ndarray:
        return (predict(_unpack(full(x), names), v_sub, v_r_v, sensor) - y) * 1e9

    return full, residual


def fit_electrostatic(
    v_sub,
    y_m,
    v_r_v: float,
    *,
    sensor: str,
    spring_constant_n_per_m: float | None = None,
    rank_tolerance: float = 1e-7,
    max_relative_std: float = 0.1,
) -> ElectrostaticFit:
    """Fit eq. 6.6 (optical) or eq. 6.7 (thermal) by nonlinear least squares, with identifiability.

    Parameters
    ----------
    v_sub : array_like
        V_sub of the points before snap-in, V.
    y_m : array_like
        Measured deflection p (optical) or tip-sample separation t_s
        (thermal) at those points, m.
    v_r_v : float
        The constant sensor voltage V_R, V.
    sensor : {"optical", "thermal"}
    spring_constant_n_per_m : float, optional
        k if known (N/m): then K_esf = ρ·k is reported with its error.
    rank_tolerance : float
        Relative singular value below which a direction is structurally
        non-identifiable.
    max_relative_std : float
        Fitted parameters with a larger relative standard deviation are
        reported as ``"poorly identifiable"``.

    Returns
    -------
    ElectrostaticFit

    Notes
    -----
    Steps: (1) relative Jacobian of all parameters at a start point, its
    SVD, and one parameter fixed per structural null direction (priority
    k, K_esf, α_R, t_h, ℓ0); (2) least squares over the free ones (log
    scale, α_R linear) from four start points (ℓ0 = 1.1, 1.5, 2.5 and 5 ×
    three times the deepest deflection, ρ through that point), keeping the
    lowest cost; (3) the SVD again at the solution, with residuals scaled by
    σ̂ (the report's singular values are in noise units) and the covariance
    σ̂²(JᵀJ)⁻¹ of the free parameters, propagated to ρ = K_esf/k.

    Raises
    ------
    ConfigError
        For a bad sensor, spring constant or threshold.
    InputError
        For fewer points than parameters + 2, or non-finite data.
    """
    v, y = _checked_inputs(v_sub, y_m, v_r_v, sensor, spring_constant_n_per_m, max_relative_std)
    names = PARAMETERS[sensor]
    log_mask = np.array([name != "alpha_r" for name in names])
    k_value = spring_constant_n_per_m if spring_constant_n_per_m is not None else _REFERENCE_K
    starts = _initial_guess(v, y, v_r_v, sensor, k_value)

    # (1) structural null space at the first start, all parameters free
    fixed, unresolved, free = _structural_step(v, y, v_r_v, sensor, starts[0], log_mask, rank_tolerance,
                                               spring_constant_n_per_m)

    # (2) least squares from each start
    sol, full, costs = _best_start(v, y, v_r_v, sensor, names, free, starts, log_mask)
    theta = full(sol.x)

    # (3) identifiability and covariance at the solution
    r_nm = sol.fun
    ident, cov = _identifiability_at_solution(v, y, v_r_v, sensor, theta, r_nm, free, log_mask, rank_tolerance)
    estimates, correlation = _estimates(names, theta, free, unresolved, cov, log_mask, spring_constant_n_per_m,
                                        max_relative_std)
    return ElectrostaticFit(
        sensor=sensor, estimates=estimates, identifiability=ident, fixed=tuple(n for n in names if n in fixed),
        correlation=correlation, rms_residual_m=math.sqrt(float(np.mean(r_nm**2))) * 1e-9, n_points=int(r_nm.size),
        theta=_unpack(theta, names), cost_starts=tuple(costs),
        residual_autocorrelation=_lag1(r_nm[np.argsort(v, kind="stable")]),
    )


def _structural_step(v, y, v_r_v, sensor, start, log_mask, rank_tolerance, spring_constant_n_per_m):
    """Step (1) of :func:`fit_electrostatic`: (fixed, unresolved, free mask) from the structural null directions.

    The null directions are those of the relative Jacobian at the first
    start point with all parameters free.
    """
    names = PARAMETERS[sensor]
    theta0 = np.array([start[n] for n in names])
    jac0 = relative_jacobian(lambda th: (predict(_unpack(th, names), v, v_r_v, sensor) - y) * 1e9, theta0, log_mask)
    null0 = analyse_identifiability(jac0, names, rank_tolerance=rank_tolerance).null_directions
    fixed, unresolved = _structural_fixes(null0, spring_constant_n_per_m)
    return fixed, unresolved, np.array([n not in fixed for n in names])


def _identifiability_at_solution(v, y, v_r_v, sensor, theta, r_nm, free, log_mask, rank_tolerance):
    """Step (3) of :func:`fit_electrostatic`: the SVD report and σ̂²(JᵀJ)⁻¹ of the free parameters at θ̂.

    Residuals are scaled by σ̂ = sqrt(rᵀr / (n - p)) so that the singular
    values are in noise units.
    """
    names = PARAMETERS[sensor]
    n, p = r_nm.size, int(np.count_nonzero(free))
    sigma_nm = math.sqrt(float(r_nm @ r_nm) / max(n - p, 1)) or 1.0

    def scaled(th: np.ndarray) -> np.ndarray:
        return (predict(_unpack(th, names), v, v_r_v, sensor) - y) * 1e9 / sigma_nm

    jac = relative_jacobian(scaled, theta, log_mask)
    ident = analyse_identifiability(jac, names, rank_tolerance=rank_tolerance)
    # residuals in noise units: σ̂²(JᵀJ)⁻¹ of the scaled problem is the covariance of δln θ
    cov = relative_covariance(jac[:, free], r_nm / sigma_nm)
    return ident, cov


def _checked_inputs(v_sub, y_m, v_r_v, sensor, spring_constant_n_per_m, max_relative_std):
    """The validated (V_sub, y) arrays of :func:`fit_electrostatic`; its ConfigError/InputError checks."""
    if sensor not in SENSORS:
        raise ConfigError(f"sensor={sensor!r} must be one of {', '.join(SENSORS)}")
    if spring_constant_n_per_m is not None and not (
        math.isfinite(spring_constant_n_per_m) and spring_constant_n_per_m > 0
    ):
        raise ConfigError(f"spring_constant_n_per_m={spring_constant_n_per_m!r} must be a finite number > 0")
    if not (math.isfinite(v_r_v)):
        raise ConfigError(f"v_r_v={v_r_v!r} must be finite")
    if not 0 < max_relative_std:
        raise ConfigError(f"max_relative_std={max_relative_std!r} must be > 0")
    v = np.asarray(v_sub, dtype=np.float64)
    y = np.asarray(y_m, dtype=np.float64)
    names = PARAMETERS[sensor]
    if v.shape != y.shape or v.ndim != 1:
        raise InputError(f"v_sub and y_m must be 1-D of equal length, got {v.shape} and {y.shape}")
    if not (np.all(np.isfinite(v)) and np.all(np.isfinite(y))):
        raise InputError("v_sub and y_m must be finite (drop unconverted samples first)")
    if v.size < len(names) + 2:
        raise InputError(f"{v.size} points cannot fit {len(names)} parameters")
    return v, y


def _structural_fixes(null_directions, spring_constant_n_per_m) -> tuple[set[str], set[str]]:
    """(fixed, unresolved): one parameter fixed per structural null direction, by ``_FIX_PRIORITY``.

    ``unresolved``: the parameters of a null direction fixed only at a
    placeholder, which get no value.
    """
    fixed = {"spring_constant_n_per_m"} if spring_constant_n_per_m is not None else set()
    unresolved: set[str] = set()
    for direction in null_directions:
        if fixed.intersection(direction.parameters) == {"spring_constant_n_per_m"} and spring_constant_n_per_m:
            continue  # resolved by the given spring constant
        if not fixed.intersection(direction.parameters):
            fixed.add(next(n for n in _FIX_PRIORITY if n in direction.parameters))
        unresolved.update(direction.parameters)
    return fixed, unresolved


def _best_start(v, y, v_r_v, sensor, names, free, starts, log_mask):
    """(solution, its full-θ map, the cost from each start): least squares from every start, lowest cost kept."""
    best = None
    costs = []
    for start in starts:
        theta_start = np.array([start[n] for n in names])
        full, residual = _residual_fn(v, y, v_r_v, sensor, names, free, theta_start, log_mask)
        x0 = np.array([math.log(t) if lg else t for t, lg in zip(theta_start[free], log_mask[free])])
        sol = scipy.optimize.least_squares(residual, x0, x_scale="jac", xtol=1e-14, ftol=1e-14, gtol=1e-14,
                                           max_nfev=2000)
        costs.append(float(sol.cost))
        if best is None or sol.cost < best[0].cost:
            best = (sol, full)
    return best[0], best[1], costs


def _lag1(r: np.ndarray) -> float:
    """Lag-1 autocorrelation of a residual sequence (0 for white noise)."""
    c = r - r.mean()
    denominator = float(c @ c)
    return float(c[1:] @ c[:-1]) / denominator if denominator > 0 else 0.0


def _estimates(names, theta, free, unresolved, cov, log_mask, k_given, max_relative_std) -> tuple[dict, dict]:
    """Parameter values and one-sigma errors from the relative covariance (δln θ, or δθ/|θ| for α_R).

    Parameters in ``unresolved`` (a null direction fixed only at a
    placeholder) get no value, whether they were fitted or fixed.
    """
    free_names = [n for n, f in zip(names, free) if f]
    index = {n: i for i, n in enumerate(free_names)}
    rel_std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    estimates: dict[str, ParameterEstimate] = {}
    for j, name in enumerate(names):
        value = float(theta[j])
        if name in unresolved:
            estimates[name] = ParameterEstimate(None, None, "not identifiable")
        elif name in index:
            std = rel_std[index[name]] * (value if log_mask[j] else max(abs(value), 1e-12))
            rel = abs(std / value) if value != 0 else math.inf
            status = "identified" if rel <= max_relative_std else "poorly identifiable"
            estimates[name] = ParameterEstimate(value, abs(float(std)), status)
        elif name == "spring_constant_n_per_m" and k_given is not None:
            estimates[name] = ParameterEstimate(value, 0.0, "fixed")
        else:
            estimates[name] = ParameterEstimate(None, None, "not identifiable")
    # ρ = K_esf/k: δln ρ = δln K_esf − δln k over whichever of the two is free
    grad = np.zeros(len(free_names))
    if "k_esf_f_m" in index:
        grad[index["k_esf_f_m"]] += 1.0
    if "spring_constant_n_per_m" in index:
        grad[index["spring_constant_n_per_m"]] -= 1.0
    k_pos, kesf_pos = names.index("spring_constant_n_per_m"), names.index("k_esf_f_m")
    ratio = float(theta[kesf_pos] / theta[k_pos])
    ratio_rel = math.sqrt(max(float(grad @ cov @ grad), 0.0))
    estimates["k_esf_over_k_m3_per_v2"] = ParameterEstimate(
        ratio, ratio * ratio_rel, "identified" if ratio_rel <= max_relative_std else "poorly identifiable"
    )
    if k_given is not None:  # K_esf from the given k: error of ρ only
        estimates["k_esf_f_m"] = ParameterEstimate(ratio * k_given, ratio * ratio_rel * k_given,
                                                   estimates["k_esf_over_k_m3_per_v2"].status)
    d = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    corr = cov / np.outer(d, d)
    correlation = {a: {b: float(corr[i, j]) for j, b in enumerate(free_names)} for i, a in enumerate(free_names)}
    return estimates, correlation
