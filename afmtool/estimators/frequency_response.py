"""Frequency-response estimation and rational transfer-function fitting.

This module holds the Fourier-domain identification shared by two features:

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
  :func:`fit_transfer_function` with an arbitrary numerator/denominator order.

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
  for a stepped sine (see :func:`stepped_sine_response`).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import scipy.optimize
import scipy.signal
from numpy.lib.stride_tricks import sliding_window_view

from afmtool.config.samples import MAX_SAMPLES
from afmtool.errors import ConfigError, InputError
from afmtool.models.free_air import FreeAirModel

__all__ = [
    "FrequencyResponse",
    "CrossSpectra",
    "H1Accumulator",
    "h1_estimate",
    "SineSegment",
    "detect_segments",
    "stepped_sine_response",
    "SteppedSineAccumulator",
    "TransferFunctionFit",
    "fit_transfer_function",
    "SecondOrderFit",
    "fit_second_order",
    "free_air_from_sweep",
    "free_air_from_response",
    "sweep_frequency_response",
    "default_nperseg",
    "spectral_sweep_fit",
    "frf_table",
]

#: Bins whose input auto spectrum is below this fraction of its maximum carry
#: no input (rounding only: a zero input, or far outside the band of a
#: band-limited drive) and get a NaN response.
_NO_INPUT_FRACTION = float(np.finfo(np.float64).eps)
#: Number of segments processed at once by the accumulator (bounds memory).
_SEGMENT_BLOCK = 256
#: The automatic fit band of :func:`free_air_from_sweep` keeps the
#: contiguous bins around the peak with |H| > |H|max / this factor (−20 dB,
#: about ±5 half-power bandwidths of a resonance).
_BAND_PEAK_FACTOR = 10.0
#: Bins with a lower coherence are not used by :func:`free_air_from_sweep`
#: (outside the band a chirp excites, H1 is noise over noise).
_BAND_MIN_COHERENCE = 0.5


# --------------------------------------------------------------------------- validation


def _is_real(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


def _check_positive(name: str, value) -> float:
    if not (_is_real(value) and math.isfinite(value) and value > 0):
        raise ConfigError(f"{name}={value!r} must be a finite number > 0")
    return float(value)


def _check_int(name: str, value, minimum: int) -> int:
    if not (isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_)) and value >= minimum):
        raise ConfigError(f"{name}={value!r} must be an integer >= {minimum}")
    return int(value)


def _signal(name: str, values) -> np.ndarray:
    """A 1-D finite float64 copy of ``values`` (the caller's array is not touched)."""
    try:
        arr = np.array(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a 1-D array of numbers") from None
    if arr.ndim != 1:
        raise InputError(f"{name} must be 1-D, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        bad = int(np.flatnonzero(~np.isfinite(arr))[0])
        raise InputError(f"{name} has a non-finite value at index {bad} ({arr[bad]!r})")
    return arr


def _signal_pair(x, y) -> tuple[np.ndarray, np.ndarray]:
    xa, ya = _signal("x", x), _signal("y", y)
    if xa.shape != ya.shape:
        raise InputError(f"x and y must have the same length, got {xa.size} and {ya.size}")
    return xa, ya


def _frozen(arr: np.ndarray) -> np.ndarray:
    arr = np.ascontiguousarray(arr)
    arr.setflags(write=False)
    return arr


def _window_array(window, nperseg: int) -> np.ndarray:
    if isinstance(window, str) or isinstance(window, tuple):
        try:
            return scipy.signal.get_window(window, nperseg)
        except ValueError as exc:
            raise ConfigError(f"window={window!r} is not a scipy.signal window ({exc})") from None
    win = np.asarray(window, dtype=np.float64)
    if win.shape != (nperseg,) or not np.all(np.isfinite(win)):
        raise ConfigError(f"window must be a window name or {nperseg=} finite values, got shape {win.shape}")
    return win


def _segmentation(nperseg, noverlap, detrend) -> tuple[int, int]:
    nperseg = _check_int("nperseg", nperseg, 2)
    noverlap = nperseg // 2 if noverlap is None else _check_int("noverlap", noverlap, 0)
    if noverlap >= nperseg:
        raise ConfigError(f"{noverlap=} must be < {nperseg=}")
    if not (detrend is False or (isinstance(detrend, str) and detrend in ("constant", "linear"))):
        raise ConfigError(f"detrend={detrend!r} must be 'constant', 'linear' or False")
    return nperseg, noverlap


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
    has_input = pxx > _NO_INPUT_FRACTION * np.max(pxx) if pxx.size else pxx > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        response = np.where(has_input, pxy / np.where(has_input, pxx, 1.0), np.nan + 0j)
        coherence = np.abs(pxy) ** 2 / (pxx * pyy)
        coherence = np.where(has_input & (pyy > 0), np.clip(coherence, 0.0, 1.0), np.nan)
        ratio = np.sqrt((1.0 - coherence) / (coherence * 2.0 * n_d))
    return FrequencyResponse(
        frequency_hz=_frozen(f),
        response=_frozen(response),
        coherence=_frozen(coherence),
        magnitude_std=_frozen(np.abs(response) * ratio),
        phase_std_rad=_frozen(ratio),
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
    fs = _check_positive("sample_rate_hz", sample_rate_hz)
    nperseg, noverlap = _segmentation(nperseg, noverlap, detrend)
    win = _window_array(window, nperseg)
    xa, ya = _signal_pair(x, y)
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
        self._fs = _check_positive("sample_rate_hz", sample_rate_hz)
        self._nperseg, self._noverlap = _segmentation(nperseg, noverlap, detrend)
        self._hop = self._nperseg - self._noverlap
        self._window = _window_array(window, self._nperseg)
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
        xc, yc = _signal_pair(x_chunk, y_chunk)
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


# --------------------------------------------------------------------------- stepped sine


class SineSegment(NamedTuple):
    """One step of a stepped-sine drive: [start_s, end_s) at ``frequency_hz``."""

    start_s: float
    end_s: float
    frequency_hz: float


def _as_segment(k: int, seg) -> SineSegment:
    if isinstance(seg, Mapping):
        try:
            values = (seg["start_s"], seg["end_s"], seg["frequency_hz"])
        except KeyError as exc:
            raise InputError(f"segments[{k}] lacks {exc.args[0]!r} (needs start_s, end_s, frequency_hz)") from None
    else:
        try:
            values = tuple(seg)
        except TypeError:
            raise InputError(f"segments[{k}]={seg!r} must be a mapping or (start_s, end_s, frequency_hz)") from None
        if len(values) != 3:
            raise InputError(f"segments[{k}]={seg!r} must have 3 values (start_s, end_s, frequency_hz)")
    start, end, freq = values
    for name, value in (("start_s", start), ("end_s", end), ("frequency_hz", freq)):
        if not (_is_real(value) and math.isfinite(value)):
            raise InputError(f"segments[{k}].{name}={value!r} must be a finite number")
    if not (0 <= start < end):
        raise InputError(f"segments[{k}] needs 0 <= start_s < end_s, got start_s={start!r}, end_s={end!r}")
    if freq <= 0:
        raise InputError(f"segments[{k}].frequency_hz={freq!r} must be > 0")
    return SineSegment(float(start), float(end), float(freq))


def stepped_sine_response(
    x,
    y,
    sample_rate_hz: float,
    segments: Sequence,
    *,
    settle_fraction: float = 0.5,
    min_periods: int = 10,
) -> FrequencyResponse:
    """Frequency response from a stepped sine by lock-in demodulation of each step.

    Parameters
    ----------
    x, y : array_like
        Input (drive) and output records, 1-D, equal length, finite.
    sample_rate_hz : float
        Sampling rate fs, Hz.
    segments : sequence
        Steps as mappings ``{"start_s", "end_s", "frequency_hz"}`` (capture
        metadata, :meth:`afmtool.sim.excitation.SteppedSine.segments`) or
        :class:`SineSegment`; times in s from the first sample, frequency in
        Hz.  See :func:`detect_segments` when the metadata lacks them.
    settle_fraction : float, optional
        Fraction of each step skipped at its start so that transients decay,
        in [0, 1).  A step of a mode with quality factor Q at f0 needs about
        2Q/(2πf0)·ln(1/ε) s to settle to a relative error ε (for Q = 200 at
        70 kHz and ε = 1e-3, 6 ms).
    min_periods : int, optional
        Fewest drive periods a step's steady-state window may hold.

    Returns
    -------
    FrequencyResponse
        ``method="stepped"``, one point per step, sorted by frequency (stable).

    Notes
    -----
    In each step, the steady-state window is the last N samples of the step
    holding an integer number P = ⌊(1 − settle_fraction)·duration·f⌋ of
    periods, N = round(P·fs/f).  Input and output are demodulated at the
    step frequency over that window (complex demodulation, :class:`_LockInSums`)
    and H = Ŷ/X̂.

    ``coherence`` is the fraction of the output power in the window that is
    at the drive line, γ² = (|Ŷ|²/2)/σ_y², σ_y² the mean-removed output
    power: 1 for a clean sinusoidal response, lower with noise, harmonics or
    unsettled transients.

    Treating the residual y − line as white noise of power σ_y²(1 − γ²), the
    lock-in error of Ŷ has variance 4σ_y²(1 − γ²)/N, so the relative random
    error of |Ŷ| and the phase error are both √((1 − γ²)/(N γ²)); the same
    for X̂ with its own γ_x², and ``magnitude_std`` = |H|·√(ε_x² + ε_y²),
    ``phase_std_rad`` = √(ε_x² + ε_y²).  Residual noise coloured near the
    drive frequency makes these optimistic.

    Raises
    ------
    ConfigError
        For a bad ``sample_rate_hz``, ``settle_fraction`` or ``min_periods``.
    InputError
        For bad records or segments, a segment outside the records, one
        with fewer than ``min_periods`` steady-state periods, or with no
        input at its frequency.
    """
    xa, ya = _signal_pair(x, y)
    accumulator = SteppedSineAccumulator(
        sample_rate_hz, segments, settle_fraction=settle_fraction, min_periods=min_periods
    )
    accumulator.add(xa, ya)
    return accumulator.result()


class _StepWindow(NamedTuple):
    """The steady-state window [first, stop) of one step, in samples from the record's start."""

    index: int
    frequency_hz: float
    end_s: float
    first: int
    stop: int


def _step_windows(steps: Sequence[SineSegment], fs: float, settle_fraction: float, min_periods: int) -> list:
    """Each step's steady-state window (see :func:`stepped_sine_response`, Notes), checked."""
    windows = []
    for k, (start, end, freq) in enumerate(steps):
        if freq >= fs / 2:
            raise InputError(f"segments[{k}].frequency_hz={freq!r} is not below the Nyquist frequency {fs / 2:g} Hz")
        if not (math.isfinite(start) and math.isfinite(end) and 0 <= start < end and end * fs <= MAX_SAMPLES):
            raise InputError(f"segments[{k}]: {start!r}..{end!r} s must be finite, 0 <= start < end, within {MAX_SAMPLES:.0e} samples")
        stop = int(math.floor(end * fs + 1e-9))
        steady_s = (1.0 - settle_fraction) * (end - start)
        periods = int(math.floor(steady_s * freq + 1e-9))
        n = int(round(periods * fs / freq))
        if periods < min_periods or n > stop:
            raise InputError(
                f"segments[{k}] ({freq:g} Hz) holds {periods} steady-state periods, fewer than {min_periods=}"
            )
        windows.append(_StepWindow(k, freq, end, stop - n, stop))
    return windows


class _LockInSums:
    """Lock-in sums of one channel over one step window, added chunk by chunk.

    The lock-in of a window of N samples is Ŷ = (2/N) Σ_n (y[n] − ȳ) e[n],
    e[n] = e^{−j2πf n/fs} with n the absolute sample index (so input and
    output share the phase reference): for y = A sin(2πf n/fs + φ) over an
    integer number of periods, Ŷ = A·e^{j(φ − π/2)}, and the line power is
    |Ŷ|²/2.  The mean-removed power is σ² = Σ(y − ȳ)²/N.  With v = y − K
    (K the window's first sample, against cancellation in σ²) and the sums
    S1 = Σv, S2 = Σv², P = Σv·e, E = Σe:  Ŷ = (2/N)(P − (S1/N)·E) and
    σ² = S2/N − (S1/N)².
    """

    __slots__ = ("shift", "s1", "s2", "p", "e", "n")

    def __init__(self) -> None:
        self.shift: float | None = None
        self.s1 = self.s2 = 0.0
        self.p = self.e = 0j
        self.n = 0

    def add(self, values: np.ndarray, phasor: np.ndarray) -> None:
        if self.shift is None:
            self.shift = float(values[0])
        shifted = values - self.shift
        self.s1 += float(np.sum(shifted))
        self.s2 += float(np.dot(shifted, shifted))
        # two real dots: numpy's float-by-complex dot takes a slow generic loop (50x slower here)
        self.p += complex(float(np.dot(shifted, phasor.real)), float(np.dot(shifted, phasor.imag)))
        self.e += complex(np.sum(phasor))
        self.n += values.size

    def lock_in(self) -> tuple[complex, float]:
        """(Ŷ, σ²) of the whole window."""
        mean = self.s1 / self.n
        amplitude = 2.0 * (self.p - mean * self.e) / self.n
        power = max(self.s2 / self.n - mean * mean, 0.0)
        return complex(amplitude), power


class SteppedSineAccumulator:
    """Streaming stepped-sine response: per-step lock-in sums accumulated over chunks.

    Feed the input and output records in chunks of any size with
    :meth:`add`; :meth:`result` gives :func:`stepped_sine_response` of the
    concatenated records (to rounding: the sums run in another order).
    Memory is O(number of steps), whatever the record length.

    Parameters
    ----------
    sample_rate_hz, segments, settle_fraction, min_periods
        As in :func:`stepped_sine_response`.

    Raises
    ------
    ConfigError
        For a bad ``sample_rate_hz``, ``settle_fraction`` or ``min_periods``.
    InputError
        For bad segments, a step at or above the Nyquist frequency or with
        fewer than ``min_periods`` steady-state periods; for bad chunks (in
        :meth:`add`); for a step ending after the records (in :meth:`result`).
    """

    def __init__(
        self, sample_rate_hz: float, segments: Sequence, *, settle_fraction: float = 0.5, min_periods: int = 10
    ) -> None:
        fs = _check_positive("sample_rate_hz", sample_rate_hz)
        if not (_is_real(settle_fraction) and 0 <= settle_fraction < 1):
            raise ConfigError(f"settle_fraction={settle_fraction!r} must be a number in [0, 1)")
        min_periods = _check_int("min_periods", min_periods, 1)
        if isinstance(segments, (str, bytes, Mapping)) or not isinstance(segments, Sequence) or not segments:
            raise InputError("segments must be a non-empty list of {start_s, end_s, frequency_hz}")
        steps = [_as_segment(k, seg) for k, seg in enumerate(segments)]
        self._fs = fs
        self._windows = _step_windows(steps, fs, settle_fraction, min_periods)
        self._first = np.array([w.first for w in self._windows], dtype=np.int64)
        self._stop = np.array([w.stop for w in self._windows], dtype=np.int64)
        self._sums = [(_LockInSums(), _LockInSums()) for _ in self._windows]
        self._n_samples = 0

    @property
    def n_samples(self) -> int:
        """Samples added so far."""
        return self._n_samples

    def add(self, x_chunk, y_chunk) -> None:
        """Accumulate the next chunk of input and output samples (any length ≥ 0)."""
        xc, yc = _signal_pair(x_chunk, y_chunk)
        lo, hi = self._n_samples, self._n_samples + xc.size
        for k in np.flatnonzero((self._first < hi) & (self._stop > lo)):
            window = self._windows[k]
            a, b = max(window.first, lo), min(window.stop, hi)
            # time is absolute (sample index) so input and output share the phase reference
            phasor = np.exp(-2j * np.pi * window.frequency_hz / self._fs * np.arange(a, b))
            sx, sy = self._sums[k]
            sx.add(xc[a - lo : b - lo], phasor)
            sy.add(yc[a - lo : b - lo], phasor)
        self._n_samples = hi

    def result(self) -> FrequencyResponse:
        """The response of every step (see :func:`stepped_sine_response`).

        Raises
        ------
        InputError
            If a step ends after the samples added so far, or its input has
            no component at its frequency.
        """
        duration = self._n_samples / self._fs
        rows = []
        for window, (sx, sy) in zip(self._windows, self._sums):
            k, freq = window.index, window.frequency_hz
            if window.end_s > duration * (1 + 1e-12) or window.stop > self._n_samples:
                raise InputError(f"segments[{k}] ends at {window.end_s!r} s, after the records end ({duration:g} s)")
            n = window.stop - window.first
            x_amp, x_power = sx.lock_in()
            y_amp, y_power = sy.lock_in()
            if abs(x_amp) == 0 or x_power == 0:
                raise InputError(f"segments[{k}]: the input has no component at {freq:g} Hz")
            gx = min(abs(x_amp) ** 2 / 2 / x_power, 1.0)
            gy = min(abs(y_amp) ** 2 / 2 / y_power, 1.0) if y_power > 0 else 0.0
            # relative lock-in errors of X̂ and Ŷ (stepped_sine_response, Notes); gx > 0 here
            rel = math.sqrt((1 - gx) / (n * gx) + ((1 - gy) / (n * gy) if gy > 0 else math.inf))
            rows.append((freq, y_amp / x_amp, gy, rel))
        rows.sort(key=lambda r: r[0])
        freq = np.array([r[0] for r in rows])
        response = np.array([r[1] for r in rows], dtype=np.complex128)
        rel = np.array([r[3] for r in rows])
        return FrequencyResponse(
            frequency_hz=_frozen(freq),
            response=_frozen(response),
            coherence=_frozen(np.array([r[2] for r in rows])),
            magnitude_std=_frozen(np.abs(response) * rel),
            phase_std_rad=_frozen(rel),
            method="stepped",
        )


#: A step's unwrapped phase may depart from a straight line by this much (rms, rad);
#: more means the frequency is not constant (e.g. a chirp).
_STEP_PHASE_RMS_RAD = 0.1
#: Blocks on each side of a candidate step boundary whose medians are compared.
_STEP_WINDOW_BLOCKS = 4


def detect_segments(
    x,
    sample_rate_hz: float,
    *,
    min_segment_s: float = 1e-3,
    tolerance_hz: float | None = None,
) -> tuple[SineSegment, ...]:
    """Find the steps of a stepped-sine drive from its instantaneous frequency.

    Parameters
    ----------
    x : array_like
        The drive (input) record, 1-D, finite.
    sample_rate_hz : float
        Sampling rate fs, Hz.
    min_segment_s : float, optional
        Shortest step to find, s.  The record is examined in blocks of
        ``min_segment_s/8``; steps shorter than 4 blocks
        (``min_segment_s/2``) are not reported.
    tolerance_hz : float, optional
        Smallest frequency step to detect, Hz.  Default: 10 robust standard
        deviations of the step statistic (Notes), and at least 1e-6·fs.

    Returns
    -------
    tuple of SineSegment
        In time order.  Adjacent steps share their boundary, placed by a
        change-point fit of the two steps' phase lines
        (:func:`_step_boundaries`); the first step starts at 0 and the last ends at the record's
        end when the drive runs up to them.  The frequency of a step is the
        slope of a straight-line fit to its unwrapped phase (away from its
        edges), Hz.  Empty if there is no stepped sine (e.g. a chirp).

    Notes
    -----
    The instantaneous frequency is f_i[n] = (φ[n+1] − φ[n])·fs/2π with φ the
    unwrapped phase of the analytic signal (:func:`scipy.signal.hilbert`) of
    the mean-removed drive (mirrored at both ends against edge ringing),
    reduced to one value f_b per block, the least-squares slope of the phase
    over the block.  At
    each block edge k the step statistic is
    d_k = median(f_b[k…k+3]) − median(f_b[k−4…k−1]); a boundary is where
    |d_k| exceeds the tolerance and is the largest within ±3 blocks.  The
    medians ignore the ringing of f_i after a step (the Hilbert transform's
    Gibbs oscillation).  Blocks whose envelope is below 0.2× the median
    envelope (no drive) also end a step.  A candidate step is rejected if its
    unwrapped phase departs from a straight line by more than 0.1 rad rms
    (so the drive needs a signal-to-noise ratio of ≳ 25 dB), or
    the medians of its two halves differ by more than the tolerance (the
    frequency drifts: a chirp).  Touching steps whose fitted frequencies
    differ by less than a quarter of the tolerance are merged (a cut caused
    by ringing near the record's ends).  The whole record is held in memory.

    Raises
    ------
    ConfigError
        For a bad ``sample_rate_hz``, ``min_segment_s`` or ``tolerance_hz``.
    InputError
        For a bad record or one shorter than 8 × ``min_segment_s``/8 blocks.
    """
    fs = _check_positive("sample_rate_hz", sample_rate_hz)
    min_segment_s = _check_positive("min_segment_s", min_segment_s)
    if tolerance_hz is not None:
        tolerance_hz = _check_positive("tolerance_hz", tolerance_hz)
    xa = _signal("x", x)
    block = max(8, int(min_segment_s * fs / 8))
    if xa.size < 8 * block:
        raise InputError(f"the record has {xa.size} samples, shorter than {min_segment_s=} s at {fs:g} Hz")
    analytic, phase = _analytic_drive(xa)
    f_block, driven = _block_frequencies(phase, analytic, block, fs)
    stat = _step_statistic(f_block)
    if tolerance_hz is None:
        tolerance_hz = max(10.0 * 1.4826 * float(np.median(np.abs(stat[1:f_block.size]))), 1e-6 * fs)
    cuts = _step_cuts(stat, f_block.size, tolerance_hz)
    steps = _fitted_steps(cuts, driven, phase, f_block, block, fs, tolerance_hz)
    if not steps:
        return ()
    return _step_boundaries(steps, phase, np.abs(analytic), driven, block, fs)


def _analytic_drive(xa: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The analytic signal of the mean-removed drive and its unwrapped phase φ[n], rad."""
    # mirror the record at both ends so the FFT's wrap-around jump, whose
    # Hilbert ringing decays only as 1/distance, lies a record away
    pad = xa.size - 1
    analytic = scipy.signal.hilbert(np.pad(xa - xa.mean(), pad, mode="reflect"))[pad : pad + xa.size]
    return analytic, np.unwrap(np.angle(analytic))


def _block_frequencies(phase: np.ndarray, analytic: np.ndarray, block: int, fs: float) -> tuple[np.ndarray, np.ndarray]:
    """Per block: the frequency f_b (Hz) and whether the drive is on (envelope > 0.2× its median)."""
    inst = np.diff(phase) * fs / (2 * np.pi)
    n_blocks = inst.size // block
    # block frequency: least-squares slope of the phase over the block (noise
    # σ_φ·√12/(2π·T_b·√N_b) Hz), which also averages the ripple of f_i
    centred_t = np.arange(block) - (block - 1) / 2.0
    blocks = phase[: n_blocks * block].reshape(n_blocks, block)
    f_block = (blocks @ centred_t) / float(centred_t @ centred_t) * fs / (2 * np.pi)
    e_block = np.median(np.abs(analytic)[: n_blocks * block].reshape(n_blocks, block), axis=1)
    return f_block, e_block > 0.2 * np.median(e_block)


def _step_statistic(f_block: np.ndarray) -> np.ndarray:
    """d_k = median(f_b[k…k+3]) − median(f_b[k−4…k−1]) at each block edge k (0 at the record's ends), Hz."""
    n_blocks, m = f_block.size, _STEP_WINDOW_BLOCKS
    stat = np.zeros(n_blocks + 1)  # stat[k]: step between blocks k−1 and k
    for k in range(1, n_blocks):
        stat[k] = np.median(f_block[k : k + m]) - np.median(f_block[max(0, k - m) : k])
    return stat


def _step_cuts(stat: np.ndarray, n_blocks: int, tolerance_hz: float) -> list[int]:
    """Block edges where |d_k| exceeds the tolerance and is the largest within ±3 blocks, with 0 and n_blocks."""
    m = _STEP_WINDOW_BLOCKS
    size = np.abs(stat)
    cuts = {0, n_blocks}
    for k in range(1, n_blocks):
        near = size[max(1, k - m + 1) : min(n_blocks, k + m)]
        if size[k] > tolerance_hz and size[k] == near.max() and not any(c in cuts for c in range(k - m + 1, k)):
            cuts.add(k)
    return sorted(cuts)


def _fitted_steps(cuts, driven, phase, f_block, block, fs, tolerance_hz) -> list:
    """[first block, end block, (frequency Hz, phase at t = 0 rad)] of each accepted step, touching equal ones merged."""
    steps = []
    for a0, b0 in zip(cuts[:-1], cuts[1:]):
        for a, b in _driven_runs(driven, a0, b0):
            line = _step_line(phase, f_block, a, b, block, fs, tolerance_hz)
            if line is None:
                continue
            if steps and steps[-1][1] == a and abs(steps[-1][2][0] - line[0]) < tolerance_hz / 4:
                # a spurious cut (ringing near the record's ends): same frequency on both sides
                a = steps.pop()[0]
                line = _step_line(phase, f_block, a, b, block, fs, tolerance_hz)
            steps.append([a, b, line])
    return steps


def _driven_runs(driven: np.ndarray, a0: int, b0: int) -> list[tuple[int, int]]:
    """Maximal runs [a, b) of driven blocks inside [a0, b0)."""
    runs, start = [], None
    for k in range(a0, b0):
        if driven[k] and start is None:
            start = k
        elif not driven[k] and start is not None:
            runs.append((start, k))
            start = None
    if start is not None:
        runs.append((start, b0))
    return runs


def _step_line(phase, f_block, a: int, b: int, block: int, fs: float, tolerance_hz: float):
    """(frequency Hz, phase offset rad) of blocks [a, b) from a line fit φ ≈ φ0 + 2πf·t, or None if not a step."""
    if b - a < 4:
        return None
    half = (a + b) // 2
    if abs(np.median(f_block[a:half]) - np.median(f_block[half:b])) > tolerance_hz:
        return None
    core = slice((a + 1) * block, (b - 1) * block)
    t = np.arange(core.start, core.stop) / fs
    slope, offset = np.polyfit(t, phase[core], 1)
    if np.sqrt(np.mean((phase[core] - slope * t - offset) ** 2)) > _STEP_PHASE_RMS_RAD:
        return None
    return float(slope / (2 * np.pi)), float(offset)


def _step_boundaries(
    steps, phase: np.ndarray, envelope: np.ndarray, driven: np.ndarray, block: int, fs: float
) -> tuple[SineSegment, ...]:
    """Sample boundaries of the steps from their block edges.

    Where step A meets step B, the boundary c (first sample of B) minimises
    Σ_{n<c} (φ[n] − L_A[n])² + Σ_{n≥c} (φ[n] − L_B[n])² over ±2 blocks,
    L_A and L_B the steps' phase lines: a change-point fit that holds with or
    without phase continuity at the step.  Next to a gap without drive, the
    edge is where the envelope crosses half its median over the step.
    """
    n = phase.size
    edges = [[a * block, b * block] for a, b, _ in steps]
    for i, (a, b, _) in enumerate(steps):
        level = 0.5 * float(np.median(envelope[a * block : b * block]))
        if a > 0 and not driven[a - 1]:
            lo = max(edges[i][0] - block, 0)
            above = np.flatnonzero(envelope[lo : edges[i][0] + block] >= level)
            edges[i][0] = lo + int(above[0]) if above.size else edges[i][0]
        if b < driven.size and not driven[b]:
            lo = edges[i][1] - block
            above = np.flatnonzero(envelope[lo : min(edges[i][1] + block, n)] >= level)
            edges[i][1] = lo + int(above[-1]) + 1 if above.size else edges[i][1]
    if np.all(driven[: steps[0][0]]):
        edges[0][0] = 0
    if np.all(driven[steps[-1][1] :]):
        edges[-1][1] = n
    for i in range(len(steps) - 1):
        if steps[i][1] != steps[i + 1][0]:
            continue
        lo, hi = max(edges[i][1] - 2 * block, 0), min(edges[i][1] + 2 * block, n)
        t = np.arange(lo, hi) / fs
        (f_a, p_a), (f_b, p_b) = steps[i][2], steps[i + 1][2]
        err_a = (phase[lo:hi] - p_a - 2 * np.pi * f_a * t) ** 2
        err_b = (phase[lo:hi] - p_b - 2 * np.pi * f_b * t) ** 2
        # cost[c] for c = lo … hi: samples before c on line A, from c on line B
        cost = np.concatenate(([0.0], np.cumsum(err_a))) + np.concatenate((np.cumsum(err_b[::-1])[::-1], [0.0]))
        edges[i][1] = edges[i + 1][0] = lo + int(np.argmin(cost))
    return tuple(SineSegment(start / fs, stop / fs, step[2][0]) for (start, stop), step in zip(edges, steps))


# --------------------------------------------------------------------------- rational fit


@dataclass(frozen=True, eq=False)
class TransferFunctionFit:
    """G(s) = N(s)/D(s)·e^{−sτ} fitted to a frequency response.

    Parameters
    ----------
    numerator : numpy.ndarray
        Coefficients of N(s), descending powers of s (s in rad/s).
    denominator : numpy.ndarray
        Coefficients of D(s), descending powers, monic (``denominator[0] == 1``).
    delay_s : float
        Pure delay τ, s.
    rms_residual : float
        √(Σ w_k |H_k − G(j2πf_k)|² / Σ w_k), in units of H.
    iterations : int
        Sanathanan–Koerner iterations at the final delay.
    converged : bool
        Whether the iterations met the tolerance.
    """

    numerator: np.ndarray
    denominator: np.ndarray
    delay_s: float
    rms_residual: float
    iterations: int
    converged: bool

    def response(self, frequency_hz) -> np.ndarray:
        """G(j2πf) = N/D·e^{−j2πfτ} at ``frequency_hz`` (Hz)."""
        s = 2j * np.pi * np.asarray(frequency_hz, dtype=np.float64)
        return np.polyval(self.numerator, s) / np.polyval(self.denominator, s) * np.exp(-s * self.delay_s)

    @property
    def poles(self) -> np.ndarray:
        """Roots of D(s), rad/s."""
        return np.roots(self.denominator)

    @property
    def zeros(self) -> np.ndarray:
        """Roots of N(s), rad/s."""
        return np.roots(self.numerator)


class _SkResult(NamedTuple):
    num: np.ndarray  # ascending powers of the scaled variable
    den: np.ndarray  # ascending, den[-1] == 1
    cost: float  # Σ w |H − N/D|²
    iterations: int
    converged: bool


def _sanathanan_koerner(
    s: np.ndarray, h: np.ndarray, weights: np.ndarray, n_num: int, n_den: int, max_iter: int, tol: float
) -> _SkResult:
    """Rational fit N/D (D monic of degree n_den) in a scaled Laplace variable s.

    Levy (1959) linearises H·D − N ≈ 0 into a linear least-squares problem;
    Sanathanan & Koerner (1963) iterate it with the weights 1/|D_{i−1}(s_k)|²
    so that at convergence the weighted error Σ w|H·D − N|²/|D|² is the
    output error Σ w|H − N/D|².  Unknowns: b_0…b_m, a_0…a_{n−1}:

        Σ_i b_i s^i − H Σ_{i<n} a_i s^i = H s^n   (×√w/|D_{i−1}|, real and imaginary parts)

    Columns are scaled to unit norm before ``lstsq`` (conditioning).
    """
    vn = s[:, None] ** np.arange(n_num + 1)
    vd = s[:, None] ** np.arange(n_den)
    matrix = np.hstack((vn, -h[:, None] * vd))
    rhs = h * s**n_den
    d_prev = np.ones_like(s)
    sqrt_w = np.sqrt(weights)
    converged = False
    iterations = 0
    num = np.zeros(n_num + 1)
    den = np.zeros(n_den + 1)
    for _ in range(max_iter):
        iterations += 1  # counted in the body: the count is returned after the loop
        row = sqrt_w / np.abs(d_prev)
        a = matrix * row[:, None]
        b = rhs * row
        a_real = np.vstack((a.real, a.imag))
        b_real = np.concatenate((b.real, b.imag))
        norms = np.linalg.norm(a_real, axis=0)
        norms[norms == 0] = 1.0
        theta = np.linalg.lstsq(a_real / norms, b_real, rcond=None)[0] / norms
        num = theta[: n_num + 1]
        den = np.append(theta[n_num + 1 :], 1.0)
        d_new = np.polynomial.polynomial.polyval(s, den)
        change = float(np.max(np.abs(d_new - d_prev) / np.maximum(np.abs(d_new), np.finfo(float).tiny)))
        d_prev = d_new
        if change < tol:
            converged = True
            break
    with np.errstate(divide="ignore", invalid="ignore"):
        model = np.polynomial.polynomial.polyval(s, num) / d_prev
        cost = float(np.sum(weights * np.abs(h - model) ** 2))
    if not math.isfinite(cost):
        cost = math.inf
    return _SkResult(num, den, cost, iterations, converged)


def _frequency_data(frequency_hz, response, weights) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    f = _signal("frequency_hz", frequency_hz)
    try:
        h = np.array(response, dtype=np.complex128)
    except (TypeError, ValueError):
        raise InputError("response must be a 1-D array of complex numbers") from None
    if h.shape != f.shape:
        raise InputError(f"response has shape {h.shape}, frequency_hz has {f.shape}")
    if not np.all(np.isfinite(h)):
        bad = int(np.flatnonzero(~np.isfinite(h))[0])
        raise InputError(f"response has a non-finite value at index {bad} ({h[bad]!r}); drop those bins first")
    if np.any(f < 0):
        raise InputError(f"frequency_hz must be >= 0, got {float(f.min())!r}")
    if weights is None:
        w = np.ones_like(f)
    else:
        w = _signal("weights", weights)
        if w.shape != f.shape:
            raise InputError(f"weights has shape {w.shape}, frequency_hz has {f.shape}")
        if np.any(w < 0) or not np.any(w > 0):
            raise InputError("weights must be >= 0 with at least one > 0")
    return f, h, w


def _delay_mode(delay) -> float | None:
    """None to estimate the delay, else the fixed delay in s."""
    if isinstance(delay, (bool, np.bool_)):
        return None if delay else 0.0
    if _is_real(delay) and math.isfinite(delay):
        return float(delay)
    raise ConfigError(f"delay={delay!r} must be True, False or a delay in s")


def _delay_bounds(delay_bounds_s, f_max: float) -> tuple[float, float]:
    if delay_bounds_s is None:
        return 0.0, 2.0 / f_max
    try:
        lo, hi = (float(v) for v in delay_bounds_s)
    except (TypeError, ValueError):
        raise ConfigError(f"delay_bounds_s={delay_bounds_s!r} must be a pair (min_s, max_s)") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise ConfigError(f"delay_bounds_s={delay_bounds_s!r} must be finite with min_s < max_s")
    return lo, hi


#: Delay grid: spacing 1/(8·f_max) (π/4 of phase at the top frequency), at most this many points.
_DELAY_GRID_MAX = 2001
#: Local minima of the grid refined by Brent's method (best first).
_DELAY_REFINED_MINIMA = 8


def _search_delay(cost_at, lo: float, hi: float, f_max: float) -> float:
    """Global 1-D search of τ in [lo, hi]: a grid, then bounded Brent refinement of its local minima.

    Near a sharp resonance the cost is nearly periodic in τ (period
    1/(2 f0): a sign flip of the gain) with narrow minima, so the grid only
    brackets them; each of the best local minima is refined and the lowest
    refined cost wins.
    """
    step = 1.0 / (8.0 * f_max)
    n = min(_DELAY_GRID_MAX, int(math.ceil((hi - lo) / step)) + 1)
    grid = np.linspace(lo, hi, max(n, 2))
    spacing = grid[1] - grid[0]
    costs = np.array([cost_at(t) for t in grid])
    padded = np.concatenate(([np.inf], costs, [np.inf]))
    minima = np.flatnonzero((padded[1:-1] <= padded[:-2]) & (padded[1:-1] <= padded[2:]))
    minima = minima[np.argsort(costs[minima])][:_DELAY_REFINED_MINIMA]
    best_tau, best_cost = float(grid[minima[0]]), float(costs[minima[0]])
    for k in minima:
        a, b = max(lo, grid[k] - spacing), min(hi, grid[k] + spacing)
        # optimise in units of the spacing so the tolerance is relative to it
        res = scipy.optimize.minimize_scalar(
            lambda u, a=a: cost_at(a + u * spacing),
            bounds=(0.0, (b - a) / spacing),
            method="bounded",
            options={"xatol": 1e-7},
        )
        if res.fun < best_cost:
            best_tau, best_cost = a + float(res.x) * spacing, float(res.fun)
    return best_tau


def fit_transfer_function(
    frequency_hz,
    response,
    n_num: int,
    n_den: int,
    *,
    weights=None,
    delay: bool | float = False,
    delay_bounds_s: tuple[float, float] | None = None,
    max_iter: int = 30,
    tol: float = 1e-10,
) -> TransferFunctionFit:
    """Fit G(s) = N(s)/D(s)·e^{−sτ} to a frequency response.

    Parameters
    ----------
    frequency_hz : array_like
        Frequencies f_k ≥ 0, Hz.
    response : array_like of complex
        Measured H_k at f_k (finite; drop NaN bins first).
    n_num, n_den : int
        Degrees of N (≥ 0) and D (≥ 1), n_num ≤ n_den (proper).
    weights : array_like, optional
        w_k ≥ 0 of the complex error; 1/var(H_k) is the maximum-likelihood
        choice (e.g. 1/``magnitude_std``² of a :class:`FrequencyResponse`).
        Default: all 1.
    delay : bool or float, optional
        False: no delay (τ = 0).  True: estimate τ in ``delay_bounds_s``.
        A number: that fixed τ, s.
    delay_bounds_s : (float, float), optional
        Search interval of τ, s; default (0, 2/f_max), two periods of the
        highest fitted frequency.  A delay longer than a period is only
        identifiable from the phase slope across the band; widen the
        interval explicitly when that is intended.
    max_iter : int, optional
        Sanathanan–Koerner iterations per delay.
    tol : float, optional
        Convergence: max relative change of D(s_k) between iterations.

    Returns
    -------
    TransferFunctionFit
        Coefficients in descending powers of s (rad/s), D monic.

    Notes
    -----
    Method: for a given τ the delay-free response H_k·e^{+j2πf_kτ} is fitted
    by Sanathanan–Koerner iterations from a Levy start
    (:func:`_sanathanan_koerner`), which converge to the minimiser of the
    output error Σ_k w_k |H_k − N(s_k)/D(s_k)·e^{−s_kτ}|².  The frequency is
    scaled by ω_max = 2π·max f_k inside the fit for conditioning.  With
    ``delay=True`` τ minimises that cost by a grid search (spacing
    1/(8 f_max), at most 2001 points) whose best 8 local minima are refined
    by bounded Brent minimisation, re-running the rational fit at each
    trial τ (near a sharp resonance the cost has narrow minima spaced by
    half a period, a sign flip of the gain; the phase slope across the band
    decides between them).  SK is a
    linear method: fast, no start values, and exact on noise-free data of
    the right order; it does not enforce stable poles (check ``poles``).

    Raises
    ------
    ConfigError
        For bad orders, ``delay``, ``delay_bounds_s``, ``max_iter`` or ``tol``.
    InputError
        For bad data, or fewer real equations (2 per frequency) than unknowns.
    """
    n_num, n_den, fixed_delay, max_iter, tol = _checked_fit_settings(n_num, n_den, delay, max_iter, tol)
    data = _scaled_frequency_data(frequency_hz, response, weights, n_num + 1 + n_den + (fixed_delay is None))

    def fit_at(tau: float) -> _SkResult:
        return _sanathanan_koerner(data.s_scaled, data.h * np.exp(1j * data.omega * tau), data.w, n_num, n_den, max_iter, tol)

    if fixed_delay is None:
        lo, hi = _delay_bounds(delay_bounds_s, data.f_max)
        tau = _search_delay(lambda t: fit_at(t).cost, lo, hi, data.f_max)
    else:
        tau = fixed_delay
    return _descaled_fit(fit_at(tau), data.scale, n_num, n_den, tau, data.w)


def _checked_fit_settings(n_num, n_den, delay, max_iter, tol) -> tuple[int, int, float | None, int, float]:
    """The checked (n_num, n_den, fixed delay or None to estimate, max_iter, tol) of :func:`fit_transfer_function`."""
    n_num = _check_int("n_num", n_num, 0)
    n_den = _check_int("n_den", n_den, 1)
    if n_num > n_den:
        raise ConfigError(f"{n_num=} must be <= {n_den=} (a proper transfer function)")
    fixed_delay = _delay_mode(delay)
    max_iter = _check_int("max_iter", max_iter, 1)
    tol = _check_positive("tol", tol)
    return n_num, n_den, fixed_delay, max_iter, tol


class _ScaledFrequencyData(NamedTuple):
    f: np.ndarray  # Hz
    h: np.ndarray  # complex response
    w: np.ndarray  # weights
    f_max: float  # Hz
    omega: np.ndarray  # 2πf, rad/s
    scale: float  # ω_max = 2π·f_max, rad/s
    s_scaled: np.ndarray  # jω/ω_max


def _scaled_frequency_data(frequency_hz, response, weights, n_unknown: int) -> _ScaledFrequencyData:
    """The checked data of :func:`fit_transfer_function`, with s scaled by ω_max for conditioning."""
    f, h, w = _frequency_data(frequency_hz, response, weights)
    if 2 * int(np.count_nonzero(w)) < n_unknown:
        raise InputError(f"{f.size} frequencies (2 real equations each) cannot fit {n_unknown} unknowns")
    f_max = float(f.max())
    if f_max <= 0:
        raise InputError("frequency_hz needs at least one frequency > 0")
    omega = 2 * np.pi * f
    scale = 2 * np.pi * f_max
    return _ScaledFrequencyData(f, h, w, f_max, omega, scale, 1j * omega / scale)


def _descaled_fit(sk: _SkResult, scale: float, n_num: int, n_den: int, tau: float, w: np.ndarray) -> TransferFunctionFit:
    """The fit in descending powers of s (rad/s) from the one in s_scaled = s/ω_max."""
    # back to s = s_scaled·scale: coefficient of s^i is c_i/scale^i; multiply by scale^n_den (monic D)
    num = sk.num * scale ** (n_den - np.arange(n_num + 1))
    den = sk.den * scale ** (n_den - np.arange(n_den + 1))
    return TransferFunctionFit(
        numerator=_frozen(num[::-1].copy()),
        denominator=_frozen(den[::-1].copy()),
        delay_s=float(tau),
        rms_residual=math.sqrt(sk.cost / float(np.sum(w))),
        iterations=sk.iterations,
        converged=sk.converged,
    )


# --------------------------------------------------------------------------- second order


@dataclass(frozen=True)
class SecondOrderFit:
    """G(s) = gain·ω0²/(s² + (ω0/Q)s + ω0²)·e^{−sτ} fitted to a frequency response.

    Parameters
    ----------
    f0_hz, q, gain, delay_s : float
        f0 = ω0/2π (Hz), Q, the DC gain (units of H, signed) and τ (s).
    f0_std_hz, q_std, gain_std, delay_std_s : float
        One-standard-deviation errors from the Jacobian at the optimum,
        scaled by the residual variance; ``delay_std_s`` is 0 when τ was
        fixed.
    rms_residual : float
        √(Σ w|H − G|²/Σ w), units of H.
    """

    f0_hz: float
    q: float
    gain: float
    delay_s: float
    f0_std_hz: float
    q_std: float
    gain_std: float
    delay_std_s: float
    rms_residual: float

    def response(self, frequency_hz) -> np.ndarray:
        """G(j2πf) at ``frequency_hz`` (Hz)."""
        return _second_order(np.asarray(frequency_hz, dtype=np.float64), self.f0_hz, self.q, self.gain, self.delay_s)


def _second_order(f: np.ndarray, f0: float, q: float, gain: float, tau: float) -> np.ndarray:
    s = 2j * np.pi * f
    w0 = 2 * np.pi * f0
    return gain * w0 * w0 / (s * s + (w0 / q) * s + w0 * w0) * np.exp(-s * tau)


def _peak_start(f: np.ndarray, h: np.ndarray) -> tuple[float, float, float]:
    """(f0, Q, gain) from the |H| peak and its half-power width (fallback start)."""
    mag = np.abs(h)
    order = np.argsort(f)
    fs_, ms_ = f[order], mag[order]
    k = int(np.argmax(ms_))
    half = ms_[k] / math.sqrt(2)
    left = np.flatnonzero(ms_[:k] < half)
    right = np.flatnonzero(ms_[k:] < half)
    lo = fs_[left[-1]] if left.size else fs_[0]
    hi = fs_[k + right[0]] if right.size else fs_[-1]
    q = max(fs_[k] / max(hi - lo, 1e-12 * fs_[k]), 0.6)
    return float(fs_[k]), float(q), float(ms_[k] / q)


def fit_second_order(
    frequency_hz,
    response,
    *,
    delay: bool | float = True,
    weights=None,
    delay_bounds_s: tuple[float, float] | None = None,
) -> SecondOrderFit:
    """Fit the delayed second-order model of the cantilever to a frequency response.

    .. math:: G(s) = \\mathrm{gain}\\,\\frac{\\omega_0^2}{s^2 + (\\omega_0/Q)s + \\omega_0^2}\\,e^{-s\\tau}

    (eq. 3.1 with the gain from drive units to deflection units, and a pure
    delay τ of the drive and acquisition path).

    Parameters
    ----------
    frequency_hz : array_like
        Frequencies, Hz (a band around the resonance).
    response : array_like of complex
        Measured H at those frequencies, finite.
    delay : bool or float, optional
        True (default): estimate τ; False: τ = 0; a number: fixed τ (s).
    weights : array_like, optional
        Weights of the complex error (1/var(H) ideally); default all 1.
    delay_bounds_s : (float, float), optional
        Search interval of τ, s; see :func:`fit_transfer_function`.

    Returns
    -------
    SecondOrderFit

    Notes
    -----
    Start: :func:`fit_transfer_function` with orders (0, 2) and the same
    delay option, giving D = s² + a1·s + a0, N = b0, hence ω0 = √a0,
    Q = ω0/a1, gain = b0/a0 (or, if that is not a resonance, the |H| peak
    and its half-power width).  Then all parameters are refined together by
    :func:`scipy.optimize.least_squares` on the weighted complex error
    √w_k·(H_k − G(j2πf_k)) (real and imaginary parts), in normalised
    parameters (f0/f0', Q/Q', gain/gain', 2πf0'·τ).  Errors:
    cov = s²·(JᵀJ)⁻¹ with s² = Σ r²/(2K − p).

    Why the delay matters: near f0 the phase of G falls through −90°; a
    delay adds −2πfτ (−126° at 70 kHz for 5 µs).  A model without τ can
    only absorb that by moving f0 and distorting Q, so leaving the delay
    out biases f0.

    Raises
    ------
    ConfigError, InputError
        As :func:`fit_transfer_function`; InputError also if fewer than 3
        frequencies are given.
    """
    fixed_delay = _delay_mode(delay)
    f, h, w = _frequency_data(frequency_hz, response, weights)
    if f.size < 3:
        raise InputError(f"a second-order fit needs at least 3 frequencies, got {f.size}")
    f0, q, gain, tau = _second_order_start(f, h, w, delay, delay_bounds_s)
    w0s = 2 * np.pi * f0
    scales = np.array([f0, q, gain, 1.0 / w0s])
    sqrt_w = np.sqrt(w)
    estimate_delay = fixed_delay is None

    def unpack(p: np.ndarray) -> tuple[float, float, float, float]:
        tau_p = p[3] * scales[3] if estimate_delay else tau
        return p[0] * scales[0], p[1] * scales[1], p[2] * scales[2], tau_p

    def residual(p: np.ndarray) -> np.ndarray:
        err = sqrt_w * (h - _second_order(f, *unpack(p)))
        return np.concatenate((err.real, err.imag))

    p0, lower, upper = _normalised_start_and_bounds(tau, scales, estimate_delay, delay_bounds_s, float(f.max()))
    sol = scipy.optimize.least_squares(residual, p0, bounds=(lower, upper), xtol=1e-14, ftol=1e-14, gtol=1e-14)
    return _second_order_record(sol, unpack(sol.x), scales, estimate_delay, w)


def _second_order_start(f, h, w, delay, delay_bounds_s) -> tuple[float, float, float, float]:
    """Start (f0, Q, gain, τ) of :func:`fit_second_order` from the (0, 2) rational fit.

    D = s² + a1·s + a0, N = b0 give ω0 = √a0, Q = ω0/a1, gain = b0/a0; if
    that is not a resonance, the |H| peak and its half-power width.
    """
    rational = fit_transfer_function(f, h, 0, 2, weights=w, delay=delay, delay_bounds_s=delay_bounds_s)
    _, a1, a0 = rational.denominator
    if a0 > 0 and a1 > 0:
        w0 = math.sqrt(a0)
        f0, q, gain = w0 / (2 * np.pi), w0 / a1, rational.numerator[-1] / a0
    else:
        f0, q, gain = _peak_start(f, h)
    tau = rational.delay_s
    if gain == 0:
        gain = float(np.max(np.abs(h))) / q
    return f0, q, gain, tau


def _normalised_start_and_bounds(tau, scales, estimate_delay, delay_bounds_s, f_max):
    """Start p0 = (1, 1, 1[, τ/scale]) of the normalised parameters and their bounds (f0, Q > 0; τ in its interval)."""
    p0 = np.array([1.0, 1.0, 1.0, tau / scales[3]])[: 4 if estimate_delay else 3]
    lower = [1e-6, 1e-6, -np.inf]
    upper = [np.inf, np.inf, np.inf]
    if estimate_delay:
        lo, hi = _delay_bounds(delay_bounds_s, f_max)
        lower.append(lo / scales[3])
        upper.append(hi / scales[3])
        p0[3] = np.clip(p0[3], lower[3], upper[3])
    return p0, lower, upper


def _second_order_record(sol, values, scales: np.ndarray, estimate_delay: bool, w: np.ndarray) -> SecondOrderFit:
    """The fit with its errors: cov = s²·(JᵀJ)⁻¹, s² = Σ r²/(2K − p), in the normalised parameters."""
    f0, q, gain, tau = values
    dof = max(sol.fun.size - sol.x.size, 1)
    s2 = float(np.dot(sol.fun, sol.fun)) / dof
    cov = s2 * np.linalg.pinv(sol.jac.T @ sol.jac)
    # |scales|: the gain's scale is the signed start gain, and a standard deviation is never negative
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None)) * np.abs(scales[: sol.x.size])
    return SecondOrderFit(
        f0_hz=float(f0),
        q=float(q),
        gain=float(gain),
        delay_s=float(tau),
        f0_std_hz=float(std[0]),
        q_std=float(std[1]),
        gain_std=float(std[2]),
        delay_std_s=float(std[3]) if estimate_delay else 0.0,
        rms_residual=math.sqrt(float(np.dot(sol.fun, sol.fun)) / float(np.sum(w))),
    )


# --------------------------------------------------------------------------- free-air route


def _resonance_band(fr: FrequencyResponse, band) -> np.ndarray:
    """Boolean mask of the bins to fit: ``band`` (Hz) or the −20 dB region around the peak."""
    f = fr.frequency_hz
    with np.errstate(invalid="ignore"):
        usable = np.isfinite(fr.response) & (f > 0) & (fr.coherence >= _BAND_MIN_COHERENCE)
    if band is not None:
        try:
            lo, hi = (float(v) for v in band)
        except (TypeError, ValueError):
            raise ConfigError(f"band={band!r} must be a pair (low_hz, high_hz)") from None
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo < hi):
            raise ConfigError(f"band={band!r} must satisfy 0 <= low_hz < high_hz")
        return usable & (f >= lo) & (f <= hi)
    if not np.any(usable):
        raise InputError("the frequency response has no usable bins")
    order = np.argsort(f)
    # unusable bins (no input, low coherence) end the region: |H| there can be anything
    mag = np.where(usable, np.abs(fr.response), -np.inf)[order]
    k = int(np.argmax(mag))
    floor = mag[k] / _BAND_PEAK_FACTOR
    lo = k
    while lo > 0 and mag[lo - 1] > floor:
        lo -= 1
    hi = k
    while hi < mag.size - 1 and mag[hi + 1] > floor:
        hi += 1
    mask = np.zeros(f.size, dtype=bool)
    mask[order[lo : hi + 1]] = True
    return mask & usable


def free_air_from_sweep(
    dither,
    deflection,
    sample_rate_hz: float,
    *,
    method: str = "record",
    segments: Sequence | None = None,
    band: tuple[float, float] | None = None,
    nperseg: int | None = None,
    delay: bool | float = True,
    hold: str = "auto",
) -> FreeAirModel:
    """Free-air model from a frequency sweep of the dither (the "sweep" route).

    Parameters
    ----------
    dither, deflection : array_like
        Drive (e.g. V) and deflection (e.g. nm) records, equal length.
    sample_rate_hz : float
        Sampling rate, Hz.
    method, segments, band, nperseg, delay, hold
        As :func:`afmtool.estimators.sweep_record.identify_sweep`: by
        default the whole-record fit (exact at any sweep rate) with the
        drive's hold told from its half-sample delay; ``method="h1"`` or
        ``"stepped"`` for :func:`spectral_sweep_fit`.

    Returns
    -------
    FreeAirModel
        ``source="sweep"``, f0, Q, gain (deflection units per dither unit)
        and ``delay_s`` with standard errors; no discrete numerator.
    """
    from afmtool.estimators.sweep_record import identify_sweep

    return identify_sweep(
        dither, deflection, sample_rate_hz, method=method, segments=segments, band=band, nperseg=nperseg,
        delay=delay, hold=hold,
    ).model


def spectral_sweep_fit(
    dither,
    deflection,
    sample_rate_hz: float,
    *,
    method: str = "h1",
    segments: Sequence | None = None,
    band: tuple[float, float] | None = None,
    nperseg: int | None = None,
    delay: bool | float = True,
) -> SecondOrderFit:
    """The delayed second-order model fitted to an H1 or stepped-sine frequency response.

    Parameters
    ----------
    dither, deflection : array_like
        Drive (e.g. V) and deflection (e.g. nm) records, equal length.
    sample_rate_hz : float
        Sampling rate, Hz.
    method : {"h1", "stepped"}, optional
        ``"h1"``: Welch H1 (:func:`h1_estimate`) of a chirp or noise drive.
        ``"stepped"``: lock-in per step (:func:`stepped_sine_response`).
    segments : sequence, optional
        Stepped-sine steps ``[{start_s, end_s, frequency_hz}]`` from the
        capture metadata; found by :func:`detect_segments` when None.
        Only for ``method="stepped"``.
    band : (float, float), optional
        Frequencies to fit, Hz.  Default: the contiguous bins around the
        peak of |H| where |H| > |H|max/10 (−20 dB, about ±5 half-power
        bandwidths of the resonance).  Either way only bins with a finite
        response and coherence ≥ 0.5 are fitted.
    nperseg : int, optional
        H1 segment length; default the largest power of two ≤ n/16
        (≈ 31 averages at 50 % overlap), at least 256.
    delay : bool or float, optional
        As :func:`fit_second_order`; keep True unless the delay is known.

    Returns
    -------
    SecondOrderFit

    Notes
    -----
    The fit (:func:`fit_second_order`) weighs each bin by 1/σ², with σ the
    random error of |H| from the coherence, plus (1e-6·|H|max)² so that
    noise-free data (σ = 0) get equal weights.  The delay τ absorbs the
    drive and acquisition latencies, including the half-sample delay of a
    zero-order-hold DAC.  Both estimates assume that each Welch segment or
    each step's settled part holds the steady-state response: a chirp that
    crosses the resonance faster than its time constant 2Q/ω0 breaks that
    (Q comes out low); the whole-record fit
    (:func:`afmtool.estimators.sweep_record.fit_record_response`) does not.

    Raises
    ------
    ConfigError
        For a bad ``method``, ``band``, ``nperseg`` or ``delay``, or
        ``segments`` with ``method="h1"``.
    InputError
        For bad records, no stepped-sine steps, or a band with fewer than
        5 usable bins (then give ``band`` or a larger ``nperseg``).
    """
    fr = sweep_frequency_response(dither, deflection, sample_rate_hz, method=method, segments=segments, nperseg=nperseg)
    return free_air_from_response(fr, band=band, delay=delay)


def default_nperseg(n_samples: int) -> int:
    """Default H1 segment length for ``n_samples``: the largest power of two ≤ n/16, at least 256.

    That is about 31 Welch averages at 50 % overlap.
    """
    return max(256, 1 << max(int(math.floor(math.log2(max(n_samples, 1) / 16))), 0))


def sweep_frequency_response(
    dither,
    deflection,
    sample_rate_hz: float,
    *,
    method: str = "h1",
    segments: Sequence | None = None,
    nperseg: int | None = None,
) -> FrequencyResponse:
    """The measured frequency response of a sweep, as :func:`free_air_from_sweep` fits it.

    Parameters are those of :func:`free_air_from_sweep`; the H1 segment
    length defaults to the largest power of two ≤ n/16, at least 256.
    """
    fs = _check_positive("sample_rate_hz", sample_rate_hz)
    if method == "h1":
        if segments is not None:
            raise ConfigError("segments apply to method='stepped', not method='h1'")
        n = np.shape(dither)[0] if np.ndim(dither) else 0
        if nperseg is None:
            nperseg = default_nperseg(n)
        return h1_estimate(dither, deflection, fs, nperseg=nperseg)
    if method == "stepped":
        if segments is None:
            segments = detect_segments(dither, fs)
            if not segments:
                raise InputError("no stepped-sine steps found in the dither; give segments from the metadata")
        return stepped_sine_response(dither, deflection, fs, segments)
    raise ConfigError(f"method={method!r} must be 'h1' or 'stepped'")


def free_air_from_response(
    fr: FrequencyResponse, *, band: tuple[float, float] | None = None, delay: bool | float = True
) -> FreeAirModel:
    """The second-order fit of :func:`free_air_from_sweep` to a measured response ``fr``."""
    mask = _resonance_band(fr, band)
    if np.count_nonzero(mask) < 5:
        raise InputError(
            f"the fit band holds {np.count_nonzero(mask)} usable frequencies, fewer than 5; "
            "give band or a finer resolution (larger nperseg, more steps)"
        )
    h = fr.response[mask]
    sigma = fr.magnitude_std[mask]
    sigma = np.where(np.isfinite(sigma), sigma, np.inf)
    weights = 1.0 / (sigma**2 + (1e-6 * np.max(np.abs(h))) ** 2)
    return fit_second_order(fr.frequency_hz[mask], h, delay=delay, weights=weights)


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
