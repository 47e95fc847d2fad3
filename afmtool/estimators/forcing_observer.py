"""The tip-sample force at the drive, estimated on the free-air model: probe loss at the information limit.

Why the force (issue 28)
------------------------
Off the sample the free-air model explains the deflection; on it the
tip-sample force F(t) drives the cantilever as an extra input.  "The tip
left the sample" is "F stopped".  In tapping F is a train of impacts locked
to the drive: its harmonics k·f_d keep their phases from period to period.
Their effect on the deflection is the response of the free-air model to
them, so the detector that knows the model sees F through the model: with
G(z) the model, the deflection is y = G·(g + f) + v, f the force in the
units of the dither g (the dither that would exert it), v white measurement
noise of rms σ.

Where the information is.  After the last impact the deflection keeps
ringing at the free-air resonance; what changes at once is the *forcing*
that sustained the on-sample amplitude against the free-air decay.  Its
component at the drive, F = F_sp·e^{jω_d n}, sets the deflection's deficit
D = G(e^{jω_d})·F_sp (|D| ≥ ΔA = A0 − A_sp); once F stops, the deficit
decays with the free-air time constant τ = 2Q/ω0, so the deflection departs
from "still tapping" by |D|·(1 − e^{−m/τ}) ≈ |D|·m/τ after m samples: a
ramp.  A test that knows D and the change time accumulates, over M samples
(:func:`information_limit`),

    d²(M) = (|D|²/(2σ²))·Σ_{m<M} (1 − ρ^m)²  ≈  π²|D|²·N_p·m³ / (6·Q²·σ²)

(ρ = e^{−1/τ} per sample, N_p samples per drive period, m = M/N_p drive
periods); no test can detect the loss with error probabilities set by d
sooner.  The higher harmonics of the impact train stop at once (a step, not
a ramp), but their response is off resonance by |1 − k²|·Q: with the
impacts' harmonics at most as strong as the fundamental they add
Σ_k 1/(3π²m²(k²−1)²) ≈ 1/(3π²m²) of d² (0.4 % at m = 3, 14 % at m = 1/2),
so the drive's component carries the information and this estimator tracks
it alone.

The estimator: a Kalman filter on the free-air model with the forcing at
the drive as two more states::

    x(n+1) = A x(n) + B (g(n) + c1(n)),   y(n) = x1(n) + a2 (g(n) + c1(n)) + v(n)
    c(n+1) = R(ω_d) c(n) + w(n),          R = [[cos ω_d, −sin ω_d], [sin ω_d, cos ω_d]]

(A, B the observable canonical form of :func:`~afmtool.estimators.observer.state_space`;
c1 = Re(F e^{jω_d n}) with F a random walk in the rotating frame, w white of
variance ``forcing_noise`` per component: the filter's memory).  The
steady-state predictor gain L comes from the discrete Riccati equation with
Q = diag(0, 0, q, q), R = σ².  After y(n) the forcing phasor is
F̂(n) = (ĉ1 + jĉ2)(n+1|n)·e^{−jω_d(n+1)}.  Off the sample F̂ sits at its
free-air level F_fa (model error, ~0) within its noise s; on the sample at
F_sp.  The Kalman filter's exponential memory reaches within a constant
factor of d(M) (the prediction in :mod:`afmtool.estimators.detectability`
measures both).

Why not the impacts themselves: an energy detector on the filter's
innovation (the GLRT for a burst of unknown shape) was tried for the
returns; at high SNR it kept reading "contact" for periods after a loss
(the filter's own mismatch until F̂ decays), and on gentle re-contacts
it saw nothing the projection had not, so it is not used.

The switch
----------
Loss needs the projection z = Re((F̂ − F_fa)·ū), ū the unit phasor of
F_sp − F_fa, below ``on`` *and* the magnitude |F̂ − F_fa| below ``big`` (a
force as strong as that in another direction is contact: the impact of a
tip returning from the free amplitude, or a switch from attractive to
repulsive tapping).  The tip is back when z rises above ``off`` (> on) or
the magnitude above ``big``::

    s(n) = 1  if s(n−1) = 0, z(n) < on and |F̂ − F_fa| < big
    s(n) = 0  if s(n−1) = 1 and (z(n) > off or |F̂ − F_fa| > big)
    s(n) = s(n−1) otherwise

The index written is z/s (the free-air noise of z in units of itself): about
N(0, 1) off the sample, |F_sp − F_fa|/s on it.  Everything streams: the
filter, the phasor and the switch carry their state across chunks, and a
chunked run equals one call bit for bit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit

from afmtool.errors import ConfigError
from afmtool.estimators._common import check_numerator
from afmtool.estimators.decimation import Decimation
from afmtool.estimators.observer import _check_denominator, _check_signals
from afmtool.jit import JIT_OPTIONS

__all__ = [
    "ForcingModel",
    "forcing_model",
    "forcing_gain",
    "memory_periods",
    "closed_loop_radius",
    "ForcingDetector",
    "ForcingState",
    "forcing_update",
    "forcing_phasors",
]


class ForcingModel(NamedTuple):
    """The free-air model with the forcing at the drive as two more states (module docstring).

    Attributes
    ----------
    denominator : tuple of 2 floats
        (b1, b0) of eq. 3.40.
    numerator : tuple of 3 floats
        (a2, a1, a0), deflection units per dither unit.
    drive_rad : float
        ω_d·T, rad per sample, in (0, π).
    """

    denominator: tuple[float, float]
    numerator: tuple[float, float, float]
    drive_rad: float

    def matrices(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """(A_a, B_a, C_a, D): transition (4, 4), dither input (4,), output (4,), feed-through."""
        b1, b0 = self.denominator
        a2, a1, a0 = self.numerator
        # B = [a1 − a2 b1, a0 − a2 b0] (observable canonical form with feed-through a2)
        bb1, bb2 = a1 - a2 * b1, a0 - a2 * b0
        cos_w, sin_w = math.cos(self.drive_rad), math.sin(self.drive_rad)
        a = np.array([
            [-b1, 1.0, bb1, 0.0],
            [-b0, 0.0, bb2, 0.0],
            [0.0, 0.0, cos_w, -sin_w],
            [0.0, 0.0, sin_w, cos_w],
        ])
        return a, np.array([bb1, bb2, 0.0, 0.0]), np.array([1.0, 0.0, a2, 0.0]), a2

    def response(self) -> complex:
        """G(e^{jω_d}): the model's response at the drive, deflection per dither unit."""
        b1, b0 = self.denominator
        a2, a1, a0 = self.numerator
        z1 = complex(math.cos(self.drive_rad), -math.sin(self.drive_rad))  # z^{-1}
        return (a2 + a1 * z1 + a0 * z1 * z1) / (1.0 + b1 * z1 + b0 * z1 * z1)


