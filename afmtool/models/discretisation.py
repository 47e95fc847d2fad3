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

How the drive was made: the two holds
-------------------------------------
The numerator depends on what the plant saw between two samples of the
drive, and there are two physical cases (``HOLDS``):

* ``"zoh"`` — a DAC at the ADC's own rate holds the drive constant over each
  sample interval (the thesis's FPGA).  The sampled plant is then exactly
  the zero-order-hold model above, at every frequency.  Seen from the
  sampled drive, the hold delays it by half a sample: at a line f the
  phase lags the continuous G(j2πf) by about 180°·f/fs (25° at 70 kHz
  sampled at 500 kHz), and the gain carries sinc(f/fs).
* ``"continuous"`` — the drive is a continuous signal that the ADC merely
  records (a function generator, or a fast DAC behind its reconstruction
  filter).  For a band-limited drive the exact sampled response at a line
  f is G(j2πf) itself, which no 3-tap numerator reproduces at every
  frequency; a first-order (triangle) hold is not it either (it scales a
  line by sinc²(f/fs), −6 % at 68 kHz sampled at 500 kHz).  afmtool uses
  the **line-matched numerator** (:func:`line_numerator`): with the pole-map
  denominator D(z), the (a2, a1, a0) that make N(z)/D(z) equal
  G(jω_m)·e^{−jω_m τ} exactly at the match line ω_m = 2πf_m (two real
  equations) and equal G(0) = 1 at DC (the third).  G(jω)·D(e^{jωT}) is
  smooth through the resonance (D's zeros cancel G's poles), so the match
  holds to < 0.1 % in gain and < 0.001° in phase at f_m ± 6 kHz for
  f0 = 70-80 kHz, Q = 170-200 at 500 kHz (``tests/test_discretisation.py``).
  The match line is the drive's main line (f0 when it is not known).

By default the hold is told apart on the free-air segment
(:func:`classify_hold`): the measured phase of deflection over dither at the
drive, less the continuous model's phase, is near 0 for a continuous drive
and near the zero-order hold's lag for a held one.  Models identified by a
discrete fit (the ARX free-air fit, eq. 3.40) carry their own numerator and
need no hold; models given by continuous parameters (f0, Q, gain from a
sweep, a thermal tune, metadata or averaging theory) are discretised with
the hold.  ``docs/conventions.md`` states the same conventions for users.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from afmtool.errors import ConfigError, InputError
from afmtool.jit import JIT_OPTIONS

#: How the drive reached the plant between samples (module docstring).
HOLDS = ("zoh", "continuous")

__all__ = [
    "HOLDS",
    "HoldDecision",
    "classify_hold",
    "line_numerator",
    "sampled_numerator",
    "rate_numerator",
    "continuous_input_filter",
    "fit_continuous_lines",
    "sampled_response",
    "is_underdamped",
    "resonance_scalar",
    "resonance_std_scalar",
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


@njit(**JIT_OPTIONS)
def resonance_scalar(b1, b0, period):
    """Eq. 3.48 for one (b1, b0): (f0 in Hz, Q), or (NaN, NaN) where (b1, b0) is not under-damped."""
    # is_underdamped, written so that NaN lands in the else branch
    if b0 > 0.0 and b0 < 1.0 and b1 * b1 < 4.0 * b0:
        decay = -math.log(b0) / (2.0 * period)
        # rounding can put the ratio a hair outside [-1, 1] at the edge
        ratio = min(max(-b1 / (2.0 * math.sqrt(b0)), -1.0), 1.0)
        damped = math.acos(ratio) / period
        f0 = math.sqrt(decay * decay + damped * damped) / (2.0 * math.pi)
        return f0, math.pi * f0 / decay
    return np.nan, np.nan


@njit(**JIT_OPTIONS)
def resonance_std_scalar(b1, b0, var_b1, cov_b1b0, var_b0, period):
    """Standard deviations of eq. 3.48's (f0 in Hz, Q) from the covariance of (b1, b0), to first order.

    With p = −ln(b0)/(2T), u = −b1/(2√b0), q = arccos(u)/T, ω0 = √(p² + q²),
    f0 = ω0/(2π) and Q = ω0/(2p), the gradients are

    * ∂p/∂b1 = 0, ∂p/∂b0 = −1/(2T·b0);
    * ∂q/∂b1 = 1/(2T√b0·√(1 − u²)), ∂q/∂b0 = −b1/(4T·b0^{3/2}·√(1 − u²));
    * ∂ω0 = (p ∂p + q ∂q)/ω0, ∂f0 = ∂ω0/(2π), ∂Q = ∂ω0/(2p) − ω0 ∂p/(2p²);

    and Var x = ∇xᵀ C ∇x.  (NaN, NaN) where (b1, b0) is not under-damped
    or the covariance is not finite.
    """
    if not (b0 > 0.0 and b0 < 1.0 and b1 * b1 < 4.0 * b0):
        return np.nan, np.nan
    root_b0 = math.sqrt(b0)
    ratio = -b1 / (2.0 * root_b0)
    sine = math.sqrt(max(1.0 - ratio * ratio, 0.0))
    decay = -math.log(b0) / (2.0 * period)
    damped = math.acos(min(max(ratio, -1.0), 1.0)) / period
    omega = math.sqrt(decay * decay + damped * damped)
    dp0 = -1.0 / (2.0 * period * b0)
    dq1 = 1.0 / (2.0 * period * root_b0 * sine)
    dq0 = -b1 / (4.0 * period * b0 * root_b0 * sine)
    dw1 = damped * dq1 / omega
    dw0 = (decay * dp0 + damped * dq0) / omega
    var_w = dw1 * dw1 * var_b1 + 2.0 * dw1 * dw0 * cov_b1b0 + dw0 * dw0 * var_b0
    dq_1 = dw1 / (2.0 * decay)
    dq_0 = dw0 / (2.0 * decay) - omega * dp0 / (2.0 * decay * decay)
    var_q = dq_1 * dq_1 * var_b1 + 2.0 * dq_1 * dq_0 * cov_b1b0 + dq_0 * dq_0 * var_b0
    if not (var_w >= 0.0 and var_q >= 0.0):  # NaN or a covariance that is not positive semi-definite
        return np.nan, np.nan
    return math.sqrt(var_w) / (2.0 * math.pi), math.sqrt(var_q)


@njit(**JIT_OPTIONS)
def _resonance_kernel(b1, b0, period, f0_out, q_out):
    """Eq. 3.48 sample by sample; NaN where (b1, b0) is not under-damped.  Returns that count."""
    flagged = 0
    for i in range(b1.shape[0]):
        f0_out[i], q_out[i] = resonance_scalar(b1[i], b0[i], period)
        if math.isnan(f0_out[i]):
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


def sampled_response(numerator, denominator, frequency_hz, sample_rate_hz: float):
    """N(e^{jωT})/D(e^{jωT}) of eq. 3.40 at ``frequency_hz`` (Hz): complex, deflection per drive unit.

    ``numerator`` is (a2, a1, a0), ``denominator`` (b1, b0), with
    N(z) = a2 + a1 z⁻¹ + a0 z⁻², D(z) = 1 + b1 z⁻¹ + b0 z⁻².
    """
    a2, a1, a0 = (float(a) for a in numerator)
    b1, b0 = (float(b) for b in denominator)
    zinv = np.exp(-2j * np.pi * np.asarray(frequency_hz, dtype=np.float64) / sample_rate_hz)
    return (a2 + a1 * zinv + a0 * zinv * zinv) / (1.0 + b1 * zinv + b0 * zinv * zinv)


def _continuous_response(f0_hz: float, q: float, frequency_hz):
    """G(jω) = ω0²/(ω0² − ω² + jωω0/Q), unit DC gain."""
    w = 2.0 * np.pi * np.asarray(frequency_hz, dtype=np.float64)
    w0 = 2.0 * np.pi * f0_hz
    return w0 * w0 / (w0 * w0 - w * w + 1j * w * w0 / q)


def line_numerator(
    f0_hz: float, q: float, sample_rate_hz: float, *, match_hz: float | None = None, delay_s: float = 0.0
) -> DiscreteNumerator:
    """Numerator of a continuously driven cantilever, exact at one line and at DC.

    Parameters
    ----------
    f0_hz, q : float
        Resonant frequency (Hz) and quality factor of
        G(s) = ω0²/(s² + (ω0/Q)s + ω0²); 0 < f0 < fs/2, Q > 1/2.
    sample_rate_hz : float
        fs = 1/T, Hz.
    match_hz : float, optional
        The match line f_m, Hz, 0 < f_m < fs/2; default f0.
    delay_s : float, optional
        A drive-path delay τ, s, included in the target at f_m.

    Returns
    -------
    DiscreteNumerator
        (a2, a1, a0) solving, with D(z) from :func:`discrete_denominator` and
        z_m = e^{jω_m T}:

        .. math::

            a_2 + a_1 z_m^{-1} + a_0 z_m^{-2} = G(j\\omega_m)\\,e^{-j\\omega_m\\tau}\\,D(z_m),
            \\qquad a_2 + a_1 + a_0 = 1 + b_1 + b_0,

        i.e. the sampled model's response equals the continuous one (times
        the delay) at f_m and its DC gain is 1 (module docstring).

    Raises
    ------
    ConfigError
        If f0, Q, fs or f_m is out of range (named with its value).
    """
    decay, _ = _poles(f0_hz, q, sample_rate_hz)  # validates f0, Q, fs
    match = float(f0_hz if match_hz is None else match_hz)
    if not (math.isfinite(match) and 0 < match < sample_rate_hz / 2):
        raise ConfigError(f"match_hz={match_hz!r} must be > 0 and below the Nyquist frequency {sample_rate_hz / 2:g} Hz")
    if not math.isfinite(delay_s):
        raise ConfigError(f"delay_s={delay_s!r} must be finite")
    b1, b0 = discrete_denominator(f0_hz, q, sample_rate_hz)
    zinv = complex(np.exp(-2j * np.pi * match / sample_rate_hz))
    target = complex(_continuous_response(f0_hz, q, match)) * complex(np.exp(-2j * np.pi * match * delay_s))
    target *= 1.0 + b1 * zinv + b0 * zinv * zinv
    system = np.array([[1.0, 1.0, 1.0], [1.0, zinv.real, (zinv * zinv).real], [0.0, zinv.imag, (zinv * zinv).imag]])
    rhs = np.array([1.0 + b1 + b0, target.real, target.imag])
    try:
        a2, a1, a0 = np.linalg.solve(system, rhs)
    except np.linalg.LinAlgError:  # e^{-jωT} ≈ 1: the line and DC give the same equation
        raise ConfigError(f"the drive at {match:g} Hz is too close to DC (fs {sample_rate_hz:g} Hz) to match "
                          "the model's numerator there") from None
    return DiscreteNumerator(float(a2), float(a1), float(a0))


def rate_numerator(
    numerator, denominator, sample_rate_hz: float, rate_hz: float, match_hz: float
) -> DiscreteNumerator:
    r"""The numerator at a lower rate that keeps a capture-rate model's response at one line and at DC.

    REEP may run on the capture filtered and decimated to ``rate_hz``
    (:mod:`afmtool.estimators.rate_reduction`).  One filter on both
    signals leaves the response at each line as the capture-rate model
    H(z) = N(z)/D(z) has it, whatever the hold.  At the new rate the
    denominator is the pole map of the same poles, z' = z^D (eq. 3.48 at
    the capture's rate, then :func:`discrete_denominator` at ``rate_hz``),
    and the numerator solves, as :func:`line_numerator` does,

    .. math:: a_2 + a_1 z_m'^{-1} + a_0 z_m'^{-2} = H(e^{j\omega_m T}) D'(z_m'),
              \qquad a_2 + a_1 + a_0 = H(1)\,D'(1),

    with z_m' = e^{jω_m T'}: exact at the match line and at DC, and smooth
    between (D′ cancels H's poles).

    Parameters
    ----------
    numerator, denominator : sequences of floats
        (a2, a1, a0) and (b1, b0) at ``sample_rate_hz``; under-damped.
    sample_rate_hz, rate_hz : float
        The capture's rate and the lower rate, Hz.
    match_hz : float
        The match line (the drive), below both Nyquist frequencies, Hz.
    """
    f0_hz, q, valid = resonance_from_denominator(denominator[0], denominator[1], sample_rate_hz)
    if not valid:
        raise ConfigError(f"the free-air denominator {tuple(denominator)!r} is not an under-damped mode")
    if not (0 < match_hz < rate_hz / 2):
        raise ConfigError(f"the match line {match_hz:g} Hz is not below the Nyquist frequency {rate_hz / 2:g} Hz")
    b1, b0 = discrete_denominator(f0_hz, q, rate_hz)
    target = complex(sampled_response(numerator, denominator, match_hz, sample_rate_hz))
    dc = complex(sampled_response(numerator, denominator, 0.0, sample_rate_hz)).real
    zinv = complex(np.exp(-2j * np.pi * match_hz / rate_hz))
    target *= 1.0 + b1 * zinv + b0 * zinv * zinv
    system = np.array([[1.0, 1.0, 1.0], [1.0, zinv.real, (zinv * zinv).real], [0.0, zinv.imag, (zinv * zinv).imag]])
    rhs = np.array([dc * (1.0 + b1 + b0), target.real, target.imag])
    a2, a1, a0 = np.linalg.solve(system, rhs)
    return DiscreteNumerator(float(a2), float(a1), float(a0))


#: Taps of :func:`continuous_input_filter` (at ≥ 4 samples per period the fit error is below 1e-6 of |B|).
INPUT_FILTER_TAPS = 12
#: Half-width of the band it matches, as a share of the drive frequency (the side lines sit within ±10 %).
INPUT_FILTER_BAND = 0.2


def continuous_input_filter(numerator, denominator, sample_rate_hz: float, drive_hz: float,
                            taps: int = INPUT_FILTER_TAPS, band: float = INPUT_FILTER_BAND,
                            at_drive: complex | None = None) -> np.ndarray:
    r"""An FIR numerator B(z) of ``taps`` taps that is exact for a continuous drive across the drive's band.

    A drive that is a continuous signal (not held between samples) forces
    the sampled cantilever through A(z)·G(jω) at each of its lines, with
    A(z) = 1 + b1 z⁻¹ + b0 z⁻² the sampled poles (eq. 3.40) and G the
    continuous transfer function.  Three taps (a2, a1, a0) match that at one
    line and at DC only (:func:`line_numerator`, :func:`rate_numerator`);
    across the side lines of a multi-line drive the mismatch is an input
    the model lacks, and at Q 20–38 it biased Q′ by 0.01–0.03 % and f0′ by
    0.3 of a row's std on noise-free reference captures, more than REEP's
    stated std at 0.02 nm of noise.  Here B is fitted by least squares to

    .. math:: B(e^{j\omega T}) = A(e^{j\omega T})\,\kappa\,G(j\omega)\,e^{-j\omega\tau}

    on a grid over drive·(1 ± ``band``) and at DC, with G from the (f0, Q)
    of ``denominator`` (eq. 3.48) and κ, τ chosen so that B/A equals the
    given model N/A at the drive (its gain and phase there are kept, as
    the three-tap numerator had them); the drive and DC weigh 100× a grid
    point.

    Parameters
    ----------
    numerator, denominator : sequences of floats
        (a2, a1, a0) and (b1, b0) of the model at ``sample_rate_hz``.
    sample_rate_hz, drive_hz : float
        The rate B runs at and the drive's main line, Hz.
    taps : int
        Length of B.
    band : float
        Half-width of the matched band over the drive frequency.
    at_drive : complex, optional
        The response B/A must have at the drive (default: N/A of the given model).

    Returns
    -------
    numpy.ndarray
        B's taps, B(z) = Σ_k B[k] z⁻ᵏ (k = 0 multiplies g(n)).
    """
    f0_hz, q, valid = resonance_from_denominator(denominator[0], denominator[1], sample_rate_hz)
    if not valid:
        raise ConfigError(f"the denominator {tuple(denominator)!r} is not an under-damped mode")
    nyquist = sample_rate_hz / 2
    if not 0 < drive_hz < nyquist:
        raise ConfigError(f"the drive {drive_hz:g} Hz is not below the Nyquist frequency {nyquist:g} Hz")
    if at_drive is None:
        at_drive = complex(sampled_response(numerator, denominator, drive_hz, sample_rate_hz))
    ratio = at_drive / complex(_continuous_response(float(f0_hz), float(q), drive_hz))
    delay = -float(np.angle(ratio)) / (2.0 * np.pi * drive_hz)
    grid = np.linspace(max(drive_hz * (1.0 - band), 0.0), min(drive_hz * (1.0 + band), 0.9 * nyquist), 64)
    frequency = np.concatenate(([0.0, drive_hz], grid))
    zinv = np.exp(-2j * np.pi * frequency / sample_rate_hz)
    poles = 1.0 + float(denominator[0]) * zinv + float(denominator[1]) * zinv * zinv
    target = poles * abs(ratio) * _continuous_response(float(f0_hz), float(q), frequency) * np.exp(
        -2j * np.pi * frequency * delay)
    basis = zinv[:, None] ** np.arange(int(taps))[None, :]
    weight = np.ones(frequency.size)
    weight[:2] = 100.0
    system = np.vstack(((basis * weight[:, None]).real, (basis * weight[:, None]).imag))
    rhs = np.concatenate(((target * weight).real, (target * weight).imag))
    solution, *_ = np.linalg.lstsq(system, rhs, rcond=None)
    return _significant(solution)


def _significant(values, digits: int = 12):
    """``values`` to ``digits`` significant digits: LAPACK's last bits depend on the arrays' memory alignment,
    and REEP's rows must not (a run from Python and one from the CLI agree bit for bit)."""
    values = np.asarray(values, dtype=np.float64)
    scale = 10.0 ** np.floor(np.log10(np.max(np.abs(values)))) if np.any(values) else 1.0
    return np.round(values / scale, digits - 1) * scale


class ContinuousLineFit(NamedTuple):
    """(f0 Hz, Q, gain κ, delay τ s) of κ·G(jω)·e^{−jωτ} fitted to a drive's line responses."""

    f0_hz: float
    q: float
    gain: float
    delay_s: float


def fit_continuous_lines(lines_hz, responses, f0_hz: float, q: float, iterations: int = 20) -> ContinuousLineFit | None:
    r"""Fit κ·G(jω)·e^{−jωτ}, G = ω0²/(ω0² − ω² + jωω0/Q), to measured responses at ≥ 3 drive lines.

    Gauss–Newton on the real and imaginary parts of H_i/|H_i| − model_i/|H_i|
    (each line weighed by its own size), from (``f0_hz``, ``q``) and the κ, τ
    that match the first line.  With a continuous drive the lines'
    responses are G's own, so (f0, Q) here carry no discretisation error;
    an ARX fit with three numerator taps on the same segment biased Q by
    0.0013 of 20 on a noise-free reference capture.  None with fewer than
    three lines, when the fit leaves the under-damped region, or when it diverges.
    """
    lines = np.asarray(lines_hz, dtype=np.float64)
    measured = np.asarray(responses, dtype=np.complex128)
    if lines.size < 3 or not np.all(np.isfinite(measured)) or np.any(measured == 0):
        return None
    first = measured[0] / _continuous_response(f0_hz, q, lines[0])
    theta = np.array([math.log(f0_hz), math.log(q), math.log(abs(first)),
                      -float(np.angle(first)) / (2.0 * math.pi * lines[0])])
    scale = 1.0 / np.abs(measured)

    def residual(x):
        f0, qq, gain, delay = math.exp(x[0]), math.exp(x[1]), math.exp(x[2]), x[3]
        model = gain * _continuous_response(f0, qq, lines) * np.exp(-2j * math.pi * lines * delay)
        r = (model - measured) * scale
        return np.concatenate((r.real, r.imag))

    steps = np.array([1e-7, 1e-6, 1e-6, 1e-3 / lines[0]])
    try:
        for _ in range(iterations):
            r = residual(theta)
            jacobian = np.column_stack([(residual(theta + np.eye(4)[k] * steps[k]) - r) / steps[k] for k in range(4)])
            step, *_ = np.linalg.lstsq(jacobian, -r, rcond=None)
            theta = theta + step
            if np.all(np.abs(step) <= 1e-12 * np.maximum(np.abs(theta), 1e-9)):
                break
        f0, qq = math.exp(theta[0]), math.exp(theta[1])
    except (OverflowError, np.linalg.LinAlgError):  # the iteration ran away (lines far from any resonance)
        return None
    if not (math.isfinite(f0) and math.isfinite(qq) and qq > 0.5):
        return None
    return ContinuousLineFit(*(float(_significant(x)) for x in (f0, qq, math.exp(theta[2]), theta[3])))


def sampled_numerator(
    f0_hz: float, q: float, sample_rate_hz: float, hold: str, *, match_hz: float | None = None
) -> DiscreteNumerator:
    """Unit-gain numerator of G for a drive made by ``hold`` (``"zoh"`` or ``"continuous"``).

    ``"zoh"`` is :func:`zoh_numerator`; ``"continuous"`` is
    :func:`line_numerator` matched at ``match_hz`` (default f0).
    """
    if hold == "zoh":
        return zoh_numerator(f0_hz, q, sample_rate_hz)
    if hold == "continuous":
        return line_numerator(f0_hz, q, sample_rate_hz, match_hz=match_hz)
    raise ConfigError(f"hold={hold!r} must be one of {HOLDS}")


class HoldDecision(NamedTuple):
    """Which hold a capture's drive had, and why (:func:`classify_hold`).

    Attributes
    ----------
    hold : str
        ``"zoh"`` or ``"continuous"``.
    reason : str
        One sentence for report.json.
    excess_phase_deg : float or None
        Measured phase at the drive less the continuous model's, degrees
        (None when nothing was measured).
    zoh_excess_deg : float or None
        The same excess a zero-order hold predicts, degrees.
    """

    hold: str
    reason: str
    excess_phase_deg: float | None = None
    zoh_excess_deg: float | None = None

    def to_dict(self) -> dict:
        return self._asdict()


def classify_hold(
    measured_response: complex, f0_hz: float, q: float, drive_hz: float, sample_rate_hz: float
) -> HoldDecision:
    """Tell a held drive from a continuous one by the phase at the drive.

    Parameters
    ----------
    measured_response : complex
        Deflection over dither at the drive line on a free-air segment
        (any gain: only its phase is used).
    f0_hz, q : float
        The free-air resonance and quality factor.
    drive_hz : float
        The drive line, Hz.
    sample_rate_hz : float
        fs, Hz.

    Returns
    -------
    HoldDecision
        The hold whose predicted excess phase, arg(H_meas/G(jω)), is nearer:
        0 for ``"continuous"``, arg(H_zoh(e^{jωT})/G(jω)) ≈ −180°·f/fs for
        ``"zoh"``.  The reason names both and the measurement.

    Notes
    -----
    The excess phase is only as good as f0 and Q: near resonance an f0 error
    δf shifts the phase by about 2Q·δf/f0 rad, so the classification needs
    δf well below f0·(πf/fs)/(4Q) (≈ 7 Hz at 70 kHz, Q = 200, fs = 500 kHz).
    """
    continuous = complex(_continuous_response(f0_hz, q, drive_hz))
    if not (continuous != 0 and math.isfinite(abs(continuous))):
        # f0 = 1e-300 Hz beside a 70 kHz drive: the model's response there is 0 and its phase undefined
        raise InputError(
            f"the free-air model (f0 {f0_hz:g} Hz, Q {q:g}) has no response at the {drive_hz:g} Hz drive "
            f"({abs(continuous):.3g}); check --f0 and --q"
        )
    zoh = complex(
        sampled_response(zoh_numerator(f0_hz, q, sample_rate_hz), discrete_denominator(f0_hz, q, sample_rate_hz),
                         drive_hz, sample_rate_hz)
    )
    excess = math.degrees(np.angle(complex(measured_response) / continuous))
    zoh_excess = math.degrees(np.angle(zoh / continuous))
    hold = "zoh" if abs(excess - zoh_excess) < abs(excess) else "continuous"
    reason = (
        f"free-air phase at the {drive_hz:g} Hz drive is {excess:+.1f} deg from the continuous model "
        f"(f0 {f0_hz:g} Hz, Q {q:g}); a zero-order hold would give {zoh_excess:+.1f} deg: {hold}"
    )
    return HoldDecision(hold, reason, excess, zoh_excess)
