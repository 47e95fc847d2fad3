"""The free-air model from the whole record of a sweep, exact at any sweep rate.

A Welch (H1) estimate of a chirp response assumes each segment holds the
steady-state response to its own input.  When the chirp crosses the
resonance faster than the mode's time constant 2Q/ω0, the response in a
segment is mostly the ringing left by earlier segments, H1 smears the peak
and the fitted Q comes out low (29 % low for Q = 180 at 70 kHz).  The
lock-in of a stepped sine has the same problem when a step is shorter than a
few time constants.

This module avoids any steady-state assumption.  It takes the discrete
Fourier transform of the *whole* record, input U_k and output Y_k at the bins
f_k = k·fs/N, and fits

.. math:: Y_k = \\mathrm{gain}\\,G(f_k)\\,e^{-j2\\pi f_k\\tau}\\,U_k + \\frac{T(f_k)}{A(f_k)} + E_k

over a band around the resonance, where

* G is the cantilever's unit-gain response (eq. 3.1) for the way the drive
  reached it (``hold``):

  - ``"continuous"``: a continuous drive that the ADC merely samples (a
    function generator), G = ω0²/A(s), A(s) = s² + (ω0/Q)s + ω0²,
    s = j2πf;
  - ``"zoh"``: a drive held by a DAC over each sample interval, G the
    zero-order-hold discrete model of eq. 3.40,
    G = (a1 z⁻¹ + a0 z⁻²)/A(z), A(z) = 1 + b1 z⁻¹ + b0 z⁻², z = e^{j2πf/fs}
    (:func:`afmtool.models.discretisation.zoh_numerator`);

* τ is a pure delay of the drive path (acquisition latencies);
* T/A is the *transient term*: the record starts and ends with the
  cantilever in motion, and a finite Fourier transform of a linear system's
  output is exactly the transfer function times the input's transform plus
  the response to the state jump x(0) − x(NT) across the record's
  wrap-around, C(sI − A)⁻¹(x(0) − x(NT)), a polynomial of degree one over
  A.  For a zero-order-held drive this is exact on the DFT.  For a
  continuous drive the DFT of the samples differs from the Fourier
  coefficients of the continuous signals by the aliases of the wrap-around
  jumps, which vary slowly across the narrow band fitted; T is therefore a
  polynomial of degree ``transient_order`` (default 3) in the normalised
  offset from the band centre, with complex coefficients, which absorbs them.
* a continuous drive switched on or off inside the record (a burst) jumps
  somewhere between two samples, which the samples cannot place; each such
  edge t_j (:func:`drive_switch_times`) adds
  gain·G·e^{−j2πfτ}·e^{−j2πf t_j}·(e_0 + e_1·x), the spectrum of that
  misplacement (a held drive needs none: its samples are exact);
* E_k is the DFT of the measurement noise.  For white noise of variance σ²
  per sample and the rectangular window of the whole record, the E_k are
  independent complex Gaussians of variance N·σ², so ordinary least squares
  on the real and imaginary parts is the maximum-likelihood fit, and its
  covariance s²(JᵀJ)⁻¹ (s² the residual variance) gives calibrated
  standard deviations.

gain and the transient coefficients enter linearly and are eliminated by
linear least squares at each trial (f0, Q, τ) (variable projection); f0, Q,
τ are found by :func:`scipy.optimize.least_squares` from the start values of
:func:`record_start_values`.  This is the frequency-domain form of the
time-domain output-error fit of the model to the measured deflection given
the measured dither, with the transient ("leakage") term of Pintelon &
Schoukens (*System Identification: A Frequency Domain Approach*, 2nd ed.,
2012), and it holds for any drive: slow or fast chirps, stepped sines,
bursts, noise.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import scipy.optimize

from afmtool.errors import ConfigError, InputError

if TYPE_CHECKING:
    from afmtool.models.free_air import FreeAirModel

__all__ = [
    "HOLDS",
    "SWEEP_METHODS",
    "RecordFit",
    "StartValues",
    "SweepIdentification",
    "drive_switch_times",
    "fit_record_response",
    "check_sweep_options",
    "identify_sweep",
    "free_air_from_sweep",
    "identify_sweep_response",
    "record_response_model",
    "record_start_values",
]

#: How the drive reached the cantilever (see the module docstring).
HOLDS = ("continuous", "zoh")
#: ``record``: the whole-record fit; ``h1``, ``stepped``: the spectral fits of sweep_spectral.
SWEEP_METHODS = ("record", "h1", "stepped")
#: Fewest bins a band may hold: the fit has 3 + 1 + 2·(order + 1) real unknowns.
_MIN_BAND_BINS = 8
#: The start values use at most about this many frequency-smoothed points across the driven band.
_START_POINTS = 400
#: Bins whose input power is below this fraction of its maximum are not driven.
_DRIVEN_FRACTION = 1e-3
#: The start values' peak search keeps smoothed points with at least this fraction of the input power.
_WELL_DRIVEN_FRACTION = 0.1


@dataclass(frozen=True, eq=False)
class RecordFit:
    """The second-order model fitted to a whole record (:func:`fit_record_response`).

    Parameters
    ----------
    f0_hz, q, gain, delay_s : float
        f0 (Hz), Q, the DC gain (output units per input unit, signed) and
        the drive-path delay τ (s) beyond the hold's own.
    f0_std_hz, q_std, gain_std, delay_std_s : float
        One-standard-deviation errors (≥ 0) from s²(JᵀJ)⁻¹; ``delay_std_s``
        is 0 when τ was fixed.
    hold : str
        ``"continuous"`` or ``"zoh"``, the model of G used.
    band_hz : (float, float)
        Lowest and highest fitted bin, Hz.
    n_bins : int
        Fitted bins.
    transient_order : int
        Degree of the transient polynomial T.
    noise_std : float
        Output noise per sample implied by the residual, √(s²_complex/N),
        output units (for white noise, its standard deviation).
    frequency_hz : numpy.ndarray
        The fitted bins, Hz.
    measured_response : numpy.ndarray of complex
        The data at those bins with the fitted transient and edge terms
        removed, (Y_k − T_k/A_k − …)/U_k: what the model gain·G·e^{−j2πfτ}
        was fitted to, for a Bode plot.  NaN where the bin holds less than
        1e-3 of the band's largest input power.
    drive_edges_s : tuple of float
        The drive's switch times modelled (``drive_edges_s`` of
        :func:`fit_record_response`), s.
    """

    f0_hz: float
    q: float
    gain: float
    delay_s: float
    f0_std_hz: float
    q_std: float
    gain_std: float
    delay_std_s: float
    hold: str
    band_hz: tuple[float, float]
    n_bins: int
    transient_order: int
    noise_std: float
    frequency_hz: np.ndarray
    measured_response: np.ndarray
    drive_edges_s: tuple[float, ...] = ()

    def response(self, frequency_hz, sample_rate_hz: float) -> np.ndarray:
        """gain·G(f)·e^{−j2πfτ} at ``frequency_hz`` (Hz) for this fit's hold."""
        f = np.asarray(frequency_hz, dtype=np.float64)
        g, _ = record_response_model(f, self.f0_hz, self.q, sample_rate_hz, self.hold)
        return self.gain * g * np.exp(-2j * np.pi * f * self.delay_s)


