"""Where REEP's f0′ and Q′ are invalid: the per-row validity flags of ``afmtool reep``.

REEP fits a linear second-order model (eq. 3.40) in a window of 1/(1 − λ)
samples.  A flag marks a row whose fitted (b1, b0) is *invalid*, not one
that is merely uncertain: how uncertain every row is, ``f0_std_hz`` and
``q_std`` say (:mod:`afmtool.estimators.rls`).  Each reason is a bit of
the ``flag`` series in ``reep.h5`` (0 = valid):

* :data:`FLAG_NOT_UNDERDAMPED` (1): (b1, b0) outside the under-damped region
  0 < b0 < 1, |b1| < 2√b0, where eq. 3.48 has no (f0′, Q′) (docs/conventions.md).
  Output-only (no dither: FM-KPFM, self-oscillation) the damping is the
  loop's, not the cantilever's, and Q′ is not identifiable: f0′ is the
  frequency the poles oscillate at, arccos(−b1/(2√b0))/(2πT), defined
  wherever the poles are a complex pair (b0 > 0, |b1| < 2√b0), and only
  rows without one are flagged (a loop that holds the oscillation puts the
  poles on the unit circle, b0 ≈ 1, on either side of it);
* :data:`FLAG_LOW_AMPLITUDE` (2): the oscillation amplitude at the drive is
  below ``min_amplitude_fraction`` of the free amplitude (the stated floor,
  1 % by default).  The regressors then carry little but noise: the bias
  compensation subtracts σ²R⁻¹θ with R ≈ A²/2, so its error grows as
  (σ/A)² faster than the first-order standard deviation says;
* :data:`FLAG_OFFSET_DRIFT` (8), with the static-offset regressor only: the
  offset p̄ = c/(1 + b1 + b0) moves within REEP's window by more than that
  constant can follow.  Its exponentially weighted variance over the window
  (the same λ), V = E_w[p̄²] − E_w[p̄]², is the power of a regressor the
  model lacks; compared with the power the oscillation gives the AR
  regressors, A²/2, V > ``max_offset_drift``·A²/2 means b1, b0 absorb it
  (a fast approach into the attractive trap, where p̄ changes by tenths of
  a nm per window beside a 0.3 nm oscillation, and f0′ reads 20–30 % low);
* :data:`FLAG_NOT_CONVERGED` (16): the estimator has not yet forgotten its
  start, the first ``warmup_windows`` windows of the stream, or its bias
  compensation has not started (σ̂² undefined, the start-up guard of
  eq. 3.39).

Bit 4 is not used: it was "σ̂² above 4× its free-air level".  σ̂² is the
window's residual variance over (1 + θᵀθ); in repulsive tapping it rises
because the tip–sample force is nonlinear, which is the model mismatch the
measurement is made of, not a reason to blank f0′ and Q′.  It stays a
series in ``reep.h5``, with its free-air level in the report.

The free-air levels come from the capture's own free-air segment, by the
same estimator (:class:`~afmtool.estimators.reep_estimator.ReepEstimator`)
and the lock-in: medians after their start-up.  Flagged rows are NaN in the
summaries, force-curve tables and images of f0′ and Q′; ``reep.h5`` keeps
the fitted values and the flag.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit

from afmtool.errors import SampleShareWarning
from afmtool.jit import JIT_OPTIONS
from afmtool.models.discretisation import resonance_scalar, resonance_std_scalar

__all__ = [
    "FLAG_NOT_UNDERDAMPED",
    "FLAG_LOW_AMPLITUDE",
    "FLAG_OFFSET_DRIFT",
    "FLAG_NOT_CONVERGED",
    "OffsetDrift",
    "FLAG_REASONS",
    "FreeAirLevels",
    "ValidityLimits",
    "free_air_levels",
    "validity_flags",
    "ReepRows",
    "reep_rows",
    "FlagCounter",
]

FLAG_NOT_UNDERDAMPED = 1
FLAG_LOW_AMPLITUDE = 2
FLAG_OFFSET_DRIFT = 8
FLAG_NOT_CONVERGED = 16

#: Report keys and the warning text of each flag bit.
FLAG_REASONS = {
    FLAG_NOT_UNDERDAMPED: ("not_underdamped", "(b1, b0) outside the under-damped region of eq. 3.48"),
    FLAG_LOW_AMPLITUDE: ("low_amplitude", "amplitude below {min_amplitude_fraction:g} of the free amplitude"),
    FLAG_NOT_CONVERGED: ("not_converged", "the estimator had not converged (start-up, or its bias compensation undefined)"),
    FLAG_OFFSET_DRIFT: (
        "offset_drift",
        "the static offset varies within the window by more than {max_offset_drift:g} of the oscillation's power A^2/2",
    ),
}


@dataclass(frozen=True)
class ValidityLimits:
    """Thresholds of the flags (module docstring).  0 switches a check off.

    Attributes
    ----------
    min_amplitude_fraction : float
        Lowest valid amplitude, as a share of the free amplitude.
    max_offset_drift : float
        Highest valid variance of the static offset over the window, as
        a share of A²/2.
    """

    min_amplitude_fraction: float
    max_offset_drift: float = 0.0


class FreeAirLevels(NamedTuple):
    """Free-air references of the flags.

    Attributes
    ----------
    amplitude : float or None
        Free amplitude at the drive, deflection units (None: unknown, the
        amplitude check is off).
    sigma2 : float or None
        REEP's σ̂² in free air, deflection units² (reported beside the σ̂² series; None: unknown).
    source : str
        Where they came from: ``"free-air segment"``, ``"metadata"`` or ``"none"``.
    """

    amplitude: float | None
    sigma2: float | None
    source: str

    def as_dict(self) -> dict:
        return {"amplitude": self.amplitude, "sigma2": self.sigma2, "source": self.source}


def free_air_levels(sigma2: np.ndarray, amplitude: np.ndarray, settled: int) -> FreeAirLevels:
    """Medians of REEP's σ̂² and the lock-in amplitude over a free-air segment, after ``settled`` samples.

    Parameters
    ----------
    sigma2, amplitude : numpy.ndarray
        σ̂²(n) (deflection units²) and amplitude (deflection units) over the segment.
    settled : int
        Leading samples to leave out (the start-up of both estimators).
    """
    s2 = sigma2[settled:]
    s2 = s2[np.isfinite(s2)]
    amp = amplitude[settled:]
    amp = amp[np.isfinite(amp)]
    return FreeAirLevels(
        float(np.median(amp)) if amp.size else None,
        float(np.median(s2)) if s2.size else None,
        "free-air segment",
    )


@njit(**JIT_OPTIONS)
def _ew_variance_step(v, lam, s0, s1, s2):
    """One sample of the EW variance: (s0, s1, s2, variance); NaN ``v`` skipped, NaN variance before any value."""
    if not math.isnan(v):
        s0 = lam * s0 + 1.0
        s1 = lam * s1 + v
        s2 = lam * s2 + v * v
    if s0 > 0.0:
        mean = s1 / s0
        return s0, s1, s2, max(s2 / s0 - mean * mean, 0.0)
    return s0, s1, s2, np.nan


@njit(**JIT_OPTIONS)
def _ew_variance_kernel(x, lam, state, out):
    """Exponentially weighted variance of ``x`` (NaN samples skipped), state = [Σλᵏ, Σλᵏx, Σλᵏx²]."""
    s0, s1, s2 = state[0], state[1], state[2]
    for i in range(x.shape[0]):
        s0, s1, s2, out[i] = _ew_variance_step(x[i], lam, s0, s1, s2)
    state[0], state[1], state[2] = s0, s1, s2


class OffsetDrift:
    """Variance of the static offset over REEP's window, streamed (the state carries across chunks).

    Parameters
    ----------
    lam : float
        REEP's forgetting factor λ per input sample.
    keep_every : int
        Input samples per output sample: the recursion runs on the output
        series with λ^keep_every.
    """

    def __init__(self, lam: float, keep_every: int) -> None:
        self._lam = float(lam) ** int(keep_every)
        self._state = np.zeros(3)

    def __call__(self, offset: np.ndarray) -> np.ndarray:
        """V(n) = E_w[p̄²] − E_w[p̄]² at every output sample, deflection units²."""
        out = np.empty(offset.shape[0])
        _ew_variance_kernel(np.ascontiguousarray(offset, dtype=np.float64), self._lam, self._state, out)
        return out


def validity_flags(
    underdamped: np.ndarray, amplitude: np.ndarray, sigma2: np.ndarray, levels: FreeAirLevels, limits: ValidityLimits,
    offset_variance: np.ndarray | None = None, settled_from: int = 0,
) -> np.ndarray:
    """The flag bits of every row (uint8, 0 = f0′ and Q′ valid), one array operation per reason.

    Parameters
    ----------
    underdamped : numpy.ndarray of bool
        Whether (b1, b0) is in the under-damped region (the ``valid`` of
        :func:`afmtool.models.discretisation.resonance_from_denominator`).
    amplitude : numpy.ndarray
        Lock-in amplitude at the drive, deflection units.
    sigma2 : numpy.ndarray
        REEP's σ̂², deflection units² (NaN in the start-up: not converged).
    levels : FreeAirLevels
    limits : ValidityLimits
    offset_variance : numpy.ndarray, optional
        V(n) of :class:`OffsetDrift`, deflection units² (static-offset
        regressor only; None skips that check).
    settled_from : int, optional
        Rows before this one are in the warm-up (not converged).
    """
    flags = np.where(underdamped, 0, FLAG_NOT_UNDERDAMPED).astype(np.uint8)
    if levels.amplitude and limits.min_amplitude_fraction > 0:
        flags |= np.where(amplitude < limits.min_amplitude_fraction * levels.amplitude, FLAG_LOW_AMPLITUDE, 0).astype(
            np.uint8
        )
    warming = np.isnan(sigma2) | (np.arange(len(flags)) < settled_from)
    flags |= np.where(warming, FLAG_NOT_CONVERGED, 0).astype(np.uint8)
    if offset_variance is not None and limits.max_offset_drift > 0:
        drifting = offset_variance > limits.max_offset_drift * 0.5 * np.square(amplitude)
        flags |= np.where(drifting, FLAG_OFFSET_DRIFT, 0).astype(np.uint8)
    return flags


class ReepRows(NamedTuple):
    """REEP's kept rows turned into physics, with their standard deviations and flags (:func:`reep_rows`)."""

    f0_hz: np.ndarray
    q: np.ndarray
    offset: np.ndarray | None
    flags: np.ndarray
    f0_std_hz: np.ndarray | None = None
    q_std: np.ndarray | None = None


