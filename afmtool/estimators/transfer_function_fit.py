"""Rational transfer functions fitted to a frequency response, and the delayed second-order model.

* :func:`fit_transfer_function` — G(s) = N(s)/D(s)·e^{−sτ} of any order by
  Sanathanan-Koerner iterations, the delay by a bounded search: the Γ maps
  of the thermal sensor (§6.6).
* :func:`fit_second_order` — G(s) = gain·ω0²/(s² + (ω0/Q)s + ω0²)·e^{−sτ}
  (eq. 3.1 with a pure delay): the sweep route's free-air model (§3.3.3).

Frequencies in Hz, s = j2πf in rad/s, coefficients in descending powers of
s as in :mod:`scipy.signal`.  Split out of
:mod:`afmtool.estimators.frequency_response` (issue 29, item 6).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import scipy.optimize

from afmtool.errors import ConfigError, InputError
from afmtool.estimators.spectral_checks import check_int, check_positive, checked_signal, frozen, is_real

__all__ = ["TransferFunctionFit", "fit_transfer_function", "SecondOrderFit", "fit_second_order"]


# --------------------------------------------------------------------------- rational fit


@dataclass(frozen=True, eq=False)
class TransferFunctionFit:
    """G(s) = N(s)/D(s)·e^{−sτ} fitted to a frequency response.

    Parameters
    ----------
    numerator : numpy.ndarray
        Coefficients of N(s), descending powers of s (s in rad/s).
    denominator : numpy.ndarray
        Coefficients of D(s), descending powers, monic (``denominator[0] == 1``).
    delay_s : float
        Pure delay τ, s.
    rms_residual : float
        √(Σ w_k |H_k − G(j2πf_k)|² / Σ w_k), in units of H.
    iterations : int
        Sanathanan–Koerner iterations at the final delay.
    converged : bool
        Whether the iterations met the tolerance.
    """

    numerator: np.ndarray
    denominator: np.ndarray
    delay_s: float
    rms_residual: float
    iterations: int
    converged: bool

    def response(self, frequency_hz) -> np.ndarray:
        """G(j2πf) = N/D·e^{−j2πfτ} at ``frequency_hz`` (Hz)."""
        s = 2j * np.pi * np.asarray(frequency_hz, dtype=np.float64)
        return np.polyval(self.numerator, s) / np.polyval(self.denominator, s) * np.exp(-s * self.delay_s)

    @property
    def poles(self) -> np.ndarray:
        """Roots of D(s), rad/s."""
        return np.roots(self.denominator)

    @property
    def zeros(self) -> np.ndarray:
        """Roots of N(s), rad/s."""
        return np.roots(self.numerator)


class _SkResult(NamedTuple):
    num: np.ndarray  # ascending powers of the scaled variable
    den: np.ndarray  # ascending, den[-1] == 1
    cost: float  # Σ w |H − N/D|²
    iterations: int
    converged: bool


def _sanathanan_koerner(
    s: np.ndarray, h: np.ndarray, weights: np.ndarray, n_num: int, n_den: int, max_iter: int, tol: float
) -> _SkResult:
    """Rational fit N/D (D monic of degree n_den) in a scaled Laplace variable s.

    Levy (1959) linearises H·D − N ≈ 0 into a linear least-squares problem;
    Sanathanan & Koerner (1963) iterate it with the weights 1/|D_{i−1}(s_k)|²
    so that at convergence the weighted error Σ w|H·D − N|²/|D|² is the
    output error Σ w|H − N/D|².  Unknowns: b_0…b_m, a_0…a_{n−1}:

        Σ_i b_i s^i − H Σ_{i<n} a_i s^i = H s^n   (×√w/|D_{i−1}|, real and imaginary parts)

    Columns are scaled to unit norm before ``lstsq`` (conditioning).
    """
    vn = s[:, None] ** np.arange(n_num + 1)
    vd = s[:, None] ** np.arange(n_den)
    matrix = np.hstack((vn, -h[:, None] * vd))
    rhs = h * s**n_den
    d_prev = np.ones_like(s)
    sqrt_w = np.sqrt(weights)
    converged = False
    iterations = 0
    num = np.zeros(n_num + 1)
    den = np.zeros(n_den + 1)
    for _ in range(max_iter):
        iterations += 1  # counted in the body: the count is returned after the loop
        row = sqrt_w / np.abs(d_prev)
        a = matrix * row[:, None]
        b = rhs * row
        a_real = np.vstack((a.real, a.imag))
        b_real = np.concatenate((b.real, b.imag))
        norms = np.linalg.norm(a_real, axis=0)
        norms[norms == 0] = 1.0
        theta = np.linalg.lstsq(a_real / norms, b_real, rcond=None)[0] / norms
        num = theta[: n_num + 1]
        den = np.append(theta[n_num + 1 :], 1.0)
        d_new = np.polynomial.polynomial.polyval(s, den)
        change = float(np.max(np.abs(d_new - d_prev) / np.maximum(np.abs(d_new), np.finfo(float).tiny)))
        d_prev = d_new
        if change < tol:
            converged = True
            break
    with np.errstate(divide="ignore", invalid="ignore"):
        model = np.polynomial.polynomial.polyval(s, num) / d_prev
        cost = float(np.sum(weights * np.abs(h - model) ** 2))
    if not math.isfinite(cost):
        cost = math.inf
    return _SkResult(num, den, cost, iterations, converged)


def _frequency_data(frequency_hz, response, weights) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    f = checked_signal("frequency_hz", frequency_hz)
    try:
        h = np.array(response, dtype=np.complex128)
    except (TypeError, ValueError):
        raise InputError("response must be a 1-D array of complex numbers") from None
    if h.shape != f.shape:
        raise InputError(f"response has shape {h.shape}, frequency_hz has {f.shape}")
    if not np.all(np.isfinite(h)):
        bad = int(np.flatnonzero(~np.isfinite(h))[0])
        raise InputError(f"response has a non-finite value at index {bad} ({h[bad]!r}); drop those bins first")
    if np.any(f < 0):
        raise InputError(f"frequency_hz must be >= 0, got {float(f.min())!r}")
    if weights is None:
        w = np.ones_like(f)
    else:
        w = checked_signal("weights", weights)
        if w.shape != f.shape:
            raise InputError(f"weights has shape {w.shape}, frequency_hz has {f.shape}")
        if np.any(w < 0) or not np.any(w > 0):
            raise InputError("weights must be >= 0 with at least one > 0")
    return f, h, w


def _delay_mode(delay) -> float | None:
    """None to estimate the delay, else the fixed delay in s."""
    if isinstance(delay, (bool, np.bool_)):
        return None if delay else 0.0
    if is_real(delay) and math.isfinite(delay):
        return float(delay)
    raise ConfigError(f"delay={delay!r} must be True, False or a delay in s")


def _delay_bounds(delay_bounds_s, f_max: float) -> tuple[float, float]:
    if delay_bounds_s is None:
        return 0.0, 2.0 / f_max
    try:
        lo, hi = (float(v) for v in delay_bounds_s)
    except (TypeError, ValueError):
        raise ConfigError(f"delay_bounds_s={delay_bounds_s!r} must be a pair (min_s, max_s)") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise ConfigError(f"delay_bounds_s={delay_bounds_s!r} must be finite with min_s < max_s")
    return lo, hi


#: Delay grid: spacing 1/(8·f_max) (π/4 of phase at the top frequency), at most this many points.
_DELAY_GRID_MAX = 2001
#: Local minima of the grid refined by Brent's method (best first).
_DELAY_REFINED_MINIMA = 8


def _search_delay(cost_at, lo: float, hi: float, f_max: float) -> float:
    """Global 1-D search of τ in [lo, hi]: a grid, then bounded Brent refinement of its local minima.

    Near a sharp resonance the cost is nearly periodic in τ (period
    1/(2 f0): a sign flip of the gain) with narrow minima, so the grid only
    brackets them; each of the best local minima is refined and the lowest
    refined cost wins.
    """
    step = 1.0 / (8.0 * f_max)
    n = min(_DELAY_GRID_MAX, int(math.ceil((hi - lo) / step)) + 1)
    grid = np.linspace(lo, hi, max(n, 2))
    spacing = grid[1] - grid[0]
    costs = np.array([cost_at(t) for t in grid])
    padded = np.concatenate(([np.inf], costs, [np.inf]))
    minima = np.flatnonzero((padded[1:-1] <= padded[:-2]) & (padded[1:-1] <= padded[2:]))
    minima = minima[np.argsort(costs[minima])][:_DELAY_REFINED_MINIMA]
    best_tau, best_cost = float(grid[minima[0]]), float(costs[minima[0]])
    for k in minima:
        a, b = max(lo, grid[k] - spacing), min(hi, grid[k] + spacing)
        # optimise in units of the spacing so the tolerance is relative to it
        res = scipy.optimize.minimize_scalar(
            lambda u, a=a: cost_at(a + u * spacing),
            bounds=(0.0, (b - a) / spacing),
            method="bounded",
            options={"xatol": 1e-7},
        )
        if res.fun < best_cost:
            best_tau, best_cost = a + float(res.x) * spacing, float(res.fun)
    return best_tau


def fit_transfer_function(
    frequency_hz,
    response,
    n_num: int,
    n_den: int,
    *,
    weights=None,
    delay: bool | float = False,
    delay_bounds_s: tuple[float, float] | None = None,
    max_iter: int = 30,
    tol: float = 1e-10,
) -> TransferFunctionFit:
    """Fit G(s) = N(s)/D(s)·e^{−sτ} to a frequency response.

    Parameters
    ----------
    frequency_hz : array_like
        Frequencies f_k ≥ 0, Hz.
    response : array_like of complex
        Measured H_k at f_k (finite; drop NaN bins first).
    n_num, n_den : int
        Degrees of N (≥ 0) and D (≥ 1), n_num ≤ n_den (proper).
    weights : array_like, optional
        w_k ≥ 0 of the complex error; 1/var(H_k) is the maximum-likelihood
        choice (e.g. 1/``magnitude_std``² of a :class:`FrequencyResponse`).
        Default: all 1.
    delay : bool or float, optional
        False: no delay (τ = 0).  True: estimate τ in ``delay_bounds_s``.
        A number: that fixed τ, s.
    delay_bounds_s : (float, float), optional
        Search interval of τ, s; default (0, 2/f_max), two periods of the
        highest fitted frequency.  A delay longer than a period is only
        identifiable from the phase slope across the band; widen the
        interval explicitly when that is intended.
    max_iter : int, optional
        Sanathanan–Koerner iterations per delay.
    tol : float, optional
        Convergence: max relative change of D(s_k) between iterations.

    Returns
    -------
    TransferFunctionFit
        Coefficients in descending powers of s (rad/s), D monic.

    Notes
    -----
    Method: for a given τ the delay-free response H_k·e^{+j2πf_kτ} is fitted
    by Sanathanan–Koerner iterations from a Levy start
    (:func:`_sanathanan_koerner`), which converge to the minimiser of the
    output error Σ_k w_k |H_k − N(s_k)/D(s_k)·e^{−s_kτ}|².  The frequency is
    scaled by ω_max = 2π·max f_k inside the fit for conditioning.  With
    ``delay=True`` τ minimises that cost by a grid search (spacing
    1/(8 f_max), at most 2001 points) whose best 8 local minima are refined
    by bounded Brent minimisation, re-running the rational fit at each
    trial τ (near a sharp resonance the cost has narrow minima spaced by
    half a period, a sign flip of the gain; the phase slope across the band
    decides between them).  SK is a
    linear method: fast, no start values, and exact on noise-free data of
    the right order; it does not enforce stable poles (check ``poles``).

    Raises
    ------
    ConfigError
        For bad orders, ``delay``, ``delay_bounds_s``, ``max_iter`` or ``tol``.
    InputError
        For bad data, or fewer real equations (2 per frequency) than unknowns.
    """
    n_num, n_den, fixed_delay, max_iter, tol = _checked_fit_settings(n_num, n_den, delay, max_iter, tol)
    data = _scaled_frequency_data(frequency_hz, response, weights, n_num + 1 + n_den + (fixed_delay is None))

    def fit_at(tau: float) -> _SkResult:
        return _sanathanan_koerner(data.s_scaled, data.h * np.exp(1j * data.omega * tau), data.w, n_num, n_den, max_iter, tol)

    if fixed_delay is None:
        lo, hi = _delay_bounds(delay_bounds_s, data.f_max)
        tau = _search_delay(lambda t: fit_at(t).cost, lo, hi, data.f_max)
    else:
        tau = fixed_delay
    return _descaled_fit(fit_at(tau), data.scale, n_num, n_den, tau, data.w)


def _checked_fit_settings(n_num, n_den, delay, max_iter, tol) -> tuple[int, int, float | None, int, float]:
    """The checked (n_num, n_den, fixed delay or None to estimate, max_iter, tol) of :func:`fit_transfer_function`."""
    n_num = check_int("n_num", n_num, 0)
    n_den = check_int("n_den", n_den, 1)
    if n_num > n_den:
        raise ConfigError(f"{n_num=} must be <= {n_den=} (a proper transfer function)")
    fixed_delay = _delay_mode(delay)
    max_iter = check_int("max_iter", max_iter, 1)
    tol = check_positive("tol", tol)
    return n_num, n_den, fixed_delay, max_iter, tol


class _ScaledFrequencyData(NamedTuple):
    f: np.ndarray  # Hz
    h: np.ndarray  # complex response
    w: np.ndarray  # weights
    f_max: float  # Hz
    omega: np.ndarray  # 2πf, rad/s
    scale: float  # ω_max = 2π·f_max, rad/s
    s_scaled: np.ndarray  # jω/ω_max


def _scaled_frequency_data(frequency_hz, response, weights, n_unknown: int) -> _ScaledFrequencyData:
    """The checked data of :func:`fit_transfer_function`, with s scaled by ω_max for conditioning."""
    f, h, w = _frequency_data(frequency_hz, response, weights)
    if 2 * int(np.count_nonzero(w)) < n_unknown:
        raise InputError(f"{f.size} frequencies (2 real equations each) cannot fit {n_unknown} unknowns")
    f_max = float(f.max())
    if f_max <= 0:
        raise InputError("frequency_hz needs at least one frequency > 0")
    omega = 2 * np.pi * f
    scale = 2 * np.pi * f_max
    return _ScaledFrequencyData(f, h, w, f_max, omega, scale, 1j * omega / scale)


def _descaled_fit(sk: _SkResult, scale: float, n_num: int, n_den: int, tau: float, w: np.ndarray) -> TransferFunctionFit:
    """The fit in descending powers of s (rad/s) from the one in s_scaled = s/ω_max."""
    # back to s = s_scaled·scale: coefficient of s^i is c_i/scale^i; multiply by scale^n_den (monic D)
    num = sk.num * scale ** (n_den - np.arange(n_num + 1))
    den = sk.den * scale ** (n_den - np.arange(n_den + 1))
    return TransferFunctionFit(
        numerator=frozen(num[::-1].copy()),
        denominator=frozen(den[::-1].copy()),
        delay_s=float(tau),
        rms_residual=math.sqrt(sk.cost / float(np.sum(w))),
        iterations=sk.iterations,
        converged=sk.converged,
    )


# --------------------------------------------------------------------------- second order


@dataclass(frozen=True)
class SecondOrderFit:
    """G(s) = gain·ω0²/(s² + (ω0/Q)s + ω0²)·e^{−sτ} fitted to a frequency response.

    Parameters
    ----------
    f0_hz, q, gain, delay_s : float
        f0 = ω0/2π (Hz), Q, the DC gain (units of H, signed) and τ (s).
    f0_std_hz, q_std, gain_std, delay_std_s : float
        One-standard-deviation errors from the Jacobian at the optimum,
        scaled by the residual variance; ``delay_std_s`` is 0 when τ was
        fixed.
    rms_residual : float
        √(Σ w|H − G|²/Σ w), units of H.
    """

    f0_hz: float
    q: float
    gain: float
    delay_s: float
    f0_std_hz: float
    q_std: float
    gain_std: float
    delay_std_s: float
    rms_residual: float

    def response(self, frequency_hz) -> np.ndarray:
        """G(j2πf) at ``frequency_hz`` (Hz)."""
        return _second_order(np.asarray(frequency_hz, dtype=np.float64), self.f0_hz, self.q, self.gain, self.delay_s)


def _second_order(f: np.ndarray, f0: float, q: float, gain: float, tau: float) -> np.ndarray:
    s = 2j * np.pi * f
    w0 = 2 * np.pi * f0
    return gain * w0 * w0 / (s * s + (w0 / q) * s + w0 * w0) * np.exp(-s * tau)


def _peak_start(f: np.ndarray, h: np.ndarray) -> tuple[float, float, float]:
    """(f0, Q, gain) from the |H| peak and its half-power width (fallback start)."""
    mag = np.abs(h)
    order = np.argsort(f)
    fs_, ms_ = f[order], mag[order]
    k = int(np.argmax(ms_))
    half = ms_[k] / math.sqrt(2)
    left = np.flatnonzero(ms_[:k] < half)
    right = np.flatnonzero(ms_[k:] < half)
    lo = fs_[left[-1]] if left.size else fs_[0]
    hi = fs_[k + right[0]] if right.size else fs_[-1]
    q = max(fs_[k] / max(hi - lo, 1e-12 * fs_[k]), 0.6)
    return float(fs_[k]), float(q), float(ms_[k] / q)


def fit_second_order(
    frequency_hz,
    response,
    *,
    delay: bool | float = True,
    weights=None,
    delay_bounds_s: tuple[float, float] | None = None,
) -> SecondOrderFit:
    """Fit the delayed second-order model of the cantilever to a frequency response.

    .. math:: G(s) = \\mathrm{gain}\\,\\frac{\\omega_0^2}{s^2 + (\\omega_0/Q)s + \\omega_0^2}\\,e^{-s\\tau}

    (eq. 3.1 with the gain from drive units to deflection units, and a pure
    delay τ of the drive and acquisition path).

    Parameters
    ----------
    frequency_hz : array_like
        Frequencies, Hz (a band around the resonance).
    response : array_like of complex
        Measured H at those frequencies, finite.
    delay : bool or float, optional
        True (default): estimate τ; False: τ = 0; a number: fixed τ (s).
    weights : array_like, optional
        Weights of the complex error (1/var(H) ideally); default all 1.
    delay_bounds_s : (float, float), optional
        Search interval of τ, s; see :func:`fit_transfer_function`.

    Returns
    -------
    SecondOrderFit

    Notes
    -----
    Start: :func:`fit_transfer_function` with orders (0, 2) and the same
    delay option, giving D = s² + a1·s + a0, N = b0, hence ω0 = √a0,
    Q = ω0/a1, gain = b0/a0 (or, if that is not a resonance, the |H| peak
    and its half-power width).  Then all parameters are refined together by
    :func:`scipy.optimize.least_squares` on the weighted complex error
    √w_k·(H_k − G(j2πf_k)) (real and imaginary parts), in normalised
    parameters (f0/f0', Q/Q', gain/gain', 2πf0'·τ).  Errors:
    cov = s²·(JᵀJ)⁻¹ with s² = Σ r²/(2K − p).

    Why the delay matters: near f0 the phase of G falls through −90°; a
    delay adds −2πfτ (−126° at 70 kHz for 5 µs).  A model without τ can
    only absorb that by moving f0 and distorting Q, so leaving the delay
    out biases f0.

    Raises
    ------
    ConfigError, InputError
        As :func:`fit_transfer_function`; InputError also if fewer than 3
        frequencies are given.
    """
    fixed_delay = _delay_mode(delay)
    f, h, w = _frequency_data(frequency_hz, response, weights)
    if f.size < 3:
        raise InputError(f"a second-order fit needs at least 3 frequencies, got {f.size}")
    f0, q, gain, tau = _second_order_start(f, h, w, delay, delay_bounds_s)
    w0s = 2 * np.pi * f0
    scales = np.array([f0, q, gain, 1.0 / w0s])
    sqrt_w = np.sqrt(w)
    estimate_delay = fixed_delay is None

    def unpack(p: np.ndarray) -> tuple[float, float, float, float]:
        tau_p = p[3] * scales[3] if estimate_delay else tau
        return p[0] * scales[0], p[1] * scales[1], p[2] * scales[2], tau_p

    def residual(p: np.ndarray) -> np.ndarray:
        err = sqrt_w * (h - _second_order(f, *unpack(p)))
        return np.concatenate((err.real, err.imag))

    p0, lower, upper = _normalised_start_and_bounds(tau, scales, estimate_delay, delay_bounds_s, float(f.max()))
    sol = scipy.optimize.least_squares(residual, p0, bounds=(lower, upper), xtol=1e-14, ftol=1e-14, gtol=1e-14)
    return _second_order_record(sol, unpack(sol.x), scales, estimate_delay, w)


def _second_order_start(f, h, w, delay, delay_bounds_s) -> tuple[float, float, float, float]:
    """Start (f0, Q, gain, τ) of :func:`fit_second_order` from the (0, 2) rational fit.

    D = s² + a1·s + a0, N = b0 give ω0 = √a0, Q = ω0/a1, gain = b0/a0; if
    that is not a resonance, the |H| peak and its half-power width.
    """
    rational = fit_transfer_function(f, h, 0, 2, weights=w, delay=delay, delay_bounds_s=delay_bounds_s)
    _, a1, a0 = rational.denominator
    if a0 > 0 and a1 > 0:
        w0 = math.sqrt(a0)
        f0, q, gain = w0 / (2 * np.pi), w0 / a1, rational.numerator[-1] / a0
    else:
        f0, q, gain = _peak_start(f, h)
    tau = rational.delay_s
    if gain == 0:
        gain = float(np.max(np.abs(h))) / q
    return f0, q, gain, tau


def _normalised_start_and_bounds(tau, scales, estimate_delay, delay_bounds_s, f_max):
    """Start p0 = (1, 1, 1[, τ/scale]) of the normalised parameters and their bounds (f0, Q > 0; τ in its interval)."""
    p0 = np.array([1.0, 1.0, 1.0, tau / scales[3]])[: 4 if estimate_delay else 3]
    lower = [1e-6, 1e-6, -np.inf]
    upper = [np.inf, np.inf, np.inf]
    if estimate_delay:
        lo, hi = _delay_bounds(delay_bounds_s, f_max)
        lower.append(lo / scales[3])
        upper.append(hi / scales[3])
        p0[3] = np.clip(p0[3], lower[3], upper[3])
    return p0, lower, upper


def _second_order_record(sol, values, scales: np.ndarray, estimate_delay: bool, w: np.ndarray) -> SecondOrderFit:
    """The fit with its errors: cov = s²·(JᵀJ)⁻¹, s² = Σ r²/(2K − p), in the normalised parameters."""
    f0, q, gain, tau = values
    dof = max(sol.fun.size - sol.x.size, 1)
    s2 = float(np.dot(sol.fun, sol.fun)) / dof
    cov = s2 * np.linalg.pinv(sol.jac.T @ sol.jac)
    # |scales|: the gain's scale is the signed start gain, and a standard deviation is never negative
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None)) * np.abs(scales[: sol.x.size])
    return SecondOrderFit(
        f0_hz=float(f0),
        q=float(q),
        gain=float(gain),
        delay_s=float(tau),
        f0_std_hz=float(std[0]),
        q_std=float(std[1]),
        gain_std=float(std[2]),
        delay_std_s=float(std[3]) if estimate_delay else 0.0,
        rms_residual=math.sqrt(float(np.dot(sol.fun, sol.fun)) / float(np.sum(w))),
    )
