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
from afmtool.estimators.spectral_checks import checked_signal
from afmtool.models.free_air import FreeAirModel

__all__ = [
    "BOLTZMANN_J_PER_K",
    "SYSTEMATIC_FACTOR",
    "ThermalFit",
    "ThermalVariant",
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
#: A spread over bands and weightings counts as systematic when it exceeds this many statistical
#: standard deviations: on clean simulated spectra noise alone moves the six fits by about one.
SYSTEMATIC_FACTOR = 2.0


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
    n_averages : float
        M, the Gamma shape of the bins: given, or (``n_averages_estimated``)
        estimated from the scatter about the fit.
    deviance, dof, p_value : float, int, float or None
        Goodness of fit: D = 2M·Σ(x − 1 − ln x) (eq. T.3) for ν = n − 4
        degrees of freedom, and P(χ²_ν > D) when M was given.
    dispersion, bin_correlation : float
        Pearson X²/ν and the residuals' correlation factor; the covariance is
        multiplied by max(1, dispersion)·bin_correlation.
    f0_spread_hz, q_spread, mean_square_spread_m2 : float
        Half the range of f0, Q and ⟨p²⟩ over ``variants``.
    f0_systematic_hz, q_systematic, spring_constant_systematic : float
        The spread where it exceeds ``SYSTEMATIC_FACTOR`` times the
        statistical std, else 0: the systematic uncertainty (Hz, –, N/m).
    variants : tuple of ThermalVariant
        The fits in half, the same and double the band, by ML and by linear
        least squares.

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
    n_averages: float = math.nan
    n_averages_estimated: bool = True
    deviance: float = math.nan
    dof: int = 0
    p_value: float | None = None
    dispersion: float = math.nan
    bin_correlation: float = 1.0
    f0_spread_hz: float = 0.0
    q_spread: float = 0.0
    f0_systematic_hz: float = 0.0
    q_systematic: float = 0.0
    mean_square_spread_m2: float = 0.0
    spring_constant_systematic: float | None = None
    variants: tuple = ()

    def warnings(self) -> list[str]:
        """What a user must know about this fit: a poor goodness of fit, a band- or weighting-dependent result."""
        out = []
        poor_fit = self.p_value is not None and self.p_value < 1e-3
        # a Hann window alone correlates neighbouring bins to a factor 1.94; independent bins give 1
        if poor_fit or self.bin_correlation > 3.0:
            fit = (f"deviance {self.deviance:.4g} for {self.dof} degrees of freedom, p = {self.p_value:.2g}"
                   if poor_fit else f"its residuals run in long stretches of one sign (correlation factor "
                   f"{self.bin_correlation:.3g})")
            out.append(
                f"the thermal peak is not a clean oscillator at its {self.n_averages:.4g} averages ({fit}); the "
                f"stated standard deviations are widened by {math.sqrt(max(1.0, self.dispersion) * self.bin_correlation):.3g}x"
            )
        if self.q_systematic or self.f0_systematic_hz or self.spring_constant_systematic:
            parts = [f"Q {min(v.q for v in self.variants):.4g}-{max(v.q for v in self.variants):.4g} "
                     f"(systematic +-{self.q_spread:.2g}, statistical +-{self.q_std:.2g})",
                     f"f0 +-{self.f0_spread_hz:.3g} Hz systematic (statistical +-{self.f0_std_hz:.2g})"]
            if self.spring_constant_systematic:
                parts.append(f"k +-{self.spring_constant_systematic:.2g} N/m systematic")
            out.append(
                "the thermal fit depends on the band and the weighting beyond its stated standard deviation: "
                + "; ".join(parts) + f" over {len(self.variants)} fits (half, same and double band; maximum "
                "likelihood and linear least squares)"
            )
        return out

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


class ThermalVariant(NamedTuple):
    """One refit for the systematic spread: its band (Hz), weighting, f0 (Hz), Q and ⟨p²⟩ (m²)."""

    band_hz: tuple[float, float]
    weighting: str
    f0_hz: float
    q: float
    mean_square_m2: float


class _Start(NamedTuple):
    f0_hz: float
    q: float
    dc_psd: float
    floor_psd: float


def _spectrum(frequency_hz, asd) -> tuple[np.ndarray, np.ndarray]:
    f = checked_signal("frequency_hz", frequency_hz)
    a = checked_signal("asd_m_per_sqrt_hz", asd)
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


class _Fit(NamedTuple):
    """One fit of the model in one band: parameters θ = (ln A, f0 (Hz), ln Q, ln W) and what came with them."""

    params: np.ndarray
    cov: np.ndarray  # covariance of θ, already inflated (Notes of fit_thermal_spectrum)
    n_bins: int
    rms_log: float
    deviance: float  # 2M·Σ(x − 1 − ln x), x = P/S (eq. T.3)
    pearson: float  # M·Σ(x − 1)²
    n_averages: float  # M used: given, or estimated from the scatter
    n_averages_estimated: bool
    bin_correlation: float  # 1 + 2·Σ_k ρ_k of the residuals x − 1, k = 1..3, at least 1

    @property
    def inflation(self) -> float:
        """The factor on the inverse information: max(1, X²/ν)·(1 + 2Σρ_k)."""
        return max(1.0, self.pearson / self.dof) * self.bin_correlation

    @property
    def start(self) -> _Start:
        ln_a, f0, ln_q, ln_w = self.params
        return _Start(float(f0), math.exp(ln_q), math.exp(ln_a), math.exp(ln_w))

    @property
    def dof(self) -> int:
        return max(self.n_bins - 4, 1)


def _model_and_gradient(f: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """S(f; θ) (eq. T.1) and ∂ln S/∂θ, θ = (ln A, f0, ln Q, ln W), shape (n, 4).

    With D = (f0² − f²)² + (f·f0/Q)² and the oscillator part O = A·f0⁴/D:
    ∂ln S/∂ln A = O/S, ∂ln S/∂f0 = (O/S)·(4/f0 − ∂D/∂f0 / D) with
    ∂D/∂f0 = 4f0(f0² − f²) + 2f²f0/Q², ∂ln S/∂ln Q = (O/S)·2(f·f0/Q)²/D and
    ∂ln S/∂ln W = W/S.
    """
    ln_a, f0, ln_q, ln_w = theta
    q, floor = math.exp(ln_q), math.exp(ln_w)
    f2 = f * f
    cross = (f * f0 / q) ** 2
    d = (f0 * f0 - f2) ** 2 + cross
    oscillator = math.exp(ln_a) * f0**4 / d
    s = oscillator + floor
    share = oscillator / s
    dd_df0 = 4.0 * f0 * (f0 * f0 - f2) + 2.0 * f2 * f0 / (q * q)
    gradient = np.column_stack([share, share * (4.0 / f0 - dd_df0 / d), share * 2.0 * cross / d, floor / s])
    return s, gradient


def _negative_log_likelihood(f: np.ndarray, psd: np.ndarray, theta: np.ndarray) -> float:
    """Σ(ln S + P/S) (eq. T.2 without the factor M and the constants)."""
    s, _ = _model_and_gradient(f, theta)
    return float(np.sum(np.log(s) + psd / s)) if np.all(s > 0) and np.all(np.isfinite(s)) else math.inf


def _fisher_scoring(f: np.ndarray, psd: np.ndarray, theta: np.ndarray, max_iterations: int = 100) -> np.ndarray:
    """Maximise the Gamma likelihood (eq. T.2) by Fisher scoring with step halving.

    The score is M·Jᵀ(x − 1) and the expected information M·JᵀJ, with
    J = ∂ln S/∂θ and x = P/S, so each step solves JᵀJ·Δ = Jᵀ(x − 1): an
    iteratively reweighted least-squares step, the weights 1/S² set by the
    model, never by the noisy data.
    """
    theta = np.array(theta, dtype=np.float64)
    cost = _negative_log_likelihood(f, psd, theta)
    for _ in range(max_iterations):
        s, jac = _model_and_gradient(f, theta)
        try:
            step = np.linalg.solve(jac.T @ jac, jac.T @ (psd / s - 1.0))
        except np.linalg.LinAlgError:
            break
        length = 1.0
        while length > 1e-8:
            trial = theta + length * step
            trial_cost = _negative_log_likelihood(f, psd, trial)
            if trial_cost <= cost:
                break
            length *= 0.5
        else:
            break
        theta, improvement, cost = trial, cost - trial_cost, trial_cost
        if improvement <= 1e-12 * max(1.0, abs(cost)):
            break
    return theta


def _residual_correlation(x: np.ndarray, lags: int = 3) -> float:
    """1 + 2·Σ_{k=1..lags} ρ_k of the residuals x − 1 (at least 1): the variance factor of correlated bins.

    A spectral window correlates neighbouring bins (Hann: ρ_1 ≈ 0.17 without
    overlap), and a peak the model does not follow leaves runs of residuals
    of one sign; either way the bins carry less information than as many
    independent ones, by this factor for short-range correlation.
    """
    r = x - 1.0
    denominator = float(r @ r)
    if r.size <= 4 * lags or denominator <= 0:
        return 1.0
    rho = [float(r[:-k] @ r[k:]) / denominator for k in range(1, lags + 1)]
    return max(1.0, 1.0 + 2.0 * sum(rho))


def _fit_ml(f: np.ndarray, psd: np.ndarray, start: _Start, n_averages: float | None,
            theta0: np.ndarray | None = None) -> _Fit:
    """The maximum-likelihood fit in the given bins (fit_thermal_spectrum, Notes).

    Started at ``theta0`` (a neighbouring band's fit), else at the log fit from ``start``.
    """
    theta = _fisher_scoring(f, psd, _log_fit_parameters(f, psd, start) if theta0 is None else theta0)
    s, jac = _model_and_gradient(f, theta)
    x = psd / s
    dof = max(f.size - 4, 1)
    sum_sq = float(np.sum((x - 1.0) ** 2))
    # without M: the Gamma shape from the scatter, Var(P/S) = 1/M
    averages = float(n_averages) if n_averages is not None else dof / max(sum_sq, 1e-300)
    pearson = averages * sum_sq
    correlation = _residual_correlation(x)
    inflation = max(1.0, pearson / dof) * correlation  # = _Fit.inflation
    try:
        cov = inflation * np.linalg.inv(averages * (jac.T @ jac))
    except np.linalg.LinAlgError:
        cov = np.full((4, 4), np.inf)
    deviance = 2.0 * averages * float(np.sum(x - 1.0 - np.log(x)))
    rms_log = math.sqrt(float(np.mean(np.log(x) ** 2)))
    return _Fit(theta, cov, f.size, rms_log, deviance, pearson, averages, n_averages is None, correlation)


def _log_fit_parameters(f: np.ndarray, psd: np.ndarray, start: _Start) -> np.ndarray:
    """Least squares on ln P − ln S over (ln A, f0/f0_start, ln Q, ln W): the start of the ML fit.

    Robust from a rough start (the log compresses the decades between peak
    and floor) and close to the ML fit, which it only starts.
    """
    log_psd = np.log(psd)
    unit = np.array([1.0, start.f0_hz, 1.0, 1.0])

    def residual(p):
        s, _ = _model_and_gradient(f, p * unit)
        with np.errstate(divide="ignore", invalid="ignore"):
            return log_psd - np.log(s)

    def jacobian(p):
        return -_model_and_gradient(f, p * unit)[1] * unit

    p0 = np.array([math.log(start.dc_psd), 1.0, math.log(start.q), math.log(start.floor_psd)])
    sol = scipy.optimize.least_squares(residual, p0, jac=jacobian, x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12)
    return sol.x * unit


def _fit_linear(f: np.ndarray, psd: np.ndarray, start: _Start) -> np.ndarray:
    """Unweighted least squares on P itself (the "linear" weighting a vendor's tune often uses): θ.

    Every bin counts the same in P, so the few bins at the peak dominate; it
    is one of the weightings whose spread is the systematic uncertainty.
    """
    scale = float(np.max(psd))
    theta0 = np.array([math.log(start.dc_psd), start.f0_hz, math.log(start.q), math.log(start.floor_psd)])
    unit = np.array([1.0, start.f0_hz, 1.0, 1.0])

    def residual(p):
        return (_model_and_gradient(f, theta0 + p * unit)[0] - psd) / scale

    def jacobian(p):
        s, gradient = _model_and_gradient(f, theta0 + p * unit)
        return s[:, None] * gradient * unit / scale  # ∂S/∂p = S·∂ln S/∂θ·∂θ/∂p

    sol = scipy.optimize.least_squares(residual, np.zeros(4), jac=jacobian, x_scale="jac", xtol=1e-12, ftol=1e-12)
    return theta0 + sol.x * np.array([1.0, start.f0_hz, 1.0, 1.0])


def fit_thermal_spectrum(frequency_hz, asd_m_per_sqrt_hz, *, band: tuple[float, float] | None = None,
                         temperature_k: float | None = 295.0, n_averages: float | None = None,
                         systematics: bool = True) -> ThermalFit:
    """Fit a simple harmonic oscillator plus a white floor to a thermal-noise spectrum by maximum likelihood.

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
    n_averages : float, optional
        Number M of averaged periodograms behind the spectrum (the Gamma
        shape of a bin: fewer than the segments where they overlap), if
        known; else M is estimated from the scatter of the bins about the fit.
    systematics : bool, optional
        Refit in half and double the band and with the linear weighting, and
        report their spread (Notes).

    Returns
    -------
    ThermalFit

    Notes
    -----
    Model (PSD, m²/Hz), eq. T.1:
    S(f) = A·f0⁴/((f0² − f²)² + (f·f0/Q)²) + W (:func:`sho_psd`), the squared
    |G(j2πf)| of eq. 3.1 driven by white thermal force noise, on a white
    detector floor.

    *Likelihood.*  A bin of an average of M periodograms is P = S·χ²_{2M}/(2M),
    a Gamma(M, S/M) variate, so (eq. T.2)

    .. math:: -\\ln L = M\\sum_i\\left(\\ln S_i + P_i/S_i\\right) + \\text{const},

    maximised over θ = (ln A, f0, ln Q, ln W) by Fisher scoring
    (:func:`_fisher_scoring`), started from a least-squares fit of ln P.  The
    ML estimate does not depend on M and has no log bias.  Its covariance is
    the inverse expected information (M·JᵀJ)⁻¹, J = ∂ln S/∂θ, multiplied by
    the dispersion max(1, X²/ν) (Pearson X² = M·Σ(x − 1)², x = P/S, ν = n − 4)
    and by the bins' correlation 1 + 2Σρ_k (:func:`_residual_correlation`).
    Goodness of fit: the deviance (eq. T.3)
    D = 2M·Σ(x − 1 − ln x), nearly χ²_ν for a clean oscillator, independent
    bins and large M; its p-value (:func:`_deviance_p_value`) is given when M is.

    *Band.*  By default f0 ± δ, where the oscillator part falls to 10 % of the
    floor, from an initial guess, then from the first fit (``_auto_band``).

    *Systematic uncertainty* (:func:`_variants`, :func:`_spread`): the spread
    of the fit over half and double the band and the linear weighting.

    *Spring constant.*  k = k_B·T/⟨p²⟩, ⟨p²⟩ = (π/2)·A·f0·Q, one-mode
    equipartition of the tip displacement; see :class:`ThermalFit`.

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
    fit_band, result = _fit_main(f, psd, positive, band, n_averages)
    limits = (_auto_skip_hz(f), float(f[-1]))
    variants = _variants(f, psd, positive, fit_band, limits, result, n_averages) if systematics else ()
    return _thermal_fit(result, fit_band, temperature_k, variants)


def _fit_main(f, psd, positive, band, n_averages) -> tuple[tuple[float, float], _Fit]:
    """(band, ML fit) in the given band, or in the automatic one: from the initial guess, then from that fit."""
    lo_hz, hi_hz = (_auto_skip_hz(f), float(f[-1])) if band is None else _check_band(band, f)
    region = positive & (f >= lo_hz) & (f <= hi_hz)
    if np.count_nonzero(region) < 8:
        raise InputError(
            f"only {np.count_nonzero(region)} usable bins in {lo_hz:g}–{hi_hz:g} Hz; at least 8 are needed"
        )
    start = _initial_guess(f[region], psd[region])
    if band is not None:
        return (lo_hz, hi_hz), _fit_in_band(f, psd, positive, (lo_hz, hi_hz), start, n_averages)
    first = _fit_in_band(f, psd, positive, _auto_band(start, lo_hz, hi_hz), start, n_averages)
    fit_band = _auto_band(first.start, lo_hz, hi_hz)
    return fit_band, _fit_in_band(f, psd, positive, fit_band, first.start, n_averages)


def _check_thermal_options(temperature_k, n_averages) -> None:
    """ConfigError unless T is a finite number > 0 or None, and M a number >= 1 or None (Welch's M is not whole)."""
    valid_temperature = _is_real(temperature_k) and math.isfinite(temperature_k) and temperature_k > 0
    if temperature_k is not None and not valid_temperature:
        raise ConfigError(f"temperature_k={temperature_k!r} must be a finite number > 0 or None")
    if n_averages is not None and not (_is_real(n_averages) and math.isfinite(n_averages) and n_averages >= 1):
        raise ConfigError(f"n_averages={n_averages!r} must be a number >= 1 or None")


def _fit_in_band(f, psd, positive, band: tuple[float, float], start: _Start, n_averages: float | None) -> _Fit:
    in_band = positive & (f >= band[0]) & (f <= band[1])
    if np.count_nonzero(in_band) < 8:
        raise InputError(
            f"only {np.count_nonzero(in_band)} usable bins in the band {band[0]:g}–{band[1]:g} Hz; "
            "at least 8 are needed (give band, or a finer spectrum)"
        )
    return _fit_ml(f[in_band], psd[in_band], start, n_averages)


def _variants(f, psd, positive, band, limits, main: _Fit, n_averages) -> tuple[ThermalVariant, ...]:
    """The fit in half, the same and double the band about f0, by ML and by linear least squares.

    A real peak is rarely a clean oscillator (asymmetric wings, a resonance
    drifting during the averaging), and then f0, Q and k depend on the band
    and on how the bins are weighted; half the range of these six fits is
    their spread, systematic where it exceeds what noise alone explains
    (:func:`_spread`).
    """
    f0 = float(main.params[1])
    found = []
    for scale in (0.5, 1.0, 2.0):
        lo = max(f0 - scale * (f0 - band[0]), limits[0])
        hi = min(f0 + scale * (band[1] - f0), limits[1])
        in_band = positive & (f >= lo) & (f <= hi)
        if np.count_nonzero(in_band) < 8:
            continue
        fb, pb = f[in_band], psd[in_band]
        for weighting in ("maximum likelihood", "linear least squares"):
            if weighting == "maximum likelihood":
                theta = main.params if scale == 1.0 else _fit_ml(fb, pb, main.start, n_averages, main.params).params
            else:
                try:
                    theta = _fit_linear(fb, pb, main.start)
                except (ValueError, ArithmeticError):
                    continue
            ln_a, f0_v, ln_q, _ = theta
            if np.all(np.isfinite(theta)) and f0_v > 0:
                mean_square = 0.5 * math.pi * math.exp(ln_a) * f0_v * math.exp(ln_q)
                found.append(ThermalVariant((float(lo), float(hi)), weighting, float(f0_v), math.exp(ln_q),
                                            mean_square))
    return tuple(found)


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


def _spread(values, std: float) -> tuple[float, float]:
    """(half the range of ``values``, the systematic part: that half range where it exceeds SYSTEMATIC_FACTOR·std).

    ``std`` is the standard deviation noise alone would give, (M·JᵀJ)⁻¹ not
    widened by the misfit, so a peak that is not a clean oscillator shows as
    a systematic spread even where its widened statistical std is large.  On
    clean simulated spectra the six fits' half range exceeds 2σ in about 5 %
    of cases (``SYSTEMATIC_FACTOR``).
    """
    values = [v for v in values if math.isfinite(v)]
    half = 0.5 * (max(values) - min(values)) if len(values) > 1 else 0.0
    return half, (half if half > SYSTEMATIC_FACTOR * std else 0.0)


def _deviance_p_value(deviance: float, dof: int, averages: float) -> float:
    """P(D' > D) for the deviance of ``dof`` independent Gamma(M) bins, in its normal approximation.

    Per bin, d = 2M(x − 1 − ln x) with x ~ Gamma(M, 1/M) has mean
    2M(ln M − ψ(M)) and variance 4M²(ψ′(M) − 1/M) (from E[x] = 1,
    Var x = 1/M, Var ln x = ψ′(M), Cov(x, ln x) = 1/M); both tend to the
    χ²₁ values 1 and 2 for large M, but at M = 2 the mean is 1.08, so the
    plain χ²_ν tail would call a clean spectrum a poor fit.
    """
    mean = 2.0 * averages * (math.log(averages) - float(scipy.special.digamma(averages)))
    variance = 4.0 * averages * averages * (float(scipy.special.polygamma(1, averages)) - 1.0 / averages)
    z = (deviance - dof * mean) / math.sqrt(max(dof * variance, 1e-300))
    return 0.5 * math.erfc(z / math.sqrt(2.0))


def _thermal_fit(result: _Fit, band, temperature_k, variants) -> ThermalFit:
    ln_a, f0, ln_q, ln_w = result.params
    cov = result.cov
    q = math.exp(ln_q)
    floor_asd = math.exp(ln_w / 2)
    peak_asd = math.exp(ln_a / 2) * q
    # d ln(√A·Q) = ½ d ln A + d ln Q;  d ln⟨p²⟩ = d ln A + d f0/f0 + d ln Q
    grad_peak = np.array([0.5, 0.0, 1.0, 0.0])
    grad_ms = np.array([1.0, 1.0 / f0, 1.0, 0.0])
    rel_peak = math.sqrt(max(float(grad_peak @ cov @ grad_peak), 0.0))
    rel_ms = math.sqrt(max(float(grad_ms @ cov @ grad_ms), 0.0))
    mean_square = 0.5 * math.pi * math.exp(ln_a) * f0 * q
    f0_std, q_std = math.sqrt(max(cov[1, 1], 0.0)), q * math.sqrt(max(cov[2, 2], 0.0))
    noise = 1.0 / math.sqrt(result.inflation)
    f0_spread, f0_sys = _spread([v.f0_hz for v in variants], noise * f0_std)
    q_spread, q_sys = _spread([v.q for v in variants], noise * q_std)
    ms_spread, ms_sys = _spread([v.mean_square_m2 for v in variants], noise * rel_ms * mean_square)
    k = k_std = k_sys = None
    if temperature_k is not None:
        k = BOLTZMANN_J_PER_K * temperature_k / mean_square
        k_std, k_sys = k * rel_ms, k * ms_sys / mean_square
    dof = result.dof
    p_value = None if result.n_averages_estimated else _deviance_p_value(result.deviance, dof, result.n_averages)
    return ThermalFit(
        f0_hz=float(f0), q=q, floor_asd_m_per_sqrt_hz=floor_asd, peak_asd_m_per_sqrt_hz=peak_asd,
        band_hz=(float(band[0]), float(band[1])), n_bins=result.n_bins, f0_std_hz=f0_std, q_std=q_std,
        floor_asd_std=0.5 * floor_asd * math.sqrt(max(cov[3, 3], 0.0)), peak_asd_std=peak_asd * rel_peak,
        mean_square_m2=mean_square, spring_constant_n_per_m=k, spring_constant_std=k_std,
        temperature_k=None if temperature_k is None else float(temperature_k), rms_log_residual=result.rms_log,
        n_averages=result.n_averages, n_averages_estimated=result.n_averages_estimated,
        deviance=result.deviance, dof=dof, p_value=p_value, dispersion=result.pearson / dof,
        bin_correlation=result.bin_correlation, f0_spread_hz=f0_spread, q_spread=q_spread,
        f0_systematic_hz=f0_sys, q_systematic=q_sys, mean_square_spread_m2=ms_spread,
        spring_constant_systematic=k_sys, variants=variants,
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