def forcing_model(denominator, numerator, drive_rad: float) -> ForcingModel:
    """A :class:`ForcingModel` after checking its parts."""
    b1, b0 = _check_denominator(denominator)
    a2, a1, a0 = check_numerator(numerator)
    if not (isinstance(drive_rad, (int, float)) and 0.0 < drive_rad < math.pi):
        raise ConfigError(f"drive_rad={drive_rad!r} must be in (0, pi) rad per sample")
    return ForcingModel((b1, b0), (a2, a1, a0), float(drive_rad))


def _filter_riccati(a: np.ndarray, c: np.ndarray, q_mat: np.ndarray, r: float, iterations: int = 60) -> np.ndarray:
    """P of the filter Riccati equation by the structure-preserving doubling algorithm.

    P = A P Aᵀ − A P Cᵀ (C P Cᵀ + r)⁻¹ C P Aᵀ + Q is the control-form equation
    of (Aᵀ, Cᵀ); doubling (Chu et al. 2004) iterates, from A₀ = Aᵀ,
    G₀ = Cᵀ r⁻¹ C, H₀ = Q, with W = (I + G_k H_k)⁻¹::

        A_{k+1} = A_k W A_k,  G_{k+1} = G_k + A_k W G_k A_kᵀ,  H_{k+1} = H_k + A_kᵀ H_k W A_k

    and H_k → P quadratically: a memory of 10⁴ samples takes about 15
    steps, where ``scipy.linalg.solve_discrete_are`` took 27 ms per call
    here (the design solves ~65).
    """
    size = a.shape[0]
    eye = np.eye(size)
    ak, gk, hk = a.T.copy(), np.outer(c, c) / r, q_mat.copy()
    for _ in range(iterations):
        w = np.linalg.solve(eye + gk @ hk, eye)
        a_next = ak @ w @ ak
        g_next = gk + ak @ w @ gk @ ak.T
        h_next = hk + ak.T @ hk @ w @ ak
        converged = np.max(np.abs(h_next - hk)) <= 1e-13 * max(1e-300, np.max(np.abs(h_next)))
        ak, gk, hk = a_next, 0.5 * (g_next + g_next.T), 0.5 * (h_next + h_next.T)
        if converged:
            return hk
    raise ConfigError("the forcing model's Riccati equation did not converge (no stabilising Kalman gain)")


