"""Free-air identification from a thermal-noise spectrum (the "thermal" route).

Without a drive, the first mode of the cantilever is excited by thermal
(Langevin) force noise, which is white, so the deflection's power spectral
density near the resonance is the squared magnitude of G(s) of eq. 3.1 times
a constant, plus the white floor of the detector:

.. math:: S(f) = A\\,\\frac{f_0^4}{(f_0^2 - f^2)^2 + (f f_0/Q)^2} + W,

with A the low-frequency level of the oscillator part (m²/Hz) and W the floor
(m²/Hz).  Fitting S gives f0 and Q; the area of the oscillator part gives the
mean-square thermal deflection ⟨p²⟩ = (π/2)·A·f0·Q and, by equipartition
(k⟨p²⟩ = k_B·T), the spring constant.  :func:`afmtool.io.psd.read_psd_csv` reads the
``--psd FILE.csv`` table.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import scipy.optimize
import scipy.signal
import scipy.special

from afmtool.errors import ConfigError, InputError
from afmtool.models.free_air import FreeAirModel

__all__ = [
    "BOLTZMANN_J_PER_K",
    "ThermalFit",
    "fit_thermal_spectrum",
    "free_air_from_thermal",
    "sho_psd",
]

#: Boltzmann constant k_B, J/K (exact, SI 2019).
BOLTZMANN_J_PER_K = 1.380649e-23

#: Bins below max(10 bins, f_max/200) are skipped by the automatic band
#: (the near-DC instrument artefacts and 1/f rise of a real spectrum).
_SKIP_BINS = 10
_SKIP_FRACTION = 1.0 / 200.0
#: The automatic band reaches out to where the oscillator part has fallen to
#: this fraction of the floor, ...
_BAND_FLOOR_FRACTION = 0.1
#: ... but at least this many half-widths f0/(2Q) and at most f0/2 either side.
_BAND_MIN_HALF_WIDTHS = 10.0
_BAND_MAX_FRACTION_OF_F0 = 0.5
#: Bins of the median filter that smooths log S before the peak search.
_SMOOTH_BINS = 5


def _is_real(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


def sho_psd(frequency_hz, f0_hz: float, q: float, dc_psd: float, floor_psd: float = 0.0) -> np.ndarray:
    """Oscillator-plus-floor PSD S(f) = A·f0⁴/((f0² − f²)² + (f·f0/Q)²) + W.

    Parameters
    ----------
    frequency_hz : array_like
        f, Hz.
    f0_hz, q : float
        Resonance f0 (Hz) and quality factor Q.
    dc_psd : float
        A, the oscillator part at f = 0, (units)²/Hz.
    floor_psd : float, optional
        W, the white floor, (units)²/Hz.

    Returns
    -------
    numpy.ndarray
        S(f), (units)²/Hz.  Its oscillator part is A·|G(j2πf)|² for the G of
        eq. 3.1, A·Q² at f0, and integrates to (π/2)·A·f0·Q over f ≥ 0.
    """
    f = np.asarray(frequency_hz, dtype=np.float64)
    f02 = f0_hz * f0_hz
    # A fit's trial parameters (or a hostile spectrum's frequencies) can reach inf/NaN; callers
    # check finiteness, so numpy's warnings would only be noise on the user's terminal.
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
        return dc_psd * f02 * f02 / ((f02 - f * f) ** 2 + (f * f0_hz / q) ** 2) + floor_psd


@dataclass(frozen=True)
class ThermalFit:
    """Simple-harmonic-oscillator fit to a thermal-noise spectrum.

    Parameters
    ----------
    f0_hz, q : float
        Resonance (Hz) and quality factor.
    floor_asd_m_per_sqrt_hz : float
        √W, the white floor, m/√Hz.
    peak_asd_m_per_sqrt_hz : float
        √A·Q, the oscillator part at f0, m/√Hz.
    band_hz : (float, float)
        The fitted band, Hz.
    n_bins : int
        Bins in the band.
    f0_std_hz, q_std, floor_asd_std, peak_asd_std : float
        One-standard-deviation errors (from the fit's Jacobian, scaled by the
        residual variance; adjacent bins are treated as independent).
    mean_square_m2 : float
        ⟨p²⟩ = (π/2)·A·f0·Q, the oscillator part's area, m².
    spring_constant_n_per_m, spring_constant_std : float or None
        k = k_B·T/⟨p²⟩ (N/m) and its error; None without a temperature.
    temperature_k : float or None
        T used for k, K.
    rms_log_residual : float
        RMS of ln S_measured − ln S_model over the band (≈ 1/√M for M
        averages when the model fits).

    Notes
    -----
    Spring constant.  k = k_B·T/⟨p²⟩ with ⟨p²⟩ = (π/2)·A·f0·Q, the area of
    the oscillator part (the floor excluded).  This assumes the spectrum is
    the **actual displacement of the tip in the first mode**, in metres,
    i.e. that the detector's deflection sensitivity has been calibrated
    (e.g. from a force curve on a hard sample) and converted to tip
    displacement.  For an optical-lever spectrum calibrated by a static force
    curve, the first mode's slope differs from the static one, and Butt &
    Jaschke (1995) give k = 0.817·k_B·T/⟨p*²⟩; for an interferometric tip
    displacement, where mode 1 holds 97.1 % of the energy, k = 0.971·k_B·T/⟨p²⟩.
    Neither factor is applied here (k is the plain one-mode equipartition of
    :class:`afmtool.models.cantilever.Cantilever`); ``identify freeair --psd``
    applies them through :mod:`afmtool.estimators.spring_constant`.
    """

    f0_hz: float
    q: float
    floor_asd_m_per_sqrt_hz: float
    peak_asd_m_per_sqrt_hz: float
    band_hz: tuple[float, float]
    n_bins: int
    f0_std_hz: float
    q_std: float
    floor_asd_std: float
    peak_asd_std: float
    mean_square_m2: float
    spring_constant_n_per_m: float | None
    spring_constant_std: float | None
    temperature_k: float | None
    rms_log_residual: float

    @property
    def dc_psd(self) -> float:
        """A = (peak ASD/Q)², m²/Hz."""
        return (self.peak_asd_m_per_sqrt_hz / self.q) ** 2

    @property
    def peak_to_floor_db(self) -> float:
        """10·log10(A·Q²/W): how far the peak stands above the floor, dB."""
        return 20.0 * math.log10(self.peak_asd_m_per_sqrt_hz / self.floor_asd_m_per_sqrt_hz)

    def psd(self, frequency_hz) -> np.ndarray:
        """Fitted S(f), m²/Hz (:func:`sho_psd`)."""
        return sho_psd(frequency_hz, self.f0_hz, self.q, self.dc_psd, self.floor_asd_m_per_sqrt_hz**2)

    def asd(self, frequency_hz) -> np.ndarray:
        """Fitted √S(f), m/√Hz."""
        return np.sqrt(self.psd(frequency_hz))

    def free_air_model(self) -> FreeAirModel:
        """The free-air model of this fit: ``source="thermal"``, gain 1.

        A thermal spectrum has no drive, so it says nothing about the gain
        from the dither to the deflection; gain is 1.0 (G of eq. 3.1 with
        unit DC gain) and ``gain_std`` None.  Supply the gain from a sweep or
        an off-sample segment where REEP's numerator needs it.
        """
        return FreeAirModel(
            f0_hz=self.f0_hz,
            q=self.q,
            gain=1.0,
            f0_std_hz=self.f0_std_hz,
            q_std=self.q_std,
            gain_std=None,
            source="thermal",
        )


class _Start(NamedTuple):
    f0_hz: float
    q: float
    dc_psd: float
    floor_psd: float


def _spectrum(frequency_hz, asd) -> tuple[np.ndarray, np.ndarray]:
    def array(name, values):
        try:
            arr = np.array(values, dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError(f"{name} must be a 1-D array of numbers") from None
        if arr.ndim != 1:
            raise InputError(f"{name} must be 1-D, got shape {arr.shape}")
        if not np.all(np.isfinite(arr)):
            bad = int(np.flatnonzero(~np.isfinite(arr))[0])
            raise InputError(f"{name} has a non-finite value at index {bad}")
        return arr

    f = array("frequency_hz", frequency_hz)
    a = array("asd_m_per_sqrt_hz", asd)
    if f.shape != a.shape:
        raise InputError(f"frequency_hz and asd_m_per_sqrt_hz differ in length: {f.size} and {a.size}")
    if f.size < 8:
        raise InputError(f"the spectrum has {f.size} bins; at least 8 are needed")
    if np.any(np.diff(f) <= 0):
        raise InputError("frequency_hz must be strictly increasing")
    if f[0] < 0 or np.any(a < 0):
        raise InputError("frequency_hz and asd_m_per_sqrt_hz must be >= 0")
    return f, a


def _auto_skip_hz(f: np.ndarray) -> float:
    df = float(np.median(np.diff(f)))
    return max(f[0] + _SKIP_BINS * df, f[-1] * _SKIP_FRACTION)


def _initial_guess(f: np.ndarray, psd: np.ndarray) -> _Start:
    """f0 from the most prominent peak, W from the median level, Q from the −3 dB width.

    Only positive PSD values are passed in.  The peak search runs on log S
    median-filtered over 5 bins; the floor is the median of S over
    [f_peak/2, 3f_peak/2]; the width is where S − W falls to half of its
    peak value (linear interpolation between bins), Q = f_peak/width.
    """
    log_s = scipy.signal.medfilt(np.log(psd), _SMOOTH_BINS) if psd.size >= _SMOOTH_BINS else np.log(psd)
    peaks, props = scipy.signal.find_peaks(log_s, prominence=0.0)
    if peaks.size == 0:
        raise InputError("the spectrum has no resonance peak in the band")
    k = int(peaks[np.argmax(props["prominences"])])
    f_peak = float(f[k])
    near = (f >= 0.5 * f_peak) & (f <= 1.5 * f_peak)
    floor = float(np.median(psd[near]))
    smooth = np.exp(log_s)
    height = smooth[k] - floor
    if height <= 0:
        raise InputError(f"the peak at {f_peak:g} Hz does not rise above the floor")
    excess = smooth - floor
    above = excess > height / 2
    lo = k
    while lo > 0 and above[lo - 1]:
        lo -= 1
    hi = k
    while hi < f.size - 1 and above[hi + 1]:
        hi += 1
    df = float(np.median(np.diff(f)))
    width = _half_crossing(f, excess, height / 2, hi, hi + 1) - _half_crossing(f, excess, height / 2, lo, lo - 1)
    q = max(f_peak / max(width, df / 2), 0.6)
    return _Start(f_peak, q, height / (q * q), floor)


def _half_crossing(f: np.ndarray, excess: np.ndarray, half: float, inner: int, outer: int) -> float:
    """Frequency (Hz) where ``excess`` falls to ``half`` between bin ``inner`` (above) and ``outer``."""
    if outer < 0 or outer >= f.size:
        return float(f[inner])
    span = excess[inner] - excess[outer]
    frac = float(np.clip((excess[inner] - half) / span, 0.0, 1.0)) if span > 0 else 0.5
    return float(f[inner] + frac * (f[outer] - f[inner]))


def _auto_band(start: _Start, f_lo: float, f_hi: float) -> tuple[float, float]:
    """f0 ± δ with δ where the oscillator part falls to 10 % of the floor (Lorentzian wings).

    Near f0, A·L(f) ≈ A·Q²/(1 + (2Q(f − f0)/f0)²), which equals r·W at
    δ = (f0/2Q)·√(A·Q²/(r·W) − 1).  δ is kept within [10·f0/(2Q), f0/2].

    The band of :func:`fit_thermal_spectrum`, in full: bins below
    max(10 bins, f_max/200) are skipped (near-DC
    artefacts, 1/f rise).  The peak is the most prominent one of the
    median-filtered log S; W0 is the median of S over [f_peak/2, 3f_peak/2];
    Q0 = f_peak/Δf_{−3 dB} from the width at half the height above W0.  The
    band is f0 ± δ where the oscillator part falls to 10 % of the floor,
    δ = (f0/2Q)·√(A·Q²/(0.1·W) − 1), kept within [10·f0/(2Q), f0/2]: wide
    enough to pin the floor, narrow enough to keep other modes and the 1/f
    rise out.  After a first fit the band is recomputed from the fitted
    parameters and the fit repeated once.
    """
    half_width = start.f0_hz / (2 * start.q)
    ratio = start.dc_psd * start.q**2 / max(start.floor_psd, 1e-300) / _BAND_FLOOR_FRACTION
    delta = half_width * math.sqrt(max(ratio - 1.0, 0.0))
    delta = min(max(delta, _BAND_MIN_HALF_WIDTHS * half_width), _BAND_MAX_FRACTION_OF_F0 * start.f0_hz)
    return max(start.f0_hz - delta, f_lo), min(start.f0_hz + delta, f_hi)


class _LogFit(NamedTuple):
    params: np.ndarray  # ln A, f0 (Hz), ln Q, ln W
    cov: np.ndarray  # covariance of (ln A, f0, ln Q, ln W)
    rms: float
    n_bins: int

    @property
    def start(self) -> _Start:
        ln_a, f0, ln_q, ln_w = self.params
        return _Start(float(f0), math.exp(ln_q), math.exp(ln_a), math.exp(ln_w))


def _fit_log_psd(f: np.ndarray, psd: np.ndarray, start: _Start) -> _LogFit:
    """Least squares on ln S − ln S_model over (ln A, f0, ln Q, ln W)."""
    log_psd = np.log(psd)
    f0_scale = start.f0_hz

    def model(p):
        return sho_psd(f, p[1] * f0_scale, math.exp(p[2]), math.exp(p[0]), math.exp(p[3]))

    def residual(p):
        return log_psd - np.log(model(p))

    p0 = np.array([math.log(start.dc_psd), 1.0, math.log(start.q), math.log(start.floor_psd)])
    sol = scipy.optimize.least_squares(residual, p0, x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12)
    dof = max(f.size - p0.size, 1)
    s2 = float(np.dot(sol.fun, sol.fun)) / dof
    cov = s2 * np.linalg.pinv(sol.jac.T @ sol.jac)
    scale = np.array([1.0, f0_scale, 1.0, 1.0])
    params = sol.x * scale
    return _LogFit(params, cov * np.outer(scale, scale), math.sqrt(float(np.mean(sol.fun**2))), f.size)


def fit_thermal_spectrum(frequency_hz, asd_m_per_sqrt_hz, *, band: tuple[float, float] | None = None,
                         temperature_k: float | None = 295.0, n_averages: int | None = None) -> ThermalFit:
    """Fit a simple harmonic oscillator plus a white floor to a thermal-noise spectrum.

    Parameters
    ----------
    frequency_hz : array_like
        Bin frequencies, Hz, strictly increasing, ≥ 0.
    asd_m_per_sqrt_hz : array_like
        Amplitude spectral density of the deflection, m/√Hz (one-sided).
    band : (float, float), optional
        Band to fit, Hz.  Default: chosen automatically (Notes).
    temperature_k : float or None, optional
        Temperature T for the equipartition spring constant, K; None to skip k.
    n_averages : int, optional
        Number of averaged periodograms M behind the spectrum, if known; used
        only to remove the bias of the log fit from A and W (Notes).

    Returns
    -------
    ThermalFit

    Notes
    -----
    Model (PSD, m²/Hz): S(f) = A·f0⁴/((f0² − f²)² + (f·f0/Q)²) + W
    (:func:`sho_psd`), i.e. the squared |G(j2πf)| of eq. 3.1 driven by white
    thermal force noise, on a white detector floor.

    *Band.*  By default f0 ± δ, where the oscillator part falls to 10 % of the
    floor, from an initial guess, then from the first fit (``_auto_band``).

    *Estimator.*  Least squares on ln S, parameters (ln A, f0, ln Q, ln W),
    by :func:`scipy.optimize.least_squares`.  Why the log: an averaged
    periodogram bin is S·χ²_{2M}/(2M), so its relative scatter is the same
    in every bin and ln S has constant variance ψ′(M) ≈ 1/M: unweighted
    least squares on ln S is then (nearly) the weighted maximum-likelihood
    fit, without weights that depend on the noisy data (which bias a PSD
    fit low), and peak and floor, decades apart, are equally represented.
    The log's bias E[ln χ²_{2M}/2M] = ψ(M) − ln M is the same in every bin,
    a constant factor on S that leaves f0 and Q unbiased and
    scales A and W by e^{ψ(M) − ln M} (≈ 1 − 1/(2M)); with ``n_averages``
    A and W are corrected for it.  Errors: cov = s²·(JᵀJ)⁻¹, s² the residual
    variance; bins correlated by a spectral window make them optimistic.
    A real peak that is not a clean oscillator (asymmetric wings, a
    resonance drifting during the averaging) shows as ``rms_log_residual``
    well above 1/√M, and then Q depends on the band.

    *Spring constant.*  k = k_B·T/⟨p²⟩, one-mode equipartition of the tip
    displacement; see :class:`ThermalFit` for what the spectrum must be.

    Raises
    ------
    ConfigError
        For a bad ``band``, ``temperature_k`` or ``n_averages``.
    InputError
        For a bad spectrum, no peak, or fewer than 8 usable bins in the band.
    """
    f, asd = _spectrum(frequency_hz, asd_m_per_sqrt_hz)
    _check_thermal_options(temperature_k, n_averages)
    psd = asd * asd
    positive = psd > 0
    if band is None:
        lo_hz, hi_hz = _auto_skip_hz(f), float(f[-1])
    else:
        lo_hz, hi_hz = _check_band(band, f)
    region = positive & (f >= lo_hz) & (f <= hi_hz)
    if np.count_nonzero(region) < 8:
        raise InputError(
            f"only {np.count_nonzero(region)} usable bins in {lo_hz:g}–{hi_hz:g} Hz; at least 8 are needed"
        )
    start = _initial_guess(f[region], psd[region])
    if band is None:
        # band from the initial guess, fit, then band from that fit and fit again
        first = _fit_in_band(f, psd, positive, _auto_band(start, lo_hz, hi_hz), start)
        fit_band = _auto_band(first.start, lo_hz, hi_hz)
        result = _fit_in_band(f, psd, positive, fit_band, first.start)
    else:
        fit_band = (lo_hz, hi_hz)
        result = _fit_in_band(f, psd, positive, fit_band, start)
    return _thermal_fit(result, fit_band, temperature_k, n_averages)


def _check_thermal_options(temperature_k, n_averages) -> None:
    """ConfigError unless T is a finite number > 0 or None, and M an integer >= 1 or None."""
    valid_temperature = _is_real(temperature_k) and math.isfinite(temperature_k) and temperature_k > 0
    if temperature_k is not None and not valid_temperature:
        raise ConfigError(f"temperature_k={temperature_k!r} must be a finite number > 0 or None")
    if n_averages is not None and not (
        isinstance(n_averages, numbers.Integral) and not isinstance(n_averages, bool) and n_averages >= 1
    ):
        raise ConfigError(f"n_averages={n_averages!r} must be an integer >= 1 or None")


def _fit_in_band(f, psd, positive, band: tuple[float, float], start: _Start) -> _LogFit:
    in_band = positive & (f >= band[0]) & (f <= band[1])
    if np.count_nonzero(in_band) < 8:
        raise InputError(
            f"only {np.count_nonzero(in_band)} usable bins in the band {band[0]:g}–{band[1]:g} Hz; "
            "at least 8 are needed (give band, or a finer spectrum)"
        )
    return _fit_log_psd(f[in_band], psd[in_band], start)


def _check_band(band, f: np.ndarray) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in band)
    except (TypeError, ValueError):
        raise ConfigError(f"band={band!r} must be a pair (low_hz, high_hz)") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo < hi):
        raise ConfigError(f"band={band!r} must satisfy 0 <= low_hz < high_hz")
    if hi < f[0] or lo > f[-1]:
        raise ConfigError(f"band={band!r} lies outside the spectrum ({f[0]:g}–{f[-1]:g} Hz)")
    return lo, hi


def _thermal_fit(result: _LogFit, band, temperature_k, n_averages) -> ThermalFit:
    ln_a, f0, ln_q, ln_w = result.params
    if n_averages is not None:
        # E[ln(S·χ²_2M/2M)] = ln S + ψ(M) − ln M: undo the constant log bias
        correction = math.log(n_averages) - float(scipy.special.digamma(n_averages))
        ln_a += correction
        ln_w += correction
    cov = result.cov
    q = math.exp(ln_q)
    floor_asd = math.exp(ln_w / 2)
    peak_asd = math.exp(ln_a / 2) * q
    # d ln(√A·Q) = ½ d ln A + d ln Q
    grad_peak = np.array([0.5, 0.0, 1.0, 0.0])
    # d ln⟨p²⟩ = d ln A + d f0/f0 + d ln Q
    grad_ms = np.array([1.0, 1.0 / f0, 1.0, 0.0])
    rel_peak = math.sqrt(max(float(grad_peak @ cov @ grad_peak), 0.0))
    rel_ms = math.sqrt(max(float(grad_ms @ cov @ grad_ms), 0.0))
    mean_square = 0.5 * math.pi * math.exp(ln_a) * f0 * q
    if temperature_k is not None:
        k = BOLTZMANN_J_PER_K * temperature_k / mean_square
        k_std = k * rel_ms
    else:
        k = k_std = None
    return ThermalFit(
        f0_hz=float(f0),
        q=q,
        floor_asd_m_per_sqrt_hz=floor_asd,
        peak_asd_m_per_sqrt_hz=peak_asd,
        band_hz=(float(band[0]), float(band[1])),
        n_bins=result.n_bins,
        f0_std_hz=math.sqrt(max(cov[1, 1], 0.0)),
        q_std=q * math.sqrt(max(cov[2, 2], 0.0)),
        floor_asd_std=0.5 * floor_asd * math.sqrt(max(cov[3, 3], 0.0)),
        peak_asd_std=peak_asd * rel_peak,
        mean_square_m2=mean_square,
        spring_constant_n_per_m=k,
        spring_constant_std=k_std,
        temperature_k=None if temperature_k is None else float(temperature_k),
        rms_log_residual=result.rms,
    )


def free_air_from_thermal(
    frequency_hz,
    asd_m_per_sqrt_hz,
    *,
    band: tuple[float, float] | None = None,
) -> FreeAirModel:
    """Free-air model from a thermal-noise spectrum (``source="thermal"``).

    Parameters
    ----------
    frequency_hz, asd_m_per_sqrt_hz, band
        As :func:`fit_thermal_spectrum`.

    Returns
    -------
    FreeAirModel
        f0 and Q with their errors; gain 1.0 and ``gain_std`` None, because a
        thermal spectrum has no drive and so carries no drive-to-deflection
        gain (see :meth:`ThermalFit.free_air_model`).  Use
        :func:`fit_thermal_spectrum` directly for the floor, the spring
        constant and the band.
    """
    return fit_thermal_spectrum(frequency_hz, asd_m_per_sqrt_hz, band=band, temperature_k=None).free_air_model()
