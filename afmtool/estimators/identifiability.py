"""Local identifiability of a nonlinear least-squares fit: SVD of the scaled Jacobian.

For residuals r(θ) = (model(θ) − data)/σ, the Jacobian in *relative*
parameters, J_rel[:, j] = ∂r/∂ln θ_j (for a parameter that may change sign,
∂r/∂θ_j·|θ_j|), measures how much one percent of each parameter moves the
fit in units of the noise.  Its singular value decomposition
J_rel = U·S·Vᵀ sorts parameter combinations (the rows of Vᵀ, in relative
units) by how well the data pin them down:

* s_i ≈ 0 (s_i ≤ ``rank_tolerance``·s_max): the combination v_i does not
  change the model at all, it is **structurally non-identifiable**.  A
  typical case: two parameters that enter only as a ratio, v ∝ (1, 1) in
  (ln a, ln b): a and b cannot be separated, but b/a can.
* s_i small but not zero: **practically** non-identifiable; to first order
  the standard deviation of v_iᵀ·δln θ is σ̂/s_i.

The covariance of the free parameters is σ̂²(JᵀJ)⁻¹ with
σ̂² = Σr²/(n − p) (first order; a profile likelihood would be needed for
strongly curved problems).  Nothing here fits: the caller passes the model.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np

from afmtool.errors import ConfigError

__all__ = [
    "relative_jacobian",
    "NullDirection",
    "Identifiability",
    "analyse_identifiability",
    "relative_covariance",
]


def relative_jacobian(
    residual: Callable[[np.ndarray], np.ndarray],
    theta: np.ndarray,
    log_scaled: Sequence[bool],
    *,
    step: float = 1e-6,
) -> np.ndarray:
    """∂r/∂ln θ_j (or ∂r/∂θ_j·max(|θ_j|, 1e-12) where not ``log_scaled``) by central differences.

    Parameters
    ----------
    residual : callable
        θ (physical units) → residual vector.
    theta : numpy.ndarray
        Where to differentiate.  Log-scaled entries must be > 0.
    log_scaled : sequence of bool
        Per parameter: perturb ln θ_j (True) or θ_j in steps of |θ_j| (False).
    step : float
        Relative step.

    Returns
    -------
    numpy.ndarray, shape (n_residuals, n_parameters)
    """
    theta = np.asarray(theta, dtype=np.float64)
    if len(log_scaled) != theta.size:
        raise ConfigError(f"log_scaled has {len(log_scaled)} entries for {theta.size} parameters")
    if not (math.isfinite(step) and 0 < step < 0.1):
        raise ConfigError(f"step={step!r} must be in (0, 0.1)")
    columns = []
    for j, is_log in enumerate(log_scaled):
        up, down = theta.copy(), theta.copy()
        if is_log:
            if not theta[j] > 0:
                raise ConfigError(f"theta[{j}]={theta[j]!r} must be > 0 to be log-scaled")
            up[j] = theta[j] * math.exp(step)
            down[j] = theta[j] * math.exp(-step)
        else:
            scale = max(abs(theta[j]), 1e-12)
            up[j] = theta[j] + step * scale
            down[j] = theta[j] - step * scale
        columns.append((residual(up) - residual(down)) / (2.0 * step))
    return np.column_stack(columns)


class NullDirection(NamedTuple):
    """A parameter combination the data do not determine.

    parameters : tuple of str
        The parameters that take part (relative weight ≥ 0.05).
    weights : tuple of float
        Their components of the unit singular vector, in relative units
        (δln θ): moving along it leaves the fit unchanged.
    identifiable_combination : str or None
        For two parameters with equal-magnitude weights, the combination the
        data *do* determine: "b/a" for equal signs, "a*b" for opposite ones.
    singular_value : float
        s_i (noise-scaled units per unit relative change).
    """

    parameters: tuple[str, ...]
    weights: tuple[float, ...]
    identifiable_combination: str | None
    singular_value: float


class Identifiability(NamedTuple):
    """SVD of the relative Jacobian: which parameter combinations the data determine.

    names : tuple of str
    singular_values : numpy.ndarray
        Descending.
    directions : numpy.ndarray
        Rows are the right singular vectors, in the same order.
    condition_number : float
        s_max/s_min (inf with an exact null direction).
    null_directions : tuple of NullDirection
        Structurally non-identifiable combinations (s ≤ rank_tolerance·s_max).
    """

    names: tuple[str, ...]
    singular_values: np.ndarray
    directions: np.ndarray
    condition_number: float
    null_directions: tuple[NullDirection, ...]


def _combination(names: Sequence[str], weights: Sequence[float]) -> str | None:
    if len(names) != 2 or not math.isclose(abs(weights[0]), abs(weights[1]), rel_tol=1e-3):
        return None
    a, b = names
    return f"{b}/{a}" if weights[0] * weights[1] > 0 else f"{a}*{b}"


def analyse_identifiability(
    jacobian: np.ndarray, names: Sequence[str], *, rank_tolerance: float = 1e-7, min_weight: float = 0.05
) -> Identifiability:
    """SVD of a relative (noise-scaled) Jacobian and its structural null space.

    Parameters
    ----------
    jacobian : numpy.ndarray, shape (n, p)
        From :func:`relative_jacobian`, residuals divided by the noise σ
        (the singular values are then in noise units).
    names : sequence of str
        Parameter names, length p.
    rank_tolerance : float
        Singular values ≤ this × the largest are structural zeros.  Central
        differences leave ~1e-10 relative in an exact null direction.
    min_weight : float
        Components below this are left out of a null direction's parameters.

    Returns
    -------
    Identifiability
    """
    jac = np.asarray(jacobian, dtype=np.float64)
    if jac.ndim != 2 or jac.shape[1] != len(names):
        raise ConfigError(f"jacobian has shape {jac.shape}, expected (n, {len(names)})")
    if not np.all(np.isfinite(jac)):
        raise ConfigError("jacobian has non-finite entries")
    if not 0 < rank_tolerance < 1:
        raise ConfigError(f"rank_tolerance={rank_tolerance!r} must be in (0, 1)")
    _, s, vt = np.linalg.svd(jac, full_matrices=False)
    s_max = float(s[0]) if s.size else 0.0
    null = []
    for i, value in enumerate(s):
        if value <= rank_tolerance * s_max:
            u = vt[i] * np.sign(vt[i, int(np.argmax(np.abs(vt[i])))])  # largest component positive
            keep = [j for j in range(u.size) if abs(u[j]) >= min_weight]
            sub_names = tuple(names[j] for j in keep)
            sub_weights = tuple(float(u[j]) for j in keep)
            null.append(NullDirection(sub_names, sub_weights, _combination(sub_names, sub_weights), float(value)))
    s_min = float(s[-1]) if s.size else 0.0
    return Identifiability(
        names=tuple(names),
        singular_values=s,
        directions=vt,
        condition_number=s_max / s_min if s_min > 0 else math.inf,
        null_directions=tuple(null),
    )


def relative_covariance(jacobian: np.ndarray, residual: np.ndarray) -> np.ndarray:
    """σ̂²(JᵀJ)⁻¹ for relative parameters, σ̂² = Σr²/(n − p) (first order).

    ``jacobian`` must have full column rank (fix the null directions first).
    """
    jac = np.asarray(jacobian, dtype=np.float64)
    r = np.asarray(residual, dtype=np.float64)
    n, p = jac.shape
    if n <= p:
        raise ConfigError(f"{n} residuals cannot give a covariance for {p} parameters")
    sigma2 = float(r @ r) / (n - p)
    # via the SVD (no explicit JᵀJ: its condition number is the square of J's)
    _, s, vt = np.linalg.svd(jac, full_matrices=False)
    if s[-1] <= 1e-12 * s[0]:
        raise ConfigError("the jacobian is rank deficient; fix the non-identifiable combinations first")
    return sigma2 * (vt.T / s**2) @ vt