def forcing_gain(model: ForcingModel, forcing_noise: float, measurement_noise: float) -> np.ndarray:
    """Steady-state Kalman predictor gain L (4,) of the augmented model.

    Parameters
    ----------
    model : ForcingModel
    forcing_noise : float
        q > 0, variance per sample of each rotating-frame forcing component,
        dither units²: larger forgets faster.
    measurement_noise : float
        σ > 0, rms of the measurement noise, deflection units.

    Notes
    -----
    P solves P = A P Aᵀ + Q − A P Cᵀ (C P Cᵀ + σ²)⁻¹ C P Aᵀ with
    Q = diag(0, 0, q, q) (:func:`_filter_riccati`), and
    L = A P Cᵀ/(C P Cᵀ + σ²), as :func:`~afmtool.estimators.observer.kalman_gain`.
    """
    if not (math.isfinite(forcing_noise) and forcing_noise > 0):
        raise ConfigError(f"forcing_noise={forcing_noise!r} must be a finite number > 0")
    if not (math.isfinite(measurement_noise) and measurement_noise > 0):
        raise ConfigError(f"measurement_noise={measurement_noise!r} must be a finite number > 0")
    a, _, c, _ = model.matrices()
    r = measurement_noise * measurement_noise
    p = _filter_riccati(a, c, np.diag([0.0, 0.0, forcing_noise, forcing_noise]), r)
    # L = A P Cᵀ (C P Cᵀ + σ²)⁻¹
    return (a @ p @ c) / float(c @ p @ c + r)


def closed_loop_radius(model: ForcingModel, gain) -> float:
    """Largest modulus of the eigenvalues of A_a − L C_a: how fast the filter forgets its start."""
    a, _, c, _ = model.matrices()
    return float(np.max(np.abs(np.linalg.eigvals(a - np.outer(np.asarray(gain, dtype=np.float64), c)))))


def memory_periods(model: ForcingModel, gain, period_samples: float) -> float:
    """The filter's slowest time constant, drive periods: −1/(ln r · N_p), r = :func:`closed_loop_radius`."""
    radius = closed_loop_radius(model, gain)
    return math.inf if radius >= 1.0 else -1.0 / (math.log(radius) * period_samples)


@dataclass(frozen=True, eq=False)
class ForcingDetector:
    """A designed forcing detector: model, gain, free-air level, direction, scale and thresholds.

    Attributes
    ----------
    model : ForcingModel
    gain : tuple of 4 floats
        L of :func:`forcing_gain`.
    reference : complex
        F_fa, the free-air level of F̂, dither units.
    direction : complex
        ū, unit phasor of F_sp − F_fa.
    scale : float
        s > 0, the free-air standard deviation of z, dither units (the index is z/s).
    on, off, big : float
        Thresholds of the switch on z (on < off) and on |F̂ − F_fa| (big), dither units.
    """

    model: ForcingModel
    gain: tuple[float, float, float, float]
    reference: complex
    direction: complex
    scale: float
    on: float
    off: float
    big: float

    def __post_init__(self) -> None:
        if not isinstance(self.model, ForcingModel):
            raise ConfigError(f"model must be a ForcingModel, got {type(self.model).__name__}")
        gain = tuple(float(v) for v in self.gain)
        if len(gain) != 4 or not all(map(math.isfinite, gain)):
            raise ConfigError(f"gain={self.gain!r} must be four finite numbers")
        object.__setattr__(self, "gain", gain)
        if not (math.isfinite(self.scale) and self.scale > 0):
            raise ConfigError(f"scale={self.scale!r} must be a finite number > 0")
        if not (abs(abs(self.direction) - 1.0) < 1e-9):
            raise ConfigError(f"direction={self.direction!r} must be a unit phasor")
        if not (math.isfinite(self.on) and math.isfinite(self.off) and self.on < self.off and self.big > 0):
            raise ConfigError(f"thresholds on={self.on!r} < off={self.off!r} and big={self.big!r} > 0 are needed")

    def coefficients(self) -> np.ndarray:
        """[b1, b0, a2, bb1, bb2, cos ω, sin ω, L0, L1, L2, L3] for the kernel."""
        return _coefficients(self.model, self.gain)

    def thresholds(self) -> np.ndarray:
        """[F_fa re, F_fa im, ū re, ū im, 1/s, on, off, big] for the kernel."""
        ref, u = complex(self.reference), complex(self.direction)
        return np.array([ref.real, ref.imag, u.real, u.imag, 1.0 / self.scale, self.on, self.off, self.big])


