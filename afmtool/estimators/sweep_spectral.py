"""The spectral forms of the sweep route to the free-air model (§3.3.3): H1 or stepped sine, then a fit.

The drive-to-deflection response G(jω) is measured with a chirp/noise
drive (H1, :func:`~afmtool.estimators.frequency_response.h1_estimate`) or
a stepped sine (:func:`~afmtool.estimators.stepped_sine.stepped_sine_response`)
and the delayed second-order model is fitted to the bins around the
resonance (:func:`~afmtool.estimators.transfer_function_fit.fit_second_order`).
The default, whole-record form of the route is
:mod:`afmtool.estimators.sweep_record`.  Split out of
:mod:`afmtool.estimators.frequency_response` (issue 29, item 6).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from afmtool.errors import ConfigError, InputError
from afmtool.estimators.frequency_response import FrequencyResponse, h1_estimate
from afmtool.estimators.spectral_checks import check_positive
from afmtool.estimators.stepped_sine import detect_segments, stepped_sine_response
from afmtool.estimators.transfer_function_fit import SecondOrderFit, fit_second_order
from afmtool.models.free_air import FreeAirModel

__all__ = ["spectral_sweep_fit", "sweep_frequency_response", "free_air_from_response", "default_nperseg"]

#: The automatic fit band keeps the contiguous bins around the peak with
#: |H| > |H|max / this factor (−20 dB, about ±5 half-power bandwidths of a resonance).
_BAND_PEAK_FACTOR = 10.0
#: Bins with a lower coherence are not fitted (outside the band a chirp
#: excites, H1 is noise over noise).
_BAND_MIN_COHERENCE = 0.5


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
    """The measured frequency response of a sweep, as :func:`~afmtool.estimators.sweep_record.free_air_from_sweep` fits it.

    Parameters are those of :func:`~afmtool.estimators.sweep_record.free_air_from_sweep`; the H1 segment
    length defaults to the largest power of two ≤ n/16, at least 256.
    """
    fs = check_positive("sample_rate_hz", sample_rate_hz)
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
    """The second-order fit of :func:`~afmtool.estimators.sweep_record.free_air_from_sweep` to a measured response ``fr``."""
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