@njit(**JIT_OPTIONS)
def oscillation_scalar(b1, b0, var_b1, cov_b1b0, var_b0, period):
    """Output-only f0′: the poles' frequency arccos(u)/(2πT), u = −b1/(2√b0), and its std; NaN without complex poles.

    With ∂θ/∂b1 = 1/(2√b0·√(1 − u²)) and ∂θ/∂b0 = −b1/(4·b0^{3/2}·√(1 − u²))
    (θ = arccos u), Var f = ∇θᵀ C ∇θ/(2πT)²; the std is NaN when the
    covariance is not finite.
    """
    if not (b0 > 0.0 and b1 * b1 < 4.0 * b0):
        return np.nan, np.nan
    root_b0 = math.sqrt(b0)
    ratio = min(max(-b1 / (2.0 * root_b0), -1.0), 1.0)
    sine = math.sqrt(max(1.0 - ratio * ratio, 1e-300))
    scale = 1.0 / (2.0 * math.pi * period)
    d1 = scale / (2.0 * root_b0 * sine)
    d0 = -scale * b1 / (4.0 * b0 * root_b0 * sine)
    variance = d1 * d1 * var_b1 + 2.0 * d1 * d0 * cov_b1b0 + d0 * d0 * var_b0
    return math.acos(ratio) * scale, (math.sqrt(variance) if variance >= 0.0 else np.nan)