def record_response_model(frequency_hz: np.ndarray, f0_hz: float, q: float, sample_rate_hz: float, hold: str):
    """Unit-gain response G and denominator A of the cantilever at ``frequency_hz`` (module docstring).

    Returns
    -------
    (numpy.ndarray, numpy.ndarray)
        G(f) (complex, DC gain 1) and A(f): A(s)/ω0² for ``"continuous"``
        (so that G = 1/A), A(z) for ``"zoh"``.
    """
    f = np.asarray(frequency_hz, dtype=np.float64)
    if hold == "continuous":
        w0 = 2.0 * np.pi * f0_hz
        sn = 2j * np.pi * f / w0
        a = sn * sn + sn / q + 1.0
        return 1.0 / a, a
    if hold == "zoh":
        from afmtool.models.discretisation import discrete_denominator, zoh_numerator

        num = zoh_numerator(f0_hz, q, sample_rate_hz)
        den = discrete_denominator(f0_hz, q, sample_rate_hz)
        zi = np.exp(-2j * np.pi * f / sample_rate_hz)
        a = 1.0 + den.b1 * zi + den.b0 * zi * zi
        return (num.a2 + num.a1 * zi + num.a0 * zi * zi) / a, a
    raise ConfigError(f"hold={hold!r} must be one of {HOLDS}")


class StartValues(NamedTuple):
    """Start values of the record fit (:func:`record_start_values`): f0 (Hz), Q, gain, delay (s)."""

    f0_hz: float
    q: float
    gain: float
    delay_s: float


