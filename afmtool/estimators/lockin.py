"""Streaming lock-in demodulation: amplitude and phase at one frequency.

The baseline imaging signals of tapping-mode AFM.  The signal is mixed with
``exp(-j·2πf·t)`` and the product low-passed by a Butterworth filter run as
``scipy.signal.lfilter`` with carried state ``zi``, so chunked and single-call
results are identical.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["LockIn", "LockInState", "LockInBlock", "default_lowpass_hz"]


def default_lowpass_hz(frequency_hz: float, sideband_offset_hz: float | None = None) -> float:
    """The documented default low-pass corner, Hz.

    One tenth of the demodulation frequency, and at most half of the
    REEP side-line offset Δf so that the f0 ± Δf lines of the three-sine
    excitation (§3.3.2) do not leak into the amplitude.
    """
    corner = frequency_hz / 10.0
    if sideband_offset_hz:
        corner = min(corner, sideband_offset_hz / 2.0)
    return corner


@dataclass(frozen=True)
class LockInBlock:
    """Per-sample demodulated output: in-phase/quadrature as one complex value."""

    amplitude: np.ndarray
    phase_rad: np.ndarray


@dataclass(frozen=True)
class LockInState:
    zi: np.ndarray
    samples_seen: int


class LockIn:
    """Complex demodulator at ``frequency_hz`` with an order-``order`` Butterworth low-pass.

    Notes
    -----
    For ``x(t) = A cos(2πft + φ)`` the low-passed product
    ``X(t) = LP[x(t)·e^{-j2πft}] → (A/2)e^{jφ}``, so the amplitude is
    ``2|X|`` and the phase ``arg X`` (rad), relative to a cosine reference
    that starts at the capture's first sample.
    """

    def __init__(self, frequency_hz: float, sample_rate_hz: float, lowpass_hz: float, order: int = 4) -> None:
        from scipy.signal import butter

        if not 0 < frequency_hz < sample_rate_hz / 2:
            raise ValueError(f"{frequency_hz=} must be in (0, sample_rate_hz/2)")
        if not 0 < lowpass_hz < sample_rate_hz / 2:
            raise ValueError(f"{lowpass_hz=} must be in (0, sample_rate_hz/2)")
        self.frequency_hz = float(frequency_hz)
        self.sample_rate_hz = float(sample_rate_hz)
        self.lowpass_hz = float(lowpass_hz)
        self.order = int(order)
        self._b, self._a = butter(order, lowpass_hz, fs=sample_rate_hz)

    def initial_state(self) -> LockInState:
        return LockInState(np.zeros(max(len(self._a), len(self._b)) - 1, dtype=np.complex128), 0)

    def process(self, x: np.ndarray, state: LockInState) -> tuple[LockInBlock, LockInState]:
        """Demodulate one chunk; return its output and the state for the next chunk."""
        from scipy.signal import lfilter

        n = state.samples_seen + np.arange(len(x))
        # The cycle count is reduced modulo 1 before the multiplication by 2π
        # so the reference phase stays exact over captures of 1e9 samples.
        cycles = np.mod(n * (self.frequency_hz / self.sample_rate_hz), 1.0)
        mixed = x * np.exp(-2j * math.pi * cycles)
        baseband, zf = lfilter(self._b, self._a, mixed, zi=state.zi)
        block = LockInBlock(2.0 * np.abs(baseband), np.angle(baseband))
        return block, LockInState(zf, state.samples_seen + len(x))