@njit(**JIT_OPTIONS)
def _rows_kernel(
    b1, b0, c, sigma2, amplitude, covariance, noise_variance, period, min_amplitude, settled_from, max_drift,
    drift_lam, drift_state, output_only, f0_out, q_out, offset_out, flags_out, f0_std_out, q_std_out,
):
    """Eq. 3.48 with its standard deviations, the offset p̄ = c/(1 + b1 + b0), its EW variance and the flags."""
    has_offset = c.shape[0] > 0
    has_covariance = covariance.shape[0] > 0
    s0, s1, s2 = drift_state[0], drift_state[1], drift_state[2]
    for i in range(b1.shape[0]):
        # the covariance is σ̂²(n)·(…): with the measurement noise known, σ̂²(n) gives way to it
        scale = noise_variance / sigma2[i] if noise_variance > 0.0 else 1.0
        var1 = scale * covariance[i, 0] if has_covariance else np.nan
        cov10 = scale * covariance[i, 1] if has_covariance else np.nan
        var0 = scale * covariance[i, 2] if has_covariance else np.nan
        if output_only:  # the loop's damping, not the cantilever's: Q' not identifiable (module docstring)
            f0, f0_std = oscillation_scalar(b1[i], b0[i], var1, cov10, var0, period)
            q, q_std = np.nan, np.nan
        else:
            f0, q = resonance_scalar(b1[i], b0[i], period)
            f0_std, q_std = resonance_std_scalar(b1[i], b0[i], var1, cov10, var0, period)
        if has_covariance:
            f0_std_out[i], q_std_out[i] = f0_std, q_std
        amp = amplitude[i]
        flag = 0
        if math.isnan(f0):
            flag |= FLAG_NOT_UNDERDAMPED
        if amp < min_amplitude:
            flag |= FLAG_LOW_AMPLITUDE
        if i < settled_from or math.isnan(sigma2[i]):
            flag |= FLAG_NOT_CONVERGED
        if has_offset:
            offset = c[i] / (1.0 + b1[i] + b0[i])
            offset_out[i] = offset
            s0, s1, s2, variance = _ew_variance_step(offset, drift_lam, s0, s1, s2)
            if variance > max_drift * 0.5 * (amp * amp):  # NaN (no offset yet) never flags
                flag |= FLAG_OFFSET_DRIFT
        f0_out[i] = f0
        q_out[i] = q
        flags_out[i] = flag
    drift_state[0], drift_state[1], drift_state[2] = s0, s1, s2


