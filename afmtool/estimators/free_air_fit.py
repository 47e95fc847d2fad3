"""The free-air model from an off-sample segment: the ARX fit of eq. 3.40 and its f0, Q, gain.

Bias-compensated least squares (plain least squares would bias the
numerator; see docs/conventions.md), by :func:`afmtool.estimators.rls.identify_arx`.
The ``identify freeair`` command (``analyses/freeair_outputs.py``) and the
free-air route of reep, probeloss and kalman-bank call it.
"""

from __future__ import annotations

import numpy as np

from afmtool.errors import InputError
from afmtool.models.free_air import FreeAirModel

__all__ = ["MIN_SEGMENT_SAMPLES", "free_air_from_segment"]

#: Fewer samples than this cannot pin five ARX coefficients with any precision.
MIN_SEGMENT_SAMPLES = 500


def _model_from_theta(theta: np.ndarray, sample_rate_hz: float) -> np.ndarray:
    from afmtool.models.discretisation import resonance_from_denominator

    b1, b0, a2, a1, a0 = theta
    f0, q, _ = resonance_from_denominator(b1, b0, sample_rate_hz)
    gain = (a2 + a1 + a0) / (1.0 + b1 + b0)
    return np.array([f0, q, gain], dtype=np.float64)


def free_air_from_segment(deflection: np.ndarray, dither: np.ndarray, sample_rate_hz: float) -> FreeAirModel:
    """Identify the free-air model from an off-sample segment (eq. 3.40).

    The five ARX coefficients come from :func:`afmtool.estimators.rls.identify_arx`
    (bias compensated, Λ = diag(1, 1, 0, 0, 0)); f0 and Q follow by eq. 3.48
    and the DC gain is (a2 + a1 + a0)/(1 + b1 + b0).  Uncertainties are the
    coefficient covariance propagated through a numerical Jacobian.
    """
    from afmtool.estimators.rls import identify_arx

    if len(deflection) < MIN_SEGMENT_SAMPLES:
        raise InputError(f"free-air segment has {len(deflection)} samples; need at least {MIN_SEGMENT_SAMPLES}")
    fit = identify_arx(deflection, dither)
    theta = fit.theta
    nominal = _model_from_theta(theta, sample_rate_hz)
    if not np.all(np.isfinite(nominal)):
        raise InputError("free-air segment does not show an under-damped resonance (eq. 3.48 invalid)")
    jacobian = np.empty((3, 5))
    for k in range(5):
        step = 1e-7 * max(abs(theta[k]), 1e-6)
        up, down = theta.copy(), theta.copy()
        up[k] += step
        down[k] -= step
        jacobian[:, k] = (_model_from_theta(up, sample_rate_hz) - _model_from_theta(down, sample_rate_hz)) / (2 * step)
    std = np.sqrt(np.maximum(np.diag(jacobian @ fit.covariance @ jacobian.T), 0.0))
    return FreeAirModel(
        f0_hz=float(nominal[0]),
        q=float(nominal[1]),
        gain=float(nominal[2]),
        f0_std_hz=float(std[0]),
        q_std=float(std[1]),
        gain_std=float(std[2]),
        source="segment",
        sample_rate_hz=float(sample_rate_hz),
        numerator=fit.numerator,
        denominator=fit.denominator,
    )
