"""``decode --mode step``: the response to a step in the surface potential V_φ (thesis §7.7, Figs. 7.9-7.12).

A step in V_φ changes the electrostatic force the lever feels, but not the
voltages the EKF is given: it is a model mismatch.  The deflection and its
amplitude at the actuation frequency then settle with the lever's own time
constant, 2Q/ω0 per e-fold, while the EKF's innovation shows the
disturbance's impulse response through the filter's error dynamics and
settles in a time set by the filter, not by Q.  This module keeps the
signals around the step as they stream (bounded: at most
``STEP_WINDOW_SAMPLES``) and measures, for the deflection, the amplitude,
the innovation and its running mean, the settling time::

    the transient = the signal less its final periodic steady state (a constant and the first two actuation
    harmonics, fitted over the last quarter of the window); its one-period rms envelope; the settling time is
    the last time after the step at which the envelope exceeds SETTLE_TOLERANCE of its peak

(the definition of ``tests/test_decode.py``'s §7.7 acceptance; for the
amplitude the steady state is a constant; with noise, the envelope's floor
is three times its median once the transient is gone), and the delay after
which the innovation's running mean first leaves its pre-step scatter by
more than ``DETECTION_SIGMA`` standard deviations.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from afmtool.errors import InputError
from afmtool.records.decode import Settling, StepDetection, StepRecord

__all__ = ["STEP_WINDOW_SAMPLES", "StepWindow", "StepSeries", "step_results"]

#: Samples kept around the step (before and after together).
STEP_WINDOW_SAMPLES = 1 << 21
#: Drive periods kept before the step (the pre-step levels and scatter).
_BEFORE_PERIODS = 40
#: The settling time ends where the transient's envelope last exceeds this share of its peak.
SETTLE_TOLERANCE = 0.05
#: The running mean is detected to move when it leaves the pre-step scatter by this many std.
DETECTION_SIGMA = 5.0


class StepSeries(NamedTuple):
    """The signals around the step: per sample from ``first`` (capture samples)."""

    first: int
    deflection: np.ndarray
    innovation: np.ndarray
    amplitude: np.ndarray


class StepWindow:
    """Keeps the deflection, innovation and held lock-in amplitude from a little before the step on."""

    def __init__(self, step_sample: int, period_samples: float, lowest: int = 0) -> None:
        self.first = max(lowest, step_sample - int(math.ceil(_BEFORE_PERIODS * period_samples)))
        self.step_sample = step_sample
        self.parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.n = 0

    def feed(self, chunk_start: int, deflection: np.ndarray, innovation: np.ndarray, amplitude: np.ndarray) -> None:
        skip = max(0, self.first - chunk_start)
        take = min(len(deflection) - skip, STEP_WINDOW_SAMPLES - self.n)
        if take > 0 and chunk_start + skip >= self.first:
            part = slice(skip, skip + take)
            self.parts.append((np.array(deflection[part], dtype=np.float64),
                               np.array(innovation[part], dtype=np.float64), np.array(amplitude[part])))
            self.n += take

    def series(self) -> StepSeries:
        if not self.parts:
            raise InputError(f"the capture ends before the V_phi step at sample {self.step_sample}")
        joined = [np.concatenate([p[k] for p in self.parts]) for k in range(3)]
        return StepSeries(self.first, *joined)


def _periodic_fit(x: np.ndarray, index: np.ndarray, actuation_rad: float):
    """The least-squares steady state of ``x`` at ``index``: a constant and the first two actuation harmonics."""
    def basis(k):
        columns = [np.ones(k.size)]
        for harmonic in (1, 2):
            columns += [np.sin(harmonic * actuation_rad * k), np.cos(harmonic * actuation_rad * k)]
        return np.column_stack(columns)

    coef, *_ = np.linalg.lstsq(basis(index.astype(np.float64)), x[index], rcond=None)
    return lambda k: basis(k.astype(np.float64)) @ coef


def _envelope(residual: np.ndarray, window: int) -> np.ndarray:
    c = np.concatenate(([0.0], np.cumsum(residual * residual)))
    return np.sqrt(np.maximum(0.0, (c[window:] - c[:-window]) / window))


def _settle_samples(x: np.ndarray, step: int, actuation_rad: float, window: int,
                    periodic: bool = True) -> tuple[float, float]:
    """(settling samples after ``step``, peak envelope) of ``x`` (module docstring).

    The steady state after the step is fitted over the last quarter of the
    window (with the actuation harmonics, or a constant for an amplitude);
    the envelope's floor is the noise, three times the envelope's median
    over that last quarter, where the transient is gone.
    """
    n = x.size
    tail = np.arange(n - max(n // 4, 4 * window), n)
    if periodic:
        steady = _periodic_fit(x, tail, actuation_rad)(np.arange(step, n))
    else:
        steady = np.full(n - step, float(np.mean(x[tail])))
    envelope = _envelope(x[step:] - steady, window)
    if envelope.size == 0 or not envelope.max() > 0:
        return 0.0, 0.0
    floor = float(np.median(envelope[tail[0] - step:])) if tail[0] - step < envelope.size else 0.0
    late = np.flatnonzero(envelope > max(SETTLE_TOLERANCE * envelope.max(), 3.0 * floor))
    return (float(late[-1] + window - 1) if late.size else 0.0), float(envelope.max())


def _running_mean(x: np.ndarray, window: int) -> np.ndarray:
    c = np.concatenate(([0.0], np.cumsum(x)))
    out = np.full(x.size, np.nan)
    out[window - 1:] = (c[window:] - c[:-window]) / window
    return out


def _detection(innovation: np.ndarray, step: int, window: int, fs: float, period: float) -> StepDetection:
    """When the innovation's running mean leaves its pre-step scatter (module docstring)."""
    mean = _running_mean(innovation, window)
    before = mean[window - 1:step]
    before = before[np.isfinite(before)]
    level = float(np.mean(before)) if before.size else 0.0
    scatter = float(np.std(before)) if before.size > 1 else 0.0
    deviation = np.abs(mean[step:] - level)
    peak = float(np.nanmax(deviation)) if deviation.size else 0.0
    threshold = max(DETECTION_SIGMA * scatter, 0.05 * peak)
    crossed = np.flatnonzero(deviation > threshold)
    delay = float(crossed[0]) if crossed.size else None
    return StepDetection(pre_step_mean_nm=level, pre_step_std_nm=scatter, peak_deviation_nm=peak,
                         threshold_nm=threshold, delay_s=None if delay is None else delay / fs,
                         delay_periods=None if delay is None else delay / period)