def reep_rows(
    b1: np.ndarray, b0: np.ndarray, c: np.ndarray | None, sigma2: np.ndarray, amplitude: np.ndarray,
    sample_rate_hz: float, levels: FreeAirLevels, limits: ValidityLimits, drift: OffsetDrift | None = None,
    covariance: np.ndarray | None = None, settled_from: int = 0, noise_variance: float | None = None,
    output_only: bool = False,
) -> ReepRows:
    """f0′, Q′ (eq. 3.48), the static offset and the flag bits of REEP's kept rows, in one pass.

    The same numbers as :func:`afmtool.models.discretisation.resonance_from_denominator`,
    ``c / (1 + b1 + b0)``, :class:`OffsetDrift` and :func:`validity_flags`
    one after the other (a test checks them bit for bit), without their
    temporaries: REEP keeps one row per drive period, and those steps cost
    more than the estimator.

    Parameters
    ----------
    b1, b0, sigma2 : numpy.ndarray
        REEP's θ = [b1, b0] and σ̂² (deflection units²) at the kept samples.
    c : numpy.ndarray or None
        The static-offset coefficient (None: no offset regressor; then
        ``drift`` is not used and ``offset`` is None).
    amplitude : numpy.ndarray
        Lock-in amplitude at the drive, deflection units.
    sample_rate_hz : float
        fs = 1/T of the capture, Hz.
    levels, limits :
        As for :func:`validity_flags`.
    drift : OffsetDrift, optional
        Carries the EW variance of the offset across blocks (needed with ``c``).
    covariance : numpy.ndarray, shape (K, 3), optional
        (var b1, cov(b1, b0), var b0) of each row (:class:`~afmtool.estimators.rls.ReepBlock`):
        gives ``f0_std_hz`` and ``q_std`` (None without it).
    settled_from : int, optional
        Rows before this one are in the warm-up (:data:`FLAG_NOT_CONVERGED`).
    noise_variance : float, optional
        The measurement noise's variance (the free-air σ̂², deflection units²).
        The covariance of a row is σ̂²(n) times a matrix of the regressors
        (``_edge_covariance_2``); σ̂²(n) is the window's residual variance, which
        on the sample also holds the part of the motion the linear model lacks
        (harmonics of the tip–sample force: 1.5–2.3× the free-air level in
        steady tapping on the reference simulator).  That part is deterministic:
        it moves f0′ from averaging theory but does not scatter it, and with
        σ̂²(n) the stated std covered REEP's own noise-free estimate in 98–99.9 %
        of tapping rows; with the measurement noise, in 94–95 % (as in free air).
        None (no free-air segment): σ̂²(n), which errs on the wide side.
    output_only : bool, optional
        REEP ran without the dither: f0′ is the poles' oscillation frequency
        and Q′ NaN (not identifiable; module docstring).
    """
    n = len(b1)
    signals = [np.ascontiguousarray(x, dtype=np.float64) for x in (b1, b0, sigma2, amplitude)]
    if c is not None and drift is None:
        raise ValueError("reep_rows needs an OffsetDrift with the offset coefficient c")
    offset_c = np.ascontiguousarray(c, dtype=np.float64) if c is not None else np.empty(0)
    amplitude_on = bool(levels.amplitude) and limits.min_amplitude_fraction > 0
    min_amplitude = limits.min_amplitude_fraction * levels.amplitude if amplitude_on else -math.inf
    max_drift = limits.max_offset_drift if limits.max_offset_drift > 0 else math.inf
    drift_lam, drift_state = (drift._lam, drift._state) if drift is not None else (1.0, np.zeros(3))
    f0, q, offset = np.empty(n), np.empty(n), np.empty(n if c is not None else 0)
    cov = np.ascontiguousarray(covariance, dtype=np.float64) if covariance is not None else np.empty((0, 3))
    f0_std, q_std = np.empty(cov.shape[0]), np.empty(cov.shape[0])
    flags = np.empty(n, dtype=np.uint8)
    _rows_kernel(
        signals[0], signals[1], offset_c, signals[2], signals[3], cov, float(noise_variance or 0.0),
        1.0 / sample_rate_hz, min_amplitude, int(settled_from), max_drift, drift_lam, drift_state, bool(output_only), f0,
        q, offset, flags, f0_std, q_std,
    )
    stds = (f0_std, q_std) if covariance is not None else (None, None)
    return ReepRows(f0, q, offset if c is not None else None, flags, *stds)


