"""Filter design, group delay and Welch spectra in numpy alone.

``scipy.signal`` does all of this, but importing it costs about 0.6–1 s
(it pulls in scipy.stats): more than a whole ``afmtool reep`` of a
1e7-sample capture.  The commands that stream large captures (reep,
probeloss, decode) take these instead; ``tests/test_filters.py`` checks
each against its scipy.signal counterpart.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

__all__ = ["butterworth_lowpass_sos", "sos_group_delay", "welch_psd"]


def butterworth_lowpass_sos(order: int, cutoff_hz: float, sample_rate_hz: float) -> np.ndarray:
    """Digital Butterworth low-pass as second-order sections, like ``scipy.signal.butter(..., output="sos")``.

    The analog prototype's poles s_k = −exp(jπm/(2N)), m = −N+1, −N+3, …, N−1,
    are scaled to the pre-warped corner ω_a = 2fs·tan(πf_c/fs) and mapped by
    the bilinear transform z = (2fs + s)/(2fs − s); all N zeros sit at z = −1.
    Conjugate pole pairs become sections [1, 2, 1]/[1, −2Re z_p, |z_p|²],
    ordered from the pole farthest from the unit circle to the nearest, and
    the overall gain (unity at DC) multiplies the first: for even N these
    are scipy's sections.  An odd N's real pole comes first, as
    [1, 1, 0]/[1, −z_p, 0]; scipy shares the zeros out differently there,
    for the same transfer function.

    Parameters
    ----------
    order : int
        Filter order N ≥ 1.
    cutoff_hz, sample_rate_hz : float
        The −3 dB corner f_c and the sampling rate fs (Hz), 0 < f_c < fs/2.

    Returns
    -------
    numpy.ndarray, shape (ceil(N/2), 6)
        Rows [b0, b1, b2, 1, a1, a2].
    """
    if not (isinstance(order, (int, np.integer)) and order >= 1):
        raise ValueError(f"{order=} must be an integer >= 1")
    if not 0 < cutoff_hz < sample_rate_hz / 2:
        raise ValueError(f"{cutoff_hz=} must be in (0, sample_rate_hz/2)")
    two_fs = 2.0 * sample_rate_hz
    warped = two_fs * math.tan(math.pi * cutoff_hz / sample_rate_hz)
    m = np.arange(-order + 1, order, 2)
    analog = warped * -np.exp(1j * np.pi * m / (2 * order))
    digital = (two_fs + analog) / (two_fs - analog)
    gain = warped**order * float(np.real(1.0 / np.prod(two_fs - analog)))
    # one pole of each conjugate pair (upper half plane), farthest from the unit circle first
    upper = sorted(digital[digital.imag > 0], key=lambda z: -abs(1.0 - abs(z)))
    sections = []
    if order % 2:
        real_pole = float(digital[np.argmin(np.abs(digital.imag))].real)
        sections.append([1.0, 1.0, 0.0, 1.0, -real_pole, 0.0])
    sections += [[1.0, 2.0, 1.0, 1.0, -2.0 * z.real, abs(z) ** 2] for z in upper]
    sos = np.array(sections)
    sos[0, :3] *= gain
    return sos


def sos_group_delay(sos: np.ndarray, frequency_hz: float, sample_rate_hz: float) -> float:
    """Group delay τ(ω) = −d arg H(e^{jω})/dω of a cascade of second-order sections, samples.

    For one polynomial c(z⁻¹) = Σ c_n z⁻ⁿ the phase derivative is
    Re[Σ n c_n e^{−jωn} / Σ c_n e^{−jωn}], so each section adds that of its
    numerator minus that of its denominator (``scipy.signal.group_delay``).
    """
    z = np.exp(-1j * 2.0 * math.pi * frequency_hz / sample_rate_hz * np.arange(3))
    n = np.arange(3)
    delay = 0.0
    for row in np.asarray(sos, dtype=np.float64):
        b, a = row[:3], row[3:]
        delay += float(np.real((n * b) @ z / (b @ z)) - np.real((n * a) @ z / (a @ z)))
    return delay


def welch_psd(x, sample_rate_hz: float, nperseg: int) -> tuple[np.ndarray, np.ndarray]:
    """One-sided power spectral density by Welch's method, units²/Hz.

    ``scipy.signal.welch`` with its defaults: a periodic Hann window,
    50 % overlap, each segment's mean removed, density scaling
    S = 2|X|²/(f_s Σw²) (the DC and Nyquist bins not doubled) and the mean
    over segments.  A record shorter than ``nperseg`` is one segment.

    Returns
    -------
    frequency_hz, psd : numpy.ndarray
    """
    values = np.asarray(x, dtype=np.float64)
    nperseg = max(1, min(int(nperseg), values.size))
    window = 0.5 - 0.5 * np.cos(2.0 * math.pi * np.arange(nperseg) / nperseg)
    step = nperseg - nperseg // 2
    segments = sliding_window_view(values, nperseg)[::step]
    segments = (segments - segments.mean(axis=1, keepdims=True)) * window
    power = np.abs(np.fft.rfft(segments, axis=1)) ** 2 / (sample_rate_hz * (window * window).sum())
    psd = power.mean(axis=0)
    if nperseg % 2:
        psd[1:] *= 2.0
    else:
        psd[1:-1] *= 2.0
    return np.fft.rfftfreq(nperseg, 1.0 / sample_rate_hz), psd
