"""Observers of the sampled cantilever: innovation, reliability index, Kalman bank.

Shared machinery of the ch. 2 reliability index (probe-loss detection) and
the §3.4.2 / ch. 5 bank of Kalman filters and adaptive observer.

Model and realisation
---------------------
The sampled cantilever of eq. 3.40,

.. math:: p(n) + b_1 p(n-1) + b_0 p(n-2) = a_2 g(n) + a_1 g(n-1) + a_0 g(n-2),

is realised in **observer canonical form** with direct feed-through a2
(:func:`state_space`)::

    x(n+1) = A x(n) + B g(n),      A = [[-b1, 1], [-b0, 0]],   B = [a1 - a2 b1, a0 - a2 b0]ᵀ
    p(n)   = C x(n) + D g(n),      C = [1, 0],                 D = a2

Eliminating x gives back eq. 3.40, and x is exactly the ``zi`` state of
``scipy.signal.lfilter([a2, a1, a0], [1, b1, b0], g, zi=x)`` (direct form II
transposed), so a plant simulated with lfilter and an observer built here
share state coordinates.  It is the discrete twin of the ch. 5 realisation
(eq. 5.1, A = [[0, −b0], [1, −b1]], C = [0, 1]) with the two states swapped.

Predictor (the observer of eqs. 2.10 and 3.49, sampled)
------------------------------------------------------
With x̂(n|n−1) the prediction of the state before y(n) is seen::

    ŷ(n)       = C x̂(n|n−1) + D g(n)
    e(n)       = y(n) − ŷ(n)                                 (the innovation)
    x̂(n+1|n)   = A x̂(n|n−1) + B g(n) + L e(n)

It is causal: e(n) uses y and g up to sample n only.  The error
x̃ = x − x̂ of a plant equal to the model obeys x̃(n+1) = (A − LC) x̃(n)
(+ noise terms, eq. 2.11), and A − LC = [[−(b1 + L1), 1], [−(b0 + L2), 0]] has the
characteristic polynomial

.. math:: z^2 + (b_1 + L_1) z + (b_0 + L_2) =: z^2 + c_1 z + c_0,

the discrete form of the s² + (b1ᵏ + L2)s + (b0ᵏ + L1) of eqs. 5.5-5.8
(gain entries swapped with the states).

Innovation as a transfer function
---------------------------------
For a fixed gain the innovation is linear time-invariant in (y, g).  From
the predictor, x̂ = (zI − Ā)⁻¹[(B − LD)G + LY] with Ā = A − LC, and in
observer canonical form C(zI − Ā)⁻¹[u1, u2]ᵀ = (u1 z + u2)/(z² + c1 z + c0),
so

.. math::

    E(z) = H_y(z)Y(z) - H_g(z)G(z),\\quad
    H_y = \\frac{1 + b_1 z^{-1} + b_0 z^{-2}}{1 + c_1 z^{-1} + c_0 z^{-2}},\\quad
    H_g = \\frac{a_2 + a_1 z^{-1} + a_0 z^{-2}}{1 + c_1 z^{-1} + c_0 z^{-2}}.

The innovation is the equation error of eq. 3.40 (the residual REEP
minimises) passed through the all-pole filter 1/(1 + c1 z⁻¹ + c0 z⁻²) set
by the gain.  :meth:`ObserverDesign.innovation_filters` returns these
coefficients; the tests check the kernels against them.

Gains
-----
* :func:`kalman_gain` — steady-state Kalman predictor gain from the discrete
  algebraic Riccati equation.  Process noise w(n) is a white force that
  enters exactly where the dither does, x(n+1) = Ax + B(g + w/k_in),
  y = Cx + D(g + w/k_in) + v, with w expressed as the static deflection it
  would cause (deflection units rms, F/k) and k_in the dither-to-deflection
  DC gain (``FreeAirModel.gain``; 1 for the normalised G of eq. 2.6, where
  the dither is itself in deflection units).  v is white measurement noise
  (deflection units rms).  This is the Bη of eq. 3.50 (B1 = B in eq. 2.9).
* :func:`gain_for_decay` — pole placement: the model's pole pair
  ρe^{±jθ} is moved radially to re^{±jθ}, keeping the oscillation
  frequency and shrinking the envelope, with r set so that the **envelope
  of the error's free response falls by the factor** ``residual`` (1/e by
  default: ``cycles`` is then the time constant in drive periods) **within**
  ``cycles`` drive periods: r^(cycles·P) = residual, P the drive period in
  samples.  For a complex pair the free response of e(n) is exactly
  r^n·(α cos nθ + β sin nθ), so the criterion holds for the envelope, not
  just asymptotically.  To 1 % takes ln(100) = 4.6 time constants.  In
  canonical form the closed form is L1 = b1(r/√b0 − 1), L2 = r² − b0.

Streaming
---------
Every update takes a state and returns ``(block, state)``; splitting a
record into chunks of any sizes gives bit-for-bit the output of one call.
The state of each observer is x̂ (two scalars) and, for the window RMS, a
ring buffer of the last W squared innovations (:class:`WindowState`).

Window RMS (the reliability index)
----------------------------------
RMS(n) = √(S(n)/W) with S(n) the boxcar sum of the last W squared samples
(W = one drive period by default, :func:`drive_period_window`).  S is
carried as a running sum S(n) = S(n−1) + e(n)² − e(n−W)² over a ring buffer
of e², re-summed exactly from the ring every 1024 samples (counted from
the start of the stream, so chunking does not move it), which bounds the
rounding error to about 1024·ε·max S instead of letting it grow with the
record.  While fewer than W samples have been seen since the stream
started the mean is over those samples.

Single observer: numba, not lfilter
-----------------------------------
The single observer is the bank kernel with one row.  On 1e7 samples it
ran at about 175 MS/s (innovation and window RMS), against 75 MS/s for the
two ``lfilter`` calls of the transfer-function form with carried ``zi``
alone and 30 MS/s with a vectorised cumulative-sum window RMS added
(``bench/bench_observer.py`` measures all three in the same run); it also
shares its code with the bank and the adaptive observer.  The bank of 5
ran at about 70 MS/s (input samples), the adaptive observer at 170 MS/s.

Thesis notes
------------
* Eq. 2.8 and the A matrices of eqs. 2.9 and 2.12 carry the damping with
  the wrong power or sign (docs/conventions.md): the model is
  p̈ + (ω0/Q)ṗ + ω0²p = ω0²g, i.e. A = [[0, 1], [−ω0², −ω0/Q]].
* Eq. 2.13: with e = x − x̂ the forcing term is (A_z − A − L(C_z − C))x
  (plus (B_z − B)g), the negative of the printed one; only its RMS is
  used, so the sign is immaterial.  Eq. 5.3 has the right sign.
* Eq. 2.12 moves ω_e² into C_z (the numerator changes on-sample), whereas
  eq. 5.13 keeps the numerator fixed; this module follows eq. 5.13 (a
  bank shares one numerator), as docs/conventions.md recommends.
* Eq. 5.15 adds RMS values of uncorrelated components; their variances add:
  RMS = (A_e²/2 + σ²_ηe + σ²_νe)^{1/2}.

NaN: a NaN sample makes every later innovation of that observer NaN, as in
the thesis's recursion; split records at gaps and start from ``initial``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import scipy.linalg
from numba import njit

from afmtool.errors import ConfigError, InputError
from afmtool.estimators._common import as_signal, check_numerator
from afmtool.jit import JIT_OPTIONS

__all__ = [
    "DiscreteStateSpace",
    "state_space",
    "KalmanGain",
    "kalman_gain",
    "decay_radius",
    "gain_for_decay",
    "InnovationFilters",
    "ObserverDesign",
    "drive_period_window",
    "WindowState",
    "RmsStep",
    "sliding_rms_update",
    "ObserverBlock",
    "ObserverState",
    "ObserverStep",
    "observer_update",
    "BankBlock",
    "BankState",
    "BankStep",
    "bank_update",
    "AdaptiveState",
    "AdaptiveStep",
    "adaptive_update",
]

#: Default envelope factor of :func:`gain_for_decay`: 1/e, so ``cycles`` is
#: the time constant of the error in drive periods.
DEFAULT_RESIDUAL = math.exp(-1.0)

# Slots of the integer window counters carried between chunks: ring slot of
# the next sample, samples seen (saturating at W), samples since the last
# exact re-summation of the window sums.
_POS, _FILLED, _SINCE = 0, 1, 2

#: The window sums are re-summed exactly from the ring every this many samples.
_RESYNC_SAMPLES = 1024


# ---------------------------------------------------------------------------
# Model, realisation and gains
# ---------------------------------------------------------------------------


class DiscreteStateSpace(NamedTuple):
    """x(n+1) = A x(n) + B g(n), p(n) = C x(n) + D g(n) (module docstring).

    Attributes
    ----------
    A : numpy.ndarray, shape (2, 2)
        [[−b1, 1], [−b0, 0]], dimensionless.
    B : numpy.ndarray, shape (2,)
        [a1 − a2 b1, a0 − a2 b0], deflection units per dither unit.
    C : numpy.ndarray, shape (2,)
        [1, 0].
    D : float
        a2, deflection units per dither unit.
    """

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: float


def _check_denominator(denominator) -> tuple[float, float]:
    try:
        b1, b0 = (float(v) for v in denominator)
    except (TypeError, ValueError):
        raise ConfigError(f"denominator={denominator!r} must be two numbers (b1, b0)") from None
    if not (math.isfinite(b1) and math.isfinite(b0)):
        raise ConfigError(f"denominator={denominator!r} must be finite")
    return b1, b0


def _frozen(a) -> np.ndarray:
    out = np.array(a, dtype=np.float64)
    out.setflags(write=False)
    return out


def state_space(b1: float, b0: float, numerator: Sequence[float]) -> DiscreteStateSpace:
    """Observer-canonical realisation of eq. 3.40.

    Parameters
    ----------
    b1, b0 : float
        Denominator (AR) coefficients of eq. 3.40, dimensionless.
    numerator : sequence of 3 floats
        (a2, a1, a0) of eq. 3.40, deflection units per dither unit.

    Returns
    -------
    DiscreteStateSpace
        A = [[−b1, 1], [−b0, 0]], B = [a1 − a2 b1, a0 − a2 b0]ᵀ, C = [1, 0],
        D = a2.  The state equals lfilter's ``zi`` for ``([a2, a1, a0],
        [1, b1, b0])``.

    Raises
    ------
    ConfigError
        If a coefficient is not a finite number.
    """
    b1, b0 = _check_denominator((b1, b0))
    a2, a1, a0 = check_numerator(numerator)
    return DiscreteStateSpace(
        A=_frozen([[-b1, 1.0], [-b0, 0.0]]),
        B=_frozen([a1 - a2 * b1, a0 - a2 * b0]),
        C=_frozen([1.0, 0.0]),
        D=a2,
    )


class KalmanGain(NamedTuple):
    """Steady-state Kalman predictor (:func:`kalman_gain`).

    Attributes
    ----------
    gain : numpy.ndarray, shape (2,)
        L = (A P Cᵀ + S)(C P Cᵀ + R)⁻¹, deflection units⁻¹·state units.
    covariance : numpy.ndarray, shape (2, 2)
        P, the steady-state covariance of x − x̂(n|n−1), deflection units².
    innovation_variance : float
        C P Cᵀ + R, the variance of e(n) when the model is exact,
        deflection units².
    """

    gain: np.ndarray
    covariance: np.ndarray
    innovation_variance: float


def _check_nonneg(name: str, value) -> float:
    if not (isinstance(value, (int, float, np.floating, np.integer)) and math.isfinite(value) and value >= 0):
        raise ConfigError(f"{name}={value!r} must be a finite number >= 0")
    return float(value)


def _check_pos(name: str, value) -> float:
    if not (isinstance(value, (int, float, np.floating, np.integer)) and math.isfinite(value) and value > 0):
        raise ConfigError(f"{name}={value!r} must be a finite number > 0")
    return float(value)


def _check_pair(ss: DiscreteStateSpace) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    if not isinstance(ss, DiscreteStateSpace):
        raise ConfigError(f"ss must be a DiscreteStateSpace, got {type(ss).__name__}")
    a = np.asarray(ss.A, dtype=np.float64)
    b = np.asarray(ss.B, dtype=np.float64).reshape(-1)
    c = np.asarray(ss.C, dtype=np.float64).reshape(-1)
    if a.shape != (2, 2) or b.shape != (2,) or c.shape != (2,):
        raise ConfigError(f"ss must have A (2, 2), B (2,), C (2,), got {a.shape}, {b.shape}, {c.shape}")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b)) and np.all(np.isfinite(c)) and math.isfinite(ss.D)):
        raise ConfigError("ss must be finite")
    return a, b, c, float(ss.D)


def kalman_gain(
    ss: DiscreteStateSpace,
    process_noise_rms: float,
    measurement_noise_rms: float,
    *,
    input_gain: float = 1.0,
) -> KalmanGain:
    """Steady-state Kalman predictor gain by the discrete algebraic Riccati equation.

    Parameters
    ----------
    ss : DiscreteStateSpace
        The observer's model, e.g. from :func:`state_space`.
    process_noise_rms : float
        σ_w, rms of the white force noise w(n) expressed as the static
        deflection it would cause (F/k), deflection units (e.g. nm).  0 gives
        the open-loop predictor L = 0 (for a stable model).
    measurement_noise_rms : float
        σ_v > 0, rms of the white measurement noise v(n), deflection units.
    input_gain : float, optional
        k_in, DC gain from dither to deflection (deflection units per dither
        unit, ``FreeAirModel.gain``); w enters as the dither w/k_in.  1 when
        the dither is already in deflection units (eq. 2.6).

    Returns
    -------
    KalmanGain
        Gain L, covariance P and innovation variance C P Cᵀ + R.

    Raises
    ------
    ConfigError
        If a noise level or gain is out of range, or the Riccati equation
        has no stabilising solution (e.g. an unstable model with σ_w = 0).

    Notes
    -----
    With B_w = B/k_in and D_w = D/k_in the noise model is
    x(n+1) = A x + B g + B_w w, y = C x + D g + D_w w + v, so the state noise
    covariance is Q = σ_w² B_w B_wᵀ, the output noise variance
    R = σ_v² + σ_w² D_w² and their cross-covariance S = σ_w² B_w D_w.  P
    solves the filter Riccati equation (``solve_discrete_are(Aᵀ, Cᵀ, Q, R,
    s=S)``)

    .. math:: P = APA^T + Q - (APC^T + S)(CPC^T + R)^{-1}(CPA^T + S^T),

    and the predictor gain is L = (APCᵀ + S)(CPCᵀ + R)⁻¹, so that
    x̂(n+1|n) = A x̂ + B g + L e.  The filter (update) gain of a textbook
    Kalman filter is K = PCᵀ(CPCᵀ + R)⁻¹, and L = A K when S = 0.
    """
    a, b, c, d = _check_pair(ss)
    sigma_w = _check_nonneg("process_noise_rms", process_noise_rms)
    sigma_v = _check_pos("measurement_noise_rms", measurement_noise_rms)
    k_in = _check_pos("input_gain", input_gain)
    b_w = b / k_in
    d_w = d / k_in
    # Q = σ_w² B_w B_wᵀ, R = σ_v² + σ_w² D_w², S = σ_w² B_w D_w
    q_mat = sigma_w * sigma_w * np.outer(b_w, b_w)
    r_mat = np.array([[sigma_v * sigma_v + sigma_w * sigma_w * d_w * d_w]])
    s_mat = (sigma_w * sigma_w * d_w * b_w).reshape(2, 1)
    c_col = c.reshape(2, 1)
    try:
        p_mat = scipy.linalg.solve_discrete_are(a.T, c_col, q_mat, r_mat, s=s_mat)
    except (ValueError, np.linalg.LinAlgError) as exc:
        raise ConfigError(f"no stabilising Kalman gain for this model and noise ({exc})") from None
    # P symmetric by construction; enforce it exactly against solver rounding
    p_mat = 0.5 * (p_mat + p_mat.T)
    # S_e = C P Cᵀ + R
    innovation_variance = float(c @ p_mat @ c + r_mat[0, 0])
    # L = (A P Cᵀ + S) S_e⁻¹
    gain = (a @ p_mat @ c + s_mat[:, 0]) / innovation_variance
    return KalmanGain(_frozen(gain), _frozen(p_mat), innovation_variance)


def decay_radius(cycles: float, drive_period_samples: float, residual: float = DEFAULT_RESIDUAL) -> float:
    """Pole radius r whose envelope r^n falls by ``residual`` in ``cycles`` drive periods.

    Parameters
    ----------
    cycles : float
        N > 0, drive periods allowed for the decay.
    drive_period_samples : float
        P = fs/f_drive > 1, samples per drive period (not rounded).
    residual : float, optional
        Envelope factor left after N periods, in (0, 1); 1/e (default)
        makes N the time constant.

    Returns
    -------
    float
        r = residual^(1/(N·P)), per sample.

    Raises
    ------
    ConfigError
        If a parameter is out of range.
    """
    n_cycles = _check_pos("cycles", cycles)
    period = _check_pos("drive_period_samples", drive_period_samples)
    if period <= 1.0:
        raise ConfigError(f"drive_period_samples={drive_period_samples!r} must be > 1")
    if not (isinstance(residual, (int, float, np.floating)) and 0.0 < residual < 1.0):
        raise ConfigError(f"residual={residual!r} must be in (0, 1)")
    # r^(N·P) = residual
    return math.exp(math.log(residual) / (n_cycles * period))


def gain_for_decay(
    A,
    C,
    cycles: float,
    drive_period_samples: float,
    *,
    residual: float = DEFAULT_RESIDUAL,
) -> np.ndarray:
    """Observer gain that makes the error envelope fall by ``residual`` in ``cycles`` drive periods.

    Parameters
    ----------
    A : array_like, shape (2, 2)
        Model matrix; its eigenvalues must be a complex pair ρe^{±jθ}
        (an under-damped mode: trace² < 4·det).
    C : array_like, shape (2,)
        Output row; (A, C) must be observable.
    cycles, drive_period_samples, residual
        As in :func:`decay_radius`.

    Returns
    -------
    numpy.ndarray, shape (2,)
        L such that A − LC has the eigenvalues re^{±jθ},
        r = :func:`decay_radius` (``cycles``, ``drive_period_samples``,
        ``residual``): the model's poles moved radially.

    Raises
    ------
    ConfigError
        If A is not an under-damped pair, (A, C) is not observable, or a
        parameter is out of range.

    Notes
    -----
    The desired characteristic polynomial is
    φ(z) = z² − tr(A)(r/ρ) z + r², ρ = √det A, and Ackermann's formula gives
    L = φ(A) O⁻¹ [0, 1]ᵀ with O = [C; CA].  In observer canonical form
    (:func:`state_space`, tr A = −b1, det A = b0) this is
    L1 = b1(r/√b0 − 1), L2 = r² − b0, the closed form the adaptive kernel
    evaluates every sample.  r > ρ (a decay slower than the model's own) is
    allowed: it places the error poles outside the model's, still stable.
    """
    a = np.asarray(A, dtype=np.float64)
    c = np.asarray(C, dtype=np.float64).reshape(-1)
    if a.shape != (2, 2) or c.shape != (2,):
        raise ConfigError(f"A must be (2, 2) and C (2,), got {a.shape} and {c.shape}")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(c))):
        raise ConfigError("A and C must be finite")
    radius = decay_radius(cycles, drive_period_samples, residual)
    trace = float(a[0, 0] + a[1, 1])
    det = float(a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0])
    if not (det > 0.0 and trace * trace < 4.0 * det):
        raise ConfigError(f"A must have a complex pole pair (trace²={trace * trace:.6g} < 4·det={4 * det:.6g})")
    obs = np.vstack((c, c @ a))
    if abs(np.linalg.det(obs)) <= 1e-14 * max(1.0, float(np.max(np.abs(obs))) ** 2):
        raise ConfigError("(A, C) is not observable")
    # φ(z) = z² + φ1 z + φ0 with φ1 = −tr(A)·r/ρ, φ0 = r²
    phi1 = -trace * radius / math.sqrt(det)
    phi0 = radius * radius
    # L = φ(A) O⁻¹ [0, 1]ᵀ                                                   (Ackermann)
    phi_a = a @ a + phi1 * a + phi0 * np.eye(2)
    return phi_a @ np.linalg.solve(obs, np.array([0.0, 1.0]))


class InnovationFilters(NamedTuple):
    """E(z) = [y_numerator/denominator]·Y(z) − [g_numerator/denominator]·G(z).

    Coefficients in increasing powers of z⁻¹, ready for ``scipy.signal.lfilter``.

    Attributes
    ----------
    y_numerator : tuple of 3 floats
        (1, b1, b0).
    g_numerator : tuple of 3 floats
        (a2, a1, a0).
    denominator : tuple of 3 floats
        (1, c1, c0) = (1, b1 + L1, b0 + L2), the error characteristic polynomial.
    """

    y_numerator: tuple[float, float, float]
    g_numerator: tuple[float, float, float]
    denominator: tuple[float, float, float]


@dataclass(frozen=True)
class ObserverDesign:
    """One observer: a model of eq. 3.40 and its predictor gain L.

    Parameters
    ----------
    denominator : tuple of 2 floats
        (b1, b0) of the observer's model, dimensionless.
    numerator : tuple of 3 floats
        (a2, a1, a0), deflection units per dither unit.  Fixed at its
        free-air value for every model of a bank (eq. 5.13).
    gain : tuple of 2 floats
        (L1, L2) of x̂(n+1|n) = A x̂ + B g + L e.
    method : str
        How L was chosen: ``"decay"``, ``"kalman"`` or ``"given"``.

    Raises
    ------
    ConfigError
        If a coefficient is not finite or the error dynamics A − LC are not
        stable (|c0| < 1 and |c1| < 1 + c0 with c1 = b1 + L1, c0 = b0 + L2).
    """

    denominator: tuple[float, float]
    numerator: tuple[float, float, float]
    gain: tuple[float, float]
    method: str = "given"

    def __post_init__(self) -> None:
        b1, b0 = _check_denominator(self.denominator)
        numerator = check_numerator(self.numerator)
        try:
            l1, l2 = (float(v) for v in self.gain)
        except (TypeError, ValueError):
            raise ConfigError(f"gain={self.gain!r} must be two numbers (L1, L2)") from None
        if not (math.isfinite(l1) and math.isfinite(l2)):
            raise ConfigError(f"gain={self.gain!r} must be finite")
        object.__setattr__(self, "denominator", (b1, b0))
        object.__setattr__(self, "numerator", numerator)
        object.__setattr__(self, "gain", (l1, l2))
        c1, c0 = b1 + l1, b0 + l2
        # Schur–Cohn (Jury) test for z² + c1 z + c0
        if not (abs(c0) < 1.0 and abs(c1) < 1.0 + c0):
            raise ConfigError(
                f"gain={self.gain!r} makes the error dynamics unstable for denominator={self.denominator!r}"
                f" (z² + {c1:.6g} z + {c0:.6g} has a root on or outside the unit circle)"
            )

    @classmethod
    def from_decay(
        cls,
        denominator: Sequence[float],
        numerator: Sequence[float],
        cycles: float,
        drive_period_samples: float,
        *,
        residual: float = DEFAULT_RESIDUAL,
    ) -> ObserverDesign:
        """Observer whose error envelope falls by ``residual`` in ``cycles`` drive periods.

        Parameters are those of :func:`state_space` and :func:`gain_for_decay`.
        """
        b1, b0 = _check_denominator(denominator)
        ss = state_space(b1, b0, numerator)
        gain = gain_for_decay(ss.A, ss.C, cycles, drive_period_samples, residual=residual)
        return cls((b1, b0), tuple(numerator), (float(gain[0]), float(gain[1])), "decay")

    @classmethod
    def from_kalman(
        cls,
        denominator: Sequence[float],
        numerator: Sequence[float],
        process_noise_rms: float,
        measurement_noise_rms: float,
        *,
        input_gain: float = 1.0,
    ) -> ObserverDesign:
        """Steady-state Kalman predictor; parameters as in :func:`kalman_gain`."""
        b1, b0 = _check_denominator(denominator)
        ss = state_space(b1, b0, numerator)
        kal = kalman_gain(ss, process_noise_rms, measurement_noise_rms, input_gain=input_gain)
        return cls((b1, b0), tuple(numerator), (float(kal.gain[0]), float(kal.gain[1])), "kalman")

    @property
    def state_space(self) -> DiscreteStateSpace:
        """The model as :class:`DiscreteStateSpace`."""
        return state_space(*self.denominator, self.numerator)

    @property
    def error_poles(self) -> np.ndarray:
        """Eigenvalues of A − LC (complex, per sample): roots of z² + c1 z + c0."""
        c = self.innovation_filters().denominator
        return np.roots(c)

    def innovation_filters(self) -> InnovationFilters:
        """Transfer functions of the innovation (module docstring)."""
        b1, b0 = self.denominator
        l1, l2 = self.gain
        return InnovationFilters((1.0, b1, b0), self.numerator, (1.0, b1 + l1, b0 + l2))


def drive_period_window(sample_rate_hz: float, drive_frequency_hz: float) -> int:
    """Default RMS window: one drive period, W = round(fs/f_drive) ≥ 1 samples.

    Parameters
    ----------
    sample_rate_hz : float
        Sampling rate fs, Hz.
    drive_frequency_hz : float
        Drive (dither) frequency, Hz, 0 < f ≤ fs/2.

    Returns
    -------
    int
        W.  A window of a whole number of samples spans a non-integer
        number of periods (7 samples = 0.98 period of 70 kHz at 500 kHz),
        which leaves a ripple of a few % at twice the drive frequency in
        the RMS of a sinusoid; choose W = k·fs/f_drive when that matters.
    """
    fs = _check_pos("sample_rate_hz", sample_rate_hz)
    f = _check_pos("drive_frequency_hz", drive_frequency_hz)
    if f > fs / 2:
        raise ConfigError(f"drive_frequency_hz={drive_frequency_hz!r} must be <= fs/2 = {fs / 2:g}")
    return max(1, round(fs / f))


# ---------------------------------------------------------------------------
# Kernels
# ---------------------------------------------------------------------------


@njit(**JIT_OPTIONS)
def _predict(x1, x2, resid, g, b1, b0, bb1, bb2, l1, l2):
    """One predictor step of one observer; ``resid`` = y(n) − D g(n).

    Returns e(n), x̂1(n+1|n), x̂2(n+1|n).
    """
    # e(n) = y(n) − C x̂(n|n−1) − D g(n),  C = [1, 0]
    e = resid - x1
    # x̂(n+1|n) = A x̂(n|n−1) + B g(n) + L e(n),  A = [[−b1, 1], [−b0, 0]]
    x1_next = -b1 * x1 + x2 + bb1 * g + l1 * e
    x2_next = -b0 * x1 + bb2 * g + l2 * e
    return e, x1_next, x2_next


@njit(**JIT_OPTIONS)
def _window_push(ring, sums, k, pos, square):
    """Put e_k(n)² in ring slot ``pos``; return the boxcar sum S_k(n)."""
    # S_k(n) = S_k(n−1) + e_k(n)² − e_k(n−W)²
    s = sums[k] + (square - ring[k, pos])
    ring[k, pos] = square
    sums[k] = s
    return s


@njit(**JIT_OPTIONS)
def _window_rms(s, inv_count):
    """√(S/count); a running sum that rounding left just below 0 reads 0 (NaN stays NaN)."""
    ms = s * inv_count
    if ms < 0.0:
        ms = 0.0
    return math.sqrt(ms)


@njit(**JIT_OPTIONS)
def _window_block_end(start, n_samples, since):
    """End of the run of samples that ends at the next exact re-summation (or the chunk)."""
    return min(n_samples, start + (_RESYNC_SAMPLES - since))


@njit(**JIT_OPTIONS)
def _window_resync(ring, sums, since):
    """After a run: when _RESYNC_SAMPLES samples have passed, re-sum every S_k exactly.

    The running sum S_k(n) = S_k(n−1) + e² − e(n−W)² rounds at every
    update; re-summing the ring bounds the error to about
    _RESYNC_SAMPLES·ε·max S over the last _RESYNC_SAMPLES samples, however
    long the record.  Done outside the per-sample loop, where a branch and
    loop every W samples would cost a quarter of the bank's speed.
    """
    if since < _RESYNC_SAMPLES:
        return since
    for k in range(ring.shape[0]):
        total = 0.0
        for j in range(ring.shape[1]):
            total += ring[k, j]
        sums[k] = total
    return 0


@njit(**JIT_OPTIONS)
def _bank_kernel(y, g, d, b1, b0, bb1, bb2, l1, l2, xhat, ring, sums, counters, out_rms, out_e):
    """N fixed observers with a shared numerator over one chunk, one loop.

    ``xhat`` (N, 2) holds x̂(n|n−1) of every observer; it, ``ring`` (N, W),
    ``sums`` (N,) and ``counters`` [pos, filled, since] are read at entry
    and written at exit.  ``out_rms`` (N, T) is preallocated; ``out_e`` is
    (N, T) to keep the innovation or (N, 0) to skip it.
    """
    n_obs = xhat.shape[0]
    n_samples = y.shape[0]
    width = ring.shape[1]
    keep_e = out_e.shape[1] == n_samples
    pos = counters[_POS]
    filled = counters[_FILLED]
    since = counters[_SINCE]
    inv_count = 1.0 / filled if filled > 0 else 0.0
    start = 0
    while start < n_samples:
        stop = _window_block_end(start, n_samples, since)
        for i in range(start, stop):
            g_n = g[i]
            # y(n) − D g(n), shared by the bank (one numerator)
            resid = y[i] - d * g_n
            if filled < width:
                filled += 1
                inv_count = 1.0 / filled
            for k in range(n_obs):
                e, x1, x2 = _predict(xhat[k, 0], xhat[k, 1], resid, g_n, b1[k], b0[k], bb1[k], bb2[k], l1[k], l2[k])
                xhat[k, 0] = x1
                xhat[k, 1] = x2
                s = _window_push(ring, sums, k, pos, e * e)
                out_rms[k, i] = _window_rms(s, inv_count)
                if keep_e:
                    out_e[k, i] = e
            pos += 1
            if pos == width:
                pos = 0
        since = _window_resync(ring, sums, since + (stop - start))
        start = stop
    counters[_POS] = pos
    counters[_FILLED] = filled
    counters[_SINCE] = since


@njit(**JIT_OPTIONS)
def _adaptive_kernel(y, g, b1s, b0s, a2, a1, a0, radius, model, xhat, ring, sums, counters, out_rms, out_e):
    """One observer whose model (b1(n), b0(n)) changes every sample.

    ``model`` = [b1, b0, held-sample count] is the model in force, carried:
    a sample whose (b1, b0) is not an under-damped pole pair (0 < b0 < 1,
    b1² < 4 b0; NaN fails too) keeps the previous model.  The gain is the
    closed form of :func:`gain_for_decay` for the model in force,
    L1 = b1(r/√b0 − 1), L2 = r² − b0.
    """
    n_samples = y.shape[0]
    width = ring.shape[1]
    b1 = model[0]
    b0 = model[1]
    n_held = model[2]
    r2 = radius * radius
    x1 = xhat[0]
    x2 = xhat[1]
    pos = counters[_POS]
    filled = counters[_FILLED]
    since = counters[_SINCE]
    inv_count = 1.0 / filled if filled > 0 else 0.0
    start = 0
    while start < n_samples:
        stop = _window_block_end(start, n_samples, since)
        for i in range(start, stop):
            nb1 = b1s[i]
            nb0 = b0s[i]
            if nb0 > 0.0 and nb0 < 1.0 and nb1 * nb1 < 4.0 * nb0:
                b1 = nb1
                b0 = nb0
            else:
                n_held += 1.0
            # L1 = b1 (r/√b0 − 1), L2 = r² − b0: poles of A(n) moved radially to r
            l1 = b1 * (radius / math.sqrt(b0) - 1.0)
            l2 = r2 - b0
            # B(n) = [a1 − a2 b1(n), a0 − a2 b0(n)]
            bb1 = a1 - a2 * b1
            bb2 = a0 - a2 * b0
            g_n = g[i]
            e, x1, x2 = _predict(x1, x2, y[i] - a2 * g_n, g_n, b1, b0, bb1, bb2, l1, l2)
            if filled < width:
                filled += 1
                inv_count = 1.0 / filled
            s = _window_push(ring, sums, 0, pos, e * e)
            out_rms[i] = _window_rms(s, inv_count)
            out_e[i] = e
            pos += 1
            if pos == width:
                pos = 0
        since = _window_resync(ring, sums, since + (stop - start))
        start = stop
    model[0] = b1
    model[1] = b0
    model[2] = n_held
    xhat[0] = x1
    xhat[1] = x2
    counters[_POS] = pos
    counters[_FILLED] = filled
    counters[_SINCE] = since


@njit(**JIT_OPTIONS)
def _rms_kernel(x, ring, sums, counters, out_rms):
    """Window RMS of each row of ``x`` (N, T); carried state as in ``_bank_kernel``."""
    n_rows = x.shape[0]
    n_samples = x.shape[1]
    width = ring.shape[1]
    pos = counters[_POS]
    filled = counters[_FILLED]
    since = counters[_SINCE]
    inv_count = 1.0 / filled if filled > 0 else 0.0
    start = 0
    while start < n_samples:
        stop = _window_block_end(start, n_samples, since)
        for i in range(start, stop):
            if filled < width:
                filled += 1
                inv_count = 1.0 / filled
            for k in range(n_rows):
                v = x[k, i]
                s = _window_push(ring, sums, k, pos, v * v)
                out_rms[k, i] = _window_rms(s, inv_count)
            pos += 1
            if pos == width:
                pos = 0
        since = _window_resync(ring, sums, since + (stop - start))
        start = stop
    counters[_POS] = pos
    counters[_FILLED] = filled
    counters[_SINCE] = since


# ---------------------------------------------------------------------------
# Sliding-window RMS
# ---------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class WindowState:
    """Carried state of a W-sample boxcar RMS over N channels.

    Attributes
    ----------
    ring : numpy.ndarray, shape (N, W), read-only
        The last W squared samples of each channel (slot ``position`` is
        the oldest), units².
    sums : numpy.ndarray, shape (N,), read-only
        Running sums S_k of the ring rows, units².
    position : int
        Ring slot the next sample goes to.
    filled : int
        Samples seen so far, saturating at W.
    since_resum : int
        Samples since the sums were last re-summed exactly from the ring.
    """

    ring: np.ndarray
    sums: np.ndarray
    position: int
    filled: int
    since_resum: int

    @classmethod
    def initial(cls, n_channels: int, window_samples: int) -> WindowState:
        """Empty window.

        Parameters
        ----------
        n_channels : int
            N ≥ 1.
        window_samples : int
            W ≥ 1, e.g. :func:`drive_period_window`.

        Raises
        ------
        ConfigError
            If N or W is not a positive integer.
        """
        for name, value in (("n_channels", n_channels), ("window_samples", window_samples)):
            if not (isinstance(value, (int, np.integer)) and not isinstance(value, bool) and value >= 1):
                raise ConfigError(f"{name}={value!r} must be an integer >= 1")
        return cls(_frozen(np.zeros((n_channels, window_samples))), _frozen(np.zeros(n_channels)), 0, 0, 0)

    @property
    def window_samples(self) -> int:
        """W."""
        return self.ring.shape[1]

    def _unpack(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return (
            np.array(self.ring, dtype=np.float64, order="C"),
            np.array(self.sums, dtype=np.float64),
            np.array([self.position, self.filled, self.since_resum], dtype=np.int64),
        )

    @staticmethod
    def _pack(ring: np.ndarray, sums: np.ndarray, counters: np.ndarray) -> WindowState:
        ring.setflags(write=False)
        sums.setflags(write=False)
        return WindowState(ring, sums, int(counters[_POS]), int(counters[_FILLED]), int(counters[_SINCE]))


class RmsStep(NamedTuple):
    """What :func:`sliding_rms_update` returns.

    Attributes
    ----------
    rms : numpy.ndarray
        √(mean of the last min(n + 1, W) squares), same shape and units as
        the input.
    state : WindowState
        State for the next chunk.
    """

    rms: np.ndarray
    state: WindowState


def sliding_rms_update(state: WindowState, x) -> RmsStep:
    """Streaming boxcar RMS (the reliability index of ch. 2 over any signal).

    Parameters
    ----------
    state : WindowState
        From :meth:`WindowState.initial` or the previous chunk.
    x : array_like, shape (T,) or (N, T)
        Samples of N channels; 1-D only when N = 1.

    Returns
    -------
    RmsStep
        RMS per sample, same shape as ``x``, and the next state.

    Raises
    ------
    InputError
        If ``x`` is not numeric or its channel count differs from the state's.

    Notes
    -----
    The same window code (``_window_push``, ``_window_advance``) runs inside
    the observer kernels, so an observer's ``rms`` equals this function
    applied to its innovation.
    """
    if not isinstance(state, WindowState):
        raise ConfigError(f"state must be a WindowState, got {type(state).__name__}")
    try:
        arr = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError("x must be an array of numbers") from None
    n_channels = state.ring.shape[0]
    if arr.ndim == 1 and n_channels == 1:
        rows = arr.reshape(1, -1)
    elif arr.ndim == 2 and arr.shape[0] == n_channels:
        rows = arr
    else:
        raise InputError(f"x must be (N={n_channels}, T){' or (T,)' if n_channels == 1 else ''}, got shape {arr.shape}")
    rows = np.ascontiguousarray(rows)
    ring, sums, counters = state._unpack()
    out = np.empty(rows.shape, dtype=np.float64)
    _rms_kernel(rows, ring, sums, counters, out)
    return RmsStep(out.reshape(arr.shape), WindowState._pack(ring, sums, counters))


# ---------------------------------------------------------------------------
# Fixed observers: single and bank
# ---------------------------------------------------------------------------


def _check_designs(designs) -> tuple[ObserverDesign, ...]:
    if isinstance(designs, ObserverDesign):
        designs = (designs,)
    try:
        designs = tuple(designs)
    except TypeError:
        raise ConfigError("designs must be a sequence of ObserverDesign") from None
    if not designs:
        raise ConfigError("designs must hold at least one ObserverDesign")
    for i, des in enumerate(designs):
        if not isinstance(des, ObserverDesign):
            raise ConfigError(f"designs[{i}] must be an ObserverDesign, got {type(des).__name__}")
    numerators = {des.numerator for des in designs}
    if len(numerators) != 1:
        raise ConfigError(f"every observer of a bank must share the numerator (eq. 5.13), got {sorted(numerators)}")
    return designs


def _check_signals(deflection, dither) -> tuple[np.ndarray, np.ndarray]:
    y = as_signal("deflection", deflection)
    g = as_signal("dither", dither)
    if g.shape != y.shape:
        raise InputError(f"dither has {g.shape[0]} samples but deflection has {y.shape[0]}")
    return y, g


def _initial_estimate(n_obs: int, estimate) -> np.ndarray:
    if estimate is None:
        return _frozen(np.zeros((n_obs, 2)))
    try:
        x0 = np.array(estimate, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError("estimate must be numbers") from None
    x0 = np.broadcast_to(x0, (n_obs, 2)) if x0.shape == (2,) else x0
    if x0.shape != (n_obs, 2) or not np.all(np.isfinite(x0)):
        raise ConfigError(f"estimate must be finite, shape (2,) or ({n_obs}, 2), got {np.shape(estimate)}")
    return _frozen(x0)


@dataclass(frozen=True, eq=False)
class BankState:
    """Everything a bank of N fixed observers carries between chunks.

    Attributes
    ----------
    designs : tuple of ObserverDesign
        The N observers (shared numerator), fixed for the stream.
    estimate : numpy.ndarray, shape (N, 2), read-only
        x̂(n|n−1) of each observer, state units (deflection units).
    window : WindowState
        The innovation-RMS window of the N observers.
    """

    designs: tuple[ObserverDesign, ...]
    estimate: np.ndarray
    window: WindowState

    @classmethod
    def initial(cls, designs: Sequence[ObserverDesign], window_samples: int, *, estimate=None) -> BankState:
        """The state before the first sample.

        Parameters
        ----------
        designs : sequence of ObserverDesign
            N ≥ 1 observers sharing one numerator.
        window_samples : int
            W of the innovation RMS, e.g. :func:`drive_period_window`.
        estimate : array_like, shape (2,) or (N, 2), optional
            x̂(0|−1); zeros by default (the plant's state is unknown, so the
            innovation starts with a transient that decays as designed).

        Raises
        ------
        ConfigError
            If the designs do not share a numerator, or W or the estimate is invalid.
        """
        designs = _check_designs(designs)
        return cls(designs, _initial_estimate(len(designs), estimate), WindowState.initial(len(designs), window_samples))

    def _coefficients(self) -> tuple:
        a2, a1, a0 = self.designs[0].numerator
        b1 = np.array([des.denominator[0] for des in self.designs])
        b0 = np.array([des.denominator[1] for des in self.designs])
        l1 = np.array([des.gain[0] for des in self.designs])
        l2 = np.array([des.gain[1] for des in self.designs])
        # B = [a1 − a2 b1, a0 − a2 b0]
        return a2, b1, b0, a1 - a2 * b1, a0 - a2 * b0, l1, l2


class BankBlock(NamedTuple):
    """Bank output for one chunk.

    Attributes
    ----------
    rms : numpy.ndarray, shape (N, T)
        Window RMS of each observer's innovation, deflection units.
    innovation : numpy.ndarray, shape (N, T), or None
        e_k(n), deflection units; None unless ``keep_innovation``.
    """

    rms: np.ndarray
    innovation: np.ndarray | None


class BankStep(NamedTuple):
    """What :func:`bank_update` returns: this chunk's output and the next state."""

    block: BankBlock
    state: BankState


def _run_bank(state: BankState, y: np.ndarray, g: np.ndarray, keep_innovation: bool) -> tuple:
    a2, b1, b0, bb1, bb2, l1, l2 = state._coefficients()
    n_obs = len(state.designs)
    xhat = np.array(state.estimate, dtype=np.float64, order="C")
    ring, sums, counters = state.window._unpack()
    out_rms = np.empty((n_obs, y.shape[0]), dtype=np.float64)
    out_e = np.empty((n_obs, y.shape[0] if keep_innovation else 0), dtype=np.float64)
    _bank_kernel(y, g, a2, b1, b0, bb1, bb2, l1, l2, xhat, ring, sums, counters, out_rms, out_e)
    xhat.setflags(write=False)
    new_state = BankState(state.designs, xhat, WindowState._pack(ring, sums, counters))
    return out_rms, (out_e if keep_innovation else None), new_state


def bank_update(state: BankState, deflection, dither, *, keep_innovation: bool = False) -> BankStep:
    """Advance N fixed observers over one chunk in one fused loop (§3.4.2, Fig. 3.2).

    Parameters
    ----------
    state : BankState
        From :meth:`BankState.initial` or the previous chunk.
    deflection : array_like, shape (T,)
        Measured deflection y(n) = p(n) + v(n), deflection units.
    dither : array_like, shape (T,)
        Dither g(n), dither units.
    keep_innovation : bool, optional
        Also return the (N, T) innovations (memory: 8·N·T bytes).

    Returns
    -------
    BankStep
        ``(block, state)``.  Chunked runs equal one call bit for bit.

    Raises
    ------
    InputError
        If the signals are not 1-D or differ in length.
    ConfigError
        If ``state`` is not a BankState.

    Notes
    -----
    For each observer k, per sample (module docstring)::

        e_k(n)       = y(n) − C x̂_k(n|n−1) − D g(n)
        x̂_k(n+1|n)   = A_k x̂_k(n|n−1) + B_k g(n) + L_k e_k(n)
        rms_k(n)     = √(Σ_{m=n−W+1}^{n} e_k(m)² / W)

    By eq. 3.51 the filter whose model matches the plant has the least
    innovation RMS.
    """
    if not isinstance(state, BankState):
        raise ConfigError(f"state must be a BankState, got {type(state).__name__}")
    y, g = _check_signals(deflection, dither)
    out_rms, out_e, new_state = _run_bank(state, y, g, bool(keep_innovation))
    return BankStep(BankBlock(out_rms, out_e), new_state)


class ObserverBlock(NamedTuple):
    """Single-observer output for one chunk.

    Attributes
    ----------
    innovation : numpy.ndarray, shape (T,)
        e(n) = y(n) − ŷ(n), deflection units.
    rms : numpy.ndarray, shape (T,)
        Window RMS of e (the reliability index of ch. 2), deflection units.
    """

    innovation: np.ndarray
    rms: np.ndarray


@dataclass(frozen=True, eq=False)
class ObserverState:
    """A single fixed observer's carried state (ch. 2 reliability index).

    Attributes
    ----------
    design : ObserverDesign
        The observer, fixed for the stream.
    estimate : numpy.ndarray, shape (2,), read-only
        x̂(n|n−1), deflection units.
    window : WindowState
        Its innovation-RMS window (one channel).
    """

    design: ObserverDesign
    estimate: np.ndarray
    window: WindowState

    @classmethod
    def initial(cls, design: ObserverDesign, window_samples: int, *, estimate=None) -> ObserverState:
        """The state before the first sample; parameters as :meth:`BankState.initial`."""
        bank = BankState.initial((design,), window_samples, estimate=estimate)
        return cls(bank.designs[0], _frozen(bank.estimate[0]), bank.window)


class ObserverStep(NamedTuple):
    """What :func:`observer_update` returns: this chunk's output and the next state."""

    block: ObserverBlock
    state: ObserverState


def observer_update(state: ObserverState, deflection, dither) -> ObserverStep:
    """Advance one fixed observer over one chunk (eqs. 2.10, 3.49, sampled).

    Parameters
    ----------
    state : ObserverState
        From :meth:`ObserverState.initial` or the previous chunk.
    deflection : array_like, shape (T,)
        y(n), deflection units.
    dither : array_like, shape (T,)
        g(n), dither units.

    Returns
    -------
    ObserverStep
        ``(block, state)`` with the innovation and its window RMS.

    Raises
    ------
    InputError
        If the signals are not 1-D or differ in length.

    Notes
    -----
    The bank kernel with one row (see the module docstring for why not
    ``lfilter``).  Equals ``lfilter`` of :meth:`ObserverDesign.innovation_filters`
    to rounding.
    """
    if not isinstance(state, ObserverState):
        raise ConfigError(f"state must be an ObserverState, got {type(state).__name__}")
    y, g = _check_signals(deflection, dither)
    bank = BankState((state.design,), state.estimate.reshape(1, 2), state.window)
    out_rms, out_e, new_bank = _run_bank(bank, y, g, True)
    estimate = new_bank.estimate[0]
    new_state = ObserverState(state.design, estimate, new_bank.window)
    return ObserverStep(ObserverBlock(out_e[0], out_rms[0]), new_state)


# ---------------------------------------------------------------------------
# Adaptive observer (§3.4.2, Fig. 3.5)
# ---------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class AdaptiveState:
    """Carried state of the adaptive observer.

    Attributes
    ----------
    numerator : tuple of 3 floats
        Fixed (a2, a1, a0) (eq. 5.13).
    pole_radius : float
        r, radius of the error poles per sample (:func:`decay_radius`).
    model : tuple of 2 floats
        (b1, b0) in force after the last sample: the last valid pair fed
        in, or the initial model.
    held_samples : int
        Samples so far whose (b1, b0) was not an under-damped pair and that
        therefore ran on the previous model.
    estimate : numpy.ndarray, shape (2,), read-only
        x̂(n|n−1), deflection units.
    window : WindowState
        Its innovation-RMS window.
    """

    numerator: tuple[float, float, float]
    pole_radius: float
    model: tuple[float, float]
    held_samples: int
    estimate: np.ndarray
    window: WindowState

    @classmethod
    def initial(
        cls,
        numerator: Sequence[float],
        initial_denominator: Sequence[float],
        pole_radius: float,
        window_samples: int,
        *,
        estimate=None,
    ) -> AdaptiveState:
        """The state before the first sample.

        Parameters
        ----------
        numerator : sequence of 3 floats
            (a2, a1, a0), e.g. ``FreeAirModel.numerator_at(fs)``.
        initial_denominator : sequence of 2 floats
            (b1, b0) used until the first valid model arrives (typically the
            free-air model; REEP's first samples are θ = 0).  Must be an
            under-damped pair.
        pole_radius : float
            r in (0, 1), e.g. ``decay_radius(cycles, fs/f_drive)``.
        window_samples : int
            W of the innovation RMS.
        estimate : array_like, shape (2,), optional
            x̂(0|−1); zeros by default.

        Raises
        ------
        ConfigError
            If a parameter is out of range.
        """
        numerator = check_numerator(numerator)
        b1, b0 = _check_denominator(initial_denominator)
        if not (0.0 < b0 < 1.0 and b1 * b1 < 4.0 * b0):
            raise ConfigError(f"initial_denominator={initial_denominator!r} must be an under-damped pole pair")
        if not (isinstance(pole_radius, (int, float, np.floating)) and 0.0 < pole_radius < 1.0):
            raise ConfigError(f"pole_radius={pole_radius!r} must be in (0, 1)")
        return cls(
            numerator,
            float(pole_radius),
            (b1, b0),
            0,
            _initial_estimate(1, estimate)[0],
            WindowState.initial(1, window_samples),
        )


class AdaptiveStep(NamedTuple):
    """What :func:`adaptive_update` returns: this chunk's output and the next state."""

    block: ObserverBlock
    state: AdaptiveState


def adaptive_update(state: AdaptiveState, deflection, dither, b1, b0) -> AdaptiveStep:
    """Advance the adaptive observer, whose model follows REEP, over one chunk.

    Parameters
    ----------
    state : AdaptiveState
        From :meth:`AdaptiveState.initial` or the previous chunk.
    deflection, dither : array_like, shape (T,)
        y(n) (deflection units) and g(n) (dither units).
    b1, b0 : array_like, shape (T,)
        The model at each sample, e.g. REEP's ``ReepBlock.b1``/``b0``.

    Returns
    -------
    AdaptiveStep
        ``(block, state)`` with the innovation and its window RMS.

    Raises
    ------
    InputError
        If an array is not 1-D or the lengths differ.

    Notes
    -----
    Time-varying predictor, per sample (module docstring)::

        e(n)       = y(n) − C x̂(n|n−1) − D g(n)
        x̂(n+1|n)   = A(n) x̂(n|n−1) + B(n) g(n) + L(n) e(n)
        L1(n) = b1(n)(r/√b0(n) − 1),  L2(n) = r² − b0(n)

    so the error poles stay at r·e^{±jθ(n)} whatever the model.  The model
    (b1(n), b0(n)) estimated from samples up to n propagates the
    prediction of sample n + 1, which keeps the observer causal.  In the
    canonical realisation a time-varying A gives
    p(n+1) + b1(n) p(n) + b0(n−1) p(n−1) = …, i.e. b0 enters one sample
    later than in eq. 3.40 read with coefficients at n + 1; the difference
    is Δb0 per sample times p, far below the noise for REEP's estimates.
    Samples whose (b1, b0) is not an under-damped pair (REEP start-up, NaN)
    keep the previous model and are counted in ``held_samples``.
    """
    if not isinstance(state, AdaptiveState):
        raise ConfigError(f"state must be an AdaptiveState, got {type(state).__name__}")
    y, g = _check_signals(deflection, dither)
    b1s = as_signal("b1", b1)
    b0s = as_signal("b0", b0)
    if b1s.shape != y.shape or b0s.shape != y.shape:
        raise InputError(f"b1 and b0 must have {y.shape[0]} samples, got {b1s.shape[0]} and {b0s.shape[0]}")
    a2, a1, a0 = state.numerator
    model = np.array([state.model[0], state.model[1], float(state.held_samples)])
    xhat = np.array(state.estimate, dtype=np.float64)
    ring, sums, counters = state.window._unpack()
    out_rms = np.empty(y.shape[0], dtype=np.float64)
    out_e = np.empty(y.shape[0], dtype=np.float64)
    _adaptive_kernel(y, g, b1s, b0s, a2, a1, a0, state.pole_radius, model, xhat, ring, sums, counters, out_rms, out_e)
    xhat.setflags(write=False)
    new_state = AdaptiveState(
        state.numerator,
        state.pole_radius,
        (float(model[0]), float(model[1])),
        int(model[2]),
        xhat,
        WindowState._pack(ring, sums, counters),
    )
    return AdaptiveStep(ObserverBlock(out_e, out_rms), new_state)