@njit(**JIT_OPTIONS)
def _forcing_step(y, g, x, coef):
    """One predictor step of the augmented filter; updates ``x`` (4,) in place, returns the innovation.

    ``coef`` = [b1, b0, a2, bb1, bb2, cos ω, sin ω, L0, L1, L2, L3].
    """
    b1, b0, a2, bb1, bb2 = coef[0], coef[1], coef[2], coef[3], coef[4]
    cos_w, sin_w = coef[5], coef[6]
    x0, x1, x2, x3 = x[0], x[1], x[2], x[3]
    u = g + x2  # the dither plus the forcing at the drive, as the plant sees them
    # e(n) = y(n) − x1 − a2·(g + c1)
    e = y - x0 - a2 * u
    # x(n+1|n) = A_a x(n|n−1) + B_a g(n) + L e(n)
    x[0] = -b1 * x0 + x1 + bb1 * u + coef[7] * e
    x[1] = -b0 * x0 + bb2 * u + coef[8] * e
    x[2] = cos_w * x2 - sin_w * x3 + coef[9] * e
    x[3] = sin_w * x2 + cos_w * x3 + coef[10] * e
    return e


@njit(**JIT_OPTIONS)
def _forcing_kernel(y, g, coef, thr, x, phasor, carried, first_keep, keep_every, out_switch, out_index, out_decisive):
    """Filter, phasor, projection and switch over one chunk (module docstring).

    ``phasor`` = [cos ω_d n0, sin ω_d n0, cos ω_d, sin ω_d] for the chunk's first
    stream sample n0; ``x`` (4,), the phasor's first two entries and
    ``carried`` [s] are read at entry and written at exit (so a chunked run
    equals one call bit for bit); ``out_decisive[0]`` is the first sample
    whose statistics set the switch whatever its state before, −1 if none.
    """
    cos_k, sin_k, cos_step, sin_step = phasor[0], phasor[1], phasor[2], phasor[3]
    ref_re, ref_im, u_re, u_im, inv_scale = thr[0], thr[1], thr[2], thr[3], thr[4]
    on, off, big = thr[5], thr[6], thr[7]
    state = carried[0]
    next_keep = first_keep
    k = 0
    decisive = -1
    for i in range(y.shape[0]):
        _forcing_step(y[i], g[i], x, coef)
        # e^{jω_d (n+1)}: the predicted state belongs to the next sample
        cos_k, sin_k = cos_k * cos_step - sin_k * sin_step, sin_k * cos_step + cos_k * sin_step
        # F̂(n) = (ĉ1 + jĉ2)(n+1|n)·e^{−jω_d(n+1)}, less the free-air level
        w_re = x[2] * cos_k + x[3] * sin_k - ref_re
        w_im = x[3] * cos_k - x[2] * sin_k - ref_im
        z = w_re * u_re + w_im * u_im
        magnitude = math.sqrt(w_re * w_re + w_im * w_im)
        loss_now = z < on and magnitude < big
        back_now = z > off or magnitude > big
        if decisive < 0 and (loss_now or back_now):
            decisive = i
        if state == 0:
            if loss_now:
                state = 1
        elif back_now:
            state = 0
        out_switch[i] = state
        if i == next_keep:
            out_index[k] = z * inv_scale
            k += 1
            next_keep += keep_every
    carried[0] = state
    phasor[0] = cos_k
    phasor[1] = sin_k
    out_decisive[0] = decisive


@njit(**JIT_OPTIONS)
def _phasor_kernel(y, g, coef, x, phasor, first_keep, keep_every, out):
    """F̂(n) at the kept samples (complex, dither units), for the design."""
    cos_k, sin_k, cos_step, sin_step = phasor[0], phasor[1], phasor[2], phasor[3]
    next_keep = first_keep
    k = 0
    for i in range(y.shape[0]):
        _forcing_step(y[i], g[i], x, coef)
        cos_k, sin_k = cos_k * cos_step - sin_k * sin_step, sin_k * cos_step + cos_k * sin_step
        if i == next_keep:
            out[k] = complex(x[2] * cos_k + x[3] * sin_k, x[3] * cos_k - x[2] * sin_k)
            k += 1
            next_keep += keep_every


def _phasor(drive_rad: float, first: int) -> np.ndarray:
    anchor = drive_rad * float(first)
    return np.array([math.cos(anchor), math.sin(anchor), math.cos(drive_rad), math.sin(drive_rad)])


def _coefficients(model: ForcingModel, gain) -> np.ndarray:
    b1, b0 = model.denominator
    a2, a1, a0 = model.numerator
    w = model.drive_rad
    return np.array([b1, b0, a2, a1 - a2 * b1, a0 - a2 * b0, math.cos(w), math.sin(w),
                     *(float(v) for v in gain)])


