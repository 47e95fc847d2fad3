"""``afmtool theory``: averaging theory (ch. 4) and its comparison with REEP (§3.4.3).

Averaging theory gives the equivalent ωe and Qe of a cantilever tapping on a
piecewise-linear force (eqs. 4.6-4.8, closed forms in
:mod:`afmtool.models.averaging`).  REEP estimates the same two numbers from
the signals alone, so along a simulated force curve, where the separation is
known, the two can be compared sample by sample.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from afmtool.models.cantilever import Cantilever
from afmtool.models.forces import PiecewiseLinearForce

__all__ = ["TheoryComparison", "compare_with_theory", "jump_neighbourhood"]


@dataclass(frozen=True)
class TheoryComparison:
    """REEP against averaging theory where the comparison is well-conditioned.

    ``mask`` selects the compared samples; the ``*_theory`` series are the
    closed-form values smoothed by REEP's own exponential window.
    """

    mask: np.ndarray
    f0_theory_hz: np.ndarray
    q_theory: np.ndarray
    f0_error_max_hz: float
    q_error_max: float
    f0_theory_change_hz: float
    q_theory_change: float
    excluded_near_jumps: int

    @property
    def f0_error_fraction(self) -> float:
        """Worst |f0′ − f0_e| as a fraction of the theory's total change along the curve."""
        return self.f0_error_max_hz / self.f0_theory_change_hz

    @property
    def q_error_fraction(self) -> float:
        return self.q_error_max / self.q_theory_change

    def summary(self) -> dict:
        return {
            "compared_samples": int(self.mask.sum()),
            "excluded_near_jumps": self.excluded_near_jumps,
            "f0_theory_change_hz": self.f0_theory_change_hz,
            "f0_error_max_hz": self.f0_error_max_hz,
            "f0_error_fraction_of_change": self.f0_error_fraction,
            "q_theory_change": self.q_theory_change,
            "q_error_max": self.q_error_max,
            "q_error_fraction_of_change": self.q_error_fraction,
        }


def jump_neighbourhood(amplitude: np.ndarray, sample_rate_hz: float, *, jump_nm: float = 1.0,
                       over_s: float = 2e-4, guard_s: float = 1e-3) -> np.ndarray:
    """Samples within ``guard_s`` of a branch jump (amplitude change > ``jump_nm`` in ``over_s``).

    At a jump between the attractive and repulsive branches the theory
    switches instantly while any estimator needs a window to follow, and
    averaging theory is ill-conditioned there (NOTES.md); these samples are
    compared qualitatively only.
    """
    step = max(1, round(over_s * sample_rate_hz))
    jump = np.zeros(len(amplitude), dtype=bool)
    if len(amplitude) > step:
        jump[step:] = np.abs(amplitude[step:] - amplitude[:-step]) > jump_nm
    guard = max(1, round(guard_s * sample_rate_hz))
    return np.convolve(jump.astype(float), np.ones(2 * guard + 1), mode="same") > 0


def compare_with_theory(
    t_s: np.ndarray,
    f0_hz: np.ndarray,
    q: np.ndarray,
    amplitude_nm: np.ndarray,
    separation_nm: np.ndarray,
    *,
    drive_frequency_hz: float,
    cantilever: Cantilever,
    force: PiecewiseLinearForce,
    forgetting_factor: float,
    free_amplitude_nm: float,
    amplitude_fraction: float = 0.6,
    skip_s: float = 5e-3,
) -> TheoryComparison:
    """Compare REEP's f0′, Q′ with averaging theory along a force curve (§3.4.3).

    The theory is evaluated at the true separation and the measured (lock-in)
    amplitude, then passed through REEP's exponential window
    ``(1 − λ)/(1 − λ z⁻¹)`` so both describe the same stretch of data.
    Compared: samples with amplitude above ``amplitude_fraction`` of the free
    amplitude, after ``skip_s``, away from branch jumps.
    """
    from scipy.signal import lfilter

    from afmtool.models.averaging import equivalent_parameters_closed_form

    omega = 2.0 * np.pi * drive_frequency_hz
    theory = equivalent_parameters_closed_form(amplitude_nm, separation_nm, omega, cantilever, force)
    lam = forgetting_factor
    window = ([1.0 - lam], [1.0, -lam])
    f0_theory = lfilter(*window, theory.f0_e_hz, zi=[lam * theory.f0_e_hz[0]])[0]
    q_theory = lfilter(*window, theory.q_e, zi=[lam * theory.q_e[0]])[0]
    dt = np.median(np.diff(t_s)) if len(t_s) > 1 else 1.0
    near_jump = jump_neighbourhood(amplitude_nm, 1.0 / dt)
    candidates = (amplitude_nm > amplitude_fraction * free_amplitude_nm) & (t_s > skip_s)
    candidates &= np.isfinite(f0_hz) & np.isfinite(q)
    mask = candidates & ~near_jump
    if not mask.any():
        raise ValueError("no samples to compare: amplitude never above the threshold")
    f0_change = float(np.ptp(f0_theory[mask]))
    q_change = float(np.ptp(q_theory[mask]))
    return TheoryComparison(
        mask,
        f0_theory,
        q_theory,
        float(np.max(np.abs(f0_hz[mask] - f0_theory[mask]))),
        float(np.max(np.abs(q[mask] - q_theory[mask]))),
        f0_change,
        q_change,
        int((candidates & near_jump).sum()),
    )