def record_start_values(dither, deflection, sample_rate_hz: float) -> StartValues:
    """Rough f0, Q, gain and delay from the frequency-smoothed ratio of the whole record's spectra.

    Parameters
    ----------
    dither, deflection : array_like
        Input and output records (as :func:`fit_record_response`).
    sample_rate_hz : float
        Sampling rate, Hz.

    Returns
    -------
    StartValues

    Notes
    -----
    The ratio Ĥ = Σ_M Y_k U_k* / Σ_M |U_k|² over blocks of M adjacent bins
    (a Daniell-smoothed empirical transfer function; M = 1 unless the driven
    band holds more than 400 bins), kept where the smoothed input power is at
    least a tenth of its maximum, needs no steady state within a segment,
    unlike a Welch estimate, so its peak is near f0 even for a fast chirp or
    a short record; the transient only blurs it.  The delayed second-order
    model is fitted to Ĥ where |Ĥ| > |Ĥ|max/10 (:func:`~afmtool.estimators.
    transfer_function_fit.fit_second_order`, weights Σ_M |U_k|²).  Q may be
    far off; :func:`fit_record_response` refines all four.

    Raises
    ------
    InputError
        If the dither drives no band, or the peak region has fewer than
        3 points.
    """
    from afmtool.estimators.transfer_function_fit import fit_second_order

    fs = _check_positive("sample_rate_hz", sample_rate_hz)
    x, y, x_scale, y_scale = _records(dither, deflection)
    u = np.fft.rfft(x - x.mean())
    v = np.fft.rfft(y - y.mean())
    freq = np.fft.rfftfreq(x.size, 1.0 / fs)
    power = np.abs(u) ** 2
    driven = np.flatnonzero(power > _DRIVEN_FRACTION * power.max())
    first, last = int(driven[0]), int(driven[-1]) + 1
    m = max(1, (last - first) // _START_POINTS)
    blocks = (last - first) // m
    if blocks < 3:
        raise InputError(f"the dither drives {last - first} frequency bins, too few to find a resonance")
    stop = first + blocks * m
    cross = (v[first:stop] * np.conj(u[first:stop])).reshape(blocks, m).sum(axis=1)
    auto = power[first:stop].reshape(blocks, m).sum(axis=1)
    f_mid = freq[first:stop].reshape(blocks, m).mean(axis=1)
    # the ratio is noise over little input where the drive is weak (a chirp's ends): search only
    # where the smoothed input power is at least a tenth of its maximum
    keep = auto > _WELL_DRIVEN_FRACTION * auto.max()
    h, f_mid, auto = cross[keep] / auto[keep], f_mid[keep], auto[keep]
    mag = np.abs(h)
    peak = int(np.argmax(mag))
    lo, hi = peak, peak
    while lo > 0 and mag[lo - 1] > mag[peak] / 10:
        lo -= 1
    while hi < mag.size - 1 and mag[hi + 1] > mag[peak] / 10:
        hi += 1
    if hi - lo + 1 < 3:
        lo, hi = max(peak - 2, 0), min(peak + 2, mag.size - 1)
    if hi - lo + 1 < 3:
        raise InputError("the response has no resonance peak inside the driven band")
    fit = fit_second_order(f_mid[lo : hi + 1], h[lo : hi + 1], weights=auto[lo : hi + 1])
    f0 = fit.f0_hz if 0 < fit.f0_hz < fs / 2 * (1 - 1e-6) else float(f_mid[peak])
    if not (0 < f0 < fs / 2 * (1 - 1e-6)):
        raise InputError(f"the response peaks at {f0:g} Hz, not below the Nyquist frequency {fs / 2:g} Hz")
    gain = fit.gain * y_scale / x_scale
    return StartValues(float(f0), float(max(fit.q, 0.6)), float(gain), float(fit.delay_s))


def _check_positive(name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise ConfigError(f"{name}={value!r} must be a finite number > 0")
    if not (math.isfinite(value) and value > 0):
        raise ConfigError(f"{name}={value!r} must be a finite number > 0")
    return float(value)


def drive_switch_times(dither, sample_rate_hz: float) -> tuple[float, ...]:
    """Where a drive switches on or off inside the record (a burst), s from the first sample.

    Parameters
    ----------
    dither : array_like
        The drive record, 1-D, finite.
    sample_rate_hz : float
        Sampling rate fs, Hz.

    Returns
    -------
    tuple of float
        The boundaries between runs of at least 8 samples where
        |u − median u| ≤ 1e-3·max|u − median u| (drive off) and the driven
        samples, at the first sample of each new run, i/fs; the record's own
        start and end are not edges.  Empty for a drive that stays on.
    """
    fs = _check_positive("sample_rate_hz", sample_rate_hz)
    u = np.asarray(dither, dtype=np.float64)
    if u.ndim != 1 or u.size < 2 * _OFF_SAMPLES:
        return ()
    centred = np.abs(u - np.median(u))
    peak = float(centred.max())
    if not peak > 0:
        return ()
    quiet = centred <= _OFF_FRACTION * peak
    # runs of quiet samples; only long ones are "off" (a sine crosses zero in a sample or two)
    change = np.flatnonzero(np.diff(quiet.astype(np.int8))) + 1
    starts = np.concatenate(([0], change))
    stops = np.concatenate((change, [u.size]))
    off = np.zeros(u.size, dtype=bool)
    for a, b in zip(starts, stops):
        if quiet[a] and b - a >= _OFF_SAMPLES:
            off[a:b] = True
    edges = np.flatnonzero(np.diff(off.astype(np.int8))) + 1
    return tuple(float(i) / fs for i in edges)


def _check_band(band) -> tuple[float, float] | None:
    if band is None:
        return None
    try:
        lo, hi = (float(v) for v in band)
    except (TypeError, ValueError):
        raise ConfigError(f"band={band!r} must be a pair (low_hz, high_hz)") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo < hi):
        raise ConfigError(f"band={band!r} must satisfy 0 <= low_hz < high_hz")
    return lo, hi


#: Degree of the smooth factor of each drive-jump term (module docstring of fit_record_response).
_EDGE_ORDER = 1
#: A drive is off where |u| stays at most this fraction of max|u| for at least _OFF_SAMPLES samples.
_OFF_FRACTION = 1e-3
_OFF_SAMPLES = 8
#: More drive switches than this are not modelled (4 unknowns each): a warning says so.
_MAX_EDGES = 16
#: A fit whose gain is within this many standard deviations of 0 found no response, only noise.
_MIN_GAIN_SIGMAS = 5.0
#: Fewest samples a record may hold.
_MIN_SAMPLES = 16


class _Records(NamedTuple):
    """The records divided by their peak deviation from the mean (so no power overflows), and those scales."""

    x: np.ndarray
    y: np.ndarray
    x_scale: float
    y_scale: float


def _records(dither, deflection) -> _Records:
    arrays = []
    for name, values in (("dither", dither), ("deflection", deflection)):
        try:
            arr = np.asarray(values, dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError(f"{name} must be a 1-D array of numbers") from None
        if arr.ndim != 1:
            raise InputError(f"{name} must be 1-D, got shape {arr.shape}")
        if arr.size < _MIN_SAMPLES:
            raise InputError(f"{name} has {arr.size} samples; a sweep needs at least {_MIN_SAMPLES}")
        if not np.all(np.isfinite(arr)):
            bad = int(np.flatnonzero(~np.isfinite(arr))[0])
            raise InputError(f"{name} has a non-finite value at index {bad} ({arr[bad]!r})")
        arrays.append(arr)
    if arrays[0].shape != arrays[1].shape:
        raise InputError(f"dither and deflection must have the same length, got {arrays[0].size} and {arrays[1].size}")
    scales = []
    for name, arr in zip(("dither", "deflection"), arrays):
        # the mean first: max|x − mean| overflows only for |x| near the largest double
        scale = float(np.max(np.abs(arr - arr.mean()))) if np.all(np.abs(arr) < 1e300) else math.inf
        if scale == 0:
            raise InputError(f"the {name} is constant: nothing to identify a response from")
        if not (math.isfinite(scale) and scale > 1e-300):
            raise InputError(f"the {name} spans {scale:g}, outside the range a fit can represent")
        scales.append(scale)
    return _Records(arrays[0] / scales[0], arrays[1] / scales[1], scales[0], scales[1])


class _Band:
    """The fitted bins: frequencies, input and output DFT values, and the normalised offset basis."""

    def __init__(self, f: np.ndarray, u: np.ndarray, y: np.ndarray, order: int, edges_s=()) -> None:
        self.f, self.u, self.y = f, u, y
        centre, half = 0.5 * (f[0] + f[-1]), 0.5 * (f[-1] - f[0])
        offset = (f - centre) / half  # in [−1, 1]
        self.powers = offset[None, :] ** np.arange(order + 1)[:, None]
        # a jump of a continuous drive at t_j: the samples misplace it by a spectrum e^{−j2πf t_j}·(smooth)
        self.edge_times = tuple(edges_s)
        self.edges = [np.exp(-2j * np.pi * f * t) * offset**m for t in edges_s for m in range(_EDGE_ORDER + 1)]
        self.y_stacked = np.concatenate((y.real, y.imag))


def _design(band: _Band, f0: float, q: float, tau: float, fs: float, hold: str) -> np.ndarray:
    """Real design matrix of the linear unknowns [gain, Re c_0, Im c_0, …] at (f0, Q, τ)."""
    g, a = record_response_model(band.f, f0, q, fs, hold)
    forced = g * np.exp(-2j * np.pi * band.f * tau) * band.u
    transient = band.powers / a[None, :]
    cols = [forced] + [c for t in transient for c in (t, 1j * t)]
    if band.edges:
        delayed = g * np.exp(-2j * np.pi * band.f * tau)
        cols += [c for e in band.edges for c in (delayed * e, 1j * delayed * e)]
    m = np.array(cols).T
    return np.vstack((m.real, m.imag))


def _solve_linear(design: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Least squares by the normal equations of the column-normalised design, refined once.

    The design is tall and thin (2K × (3 + 2·order)); numpy's SVD or QR of it
    cost 10–300× more than these 9 × 9 solves.  Normalised columns keep the
    Gram matrix's condition number the square of a modest one, and one step
    of iterative refinement recovers the accuracy a QR would give.
    """
    norms = np.linalg.norm(design, axis=0)
    norms[norms == 0] = 1.0
    a = design / norms
    gram = a.T @ a
    try:
        x = np.linalg.solve(gram, a.T @ y)
        x += np.linalg.solve(gram, a.T @ (y - a @ x))
    except np.linalg.LinAlgError:  # rank deficient (e.g. no input in the band): the minimum-norm answer
        x = np.linalg.lstsq(a, y, rcond=None)[0]
    return x / norms


def _band_mask(f: np.ndarray, f0: float, q: float, halfwidths: float, band, fs: float) -> np.ndarray:
    if band is None:
        half = halfwidths * f0 / (2.0 * q)
        lo, hi = f0 - half, f0 + half
    else:
        lo, hi = band
    return (f > max(lo, 0.0)) & (f < min(hi, fs / 2))


def fit_record_response(
    dither,
    deflection,
    sample_rate_hz: float,
    *,
    f0_start_hz: float,
    q_start: float,
    delay_start_s: float = 0.0,
    hold: str = "continuous",
    delay: bool | float = True,
    band: tuple[float, float] | None = None,
    band_halfwidths: float = 8.0,
    transient_order: int = 3,
    drive_edges_s: tuple[float, ...] = (),
    delay_search: bool = True,
) -> RecordFit:
    """Fit f0, Q, gain and delay to the whole record's DFT, with a transient term (module docstring).

    Parameters
    ----------
    dither, deflection : array_like
        Input (e.g. V) and output (e.g. nm) records, 1-D, equal length,
        finite.  Not modified.
    sample_rate_hz : float
        Sampling rate fs, Hz.
    f0_start_hz, q_start : float
        Start values (e.g. from an H1 fit, which may be far off in Q for a
        fast chirp); they also centre the first band.
    delay_start_s : float, optional
        Start value of τ, s.  τ is searched within ±1/(4·f0) of it, so that
        the fit cannot trade a sign flip of the gain for half a period of
        delay.
    hold : {"continuous", "zoh"}, optional
        The model of G (module docstring).
    delay : bool or float, optional
        True: estimate τ; False: τ = 0; a number: that fixed τ, s.
    band : (float, float), optional
        Frequencies to fit, Hz.  Default: f0 ± ``band_halfwidths`` half-power
        half-widths f0/(2Q), taken from the start values and then once more
        from the first fit's.
    band_halfwidths : float, optional
        See ``band``; default 8 (±4·f0/Q).
    transient_order : int, optional
        Degree of the transient polynomial T, ≥ 1.
    drive_edges_s : tuple of float, optional
        Times (s from the first sample) where a continuous drive switches on
        or off abruptly inside the record (:func:`drive_switch_times`).  The
        samples cannot say where between two samples the jump fell, so the
        DFT of the sampled dither misses a term e^{−j2πf t_j}·(smooth in f);
        each edge adds gain·G·e^{−j2πfτ}·e^{−j2πf t_j}·(e_0 + e_1·x) with
        complex e_0, e_1 (x the normalised offset in the band) to the model.
        Not needed for a held drive, whose samples are exact.
    delay_search : bool, optional
        True (default): also start from τ ± half a period and keep the best
        (a rough start may sit on the sign-flipped branch).  False when
        ``delay_start_s`` comes from a fit of the same record.

    Returns
    -------
    RecordFit

    Raises
    ------
    ConfigError
        For bad start values, ``hold``, ``delay``, ``band`` or orders.
    InputError
        For bad records, or a band holding fewer than 8 bins or
        fewer than twice as many real equations as unknowns (the record is
        too short for the resolution the resonance needs: N/fs ≳ 4Q/f0).
    """
    fs, f0_start, q_start, fixed_delay, band, order, edges = _record_options(
        sample_rate_hz, f0_start_hz, q_start, band_halfwidths, hold, transient_order, delay, band, drive_edges_s
    )
    x, y, x_scale, y_scale = _records(dither, deflection)
    spectra = _RecordSpectra(np.fft.rfftfreq(x.size, 1.0 / fs), np.fft.rfft(x), np.fft.rfft(y), x.size, fs)
    tau0 = float(delay_start_s) if fixed_delay is None else fixed_delay
    fit = _band_fits(spectra, hold, order, edges, f0_start, max(q_start, 0.6), tau0, fixed_delay, band, band_halfwidths,
                     delay_search)
    return _checked_result(fit.result, y_scale / x_scale, y_scale, fs)


class _RecordSpectra(NamedTuple):
    freq: np.ndarray  # rfft bin frequencies, Hz
    u: np.ndarray  # DFT of the (scaled) dither
    y: np.ndarray  # DFT of the (scaled) deflection
    n_samples: int
    fs: float  # Hz


def _band_fits(spectra: _RecordSpectra, hold, order, edges, f0, q, tau0, fixed_delay, band, band_halfwidths,
               delay_search):
    """Fit in the band around the start values, then once more in the band around that fit's (unless ``band`` is given)."""
    fs, n = spectra.fs, spectra.n_samples
    n_unknown = 1 + 2 * (order + 1) + 2 * (_EDGE_ORDER + 1) * len(edges) + 2 + (fixed_delay is None)
    tau = tau0
    fit = None
    for _ in range(1 if band is not None else 2):
        data = _band_data(spectra, _band_mask(spectra.freq, f0, q, band_halfwidths, band, fs), n_unknown, order, edges)
        if fixed_delay is None and fit is None and delay_search:
            # a delay of half a period is a sign flip of the gain at f0: only the phase slope across
            # the band tells the two apart, so start from both neighbours too and keep the best
            half = 0.5 / f0
            tries = [_fit_band(data, fs, hold, f0, q, tau + k * half, tau + k * half, None, n) for k in (0, -1, 1)]
            fit = _likeliest_branch(tries, 2 * data.f.size - n_unknown)
        else:
            fit = _fit_band(data, fs, hold, f0, q, tau, tau if fixed_delay is None else tau0, fixed_delay, n)
        f0, q, tau = fit.f0_hz, fit.q, fit.delay_s
    return fit


def _band_data(spectra: _RecordSpectra, mask: np.ndarray, n_unknown: int, order, edges) -> _Band:
    """The bins of the fit band, after checking they are enough for the unknowns (≥ 8 and ≥ n_unknown complex)."""
    k = int(np.count_nonzero(mask))
    if k < _MIN_BAND_BINS or 2 * k < 2 * n_unknown:
        per_edge = f", {2 * (_EDGE_ORDER + 1)} per drive switch" if edges else ""
        raise InputError(
            f"the fit band holds {k} frequency bins of {spectra.fs / spectra.n_samples:g} Hz, too few for {n_unknown} unknowns"
            f"{per_edge}; a longer record (finer resolution) is needed"
        )
    return _Band(spectra.freq[mask], spectra.u[mask], spectra.y[mask], order, edges)


def _record_options(sample_rate_hz, f0_start_hz, q_start, band_halfwidths, hold, transient_order, delay, band,
                    drive_edges_s):
    """The checked options of :func:`fit_record_response`.

    Returns (fs, f0 start, Q start, the fixed delay or None, band, transient
    order, drive edges).
    """
    fs = _check_positive("sample_rate_hz", sample_rate_hz)
    f0_start = _check_positive("f0_start_hz", f0_start_hz)
    q_start = _check_positive("q_start", q_start)
    _check_positive("band_halfwidths", band_halfwidths)
    if hold not in HOLDS:
        raise ConfigError(f"hold={hold!r} must be one of {HOLDS}")
    if isinstance(transient_order, bool) or not isinstance(transient_order, (int, np.integer)) or transient_order < 1:
        raise ConfigError(f"transient_order={transient_order!r} must be an integer >= 1")
    if isinstance(delay, (bool, np.bool_)):
        fixed_delay = None if delay else 0.0
    elif isinstance(delay, (int, float)) and math.isfinite(delay):
        fixed_delay = float(delay)
    else:
        raise ConfigError(f"delay={delay!r} must be True, False or a delay in s")
    band = _check_band(band)
    if not f0_start < fs / 2:
        raise ConfigError(f"f0_start_hz={f0_start_hz!r} must be below the Nyquist frequency {fs / 2:g} Hz")
    edges = tuple(float(t) for t in drive_edges_s)
    if not all(math.isfinite(t) for t in edges):
        raise ConfigError(f"drive_edges_s={drive_edges_s!r} must be finite times in s")
    return fs, f0_start, q_start, fixed_delay, band, int(transient_order), edges


def _checked_result(result: RecordFit, unit: float, y_scale: float, fs: float) -> RecordFit:
    """``result`` back in the records' units (gain × ``unit``, noise × ``y_scale``); InputError if degenerate."""
    result = replace(
        result, gain=result.gain * unit, gain_std=result.gain_std * unit, noise_std=result.noise_std * y_scale,
        measured_response=_frozen(result.measured_response * unit),
    )
    values = (result.f0_hz, result.q, result.gain, result.f0_std_hz, result.q_std, result.gain_std)
    inside = result.band_hz[0] <= result.f0_hz <= result.band_hz[1] and result.f0_hz < fs / 2 * (1 - 1e-6)
    if not (all(math.isfinite(v) for v in values) and inside and result.gain != 0 and result.f0_std_hz > 0
            and result.q_std > 0):
        raise InputError(
            "the deflection shows no resonant response to the dither in the band "
            f"{result.band_hz[0]:g}–{result.band_hz[1]:g} Hz (a degenerate fit)"
        )
    if abs(result.gain) < _MIN_GAIN_SIGMAS * result.gain_std or result.q_std > 0.5 * result.q:
        raise InputError(
            f"the deflection shows no significant resonant response to the dither: gain {result.gain:.3g} ± "
            f"{result.gain_std:.2g}, Q {result.q:.3g} ± {result.q_std:.2g}"
        )
    return result


def _likeliest_branch(tries: list, dof: int):
    """The fit with the smallest |τ| among those whose cost is within 25 s² of the best.

    A drive path rarely delays by more than a fraction of a period, so a
    branch farther from τ = 0 must earn its place: a likelihood-ratio
    margin Δχ² = Δcost/s² > 25 (5σ) over the nearer one.
    """
    best = min(tries, key=lambda r: r.cost)
    margin = 25.0 * best.cost / max(dof, 1)
    close = [r for r in tries if r.cost <= best.cost + margin]
    return min(close, key=lambda r: abs(r.delay_s))


def _frozen(arr: np.ndarray) -> np.ndarray:
    arr = np.array(arr)
    arr.setflags(write=False)
    return arr


def _corrected_response(data: _Band, model_stacked: np.ndarray, f0, q, tau, fs, hold, gain) -> np.ndarray:
    """(Y − (model − forced part))/U: the measurement with the fitted transient and edge terms removed."""
    k = data.f.size
    model = model_stacked[:k] + 1j * model_stacked[k:]
    g, _ = record_response_model(data.f, f0, q, fs, hold)
    forced = gain * g * np.exp(-2j * np.pi * data.f * tau) * data.u
    power = np.abs(data.u) ** 2
    driven = power >= 1e-3 * power.max()
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(driven, (data.y - (model - forced)) / data.u, np.nan + 0j)


class _BandFit(NamedTuple):
    result: RecordFit
    cost: float
    f0_hz: float
    q: float
    delay_s: float


def _parameter_std(data: _Band, physical: list[float], tau: float, linear: np.ndarray, design: np.ndarray,
                   resid: np.ndarray, fs: float, hold: str, delay_step: float) -> tuple[np.ndarray, float]:
    """Standard errors of (f0, Q, [τ], gain, c…) at the optimum, and the residual variance s².

    The Jacobian of the residual in the physical unknowns: the linear ones are
    −design; the nonlinear ones (``physical``: f0, Q and τ when estimated) by
    central differences at fixed linear unknowns (τ's step ``delay_step``).
    """
    estimate_delay = len(physical) == 3
    steps = [1e-7 * physical[0], 1e-6 * physical[1], delay_step][: len(physical)]

    def model_at(values: list[float]) -> np.ndarray:
        tau_v = values[2] if estimate_delay else tau
        return _design(data, values[0], values[1], tau_v, fs, hold) @ linear

    columns = []
    for i, step in enumerate(steps):
        up, down = list(physical), list(physical)
        up[i] += step
        down[i] -= step
        columns.append(-(model_at(up) - model_at(down)) / (2.0 * step))
    jac = np.column_stack(columns + [-design])
    dof = max(resid.size - jac.shape[1], 1)
    s2 = float(resid @ resid) / dof
    # scale the columns before inverting (f0 in Hz next to transient coefficients of any size)
    col_norm = np.linalg.norm(jac, axis=0)
    col_norm[col_norm == 0] = 1.0
    jn = jac / col_norm
    cov = s2 * np.linalg.pinv(jn.T @ jn) / np.outer(col_norm, col_norm)
    return np.sqrt(np.clip(np.diag(cov), 0.0, None)), s2


def _fit_band(
    data: _Band, fs: float, hold: str, f0s: float, qs: float, tau_s: float, tau0: float, fixed_delay, n: int
) -> _BandFit:
    """Variable-projection fit on one band, then the covariance of all unknowns."""
    w0s = 2.0 * np.pi * f0s
    estimate_delay = fixed_delay is None
    quarter = 0.25 / f0s  # ± a quarter period around the start delay (docstring of fit_record_response)

    def unpack(p: np.ndarray) -> tuple[float, float, float]:
        tau = tau0 + p[2] / w0s if estimate_delay else fixed_delay
        return f0s * p[0], qs * math.exp(p[1]), tau

    def residual(p: np.ndarray) -> np.ndarray:
        design = _design(data, *unpack(p), fs, hold)
        return data.y_stacked - design @ _solve_linear(design, data.y_stacked)

    p0 = np.array([1.0, 0.0, (tau_s - tau0) * w0s])[: 3 if estimate_delay else 2]
    # f0 stays below Nyquist and Q above 1/2 (an under-damped mode)
    lower = [1e-3, math.log(0.51 / qs)]
    upper = [0.5 * fs / f0s * (1 - 1e-9), math.log(1e7 / qs)]
    if estimate_delay:
        lower.append(-quarter * w0s)
        upper.append(quarter * w0s)
    p0 = np.clip(p0, np.array(lower) + 1e-12, np.array(upper) - 1e-12)
    sol = scipy.optimize.least_squares(
        residual, p0, bounds=(lower, upper), x_scale=np.array([1e-4, 1e-2, 1e-2])[: p0.size],
        xtol=1e-12, ftol=1e-12, gtol=1e-12,
    )
    f0, q, tau = unpack(sol.x)
    design = _design(data, f0, q, tau, fs, hold)
    linear = _solve_linear(design, data.y_stacked)
    resid = data.y_stacked - design @ linear
    physical = [f0, q] + ([tau] if estimate_delay else [])
    std, s2 = _parameter_std(data, physical, tau, linear, design, resid, fs, hold, 1e-4 / w0s)
    n_nl = len(physical)
    result = RecordFit(
        f0_hz=float(f0),
        q=float(q),
        gain=float(linear[0]),
        delay_s=float(tau),
        f0_std_hz=float(std[0]),
        q_std=float(std[1]),
        gain_std=float(std[n_nl]),
        delay_std_s=float(std[2]) if estimate_delay else 0.0,
        hold=hold,
        band_hz=(float(data.f[0]), float(data.f[-1])),
        n_bins=int(data.f.size),
        transient_order=int(data.powers.shape[0] - 1),
        # s2 is the variance of each real part; the complex DFT noise has 2·s2 = N·σ²
        noise_std=math.sqrt(2.0 * s2 / n),
        frequency_hz=_frozen(data.f),
        measured_response=_frozen(_corrected_response(data, design @ linear, f0, q, tau, fs, hold, linear[0])),
        drive_edges_s=tuple(float(t) for t in data.edge_times),
    )
    return _BandFit(result, float(resid @ resid), result.f0_hz, result.q, result.delay_s)


class SweepIdentification(NamedTuple):
    """The sweep route's result (:func:`identify_sweep`).

    Attributes
    ----------
    model : FreeAirModel
        ``source="sweep"``.
    method : str
        ``"record"``, ``"h1"`` or ``"stepped"``.
    hold : str
        The hold of the model fitted: ``"continuous"`` or ``"zoh"`` (the
        spectral methods fit the continuous model, their delay absorbing a
        hold's T/2).
    hold_reason : str
        Why that hold: given, or what the automatic choice saw.
    fit : RecordFit or SecondOrderFit
        The fit behind the model.
    warnings : tuple of str
        What the user should know about the fit (e.g. drive switches not
        modelled).
    response : FrequencyResponse or None
        The measured response the spectral methods fitted (H1 or stepped
        sine); None for ``"record"``, whose measurement is ``fit``'s own.
    """

    model: object
    method: str
    hold: str
    hold_reason: str
    fit: object
    warnings: tuple[str, ...] = ()
    response: object = None


def _auto_hold(continuous: RecordFit, sample_rate_hz: float) -> tuple[str, str]:
    """zoh or continuous from the continuous-model fit's delay (0 or T/2; a hold delays by T/2, docs/conventions.md)."""
    period = 1.0 / sample_rate_hz
    tau, tau_std = continuous.delay_s, continuous.delay_std_s
    seen = f"the continuous-drive model needs a delay of {tau * 1e6:.4g} µs ± {tau_std * 1e6:.2g} µs"
    if tau_std > period / 8:
        return "continuous", f"{seen}, too uncertain to tell a hold's half sample; continuous assumed"
    if abs(tau) <= period / 4:
        return "continuous", f"{seen}, within a quarter sample of 0: a continuous drive"
    if abs(tau - period / 2) <= period / 4:
        return "zoh", f"{seen}, within a quarter sample of half a sample ({period * 5e5:.4g} µs): a zero-order-held drive"
    return "continuous", f"{seen}, neither 0 nor half a sample (an instrument delay); continuous assumed"


def _record_route(dither, deflection, fs: float, delay, band, hold: str) -> tuple[RecordFit, str, str, tuple]:
    """The record method of :func:`identify_sweep`: (fit, hold, reason, warnings).

    A first fit without drive-edge terms (which could absorb part of a short
    burst's forced response and blur the delay) fixes the delay branch and,
    for ``hold="auto"``, the hold; the final fit starts from it, with the
    edge terms when the drive is continuous and switches inside the record.
    """
    start = record_start_values(dither, deflection, fs)
    first_hold = "continuous" if hold == "auto" else hold
    first = fit_record_response(
        dither, deflection, fs, f0_start_hz=start.f0_hz, q_start=start.q, delay_start_s=start.delay_s,
        hold=first_hold, delay=delay, band=band,
    )
    if hold != "auto":
        chosen, reason = hold, "given"
    elif delay is not True:
        chosen, reason = "continuous", "the delay was fixed, so the hold's half sample cannot be seen; continuous assumed"
    else:
        chosen, reason = _auto_hold(first, fs)
    edges = drive_switch_times(dither, fs) if chosen == "continuous" else ()
    warnings: tuple[str, ...] = ()
    if len(edges) > _MAX_EDGES:
        warning = (
            f"the continuous drive switches on or off {len(edges)} times inside the record; only up to "
            f"{_MAX_EDGES} switches are modelled, so each leaves a jump the samples cannot place and f0, Q may "
            "be biased: give one burst per record, or a drive held by a DAC (--drive-hold zoh)"
        )
        warnings = (warning,)
        edges = ()
    if chosen == first_hold and not edges:
        return first, chosen, reason, warnings
    # the zero-order hold's own half sample leaves the drive-path delay
    shift = 0.5 / fs if chosen != first_hold else 0.0
    final = fit_record_response(
        dither, deflection, fs, f0_start_hz=first.f0_hz, q_start=first.q, delay_start_s=first.delay_s - shift,
        delay_search=False, hold=chosen, delay=delay, band=band, drive_edges_s=edges,
    )
    return final, chosen, reason, warnings


def identify_sweep(
    dither,
    deflection,
    sample_rate_hz: float,
    *,
    method: str = "record",
    segments=None,
    band: tuple[float, float] | None = None,
    nperseg: int | None = None,
    delay: bool | float = True,
    hold: str = "auto",
) -> SweepIdentification:
    """Free-air model from a frequency sweep of the dither (the "sweep" route).

    Parameters
    ----------
    dither, deflection : array_like
        Drive (e.g. V) and deflection (e.g. nm) records, equal length.
    sample_rate_hz : float
        Sampling rate, Hz.
    method : {"record", "h1", "stepped"}, optional
        ``"record"`` (default): the whole-record fit
        (:func:`fit_record_response` from :func:`record_start_values`),
        exact for any drive and any sweep rate.  ``"h1"``, ``"stepped"``:
        the spectral fits of
        :func:`afmtool.estimators.sweep_spectral.spectral_sweep_fit`,
        which need each Welch segment or step to be in steady state.
    segments, nperseg : optional
        Only for the spectral methods (see there).
    band : (float, float), optional
        Frequencies to fit, Hz; default chosen around the resonance.
    delay : bool or float, optional
        True: estimate the drive-path delay; False: none; a number: that
        fixed delay, s.
    hold : {"auto", "continuous", "zoh"}, optional
        How the drive reached the cantilever (record method only).
        ``"auto"``: fit the continuous-drive model with a free delay; a
        delay within a quarter sample of T/2 (the half sample a zero-order
        hold adds) means a held drive, which is then refitted with the
        zero-order-hold model; a delay near 0, an uncertain one or any
        other delay keeps the continuous model.  The reason is returned.

    Returns
    -------
    SweepIdentification

    Notes
    -----
    Memory: ``"record"`` needs the whole records and their DFTs (about six
    float64 arrays of the record's length at the peak); a capture streams
    only the two records into it.  The spectral methods need no record when
    their response is accumulated chunk by chunk
    (:class:`~afmtool.estimators.stages.ResponseStage`, then
    :func:`identify_sweep_response`).

    Raises
    ------
    ConfigError
        For a bad ``method``, ``hold``, ``band`` or ``delay``, spectral-only
        options with ``method="record"``, or a hold other than auto or
        continuous with a spectral method.
    InputError
        For bad records, or one too short for the resonance's bandwidth.
    """
    check_sweep_options(method, hold)
    if method != "record":
        from afmtool.estimators.sweep_spectral import sweep_frequency_response

        fr = sweep_frequency_response(
            dither, deflection, sample_rate_hz, method=method, segments=segments, nperseg=nperseg
        )
        return identify_sweep_response(fr, band=band, delay=delay)
    if segments is not None or nperseg is not None:
        raise ConfigError("segments and nperseg apply to method='h1' or 'stepped', not method='record'")
    band = _check_band(band)
    fit, chosen, reason, warnings = _record_route(dither, deflection, float(sample_rate_hz), delay, band, hold)
    return SweepIdentification(_sweep_model(fit), method, chosen, reason, fit, warnings)


def check_sweep_options(method: str, hold: str) -> None:
    """Raise ConfigError for a ``method`` or ``hold`` that :func:`identify_sweep` refuses (before any data is read)."""
    if method not in SWEEP_METHODS:
        raise ConfigError(f"method={method!r} must be one of {SWEEP_METHODS}")
    if hold != "auto" and hold not in HOLDS:
        raise ConfigError(f"hold={hold!r} must be 'auto' or one of {HOLDS}")
    if method != "record" and hold == "zoh":
        raise ConfigError(f"hold='zoh' needs method='record'; method={method!r} fits the continuous model")


def identify_sweep_response(fr, *, band: tuple[float, float] | None = None, delay: bool | float = True):
    """The spectral methods of :func:`identify_sweep` from a response already measured.

    ``fr`` is an H1 or stepped-sine :class:`~afmtool.estimators.frequency_response.FrequencyResponse`
    of the sweep (e.g. accumulated chunk by chunk); the delayed second-order
    model is fitted to it by
    :func:`~afmtool.estimators.sweep_spectral.free_air_from_response`.
    ``band`` and ``delay`` as in :func:`identify_sweep`.  The result carries
    ``fr`` as its ``response``.
    """
    from afmtool.estimators.sweep_spectral import free_air_from_response

    fit = free_air_from_response(fr, band=band, delay=delay)
    return SweepIdentification(
        _sweep_model(fit), fr.method, "continuous", "the spectral fit's delay absorbs any hold", fit, (), fr
    )


def _sweep_model(fit):
    """The FreeAirModel (``source="sweep"``) of a record or second-order fit."""
    from afmtool.models.free_air import FreeAirModel

    return FreeAirModel(
        f0_hz=fit.f0_hz,
        q=fit.q,
        gain=fit.gain,
        f0_std_hz=fit.f0_std_hz,
        q_std=fit.q_std,
        gain_std=fit.gain_std,
        source="sweep",
        delay_s=fit.delay_s,
    )


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
        As :func:`identify_sweep`: by
        default the whole-record fit (exact at any sweep rate) with the
        drive's hold told from its half-sample delay; ``method="h1"`` or
        ``"stepped"`` for :func:`~afmtool.estimators.sweep_spectral.spectral_sweep_fit`.

    Returns
    -------
    FreeAirModel
        ``source="sweep"``, f0, Q, gain (deflection units per dither unit)
        and ``delay_s`` with standard errors; no discrete numerator.
    """
    return identify_sweep(
        dither, deflection, sample_rate_hz, method=method, segments=segments, band=band, nperseg=nperseg,
        delay=delay, hold=hold,
    ).model
