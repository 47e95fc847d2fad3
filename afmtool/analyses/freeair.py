"""Free-air model identification (``afmtool identify freeair``), three routes.

* ``segment``: an off-sample stretch of a capture with dither and
  deflection, fitted as the ARX model of eq. 3.40 by bias-compensated least
  squares (plain least squares would bias the numerator; see NOTES.md).
* ``sweep``: a chirp/broadband or stepped-sine capture: H1 estimate, then a
  second-order fit with a pure delay.
* ``thermal``: a thermal-noise amplitude spectral density: a simple harmonic
  oscillator plus a white floor.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from afmtool.errors import InputError
from afmtool.io.capture import Chunk
from afmtool.models.free_air import FreeAirModel

__all__ = ["free_air_from_segment", "read_segment", "replay_held"]

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


def replay_held(held: list[Chunk], rest: Iterator[Chunk]) -> Iterator[Chunk]:
    """Yield ``held`` chunks then ``rest``, dropping each held chunk once it is handed on."""
    while held:
        yield held.pop(0)
    yield from rest


def read_segment(
    chunks: Iterator[Chunk], names: tuple[str, ...], start_sample: int, end_sample: int
) -> tuple[dict[str, np.ndarray], Iterator[Chunk]]:
    """Samples [start_sample, end_sample) of ``names``, read ahead from a single-pass stream.

    Returns the segment and an iterator over every chunk of the capture, the
    read-ahead ones first, so the stream (stdin included) is read once.
    """
    held: list[Chunk] = []
    for chunk in chunks:
        held.append(chunk)
        if chunk.start + len(chunk) >= end_sample:
            break
    available = held[-1].start + len(held[-1]) if held else 0
    if available < end_sample:
        raise InputError(f"segment ends at sample {end_sample} but the capture has only {available} samples")
    segment = {
        name: np.concatenate([c.data[name] for c in held])[start_sample:end_sample] for name in names
    }
    return segment, replay_held(held, chunks)
