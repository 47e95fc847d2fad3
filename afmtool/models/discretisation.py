"""Sampled forms of the one-mode cantilever.

The discrete model of eq. 3.40 is

.. math:: p(n) + b_1 p(n-1) + b_0 p(n-2) = a_2 g(n) + a_1 g(n-1) + a_0 g(n-2),

i.e. ``scipy.signal.lfilter([a2, a1, a0], [1, b1, b0], g)``.  For the
continuous model G(s) = ω0²/(s² + (ω0/Q)s + ω0²) (eq. 3.1) with poles
s = −p ± jq,

* p = ω0/(2Q) (decay rate, 1/s) and q = ω0·√(1 − 1/(4Q²)) (damped angular
  frequency, rad/s);
* the pole map z = e^{sT} (T = 1/fs) gives the denominator
  b1 = −2e^{−pT}cos(qT), b0 = e^{−2pT}.  This is what the zero-order-hold,
  impulse-invariant and "triangular" (eq. 3.44) discretisations share, and
  eq. 3.48 inverts it;
* the zero-order-hold numerator follows from H(z) = (1 − z⁻¹)·Z{G(s)/s}
  with the step response y(t) = 1 − e^{−pt}(cos qt + (p/q) sin qt):

  .. math::

      a_2 = 0,\\quad a_1 = 1 - e^{-pT}(\\cos qT + (p/q)\\sin qT),\\quad
      a_0 = e^{-2pT} - e^{-pT}(\\cos qT - (p/q)\\sin qT),

  and a1 + a0 = 1 + b1 + b0, so the DC gain is 1 like G(0).

These closed forms are checked against ``scipy.signal.cont2discrete`` in
``tests/test_sim.py``.  They need an under-damped mode (Q > 1/2) sampled
above twice its resonance (f0 < fs/2), so that qT < π and the map from
(f0, Q) to (b1, b0) is one-to-one.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from afmtool.errors import ConfigError

__all__ = [
    "is_underdamped",
    "DiscreteDenominator",
    "DiscreteNumerator",
    "ResonanceFromDenominator",
    "discrete_denominator",
    "zoh_numerator",
    "resonance_from_denominator",
]


class DiscreteDenominator(NamedTuple):
    """AR coefficients (b1, b0) of eq. 3.40 (dimensionless).

    Fields are floats for scalar inputs and arrays of the broadcast input
    shape otherwise.
    """

    b1: float | np.ndarray
    b0: float | np.ndarray


class DiscreteNumerator(NamedTuple):
    """Numerator (a2, a1, a0) of eq. 3.40, multiplying g(n), g(n−1), g(n−2)."""

    a2: float
    a1: float
    a0: float


class ResonanceFromDenominator(NamedTuple):
    """(f0, Q) recovered from (b1, b0) by eq. 3.48.

    ``f0_hz`` (Hz) and ``q`` are NaN where ``valid`` is False, i.e. where
    (b1, b0) is not the pole pair of an under-damped mode.
    """

    f0_hz: float | np.ndarray
    q: float | np.ndarray
    valid: bool | np.ndarray


def _poles(f0_hz, q, sample_rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """Decay rate p (1/s) and damped frequency q (rad/s), validated."""
    f0 = np.asarray(f0_hz, dtype=np.float64)
    qf = np.asarray(q, dtype=np.float64)
    if not (math.isfinite(sample_rate_hz) and sample_rate_hz > 0):
        raise ConfigError(f"sample_rate_hz={sample_rate_hz!r} must be a finite number > 0")
    if not np.all(np.isfinite(f0) & (f0 > 0) & (f0 < sample_rate_hz / 2)):
        raise ConfigError(
            f"f0_hz={f0_hz!r} must be > 0 and below the Nyquist frequency {sample_rate_hz / 2:g} Hz"
        )
    if not np.all(np.isfinite(qf) & (qf > 0.5)):
        raise ConfigError(f"q={q!r} must be a finite number > 0.5 (an under-damped mode)")
    w0 = 2.0 * np.pi * f0
    decay = w0 / (2.0 * qf)
    damped = w0 * np.sqrt(1.0 - 1.0 / (4.0 * qf * qf))
    return decay, damped


def _scalar_or_array(x: np.ndarray) -> float | np.ndarray:
    return float(x) if x.ndim == 0 else x


def discrete_denominator(f0_hz, q, sample_rate_hz: float) -> DiscreteDenominator:
    """Denominator (b1, b0) of the sampled cantilever by the pole map z = e^{sT}.

    Parameters
    ----------
    f0_hz : float or array_like
        Resonant frequency f0, Hz; 0 < f0 < fs/2.
    q : float or array_like
        Quality factor Q > 1/2, broadcast against ``f0_hz``.
    sample_rate_hz : float
        Sampling rate fs = 1/T, Hz.

    Returns
    -------
    DiscreteDenominator
        b1 = −2e^{−pT}cos(qT) and b0 = e^{−2pT}, with p = ω0/(2Q) and
        q = ω0·√(1 − 1/(4Q²)): the inverse of eq. 3.48.

    Raises
    ------
    ConfigError
        If f0, Q or fs is out of range (named with its value).
    """
    decay, damped = _poles(f0_hz, q, sample_rate_hz)
    period = 1.0 / sample_rate_hz
    envelope = np.exp(-decay * period)
    b1 = -2.0 * envelope * np.cos(damped * period)
    b0 = envelope * envelope
    return DiscreteDenominator(_scalar_or_array(b1), _scalar_or_array(b0))


def zoh_numerator(f0_hz: float, q: float, sample_rate_hz: float) -> DiscreteNumerator:
    """Zero-order-hold numerator (a2, a1, a0) of G(s) = ω0²/(s² + (ω0/Q)s + ω0²).

    Parameters
    ----------
    f0_hz : float
        Resonant frequency f0, Hz; 0 < f0 < fs/2.
    q : float
        Quality factor Q > 1/2.
    sample_rate_hz : float
        Sampling rate fs = 1/T, Hz.

    Returns
    -------
    DiscreteNumerator
        a2 = 0 (a zero-order hold has no direct feed-through),
        a1 = 1 − e^{−pT}(cos qT + (p/q) sin qT) and
        a0 = e^{−2pT} − e^{−pT}(cos qT − (p/q) sin qT) (module docstring).
        With :func:`discrete_denominator` this is the exact discrete-time
        response of G to a piecewise-constant input; DC gain 1.

    Notes
    -----
    The closed forms lose relative precision as (ω0T)² approaches machine
    epsilon (oversampling beyond ~1e6), far outside AFM use.
    """
    decay, damped = _poles(f0_hz, q, sample_rate_hz)
    decay, damped = float(decay), float(damped)
    period = 1.0 / sample_rate_hz
    envelope = math.exp(-decay * period)
    cos_qt = math.cos(damped * period)
    ratio_sin = (decay / damped) * math.sin(damped * period)
    a1 = 1.0 - envelope * (cos_qt + ratio_sin)
    a0 = envelope * envelope - envelope * (cos_qt - ratio_sin)
    return DiscreteNumerator(0.0, a1, a0)


def is_underdamped(b1, b0) -> np.ndarray:
    """Where (b1, b0) is the pole pair of an under-damped mode: 0 < b0 < 1 and b1² < 4·b0.

    The validity condition of eq. 3.48 (|b1| < 2√b0), without a square root.
    """
    b1a = np.asarray(b1, dtype=np.float64)
    b0a = np.asarray(b0, dtype=np.float64)
    return (b0a > 0) & (b0a < 1) & (b1a * b1a < 4.0 * b0a)


@njit(cache=True, nogil=True)
def _resonance_kernel(b1, b0, period, f0_out, q_out):  # noqa: PLR0913
    """Eq. 3.48 sample by sample; NaN where (b1, b0) is not under-damped.  Returns that count."""
    flagged = 0
    for i in range(b1.shape[0]):
        x1 = b1[i]
        x0 = b0[i]
        # is_underdamped, written so that NaN lands in the else branch
        if x0 > 0.0 and x0 < 1.0 and x1 * x1 < 4.0 * x0:
            decay = -math.log(x0) / (2.0 * period)
            # rounding can put the ratio a hair outside [-1, 1] at the edge
            ratio = min(max(-x1 / (2.0 * math.sqrt(x0)), -1.0), 1.0)
            damped = math.acos(ratio) / period
            f0 = math.sqrt(decay * decay + damped * damped) / (2.0 * math.pi)
            f0_out[i] = f0
            q_out[i] = math.pi * f0 / decay
        else:
            f0_out[i] = np.nan
            q_out[i] = np.nan
            flagged += 1
    return flagged


def resonance_from_denominator(b1, b0, sample_rate_hz: float) -> ResonanceFromDenominator:
    """Resonant frequency and quality factor from (b1, b0), eq. 3.48.

    Parameters
    ----------
    b1, b0 : float or array_like
        AR coefficients of eq. 3.40.
    sample_rate_hz : float
        Sampling rate fs = 1/T, Hz.

    Returns
    -------
    ResonanceFromDenominator
        p = −ln(b0)/(2T), q = arccos(−b1/(2√b0))/T, f0 = √(p² + q²)/(2π) (Hz),
        Q = π·f0/p.  Valid only where 0 < b0 < 1 and |b1| < 2√b0; elsewhere
        f0 and Q are NaN and ``valid`` is False.

    Notes
    -----
    One numba pass with no temporaries: REEP converts every kept sample,
    and the numpy expression cost as much as the estimator itself.
    """
    if not (math.isfinite(sample_rate_hz) and sample_rate_hz > 0):
        raise ConfigError(f"sample_rate_hz={sample_rate_hz!r} must be a finite number > 0")
    b1a, b0a = np.broadcast_arrays(np.asarray(b1, dtype=np.float64), np.asarray(b0, dtype=np.float64))
    flat_b1 = np.ascontiguousarray(b1a).ravel()
    flat_b0 = np.ascontiguousarray(b0a).ravel()
    f0 = np.empty_like(flat_b1)
    qf = np.empty_like(flat_b1)
    _resonance_kernel(flat_b1, flat_b0, 1.0 / sample_rate_hz, f0, qf)
    if b1a.ndim == 0:
        return ResonanceFromDenominator(float(f0[0]), float(qf[0]), bool(np.isfinite(f0[0])))
    f0 = f0.reshape(b1a.shape)
    return ResonanceFromDenominator(f0, qf.reshape(b1a.shape), np.isfinite(f0))
