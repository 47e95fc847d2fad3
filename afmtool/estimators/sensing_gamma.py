"""The sensing transfer function Γ_IR,ts with feed-through removal (thesis §6.6.1, eqs. 6.15, 6.16).

From a sweep of V_sub near the sample (channels ``v_sub``,
``thermal_current``, ``deflection``) and one with the tip in contact
(``v_sub``, ``thermal_current``):

* Γ_IR,V: V_sub → I_R near the sample;
* Γ_ts,V: V_sub → t_s, from the optical deflection (Δt_s = Δp, the sample
  does not move);
* Γ_sp: V_sub → I_R in contact (Δt_s = 0), the direct feed-through of
  Fig. 6.17;
* Γ_IR,ts = (Γ_IR,V − Γ_sp)/Γ_ts,V (eq. 6.15), and the uncorrected
  Γ_IR,V/Γ_ts,V (eq. 6.16), whose magnitude rises falsely at high frequency.

The frequency responses come from :mod:`afmtool.estimators.frequency_response`
(H1, streamed chunk by chunk through :class:`H1Accumulator`, or lock-in sums
per stepped-sine segment), as a stage of :func:`afmtool.pipeline.run_stream`
(:func:`gamma_response_stage`).  Units are brought to µA, nm and V, so Γ_IR,ts is in
µA/nm, Γ_IR,V and Γ_sp in µA/V and Γ_ts,V in nm/V.  Nothing here reads or
writes files; :mod:`afmtool.analyses.gamma_outputs` does.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from afmtool.errors import ConfigError, InputError
from afmtool.estimators.frequency_response import FrequencyResponse
from afmtool.estimators.stages import ResponseStage, run_stages
from afmtool.estimators.stepped_sine import SineSegment, detect_segments
from afmtool.estimators.sweep_spectral import default_nperseg
from afmtool.estimators.transfer_function_fit import TransferFunctionFit, fit_transfer_function

if TYPE_CHECKING:  # an annotation only: estimators take chunks, they do not read captures
    from afmtool.io.capture import Chunk

__all__ = [
    "UNIT_SCALES",
    "CANONICAL_UNITS",
    "UnitScale",
    "canonical_scale",
    "responses_from_chunks",
    "merge_split_steps",
    "scale_response",
    "resample_response",
    "sensing_response",
    "uncorrected_response",
    "GammaResponses",
    "combine_gamma",
    "usable_mask",
    "usable_band",
    "SensingSummary",
    "sensing_summary",
    "FeedthroughRise",
    "feedthrough_rise",
    "FeedthroughFit",
    "fit_feedthrough",
    "auto_nperseg",
    "gamma_response_stage",
]

#: Factors to the canonical units µA (current), nm (length) and V (voltage).
UNIT_SCALES: Mapping[str, Mapping[str, float]] = {
    "current": {"A": 1e6, "mA": 1e3, "uA": 1.0, "µA": 1.0, "nA": 1e-3},
    "length": {"m": 1e9, "mm": 1e6, "um": 1e3, "µm": 1e3, "nm": 1.0, "pm": 1e-3},
    "voltage": {"V": 1.0, "mV": 1e-3},
}
#: The canonical unit of each kind.
CANONICAL_UNITS: Mapping[str, str] = {"current": "uA", "length": "nm", "voltage": "V"}


class UnitScale(NamedTuple):
    """``factor`` to the canonical unit; ``assumed``: the channel had no units and canonical ones were assumed."""

    factor: float
    assumed: bool


def canonical_scale(kind: str, units: str, channel: str) -> UnitScale:
    """How to bring channel ``channel`` with ``units`` to the canonical unit of ``kind`` (µA, nm or V).

    Raises
    ------
    InputError
        If ``units`` is neither empty nor a known unit of ``kind``.
    """
    table = UNIT_SCALES[kind]
    if units == "":
        return UnitScale(1.0, True)
    if units not in table:
        raise InputError(
            f"channel {channel!r} has units {units!r}; expected a {kind} unit ({', '.join(table)})"
        )
    return UnitScale(table[units], False)


def _frozen(values) -> np.ndarray:
    arr = np.ascontiguousarray(values)
    arr.setflags(write=False)
    return arr


def auto_nperseg(n_samples: int) -> int:
    """Largest power of two ≤ n/16 (≈ 31 Welch averages at 50 % overlap), at least 256."""
    return default_nperseg(n_samples)


# --------------------------------------------------------------------------- estimation


def gamma_response_stage(
    x: str,
    ys: Sequence[str],
    *,
    method: str,
    nperseg: int,
    segments: Sequence | None = None,
    settle_fraction: float = 0.5,
    min_periods: int = 4,
) -> ResponseStage:
    """The stage measuring the responses from channel ``x`` to each of ``ys`` for a Γ sweep.

    ``"h1"``: Welch H1 per output (memory O(nperseg + chunk)).
    ``"stepped"``: lock-in per step, the steps from ``segments`` (metadata;
    memory O(steps)) or, when None, found in the drive by
    :func:`detect_segments` and :func:`merge_split_steps` (the records are
    then kept: memory one float64 array per channel).  See
    :class:`~afmtool.estimators.stages.ResponseStage`.
    """
    return ResponseStage(
        x, ys, method=method, nperseg=nperseg, segments=segments, find_steps=_find_steps,
        settle_fraction=settle_fraction, min_periods=min_periods,
    )


def _find_steps(x: np.ndarray, sample_rate_hz: float) -> tuple[SineSegment, ...]:
    return merge_split_steps(detect_segments(x, sample_rate_hz))


def responses_from_chunks(
    chunks: Iterable[Chunk],
    sample_rate_hz: float,
    x: str,
    ys: Sequence[str],
    *,
    method: str,
    nperseg: int,
    segments: Sequence | None = None,
    settle_fraction: float = 0.5,
    min_periods: int = 4,
) -> dict[str, FrequencyResponse]:
    """Frequency responses from channel ``x`` to each channel of ``ys``, one pass over ``chunks`` in memory.

    Parameters
    ----------
    chunks : iterable of Chunk
        Aligned blocks holding ``x`` and every name in ``ys``.
    sample_rate_hz : float
        Hz.
    x, ys, method, nperseg, segments, settle_fraction, min_periods
        As :func:`gamma_response_stage`, which this runs over ``chunks``
        (a capture streams it through :func:`afmtool.pipeline.run_stream`).

    Returns
    -------
    dict
        Output channel → FrequencyResponse in the capture's units.
    """
    stage = gamma_response_stage(x, ys, method=method, nperseg=nperseg, segments=segments,
                                 settle_fraction=settle_fraction, min_periods=min_periods)
    (responses,) = run_stages(chunks, [stage], sample_rate_hz)
    return responses


#: Touching detected steps closer in frequency than this fraction are one step split by edge ringing.
_SPLIT_STEP_FRACTION = 0.05


def merge_split_steps(segments: Sequence[SineSegment], fraction: float = _SPLIT_STEP_FRACTION) -> tuple[SineSegment, ...]:
    """Join neighbouring steps whose frequencies differ by less than ``fraction`` (relative).

    :func:`detect_segments` can cut a long low-frequency step where the
    Hilbert transform rings after the previous step (the ringing lasts a few
    periods of the new frequency, longer than its comparison window); the
    pieces then have nearly the same frequency.  A logarithmic sweep's real
    steps differ by far more (26 % at 10 steps per decade).  The joined step
    keeps the frequency of its longest piece, whose phase-line fit is the
    most precise.
    """
    merged: list[list] = []  # [start, end, frequency, longest duration]
    for seg in segments:
        duration = seg.end_s - seg.start_s
        # neighbours: touching, or a gap shorter than half the shorter piece (the detector dropped a few blocks)
        near = bool(merged) and 0 <= seg.start_s - merged[-1][1] <= 0.5 * min(duration, merged[-1][1] - merged[-1][0])
        if near and abs(seg.frequency_hz - merged[-1][2]) < fraction * merged[-1][2]:
            merged[-1][1] = seg.end_s
            if duration > merged[-1][3]:
                merged[-1][2], merged[-1][3] = seg.frequency_hz, duration
        else:
            merged.append([seg.start_s, seg.end_s, seg.frequency_hz, duration])
    return tuple(SineSegment(a, b, f) for a, b, f, _ in merged)


def scale_response(fr: FrequencyResponse, factor: float) -> FrequencyResponse:
    """The same response in other units: H and its magnitude error times ``factor`` (> 0)."""
    if not (math.isfinite(factor) and factor > 0):
        raise ConfigError(f"factor={factor!r} must be a finite number > 0")
    return replace(fr, response=_frozen(fr.response * factor), magnitude_std=_frozen(fr.magnitude_std * factor))


def resample_response(fr: FrequencyResponse, frequency_hz) -> FrequencyResponse:
    """``fr`` interpolated onto ``frequency_hz`` (Hz): log-magnitude and unwrapped phase, linear in log f.

    Outside the finite, positive-frequency range of ``fr`` the result is
    NaN.  Coherence and errors are interpolated linearly in log f.
    """
    target = np.asarray(frequency_hz, dtype=np.float64)
    f = fr.frequency_hz
    ok = np.isfinite(fr.response) & (f > 0) & (np.abs(fr.response) > 0)
    if np.count_nonzero(ok) < 2:
        raise InputError("a response needs at least two finite bins to be resampled")
    lf, h = np.log(f[ok]), fr.response[ok]
    inside = (target >= f[ok].min()) & (target <= f[ok].max())
    lt = np.log(np.where(inside, target, f[ok].min()))

    def interp(values: np.ndarray) -> np.ndarray:
        return np.where(inside, np.interp(lt, lf, values), np.nan)

    magnitude = np.exp(interp(np.log(np.abs(h))))
    phase = interp(np.unwrap(np.angle(h)))
    return FrequencyResponse(
        frequency_hz=_frozen(target.copy()),
        response=_frozen(magnitude * np.exp(1j * phase)),
        coherence=_frozen(interp(fr.coherence[ok])),
        magnitude_std=_frozen(interp(fr.magnitude_std[ok])),
        phase_std_rad=_frozen(interp(fr.phase_std_rad[ok])),
        method=fr.method,
        n_averages=fr.n_averages,
    )


# --------------------------------------------------------------------------- eqs. 6.15, 6.16


def _same_grid(*responses: FrequencyResponse) -> None:
    first = responses[0].frequency_hz
    for fr in responses[1:]:
        if fr.frequency_hz.shape != first.shape or not np.allclose(fr.frequency_hz, first, rtol=1e-9, atol=0):
            raise InputError("the frequency responses are not on one frequency grid; resample them first")


def _difference_ratio(
    numerator: FrequencyResponse, denominator: FrequencyResponse, subtract: FrequencyResponse | None
) -> FrequencyResponse:
    """(A − B)/G with first-order error propagation (the one core of eqs. 6.15 and 6.16).

    Each estimate's random error is treated as circular complex noise of
    standard deviation σ = ``magnitude_std`` (H1 and the lock-in have equal
    relative magnitude and phase errors), independent between A, B and G
    (different output channels and captures).  Then

    .. math:: \\sigma_\\Gamma^2 = \\frac{\\sigma_A^2 + \\sigma_B^2}{|G|^2}
              + |\\Gamma|^2\\frac{\\sigma_G^2}{|G|^2},

    ``magnitude_std`` = σ_Γ and ``phase_std_rad`` = σ_Γ/|Γ|.  The coherence
    of the result is the smaller of those of A and G (the feed-through's
    own coherence is low wherever it is small, and is not used).
    """
    pieces = (numerator, denominator) if subtract is None else (numerator, denominator, subtract)
    _same_grid(*pieces)
    a, g = numerator.response, denominator.response
    var = numerator.magnitude_std**2
    if subtract is not None:
        a = a - subtract.response
        var = var + subtract.magnitude_std**2
    with np.errstate(divide="ignore", invalid="ignore"):
        gamma = a / g
        # σ_Γ² = (σ_A² + σ_B²)/|G|² + |Γ|²σ_G²/|G|²
        std = np.sqrt((var + np.abs(gamma) ** 2 * denominator.magnitude_std**2) / np.abs(g) ** 2)
        phase_std = std / np.abs(gamma)
    return FrequencyResponse(
        frequency_hz=_frozen(numerator.frequency_hz.copy()),
        response=_frozen(gamma),
        coherence=_frozen(np.fmin(numerator.coherence, denominator.coherence)),
        magnitude_std=_frozen(std),
        phase_std_rad=_frozen(phase_std),
        method=numerator.method,
        n_averages=numerator.n_averages,
    )


def sensing_response(
    ir_v: FrequencyResponse, ts_v: FrequencyResponse, feedthrough: FrequencyResponse
) -> FrequencyResponse:
    """Γ_IR,ts = (Γ_IR,V − Γ_sp)/Γ_ts,V (eq. 6.15), with propagated errors.

    Parameters
    ----------
    ir_v : FrequencyResponse
        Γ_IR,V, V_sub → I_R near the sample (µA/V).
    ts_v : FrequencyResponse
        Γ_ts,V, V_sub → t_s (nm/V): the optical deflection, Δt_s = Δp.
    feedthrough : FrequencyResponse
        Γ_sp, V_sub → I_R with the tip in contact (Δt_s = 0), µA/V.

    Returns
    -------
    FrequencyResponse
        µA/nm, on the common grid (see :func:`_difference_ratio`).
    """
    return _difference_ratio(ir_v, ts_v, feedthrough)


def uncorrected_response(ir_v: FrequencyResponse, ts_v: FrequencyResponse) -> FrequencyResponse:
    """Γ_IR,V/Γ_ts,V (eq. 6.16): the sensing map with the feed-through left in, µA/nm."""
    return _difference_ratio(ir_v, ts_v, None)


@dataclass(frozen=True, eq=False)
class GammaResponses:
    """Every Γ of §6.6.1 on one frequency grid (µA, nm, V)."""

    ir_v: FrequencyResponse
    ts_v: FrequencyResponse
    feedthrough: FrequencyResponse
    ir_ts: FrequencyResponse
    ir_ts_uncorrected: FrequencyResponse

    @property
    def frequency_hz(self) -> np.ndarray:
        return self.ir_ts.frequency_hz


def combine_gamma(
    ir_v: FrequencyResponse, ts_v: FrequencyResponse, feedthrough: FrequencyResponse
) -> GammaResponses:
    """Put Γ_sp on the grid of the near-sample sweep if needed, then apply eqs. 6.15 and 6.16."""
    _same_grid(ir_v, ts_v)
    grid = ir_v.frequency_hz
    same = feedthrough.frequency_hz.shape == grid.shape and np.allclose(feedthrough.frequency_hz, grid, rtol=1e-9)
    sp = feedthrough if same else resample_response(feedthrough, grid)
    return GammaResponses(ir_v, ts_v, sp, sensing_response(ir_v, ts_v, sp), uncorrected_response(ir_v, ts_v))


# --------------------------------------------------------------------------- figures of merit


def usable_mask(gamma: GammaResponses, min_coherence: float) -> np.ndarray:
    """Bins with f > 0, finite Γ_IR,ts and coherence ≥ ``min_coherence`` for both Γ_IR,V and Γ_ts,V.

    The feed-through's coherence is not required: in contact the current
    responds only through Γ_sp, which is tiny at low frequency, so its
    coherence is low exactly where its contribution to eq. 6.15 is
    negligible; its error still enters the propagated error of Γ_IR,ts.
    """
    if not (isinstance(min_coherence, (int, float)) and 0 <= min_coherence <= 1):
        raise ConfigError(f"min_coherence={min_coherence!r} must be a number in [0, 1]")
    f = gamma.frequency_hz
    with np.errstate(invalid="ignore"):
        return (
            (f > 0)
            & np.isfinite(gamma.ir_ts.response)
            & (gamma.ir_v.coherence >= min_coherence)
            & (gamma.ts_v.coherence >= min_coherence)
        )


def usable_band(frequency_hz: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """(low, high) Hz of the longest run of consecutive usable bins (in frequency order)."""
    order = np.argsort(frequency_hz)
    ok = np.asarray(mask)[order]
    best, start, best_run = (0, 0), None, 0
    for k, flag in enumerate(np.append(ok, False)):
        if flag and start is None:
            start = k
        elif not flag and start is not None:
            if k - start > best_run:
                best_run, best = k - start, (start, k - 1)
            start = None
    if best_run == 0:
        raise InputError("no usable frequencies: the coherence is below min_coherence everywhere")
    f = np.asarray(frequency_hz)[order]
    return float(f[best[0]]), float(f[best[1]])


class SensingSummary(NamedTuple):
    """The numbers that matter of a low-pass sensing map (§6.6.1).

    dc_sensitivity : float
        Γ(0), signed (µA/nm for Γ_IR,ts): the real part of the DC
        extrapolation (its imaginary part is 0 for a real system).
    bandwidth_hz : float
        Lowest frequency where |Γ| = |Γ(0)|/√2 (−3 dB), Hz; NaN if |Γ| stays above.
    roll_off_db_per_decade : float
        Least-squares slope of 20·log10|Γ| against log10 f over ``roll_off_band_hz``,
        each bin weighted by its share of log10 f (so each decade counts the
        same on a linear H1 grid or a logarithmic stepped grid).
    roll_off_band_hz : (float, float)
        The band of that fit, Hz.
    dc_band_hz : (float, float)
        The band used to extrapolate Γ(0), Hz.
    """

    dc_sensitivity: float
    bandwidth_hz: float
    roll_off_db_per_decade: float
    roll_off_band_hz: tuple[float, float]
    dc_band_hz: tuple[float, float]


def _dc_extrapolation(f: np.ndarray, h: np.ndarray) -> complex:
    """Γ(0) from a complex polynomial c0 + c1·s + c2·s² fitted to the lowest bins (s = j2πf).

    A rational Γ is analytic at s = 0, so over a band well below its first
    pole the Taylor polynomial fits to within its third-order term; c0 is
    the DC value.  Least squares, s scaled by the band's top for conditioning.
    """
    degree = min(2, f.size - 1)
    s = 1j * f / f.max()
    basis = s[:, None] ** np.arange(degree + 1)
    coefficients = np.linalg.lstsq(basis, h, rcond=None)[0]
    return complex(coefficients[0])


def _crossing(f: np.ndarray, magnitude_db: np.ndarray, level_db: float) -> float:
    """Lowest f where the magnitude falls through ``level_db``: a line in (log10 f, dB) over ±0.1 decade.

    The local straight-line fit averages the noise of neighbouring bins
    (a 0.1 dB error would otherwise move a −5 dB/decade crossing by 5 %).
    """
    below = np.flatnonzero(magnitude_db < level_db)
    if below.size == 0:
        return math.nan
    lf = np.log10(f)
    centre = lf[below[0]]
    near = np.abs(lf - centre) <= 0.1
    if np.count_nonzero(near) < 3:  # sparse grid (stepped sine): the two bracketing bins
        k = max(int(below[0]), 1)
        near = np.zeros(f.size, dtype=bool)
        near[k - 1 : k + 1] = True
    slope, intercept = np.polyfit(lf[near], magnitude_db[near], 1)
    if slope >= 0:
        return float(f[below[0]])
    return float(10.0 ** ((level_db - intercept) / slope))


def _dc_and_bandwidth(f, h, magnitude_db, dc_band_factor) -> tuple[complex, float, np.ndarray]:
    """Γ(0), the −3 dB bandwidth f_bw (Hz, NaN if |Γ| never falls 3 dB) and the bins Γ(0) came from.

    Three passes of: f_bw where |Γ| crosses |Γ(0)|/√2, then Γ(0)
    extrapolated from the bins below ``dc_band_factor``·f_bw (at least the
    three lowest), starting from the mean of the three lowest bins.
    """
    dc = complex(np.mean(h[:3]))
    low = f[:3]
    for _ in range(3):
        bandwidth = _crossing(f, magnitude_db, 20.0 * math.log10(abs(dc)) - 10.0 * math.log10(2.0))
        limit = dc_band_factor * (bandwidth if math.isfinite(bandwidth) else f[-1])
        low_mask = f <= limit
        if np.count_nonzero(low_mask) < 3:
            low_mask = np.zeros(f.size, dtype=bool)
            low_mask[:3] = True
        low = f[low_mask]
        dc = _dc_extrapolation(low, h[low_mask])
    return dc, bandwidth, low


def sensing_summary(
    fr: FrequencyResponse,
    mask: np.ndarray,
    *,
    roll_off_start_factor: float = 2.0,
    roll_off_stop_factor: float = 10.0,
    dc_band_factor: float = 0.25,
) -> SensingSummary:
    """DC sensitivity, −3 dB bandwidth and roll-off of a low-pass response.

    Parameters
    ----------
    fr : FrequencyResponse
        Γ_IR,ts (or any low-pass map).
    mask : numpy.ndarray of bool
        Bins to use (:func:`usable_mask`).
    roll_off_start_factor, roll_off_stop_factor : float
        The roll-off is fitted from start·f_bw to min(stop·f_bw, the top
        usable frequency).
    dc_band_factor : float
        Γ(0) is extrapolated from the bins below this fraction of f_bw
        (at least the three lowest).

    Returns
    -------
    SensingSummary

    Notes
    -----
    The bandwidth and the DC value depend on each other: with a roll-off
    of ~10 dB/decade, |Γ| falls only ~5 dB/decade at f_bw, so a 1 % error in
    |Γ(0)| moves f_bw by ~4 %.  Hence Γ(0) is extrapolated, not read from
    the lowest bin: start from the mean of the three lowest bins, find
    f_bw, extrapolate Γ(0) from the bins below ``dc_band_factor``·f_bw
    (:func:`_dc_extrapolation`), and repeat (three passes).

    Raises
    ------
    InputError
        With fewer than 4 usable bins, or no roll-off band.
    """
    if not (roll_off_start_factor > 0 and roll_off_stop_factor > roll_off_start_factor):
        raise ConfigError(
            f"roll_off_start_factor={roll_off_start_factor!r} and roll_off_stop_factor={roll_off_stop_factor!r} "
            "must satisfy 0 < start < stop"
        )
    if not 0 < dc_band_factor < 1:
        raise ConfigError(f"dc_band_factor={dc_band_factor!r} must be in (0, 1)")
    order = np.argsort(fr.frequency_hz)
    keep = np.asarray(mask)[order]
    f, h = fr.frequency_hz[order][keep], fr.response[order][keep]
    if f.size < 4:
        raise InputError(f"only {f.size} usable frequencies; at least 4 are needed for the sensing summary")
    magnitude_db = 20.0 * np.log10(np.abs(h))
    dc, bandwidth, low = _dc_and_bandwidth(f, h, magnitude_db, dc_band_factor)
    if not math.isfinite(bandwidth):
        return SensingSummary(dc.real, math.nan, math.nan, (math.nan, math.nan), (float(low[0]), float(low[-1])))
    lo, hi = roll_off_start_factor * bandwidth, min(roll_off_stop_factor * bandwidth, float(f[-1]))
    band = (f >= lo) & (f <= hi)
    if np.count_nonzero(band) < 2:
        raise InputError(
            f"no usable frequencies between {lo:.4g} and {hi:.4g} Hz to fit the roll-off; extend the sweep"
        )
    lf = np.log10(f[band])
    # every decade weighs the same whatever the bin spacing (linear for H1, logarithmic for stepped sines)
    weight = np.sqrt(np.gradient(lf)) if lf.size > 2 else np.ones_like(lf)
    slope = float(np.polyfit(lf, magnitude_db[band], 1, w=weight)[0])
    return SensingSummary(
        dc_sensitivity=dc.real,
        bandwidth_hz=bandwidth,
        roll_off_db_per_decade=slope,
        roll_off_band_hz=(float(f[band][0]), float(f[band][-1])),
        dc_band_hz=(float(low[0]), float(low[-1])),
    )


class FeedthroughRise(NamedTuple):
    """How much the feed-through inflates the uncorrected Γ (eq. 6.16) at the top of the band.

    excess_db : float
        20·log10(|Γ_unc|/|Γ_IR,ts|) averaged over the top third of a decade
        of the usable band, dB (> 0: the false rise of Fig. 6.20).
    uncorrected_slope_db_per_decade, corrected_slope_db_per_decade : float
        Slopes of both magnitudes over that band.
    band_hz : (float, float)
    """

    excess_db: float
    uncorrected_slope_db_per_decade: float
    corrected_slope_db_per_decade: float
    band_hz: tuple[float, float]


def feedthrough_rise(corrected: FrequencyResponse, uncorrected: FrequencyResponse, mask: np.ndarray) -> FeedthroughRise:
    """Compare eqs. 6.16 and 6.15 over the top third of a decade of the usable bins."""
    _same_grid(corrected, uncorrected)
    f = corrected.frequency_hz
    top = float(np.max(f[mask]))
    band = mask & (f >= top / 10 ** (1 / 3))
    if np.count_nonzero(band) < 2:
        raise InputError("fewer than 2 usable frequencies in the top third of a decade")
    lf = np.log10(f[band])
    mc = 20 * np.log10(np.abs(corrected.response[band]))
    mu = 20 * np.log10(np.abs(uncorrected.response[band]))
    return FeedthroughRise(
        excess_db=float(np.mean(mu - mc)),
        uncorrected_slope_db_per_decade=float(np.polyfit(lf, mu, 1)[0]),
        corrected_slope_db_per_decade=float(np.polyfit(lf, mc, 1)[0]),
        band_hz=(float(f[band].min()), top),
    )


class FeedthroughFit(NamedTuple):
    """Γ_sp ≈ (b1·s + b0)/(s + a0) fitted where the contact sweep is coherent (Fig. 6.18's transfer-function fit).

    capacitance_pf : float
        The low-frequency capacitive slope b1/a0 of Γ_sp in µA/V per rad/s, as
        a coupling capacitance C_c (pF): Γ_sp ≈ C_c·s below the pole.
    pole_hz : float
        a0/2π, Hz.
    fit : TransferFunctionFit
        In µA/V, s in rad/s.
    band_hz : (float, float)
    """

    capacitance_pf: float
    pole_hz: float
    fit: TransferFunctionFit
    band_hz: tuple[float, float]


def fit_feedthrough(fr: FrequencyResponse, min_coherence: float) -> FeedthroughFit:
    """First-order rational fit of the feed-through Γ_sp (µA/V), weighted by 1/σ², on its coherent bins.

    Raises
    ------
    InputError
        With fewer than 4 coherent bins (no measurable feed-through).
    """
    f = fr.frequency_hz
    with np.errstate(invalid="ignore"):
        use = (f > 0) & np.isfinite(fr.response) & (fr.coherence >= min_coherence) & (fr.magnitude_std > 0)
    if np.count_nonzero(use) < 4:
        raise InputError(f"the feed-through is coherent (>= {min_coherence:g}) in {np.count_nonzero(use)} bins only")
    fit = fit_transfer_function(f[use], fr.response[use], 1, 1, weights=1.0 / fr.magnitude_std[use] ** 2)
    b1, _b0 = fit.numerator
    a0 = fit.denominator[1]
    # Γ_sp(s) ≈ (b0 + b1·s)/a0 below the pole: the capacitive part b1/a0 (µA/V·s) = C_c·1e6
    return FeedthroughFit(b1 / a0 * 1e-6 * 1e12, a0 / (2 * math.pi), fit, (float(f[use].min()), float(f[use].max())))