def forcing_phasors(model: ForcingModel, gain, deflection, dither, *, keep_every: int = 1,
                    first: int = 0) -> np.ndarray:
    """F̂(n) (complex, dither units) at samples n with (n + 1) % keep_every == 0, from a zero start.

    For the design (:mod:`afmtool.estimators.detectability`): the free-air
    level and noise, the on-sample forcing of a survey, a synthetic record.
    ``first`` is the stream index of the first sample (the phasor's anchor).
    """
    y, g = _check_signals(deflection, dither)
    decimation = Decimation(int(keep_every))
    out = np.empty(decimation.count(first, y.shape[0]), dtype=np.complex128)
    _phasor_kernel(y, g, _coefficients(model, gain), np.zeros(4), _phasor(model.drive_rad, first),
                   decimation.first_kept(first), int(keep_every), out)
    return out


@dataclass(frozen=True, eq=False)
class ForcingState:
    """Carried state of :func:`forcing_update`.

    Attributes
    ----------
    detector : ForcingDetector
    estimate : numpy.ndarray, shape (4,)
        x̂(n|n−1) of the next sample.
    switch : int
        s of the last sample.
    samples_seen : int
        The next sample's index in the stream.
    phasor : (float, float)
        (cos, sin) of ω_d·samples_seen, rotated on from the start (anchored
        once, at :meth:`initial`).
    """

    detector: ForcingDetector
    estimate: np.ndarray
    switch: int = 0
    samples_seen: int = 0
    phasor: tuple[float, float] = (1.0, 0.0)

    @classmethod
    def initial(cls, detector: ForcingDetector, *, samples_seen: int = 0) -> ForcingState:
        """The detector before its first sample, ``samples_seen`` samples into the stream."""
        anchor = _phasor(detector.model.drive_rad, int(samples_seen))
        return cls(detector, np.zeros(4), 0, int(samples_seen), (float(anchor[0]), float(anchor[1])))

    def __post_init__(self) -> None:
        if not isinstance(self.detector, ForcingDetector):
            raise ConfigError(f"detector must be a ForcingDetector, got {type(self.detector).__name__}")
        estimate = np.array(self.estimate, dtype=np.float64).reshape(4)
        estimate.setflags(write=False)
        object.__setattr__(self, "estimate", estimate)
        if self.switch not in (0, 1):
            raise ConfigError(f"switch={self.switch!r} must be 0 or 1")
        if not (isinstance(self.samples_seen, (int, np.integer)) and self.samples_seen >= 0):
            raise ConfigError(f"samples_seen={self.samples_seen!r} must be an integer >= 0")


def forcing_update(state: ForcingState, deflection, dither, *, keep_every: int = 1):
    """The forcing detector over one chunk: ``(ReliabilityBlock, next state)``.

    Parameters
    ----------
    state : ForcingState
    deflection, dither : array_like, shape (T,)
        y(n) (deflection units) and g(n) (dither units).
    keep_every : int, optional
        The index is returned at the samples n with (n + 1) % keep_every == 0.

    Returns
    -------
    ReliabilityStep
        The switch at every sample, the index z/s at the kept ones, the first
        decisive sample; chunked runs equal one call bit for bit.
    """
    from afmtool.estimators.reliability import ReliabilityBlock, ReliabilityStep

    if not isinstance(state, ForcingState):
        raise ConfigError(f"state must be a ForcingState, got {type(state).__name__}")
    if not (isinstance(keep_every, (int, np.integer)) and not isinstance(keep_every, bool) and keep_every >= 1):
        raise ConfigError(f"keep_every={keep_every!r} must be an integer >= 1")
    y, g = _check_signals(deflection, dither)
    detector = state.detector
    n = y.shape[0]
    decimation = Decimation(int(keep_every))
    switch = np.empty(n, dtype=np.int8)
    index = np.empty(decimation.count(state.samples_seen, n), dtype=np.float64)
    x = np.array(state.estimate, dtype=np.float64)
    carried = np.array([state.switch], dtype=np.int64)
    decisive = np.empty(1, dtype=np.int64)
    w = detector.model.drive_rad
    phasor = np.array([state.phasor[0], state.phasor[1], math.cos(w), math.sin(w)])
    _forcing_kernel(y, g, detector.coefficients(), detector.thresholds(), x, phasor, carried,
                    decimation.first_kept(state.samples_seen), int(keep_every), switch, index, decisive)
    new_state = ForcingState(detector, x, int(carried[0]), state.samples_seen + n, (float(phasor[0]), float(phasor[1])))
    return ReliabilityStep(ReliabilityBlock(switch, index, int(decisive[0])), new_state)
