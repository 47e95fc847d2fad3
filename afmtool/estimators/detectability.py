"""Predicted detectability of probe loss on one capture, before the run (issue 28, items 1-2).

Inputs measured on the capture itself: the free-air model, the measurement
noise σ (the free-air segment's deflection less its drive line), the free
amplitude A0 and, from a survey of the capture after the free-air segment,
the on-sample amplitude A_sp (the mode of the amplitude's distribution
below A0: :func:`estimate_on_sample`) and the forcing at the drive that
holds it there, F_sp (:mod:`afmtool.estimators.forcing_observer`).

The information limit
---------------------
:func:`information_limit`: the drive periods after the last impact before
a test that knows everything but the change time could tell "the impacts
stopped" from "they go on", at d = ``LIMIT_SEPARATION`` standard
deviations (the on-sample false-alarm margin the detectors use; the median
detection).  d²(M) is the energy, over σ², of the deflection the missing
impacts would have caused, from the end of the last one
(:mod:`afmtool.estimators.forcing_observer` derives it: a ramp, d² ∝ m³).

A detector's prediction
-----------------------
:func:`synthetic_record` builds, on the free-air model, what the detector
will see: impact trains at the drive (Gaussian pulses, 5 % of a period
wide, whose fundamental is F_sp) switched off for ``off_periods`` and on
for ``on_periods``, ``events`` times, plus white noise; the signal and the
noise are kept apart, so that a candidate's noise can be scaled to what it
measures on the capture's free-air segment.  Running a candidate over it
and scoring it as the capture's ``/truth`` is scored
(:func:`score_switch`) gives its median latency λ (from the end of the last
impact, as ``/truth/contact`` counts), its return lag ρ (from the first
impact back), its recall of 5-period events and its false alarms on the
sample.  Precision depends on the loss events of the capture; it is
predicted for ``REFERENCE_LOSS_PERIODS``-period events among
``REFERENCE_ON_PERIODS`` drive periods on the sample (the issue's test
captures: 5-40 periods, mean 15, every 300)::

    precision = (L − λ) / ((L − λ) + ρ + f_on·T_on)

with f_on the fraction of on-sample time the false alarms flag; or for the
loss events a provisional detector finds in the survey
(:func:`survey_events`, :func:`predicted_precision`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from afmtool.errors import ConfigError
from afmtool.jit import JIT_OPTIONS

__all__ = [
    "LIMIT_SEPARATION",
    "REFERENCE_LOSS_PERIODS",
    "REFERENCE_ON_PERIODS",
    "OnSample",
    "estimate_on_sample",
    "SyntheticRecord",
    "synthetic_record",
    "SwitchScores",
    "score_switch",
    "LossEvents",
    "REFERENCE_EVENTS",
    "predicted_precision",
    "survey_events",
    "information_limit",
    "measurement_noise",
]

#: Separation (standard deviations) the information limit is quoted at: the detectors' on-sample margin.
LIMIT_SEPARATION = 4.5
#: The loss events and on-sample stretches the predicted precision refers to, drive periods.
REFERENCE_LOSS_PERIODS = 15.0
REFERENCE_ON_PERIODS = 300.0
#: Width of a synthetic impact (Gaussian σ), drive periods; and its floor, samples.
_PULSE_PERIODS = 0.05
_PULSE_MIN_SAMPLES = 0.6


class OnSample(NamedTuple):
    """What a survey of the capture says about the tip on the sample.

    Attributes
    ----------
    free_amplitude : float
        A0, deflection units.
    amplitude : float
        A_sp: the set point given, or the mode of the survey's amplitude
        distribution below A0, deflection units.
    amplitude_source : str
        ``"setpoint"``, ``"estimated"``, or ``"estimated: the set point matches
        no stretch of the capture"`` (a set point given, but the survey never
        taps at it: the capture's own amplitude is used).
    forcing : complex
        F_sp − F_fa, the on-sample forcing at the drive less its free-air
        level, dither units.
    forcing_source : str
        ``"survey"`` (F̂ over the samples at A_sp) or ``"setpoint"`` (a pure
        amplitude deficit, F = (A_sp/A0 − 1)·U, when the survey found none).
    periods_on_sample : float
        Survey drive periods at A_sp (within the steady band).
    """

    free_amplitude: float
    amplitude: float
    amplitude_source: str
    forcing: complex
    forcing_source: str
    periods_on_sample: float


def _mode(values: np.ndarray, bin_width: float) -> float:
    """The mode of ``values``: the fullest bin of a histogram smoothed over ±2 bins, refined by its mean."""
    low, high = float(values.min()), float(values.max())
    bins = max(1, math.ceil((high - low) / bin_width))
    counts, edges = np.histogram(values, bins=bins, range=(low, low + bins * bin_width))
    smooth = np.convolve(counts, np.ones(5), mode="same")
    k = int(np.argmax(smooth))
    inside = values[(values >= edges[max(0, k - 2)]) & (values < edges[min(bins, k + 3)])]
    return float(np.mean(inside)) if inside.size else float(0.5 * (edges[k] + edges[k + 1]))


def estimate_on_sample(amplitude: np.ndarray, phasors: np.ndarray, free_amplitude: float, free_spread: float,
                       reference: complex, period_rows: float, *, setpoint: float | None = None,
                       drive_phasor: complex | None = None) -> OnSample | None:
    """A_sp and F_sp from a survey (module docstring); None when it holds no on-sample stretch.

    Parameters
    ----------
    amplitude : numpy.ndarray
        Lock-in amplitude over the survey, deflection units, at ``phasors``' rows.
    phasors : numpy.ndarray of complex
        F̂ at the same rows, dither units.
    free_amplitude, free_spread : float
        A0 and the standard deviation of the amplitude over the free-air segment.
    reference : complex
        F_fa, the free-air level of F̂.
    period_rows : float
        Rows per drive period (for ``periods_on_sample``).
    setpoint : float, optional
        A_sp given (``--setpoint``); it replaces the estimate.
    drive_phasor : complex, optional
        U, the dither's phasor at the drive: F_sp from the set point when
        the survey has no stretch at A_sp.
    """
    if free_amplitude <= 0:
        return None
    finite = np.isfinite(amplitude) & np.isfinite(phasors)
    amplitude, phasors = amplitude[finite], phasors[finite]
    # below A0 by more than its free-air scatter, or 2 %
    below = amplitude < free_amplitude - max(0.02 * free_amplitude, 5.0 * free_spread)
    band = max(0.02 * free_amplitude, 3.0 * free_spread)
    enough = np.count_nonzero(below) >= max(1.0, 3 * period_rows)
    estimated = _mode(amplitude[below], 0.005 * free_amplitude) if enough else None

    def at(a_sp: float) -> tuple[np.ndarray, float]:
        steady = below & (np.abs(amplitude - a_sp) < band)
        return steady, float(np.count_nonzero(steady) / period_rows) if period_rows > 0 else 0.0

    # a set point far from where the capture taps (the mode) is passed through only by transients
    setpoint_fits = bool(setpoint) and (estimated is None or abs(setpoint - estimated) <= max(2.0 * band,
                                                                                               0.05 * free_amplitude))
    candidates = ([(float(setpoint), "setpoint")] if setpoint_fits else []) + (
        [(estimated, "estimated" if not setpoint else "estimated: the set point matches no stretch of the capture")]
        if estimated is not None else [])
    for a_sp, source in candidates:
        steady, periods = at(a_sp)
        if periods >= 3:
            forcing = complex(np.median(phasors[steady].real), np.median(phasors[steady].imag)) - reference
            return OnSample(float(free_amplitude), a_sp, source, forcing, "survey", periods)
    if drive_phasor is None or not setpoint:
        return None
    # y = G (U + F): an amplitude scaled by A_sp/A0 at the free-air phase needs F = (A_sp/A0 − 1) U
    a_sp = float(setpoint)
    return OnSample(float(free_amplitude), a_sp, "setpoint", (a_sp / free_amplitude - 1.0) * complex(drive_phasor),
                    "setpoint", 0.0)


def measurement_noise(deflection: np.ndarray, sample_rate_hz: float, lines_hz) -> float:
    """σ: the rms of the free-air deflection less a constant and its drive lines (least squares), deflection units.

    ``lines_hz``: the drive line first, then any side lines (a three-sine's).
    """
    y = np.asarray(deflection, dtype=np.float64)
    n = np.arange(y.size)
    columns = [np.ones(y.size)]
    for line in np.atleast_1d(lines_hz):
        w = 2.0 * math.pi * float(line) / sample_rate_hz
        columns += [np.cos(w * n), np.sin(w * n)]
    basis = np.column_stack(columns)
    coef, *_ = np.linalg.lstsq(basis, y, rcond=None)
    residual = y - basis @ coef
    return float(np.sqrt(np.mean(residual * residual) * y.size / max(1, y.size - basis.shape[1])))


# ----------------------------------------------------------------------------------- synthetic record


@njit(**JIT_OPTIONS)
def _plant_kernel(f, b1, b0, a2, a1, a0, out):
    """y(n) = a2 f(n) + a1 f(n−1) + a0 f(n−2) − b1 y(n−1) − b0 y(n−2) from rest (eq. 3.40)."""
    f1 = 0.0
    f2 = 0.0
    y1 = 0.0
    y2 = 0.0
    for n in range(f.shape[0]):
        y = a2 * f[n] + a1 * f1 + a0 * f2 - b1 * y1 - b0 * y2
        out[n] = y
        f2, f1 = f1, f[n]
        y2, y1 = y1, y


class SyntheticRecord(NamedTuple):
    """Impact trains on the free-air model, switched off and on (module docstring).

    Attributes
    ----------
    signal : numpy.ndarray
        The deflection the impacts cause (no drive: the detectors are linear in it), deflection units.
    noise : numpy.ndarray
        White noise of rms σ, deflection units.
    contact : numpy.ndarray of uint8
        1 while the tip is on the sample (from w before the first impact of a stretch to w after its last).
    first_scored : int
        The first sample after the warm-up.
    period_samples : float
    """

    signal: np.ndarray
    noise: np.ndarray
    contact: np.ndarray
    first_scored: int
    period_samples: float


def _pulse_height(forcing: complex, period: float, width: float) -> float:
    """Height A of Gaussian pulses of σ ``width`` every ``period`` samples whose fundamental has amplitude |forcing|."""
    # p(t) = A Σ_k exp(−(t − t_k)²/2w²) has a fundamental of amplitude 2A·w√(2π)/N_p·e^{−(ωw)²/2}
    omega = 2.0 * math.pi / period
    return abs(forcing) * period / (2.0 * width * math.sqrt(2.0 * math.pi)) * math.exp(0.5 * (omega * width) ** 2)


def _pulses(centres: np.ndarray, height: float, width: float, n: int) -> np.ndarray:
    """Σ_k height·exp(−(t − centres_k)²/2w²) at t = 0 … n−1."""
    out = np.zeros(n)
    reach = int(math.ceil(5.0 * width))
    for centre in centres:
        lo, hi = max(0, int(centre) - reach), min(n, int(centre) + reach + 2)
        if lo < hi:
            t = np.arange(lo, hi)
            out[lo:hi] += height * np.exp(-0.5 * ((t - centre) / width) ** 2)
    return out


def _impact_offset(forcing: complex, period: float) -> float:
    """Where in a period the impacts whose fundamental is Re(F e^{jωn}) fall: ωn + arg F = 0 (mod 2π)."""
    return (-math.atan2(forcing.imag, forcing.real) * period / (2.0 * math.pi)) % period


def synthetic_record(denominator, numerator, forcing: complex, period_samples: float, sigma: float, *,
                     events: int = 40, on_periods: int = 40, off_periods: int = 20, warmup_periods: int = 0,
                     seed: int = 20240628) -> SyntheticRecord:
    """Impact trains at the drive, off for ``off_periods`` and on for ``on_periods``, ``events`` times.

    Parameters
    ----------
    denominator, numerator
        The free-air model at the capture's rate.
    forcing : complex
        F_sp − F_fa, dither units (its fundamental at the drive).
    period_samples : float
        N_p = fs/f_d.
    sigma : float
        σ of the white noise, deflection units.
    warmup_periods : int, optional
        On-sample periods before the first event (default: five of the
        model's time constants, so the first event starts in steady tapping).
    seed : int, optional
        The noise's seed (the prediction is reproducible).
    """
    if not (period_samples > 2 and sigma > 0 and abs(forcing) > 0):
        raise ConfigError(f"a synthetic record needs N_p > 2, sigma > 0 and a forcing: {period_samples}, {sigma}, "
                          f"{forcing}")
    b1, b0 = (float(v) for v in denominator)
    a2, a1, a0 = (float(v) for v in numerator)
    if not warmup_periods:
        tau_samples = -2.0 / math.log(b0) if 0 < b0 < 1 else 100.0 * period_samples  # ρ² = b0
        warmup_periods = int(math.ceil(5.0 * tau_samples / period_samples)) + 10
    cycle = on_periods + off_periods
    total_periods = warmup_periods + events * cycle + on_periods
    n = int(math.ceil(total_periods * period_samples))
    active = np.ones(total_periods + 1, dtype=bool)
    for e in range(events):
        start = warmup_periods + e * cycle
        active[start:start + off_periods] = False
    width = max(_PULSE_MIN_SAMPLES, _PULSE_PERIODS * period_samples)
    offset = _impact_offset(forcing, period_samples)
    f = _pulses(offset + np.flatnonzero(active) * period_samples, _pulse_height(forcing, period_samples, width),
                width, n)
    signal = np.empty(n)
    _plant_kernel(f, b1, b0, a2, a1, a0, signal)
    contact = np.zeros(n, dtype=np.uint8)
    # the tip touches within w of an impact's centre (the attractive set at A_sp/A0 0.5-0.8 spends ±4 % of a
    # period in range), and between the impacts of a stretch it is on; a sample counts as contact when any of
    # [n, n + 1) does, as /truth/contact counts it
    runs = np.flatnonzero(np.diff(np.concatenate([[0], active.astype(np.int8), [0]])))
    for first, stop in zip(runs[::2], runs[1::2]):
        lo = max(0, int(math.floor(offset + first * period_samples - width)))
        hi = min(n, int(math.ceil(offset + (stop - 1) * period_samples + width)))
        contact[lo:hi] = 1
    noise = sigma * np.random.default_rng(seed).standard_normal(n)
    # scored from a period before the first loss, on the sample
    return SyntheticRecord(signal, noise, contact, int((warmup_periods - 1) * period_samples), float(period_samples))


# ----------------------------------------------------------------------------------- scores


class SwitchScores(NamedTuple):
    """A switch scored against a synthetic record (module docstring).

    Attributes
    ----------
    latency_periods : float
        Median latency of the detected onsets, drive periods (inf if none).
    return_periods : float
        Median delay from the first impact back to the switch's release, drive periods.
    recall_5 : float
        Share of onsets detected within 5 drive periods (the shortest scored events).
    recall : float
        Share of onsets detected at all.
    false_fraction : float
        Share of on-sample time flagged away from the returns (false alarms).
    on_flagged : float
        Share of on-sample time flagged, the returns included.
    """

    latency_periods: float
    return_periods: float
    recall_5: float
    recall: float
    false_fraction: float
    on_flagged: float


def score_switch(switch: np.ndarray, contact: np.ndarray, period_samples: float, first_scored: int) -> SwitchScores:
    """Latency, return lag, recall and false alarms of ``switch`` against ``contact`` (synthetic truth)."""
    s = np.asarray(switch[first_scored:], dtype=bool)
    c = np.asarray(contact[first_scored:], dtype=bool)
    if not c[0]:
        raise ConfigError("a synthetic record's scored part must start on the sample")
    edges = np.flatnonzero(np.diff(c.astype(np.int8)))
    onsets, returns = edges[::2] + 1, edges[1::2] + 1
    latency, back = [], []
    settled = np.zeros(s.size, dtype=bool)  # on-sample samples away from the returns
    for k, start in enumerate(onsets):
        stop = returns[k] if k < returns.size else s.size
        # as /truth scores it: a detection must begin after the switch let go of the previous loss
        rearm = returns[k - 1] if k > 0 else 0
        released = not s[rearm:start].all() if start > rearm else not s[start]
        hit = np.flatnonzero(s[start:stop])
        latency.append(hit[0] if hit.size and released else math.inf)
    for k, start in enumerate(returns):
        stop = onsets[k + 1] if k + 1 < onsets.size else s.size
        release = np.flatnonzero(~s[start:stop])
        lag = release[0] if release.size else stop - start
        back.append(lag)
        settled[start + lag:stop] = True
    lat = np.array(latency, dtype=np.float64) / period_samples
    detected = np.isfinite(lat)
    on = c
    return SwitchScores(
        float(np.median(lat[detected])) if detected.any() else math.inf,
        float(np.median(back)) / period_samples if back else 0.0,
        float(np.mean(lat < 5.0)) if lat.size else 0.0,
        float(np.mean(detected)) if lat.size else 0.0,
        float(np.mean(s[settled])) if settled.any() else 0.0,
        float(np.mean(s[on])) if on.any() else 0.0,
    )


class LossEvents(NamedTuple):
    """The loss events a precision is predicted for, drive periods.

    Attributes
    ----------
    durations : numpy.ndarray
        Length of each loss event.
    on_periods : float
        Time on the sample over the same stretch.
    source : str
        ``"survey"`` (estimated from the capture) or ``"reference"``.
    """

    durations: np.ndarray
    on_periods: float
    source: str


#: The reference events: one of ``REFERENCE_LOSS_PERIODS`` every ``REFERENCE_ON_PERIODS``.
REFERENCE_EVENTS = LossEvents(np.array([REFERENCE_LOSS_PERIODS]), REFERENCE_ON_PERIODS, "reference")


def predicted_precision(scores: SwitchScores, events: LossEvents = REFERENCE_EVENTS) -> float:
    """Time-weighted precision on ``events`` (module docstring)::

        Σ_e (L_e − λ)⁺ / (Σ_e (L_e − λ)⁺ + n_λ·ρ + f_on·T_on),   n_λ = #{e: L_e > λ}
    """
    remaining = np.maximum(0.0, np.asarray(events.durations, dtype=np.float64) - scores.latency_periods)
    flagged_loss = float(np.sum(remaining))
    false = float(np.count_nonzero(remaining)) * scores.return_periods + scores.false_fraction * events.on_periods
    return flagged_loss / (flagged_loss + false) if flagged_loss + false > 0 else 0.0


def survey_events(switch_events, n_survey: int, period_samples: float, latency: float,
                  return_lag: float) -> LossEvents | None:
    """The survey's loss events from a provisional detector's events (samples from the survey's start).

    A detected event [s, e) stands for a loss of about (e − s)/N_p + λ − ρ
    drive periods (the detector enters λ late and leaves ρ late).  An event
    from the survey's first sample has no onset (the tip had not yet
    touched) and is left out.  None when no event remains.
    """
    starts, ends = (np.asarray(v, dtype=np.int64) for v in switch_events)
    keep = starts > 0
    if not keep.any():
        return None
    durations = np.maximum(0.0, (ends[keep] - starts[keep]) / period_samples + latency - return_lag)
    first = int(np.flatnonzero(keep)[0])
    span = (n_survey - starts[first]) / period_samples
    return LossEvents(durations, max(0.0, span - float(np.sum(durations))), "survey")


# ----------------------------------------------------------------------------------- information limit


def information_limit(denominator, numerator, forcing: complex, period_samples: float, sigma: float,
                      *, separation: float = LIMIT_SEPARATION, horizon_periods: float = 60.0) -> float:
    """Drive periods after the last impact before d(M) reaches ``separation`` (module docstring); inf beyond the horizon.

    d²(M) = Σ δ(n)²/σ² over the M samples after the end of the last impact,
    δ the deflection the missing impacts would have caused (from rest: the
    ones before them are common to both hypotheses), averaged over the
    impact's position within a sample.
    """
    n = int(math.ceil((horizon_periods + 2) * period_samples))
    width = max(_PULSE_MIN_SAMPLES, _PULSE_PERIODS * period_samples)
    height = _pulse_height(forcing, period_samples, width)
    b1, b0 = (float(v) for v in denominator)
    a2, a1, a0 = (float(v) for v in numerator)
    reached_at = []
    for shift in (0.0, 0.25, 0.5, 0.75):  # the impact's position within a sample
        last = width + shift
        # the impacts that would have followed the last one, every N_p
        missing = last + period_samples * np.arange(1, int(horizon_periods) + 2)
        delta = np.empty(n)
        _plant_kernel(_pulses(missing, height, width, n), b1, b0, a2, a1, a0, delta)
        start = int(math.ceil(last + width))  # the contact ends w after the last impact's centre
        d2 = np.cumsum(delta[start:] ** 2) / (sigma * sigma)
        reached = np.flatnonzero(d2 >= separation * separation)
        reached_at.append(reached[0] / period_samples if reached.size else math.inf)
    return float(np.median(reached_at))