def step_results(series: StepSeries, step_sample: int, fs: float, actuation_hz: float, f0_hz: float, q: float,
                 mean_window: int) -> StepRecord:
    """Settling times and the detection delay (module docstring), in s and actuation periods."""
    period = fs / actuation_hz
    step = step_sample - series.first
    if not 0 < step < series.deflection.size - 8 * mean_window:
        raise InputError(f"the V_phi step at {step_sample / fs:g} s leaves too little capture on either side "
                         "(--step-time)")
    rad = 2.0 * math.pi * actuation_hz / fs
    settled = {}
    for name in ("deflection", "amplitude", "innovation"):
        settle, peak = _settle_samples(getattr(series, name), step, rad, mean_window, periodic=name != "amplitude")
        settled[name] = Settling(settling_s=settle / fs, settling_periods=settle / period, transient_peak_nm=peak)
    lever = 2.0 * q / (2.0 * math.pi * f0_hz)  # 2Q/ω0
    return StepRecord(
        time_s=step_sample / fs, lever_time_constant_s=lever, lever_time_constant_periods=lever * actuation_hz,
        deflection=settled["deflection"], amplitude=settled["amplitude"], innovation=settled["innovation"],
        innovation_mean=_detection(series.innovation, step, mean_window, fs, period),
        window_s=(series.first / fs, (series.first + series.deflection.size) / fs),
        settling=f"last time the one-period rms envelope of the transient exceeds {SETTLE_TOLERANCE:g} of its peak",
    )