@dataclass
class FlagCounter:
    """Counts of flagged samples, in all and by reason (a sample may have several)."""

    total: int = 0
    flagged: int = 0
    by_bit: dict = None

    def __post_init__(self) -> None:
        self.by_bit = {bit: 0 for bit in FLAG_REASONS}

    def add(self, flags: np.ndarray) -> None:
        # one pass: how many rows carry each combination of the bits
        per_value = np.bincount(np.asarray(flags, dtype=np.uint8), minlength=32)
        values = np.arange(per_value.size)
        self.total += int(flags.size)
        self.flagged += int(flags.size - per_value[0])
        for bit in FLAG_REASONS:
            self.by_bit[bit] += int(per_value[(values & bit) != 0].sum())

    def as_dict(self) -> dict:
        return {
            "samples": self.total,
            "flagged": self.flagged,
            "fraction": self.flagged / self.total if self.total else 0.0,
            **{FLAG_REASONS[bit][0]: count for bit, count in self.by_bit.items()},
        }

    def reason(self, bit: int, limits: ValidityLimits) -> str:
        """The words of one flag bit, with its threshold."""
        return FLAG_REASONS[bit][1].format(
            min_amplitude_fraction=limits.min_amplitude_fraction, max_offset_drift=limits.max_offset_drift
        )

    def mostly_flagged(self, limits: ValidityLimits) -> SampleShareWarning | None:
        """A warning that most rows are invalid, naming the commonest reason; None if at most half are."""
        if not self.total or self.flagged * 2 <= self.total:
            return None
        bit, count = max(self.by_bit.items(), key=lambda item: item[1])
        return SampleShareWarning(
            f"most of REEP's rows are invalid: {self.flagged / self.total:.0%} flagged after the warm-up, "
            f"mostly ({count / self.total:.0%} of the rows) because {self.reason(bit, limits)}",
            self.flagged, self.total,
        )

    def warnings(self, limits: ValidityLimits) -> list[str]:
        """One warning per reason that flagged something, saying why and how many; first, if most are flagged, why."""
        mostly = self.mostly_flagged(limits)
        out = [mostly] if mostly else []
        for bit, count in self.by_bit.items():
            if count:
                samples = "output sample" if self.total == 1 else "output samples"
                out.append(SampleShareWarning(
                    f"{count} of {self.total} {samples} after the warm-up ({100 * count / self.total:.2g} %) "
                    f"flagged: {self.reason(bit, limits)}; "
                    "their f0' and Q' are invalid and NaN in the summary, force curves and images "
                    "(reep.h5 keeps them, with 'flag')", count, self.total,
                ))
        return out
