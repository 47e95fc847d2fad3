"""Frequency-response records and the H1 estimate, batch and streaming.

The Fourier-domain identification is four modules: this one (the
:class:`FrequencyResponse` record, H1 and its accumulator, the Bode
table); :mod:`afmtool.estimators.stepped_sine` (lock-in per step, steps
found in the drive); :mod:`afmtool.estimators.transfer_function_fit`
(rational and second-order fits); and
:mod:`afmtool.estimators.sweep_spectral` (the spectral forms of the sweep
route).  They serve two features:

* the spectral forms of the **sweep route** to the free-air model whose
  numerator REEP keeps fixed (§3.3.3; the default, whole-record form is
  :mod:`afmtool.estimators.sweep_record`): the response G(jω) from the
  dither to the deflection is measured with a chirp/noise drive (H1
  estimator) or a stepped sine (lock-in per step), and the second-order model
  G(s) = gain·ω0²/(s² + (ω0/Q)s + ω0²)·e^{−sτ} (eq. 3.1 with a pure delay τ
  of the drive path) is fitted to it, as §6.7.1 does with a chirp on V_sub,
  giving a :class:`~afmtool.models.free_air.FreeAirModel` with
  ``source="sweep"``;
* the **Γ transfer functions** of the thermal sensor (§6.6): Γ_p,V (eq. 6.14),
  Γ_IR,V, the feed-through Γ_sp and the sensing map Γ_IR,ts of eq. 6.15, and
  H(jω) as the ratio of the cross spectrum of (Δt_s, ΔT1) to the auto
  spectrum of Δt_s (§6.6.2), which is exactly the H1 estimate below.  These
  low-pass maps (≈12 kHz bandwidth, ≈10 dB/decade roll-off) are fitted by
  :func:`~afmtool.estimators.transfer_function_fit.fit_transfer_function` with an arbitrary numerator/denominator order.

Conventions
-----------
* The response is output/input: H = Y/X with X, Y the Fourier transforms of
  the input ``x`` and the output ``y``; phase is the phase of y relative to x
  (negative = lagging).  Cross spectra are P_xy = E[X*·Y] as in
  :func:`scipy.signal.csd`.
* Frequencies are in Hz; the Laplace variable s = j2πf is in rad/s, and
  polynomial coefficients are in descending powers of s, as in
  :mod:`scipy.signal`.
* Every estimate is a :class:`FrequencyResponse`; its ``coherence`` is the
  magnitude-squared coherence for H1 and the analogous line-power fraction
  for a stepped sine (see :func:`~afmtool.estimators.stepped_sine.stepped_sine_response`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import scipy.signal
from numpy.lib.stride_tricks import sliding_window_view

from afmtool.errors import ConfigError, InputError
from afmtool.estimators.spectral_checks import check_positive, frozen, segmentation, signal_pair, window_array

__all__ = [
    "FrequencyResponse",
    "CrossSpectra",
    "H1Accumulator",
    "h1_estimate",
    "frf_table",
]

#: Bins whose input auto spectrum is below this fraction of its maximum carry
#: no input (rounding only: a zero input, or far outside the band of a
#: band-limited drive) and get a NaN response.
NO_INPUT_FRACTION = float(np.finfo(np.float64).eps)
#: Number of segments processed at once by the accumulator (bounds memory).
_SEGMENT_BLOCK = 256


# --------------------------------------------------------------------------- records


@dataclass(frozen=True, eq=False)
class FrequencyResponse:
    """A measured frequency response H(j2πf) = Y/X with its quality.

    Parameters
    ----------
    frequency_hz : numpy.ndarray
        Frequencies, Hz.
    response : numpy.ndarray of complex
        H at each frequency, output units per input unit.  NaN where the
        input carries no power.
    coherence : numpy.ndarray
        γ² in [0, 1]: magnitude-squared coherence (H1) or the fraction of the
        output power at the drive line (stepped sine).
    magnitude_std : numpy.ndarray
        One-standard-deviation random error of |H|, same units as H.
    phase_std_rad : numpy.ndarray
        One-standard-deviation random error of the phase of H, rad.
    method : str
        ``"h1"`` or ``"stepped"``.
    n_averages : float
        H1: the number of statistically independent averages n_d behind the
        error estimates (Welch-corrected for overlap).  Stepped sine: NaN.
    """

    frequency_hz: np.ndarray
    response: np.ndarray
    coherence: np.ndarray
    magnitude_std: np.ndarray
    phase_std_rad: np.ndarray
    method: str
    n_averages: float = float("nan")

    @property
    def magnitude(self) -> np.ndarray:
        """|H|, output units per input unit."""
        return np.abs(self.response)

    @property
    def phase_rad(self) -> np.ndarray:
        """Phase of H in (−π, π], rad."""
        return np.angle(self.response)


class CrossSpectra(NamedTuple):
    """Averaged one-sided spectral densities, as :func:`scipy.signal.csd` scales them.

    ``pxx``, ``pyy`` in (input unit)²/Hz and (output unit)²/Hz; ``pxy`` =
    E[X*·Y] in input·output units/Hz.  ``n_segments`` is the number of
    averaged segments K and ``n_averages`` the equivalent number of
    independent ones n_d (:func:`_welch_independent_averages`).
    """

    frequency_hz: np.ndarray
    pxx: np.ndarray
    pyy: np.ndarray
    pxy: np.ndarray
    n_segments: int
    n_averages: float


def _welch_independent_averages(window: np.ndarray, hop: int, n_segments: int) -> float:
    """Equivalent number of independent averages n_d of a Welch estimate.

    Welch (1967, IEEE Trans. Audio Electroacoust. 15, 70–73): for K
    segments shifted by D samples the variance of the averaged spectrum of a
    Gaussian, locally white process is that of
    n_d = K / (1 + 2 Σ_{j=1}^{K−1} (1 − j/K) ρ²(jD)) independent averages,
    with ρ(jD) = Σ_n w[n]·w[n+jD] / Σ_n w[n]².  For a Hann window at 50 %
    overlap ρ(D) ≈ 0.167 and n_d ≈ K/1.06.
    """
    k = n_segments
    energy = float(np.dot(window, window))
    total = 1.0
    j = 1
    while j < k and j * hop < window.size:
        rho = float(np.dot(window[: window.size - j * hop], window[j * hop :])) / energy
        total += 2.0 * (1.0 - j / k) * rho * rho
        j += 1
    return k / total


def _h1_from_spectra(spectra: CrossSpectra) -> FrequencyResponse:
    """H1 = P_xy/P_xx, γ² = |P_xy|²/(P_xx·P_yy) and their random errors (see :func:`h1_estimate`)."""
    f, pxx, pyy, pxy, _k, n_d = spectra
    has_input = pxx > NO_INPUT_FRACTION * np.max(pxx) if pxx.size else pxx > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        response = np.where(has_input, pxy / np.where(has_input, pxx, 1.0), np.nan + 0j)
        coherence = np.abs(pxy) ** 2 / (pxx * pyy)
        coherence = np.where(has_input & (pyy > 0), np.clip(coherence, 0.0, 1.0), np.nan)
        ratio = np.sqrt((1.0 - coherence) / (coherence * 2.0 * n_d))
    return FrequencyResponse(
        frequency_hz=frozen(f),
        response=frozen(response),
        coherence=frozen(coherence),
        magnitude_std=frozen(np.abs(response) * ratio),
        phase_std_rad=frozen(ratio),
        method="h1",
        n_averages=float(n_d),
    )


# --------------------------------------------------------------------------- H1, batch


def h1_estimate(
    x,
    y,
    sample_rate_hz: float,
    *,
    nperseg: int,
    noverlap: int | None = None,
    window="hann",
    detrend="constant",
) -> FrequencyResponse:
    """H1 frequency-response estimate H1(f) = P_xy(f)/P_xx(f) from Welch averages.

    Parameters
    ----------
    x, y : array_like
        Input (e.g. dither, V) and output (e.g. deflection, nm) records, 1-D,
        equal length ≥ ``nperseg``, finite.
    sample_rate_hz : float
        Sampling rate fs, Hz.
    nperseg : int
        Segment length; the resolution is fs/nperseg Hz.
    noverlap : int, optional
        Overlap of consecutive segments, samples; default ``nperseg // 2``.
    window : str, tuple or array_like, optional
        :func:`scipy.signal.get_window` spec or the window itself
        (default ``"hann"``, periodic).
    detrend : {"constant", "linear", False}, optional
        Per-segment detrending, as in :func:`scipy.signal.csd`.

    Returns
    -------
    FrequencyResponse
        ``method="h1"``, on the one-sided grid k·fs/nperseg.

    Notes
    -----
    With segments k = 1…K and their windowed transforms X_k, Y_k,

    .. math:: \\hat H_1 = \\frac{\\sum_k X_k^* Y_k}{\\sum_k |X_k|^2},\\qquad
              \\hat\\gamma^2 = \\frac{|\\sum_k X_k^* Y_k|^2}{\\sum_k |X_k|^2 \\sum_k |Y_k|^2}.

    H1 is unbiased by noise on the output (the usual case: deflection noise)
    and biased low by noise on the input.  This is also how §6.6.2 obtains
    H(jω) = C_{T1,ts}/C_{ts,ts}.  The spectra come from
    :func:`scipy.signal.csd` and :func:`scipy.signal.welch`;
    :class:`H1Accumulator` gives the same result chunk by chunk.

    Random errors: Bendat & Piersol's first-order formulas for a
    single-input/single-output frequency-response estimate (Bendat &
    Piersol, *Random Data*, 4th ed., 2010, ch. 9, gain- and phase-factor
    estimates),

    .. math:: \\varepsilon[|\\hat H|] = \\frac{\\sqrt{1-\\gamma^2}}{|\\gamma|\\sqrt{2 n_d}},\\qquad
              \\mathrm{s.d.}[\\hat\\phi] \\approx \\frac{\\sqrt{1-\\gamma^2}}{|\\gamma|\\sqrt{2 n_d}}\\ \\mathrm{rad},

    so ``magnitude_std`` = |Ĥ|·ε and ``phase_std_rad`` = s.d.[φ̂], with the
    estimated γ̂² for γ² and n_d the number of independent averages, K
    corrected for overlap after Welch (1967) (``n_averages``).  They hold
    for small errors (ε ≲ 0.2) and say nothing about bias (leakage,
    resolution).  With a swept drive (chirp) each bin is excited in only a
    few segments, γ̂² is then biased towards 1 and the errors are optimistic;
    a noise drive or a stepped sine gives calibrated ones.

    Raises
    ------
    ConfigError
        For a bad ``sample_rate_hz``, ``nperseg``, ``noverlap``, ``window``
        or ``detrend`` (named with its value).
    InputError
        If x, y are not equal-length finite 1-D arrays of ≥ ``nperseg`` samples.
    """
    fs = check_positive("sample_rate_hz", sample_rate_hz)
    nperseg, noverlap = segmentation(nperseg, noverlap, detrend)
    win = window_array(window, nperseg)
    xa, ya = signal_pair(x, y)
    if xa.size < nperseg:
        raise InputError(f"the records have {xa.size} samples, fewer than {nperseg=}")
    return _h1_from_spectra(_welch_cross_spectra(xa, ya, fs, win, nperseg, noverlap, detrend))


def _welch_cross_spectra(xa, ya, fs, win, nperseg, noverlap, detrend) -> CrossSpectra:
    """P_xx, P_yy, P_xy by Welch averaging (scipy.signal.csd/welch), with K and the overlap-corrected n_d."""
    kwargs = dict(fs=fs, window=win, nperseg=nperseg, noverlap=noverlap, detrend=detrend)
    f, pxy = scipy.signal.csd(xa, ya, **kwargs)
    _, pxx = scipy.signal.welch(xa, **kwargs)
    _, pyy = scipy.signal.welch(ya, **kwargs)
    hop = nperseg - noverlap
    n_segments = (xa.size - noverlap) // hop
    n_d = _welch_independent_averages(win, hop, n_segments)
    return CrossSpectra(f, pxx, pyy, pxy, n_segments, n_d)


# --------------------------------------------------------------------------- H1, streaming


class H1Accumulator:
    """Streaming H1: Welch cross/auto spectra accumulated over chunks.

    Feed the input and output records in chunks of any size with
    :meth:`add`; segments straddling chunk boundaries are completed from a
    carried tail of at most ``nperseg − 1`` samples, so the segments
    (start 0, hop, 2·hop, … with hop = nperseg − noverlap) are exactly those
    of :func:`h1_estimate` on the concatenated records, and :meth:`result`
    equals it to rounding.  Memory is O(nperseg + chunk), whatever the
    record length.

    Parameters
    ----------
    sample_rate_hz, nperseg, noverlap, window, detrend
        As in :func:`h1_estimate`.

    Notes
    -----
    Per segment: detrend, multiply by the window w, real FFT, and add
    X*·Y, |X|², |Y|² to running sums.  The densities are the sums divided by
    K·fs·Σw² and doubled except at DC and Nyquist, as
    :func:`scipy.signal.csd` scales them.  Samples after the last complete
    segment are ignored, as in :func:`scipy.signal.csd`.
    """

    def __init__(
        self,
        sample_rate_hz: float,
        nperseg: int,
        *,
        noverlap: int | None = None,
        window="hann",
        detrend="constant",
    ) -> None:
        self._fs = check_positive("sample_rate_hz", sample_rate_hz)
        self._nperseg, self._noverlap = segmentation(nperseg, noverlap, detrend)
        self._hop = self._nperseg - self._noverlap
        self._window = window_array(window, self._nperseg)
        self._detrend = detrend
        n_bins = self._nperseg // 2 + 1
        self._sxx = np.zeros(n_bins)
        self._syy = np.zeros(n_bins)
        self._sxy = np.zeros(n_bins, dtype=np.complex128)
        self._n_segments = 0
        # samples from the start of the next (incomplete) segment onwards
        self._tail_x = np.empty(0)
        self._tail_y = np.empty(0)

    @property
    def n_segments(self) -> int:
        """Segments accumulated so far."""
        return self._n_segments

    def add(self, x_chunk, y_chunk) -> None:
        """Accumulate the next chunk of input and output samples (any length ≥ 0).

        Raises
        ------
        InputError
            If the chunks are not equal-length finite 1-D arrays.
        """
        xc, yc = signal_pair(x_chunk, y_chunk)
        bx = np.concatenate((self._tail_x, xc))
        by = np.concatenate((self._tail_y, yc))
        n_new = 0 if bx.size < self._nperseg else (bx.size - self._nperseg) // self._hop + 1
        if n_new:
            seg_x = sliding_window_view(bx, self._nperseg)[:: self._hop][:n_new]
            seg_y = sliding_window_view(by, self._nperseg)[:: self._hop][:n_new]
            for start in range(0, n_new, _SEGMENT_BLOCK):
                self._accumulate(seg_x[start : start + _SEGMENT_BLOCK], seg_y[start : start + _SEGMENT_BLOCK])
        self._tail_x = bx[n_new * self._hop :].copy()
        self._tail_y = by[n_new * self._hop :].copy()

    def _accumulate(self, seg_x: np.ndarray, seg_y: np.ndarray) -> None:
        if self._detrend is not False:
            seg_x = scipy.signal.detrend(seg_x, type=self._detrend, axis=-1)
            seg_y = scipy.signal.detrend(seg_y, type=self._detrend, axis=-1)
        fx = np.fft.rfft(seg_x * self._window, axis=-1)
        fy = np.fft.rfft(seg_y * self._window, axis=-1)
        self._sxx += np.sum(fx.real**2 + fx.imag**2, axis=0)
        self._syy += np.sum(fy.real**2 + fy.imag**2, axis=0)
        self._sxy += np.sum(np.conj(fx) * fy, axis=0)
        self._n_segments += seg_x.shape[0]

    def spectra(self) -> CrossSpectra:
        """The averaged densities so far (scaled like :func:`scipy.signal.csd`).

        Raises
        ------
        InputError
            If no complete segment has been accumulated yet.
        """
        k = self._n_segments
        if k == 0:
            raise InputError(f"no complete segment yet: fewer than nperseg={self._nperseg} samples were added")
        scale = np.full(self._sxx.size, 1.0 / (k * self._fs * float(np.dot(self._window, self._window))))
        # one-sided densities: double all bins but DC (and Nyquist for even nperseg)
        scale[1 : None if self._nperseg % 2 else -1] *= 2.0
        freq = np.fft.rfftfreq(self._nperseg, 1.0 / self._fs)
        n_d = _welch_independent_averages(self._window, self._hop, k)
        return CrossSpectra(freq, self._sxx * scale, self._syy * scale, self._sxy * scale, k, n_d)

    def result(self) -> FrequencyResponse:
        """The H1 estimate from everything added so far (see :func:`h1_estimate`)."""
        return _h1_from_spectra(self.spectra())


# --------------------------------------------------------------------------- tables


def frf_table(fr: FrequencyResponse) -> dict[str, np.ndarray]:
    """Bode-table columns of a frequency response, for the CSV/HDF5 writers.

    Parameters
    ----------
    fr : FrequencyResponse

    Returns
    -------
    dict of str to numpy.ndarray
        ``frequency_hz`` (Hz), ``magnitude`` (|H|), ``magnitude_db``
        (20·log10|H|, dB), ``phase_deg`` (wrapped to (−180°, 180°]),
        ``coherence``, ``magnitude_std`` (units of H) and ``phase_std_deg``
        (deg), each a float64 array of the same length.
    """
    if not isinstance(fr, FrequencyResponse):
        raise ConfigError(f"fr must be a FrequencyResponse, got {type(fr).__name__}")
    magnitude = np.abs(fr.response)
    with np.errstate(divide="ignore", invalid="ignore"):
        magnitude_db = 20.0 * np.log10(magnitude)
    return {
        "frequency_hz": np.array(fr.frequency_hz, dtype=np.float64),
        "magnitude": magnitude,
        "magnitude_db": magnitude_db,
        "phase_deg": np.degrees(np.angle(fr.response)),
        "coherence": np.array(fr.coherence, dtype=np.float64),
        "magnitude_std": np.array(fr.magnitude_std, dtype=np.float64),
        "phase_std_deg": np.degrees(fr.phase_std_rad),
    }
