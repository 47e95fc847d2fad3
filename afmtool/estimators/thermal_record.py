"""The thermal-noise spectrum of a deflection time record, by Welch's method, streamed (``identify freeair --thermal``).

Without a drive the deflection is the first mode's thermal motion plus the
detector's white noise; its one-sided PSD, estimated here, is what
:func:`afmtool.estimators.thermal_noise.fit_thermal_spectrum` fits by maximum
likelihood.  :class:`WelchPsdStage` averages periodograms of Hann-windowed,
half-overlapped segments as the chunks stream past (memory O(nperseg +
chunk)), so a record larger than memory is fine.

*Averages.*  K segments overlapped by half are not K independent
periodograms.  For a Hann window Welch's overlap correlation is
c(½) = 0.1667 (Welch 1967, Table 1), and the variance of the average is
S²/K·(1 + 2c²(K − 1)/K) (eq. W.1), so the Gamma shape handed to the fit is
M = K/(1 + 2c²(K − 1)/K), about K/1.056.  Neighbouring bins of a Hann
periodogram are correlated (ρ₁ = (2/3)² = 0.44, ρ₂ = (1/6)² = 0.03); the fit
measures that from its residuals (``bin_correlation``) and widens its
errors by it.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from afmtool.errors import InputError
from afmtool.records.freeair import ThermalSpectrumRecord

__all__ = ["HANN_OVERLAP_CORRELATION", "ThermalSpectrum", "WelchPsdStage", "default_segment_length"]

#: Welch's c(½) for the Hann window: the correlation of two half-overlapped periodograms (eq. W.1).
HANN_OVERLAP_CORRELATION = 0.1667
#: The automatic segment length keeps at least this many half-overlapped segments.
MIN_SEGMENTS = 64


class ThermalSpectrum(NamedTuple):
    """A one-sided deflection spectrum: frequency (Hz), ASD (m/√Hz), the Gamma shape M and how it was made."""

    frequency_hz: np.ndarray
    asd_m_per_sqrt_hz: np.ndarray
    n_averages: float | None
    details: ThermalSpectrumRecord  #: how it was made, for the report


def default_segment_length(n_samples: int | None, sample_rate_hz: float, resolution_hz: float = 0.0) -> int:
    """nperseg: fs/resolution rounded to a power of two, else the longest power of two with ≥ 64 segments.

    Raises
    ------
    InputError
        If the record is too short for 64 segments of 64 samples, or its length is unknown
        and no resolution is given.
    """
    if resolution_hz > 0:
        return max(16, 1 << round(math.log2(sample_rate_hz / resolution_hz)))
    if not n_samples:
        raise InputError("the record's length is unknown (a stream): give --resolution (Hz) for the thermal spectrum")
    # K = 2n/nperseg − 1 half-overlapped segments ≥ MIN_SEGMENTS
    longest = 2 * n_samples / (MIN_SEGMENTS + 1)
    if longest < 64:
        raise InputError(f"the record has {n_samples} samples: too short for {MIN_SEGMENTS} half-overlapped "
                         "segments of 64 samples; record longer")
    return 1 << int(math.floor(math.log2(longest)))


class WelchPsdStage:
    """Welch PSD of one channel (Hann, half overlap, mean removed per segment), accumulated chunk by chunk.

    A :class:`afmtool.pipeline.Stage`: ``finish()`` returns a
    :class:`ThermalSpectrum` with the density in m²/Hz converted from the
    channel's ``nm``, and M of eq. W.1.

    Parameters
    ----------
    channel : str
        The deflection channel (nm, as :mod:`afmtool.io.units` delivers it).
    nperseg : int, optional
        Segment length; default from the reader's length (:func:`default_segment_length`).
    resolution_hz : float, optional
        Wanted resolution fs/nperseg, Hz, when ``nperseg`` is not given.
    """

    def __init__(self, channel: str = "deflection", nperseg: int | None = None, resolution_hz: float = 0.0) -> None:
        self._channel = channel
        self._nperseg = nperseg
        self._resolution = resolution_hz
        self._sum: np.ndarray | None = None
        self._tail = np.empty(0)
        self._segments = 0
        self._fs = math.nan
        self._window = np.empty(0)

    def prepare(self, head) -> None:
        self._fs = float(head.info.sample_rate_hz)
        if self._nperseg is None:
            self._nperseg = default_segment_length(head.info.n_samples, self._fs, self._resolution)
        n = self._nperseg
        self._window = 0.5 - 0.5 * np.cos(2.0 * np.pi * np.arange(n) / n)  # periodic Hann
        self._sum = np.zeros(n // 2 + 1)

    def step(self, chunk) -> None:
        values = np.concatenate((self._tail, np.asarray(chunk.data[self._channel], dtype=np.float64)))
        n, hop = self._nperseg, self._nperseg // 2
        count = 0 if values.size < n else (values.size - n) // hop + 1
        if count:
            segments = np.lib.stride_tricks.sliding_window_view(values, n)[::hop][:count]
            for start in range(0, count, 64):
                block = segments[start : start + 64]
                block = (block - block.mean(axis=1, keepdims=True)) * self._window
                self._sum += np.sum(np.abs(np.fft.rfft(block, axis=1)) ** 2, axis=0)
            self._segments += count
        self._tail = values[count * hop :].copy()

    def finish(self) -> ThermalSpectrum:
        k, n = self._segments, self._nperseg
        if k < 2:
            raise InputError(f"the record holds {k} segment(s) of {n} samples: too short for a thermal spectrum")
        # one-sided density: |X|²/(fs·Σw²), doubled except at DC and Nyquist (as scipy.signal.welch)
        psd_nm2 = self._sum / (k * self._fs * float(np.sum(self._window**2)))
        psd_nm2[1 : -1 if n % 2 == 0 else None] *= 2.0
        frequency = np.fft.rfftfreq(n, 1.0 / self._fs)
        c = HANN_OVERLAP_CORRELATION
        averages = k / (1.0 + 2.0 * c * c * (k - 1) / k)  # eq. W.1
        details = ThermalSpectrumRecord(method="Welch: Hann window, half overlap, mean removed per segment",
                                        nperseg=n, segments=k, resolution_hz=self._fs / n,
                                        n_averages_effective=averages)
        return ThermalSpectrum(frequency, np.sqrt(psd_nm2) * 1e-9, averages, details)
