"""Reliability index and switching signal of ch. 2 (probe-loss detection).

The observer of eqs. 2.10/3.49 runs on the free-air model
(:mod:`afmtool.estimators.observer`); its innovation e(n) = y(n) − ŷ(n) is
small when the free-air model fits (tip off the sample) and large when the
tip-sample force drives the forcing term of eq. 2.13 (tip on the sample).

Reliability index
-----------------
The index is the innovation's window RMS (W samples, one drive period by
default) divided by its free-air level::

    index(n) = RMS_W(e)(n) / ρ_fa,        ρ_fa = √(mean of RMS_W(e)² over a free-air segment)

so it reads about 1 off the sample and several times more on it.  Probe loss
means the index is **low** (docs/conventions.md, ch. 2).

Coherent index (``index="coherent"``, an addition to the thesis)
----------------------------------------------------------------
On the sample the innovation is mostly a sinusoid at the drive (the
equation error of the tip-sample force through the error dynamics, below);
in free air it is white.  The RMS index sees the sinusoid's power on top of
the noise's, √(1 + c²/2) for a sinusoid of amplitude c·σ, so it barely
rises while c < 2.  The coherent index demodulates the innovation at the
drive over the same window::

    X(n) = (2/W) Σ_{k=n−W+1..n} e(k)·e^{−jω_d k},    index(n) = |X(n)| / ρ_fa

with ρ_fa = √(mean |X|²) in free air (= 2σ/√W for white e of rms σ).  The
sinusoid then reads c·√W/2, linear in c: at Q = 400 and 0.05-0.1 nm of
noise (c ≈ 1.4 per drive period of observer memory) it is what separates the
sample from free air.  Its free-air index is Rayleigh (2 degrees of
freedom, 0.999 quantile 2.63) where the RMS index is χ_W (1.86 for W = 7),
so it pays off from about 1.5 drive periods of window (tests/test_probeloss_reference.py).
k counts samples from the stream's first, so the phasor, and the index,
do not depend on the chunking.

Switching signal
----------------
A two-threshold (hysteresis) comparator on the index, 0 < on < off::

    s(n) = 1  if s(n−1) = 0 and index(n) < on        (loss declared)
    s(n) = 0  if s(n−1) = 1 and index(n) > off       (tip back on the sample)
    s(n) = s(n−1) otherwise (NaN keeps the state)

1 means probe loss.  The same comparator, with the inequalities reversed
(``loss_when="above"``), is the amplitude baseline of Ando et al. (thesis
§2.2): loss while the lock-in amplitude exceeds A_upper (on = off = A_upper).

Automatic thresholds
--------------------
:func:`calibrate_index` sets them from free-air statistics of the index
itself: ``on`` is the ``quantile`` quantile of the free-air index (by default
0.999: a free-air stretch reads "loss" 99.9 % of the time) times
``on_margin``, and ``off = off_ratio · on``, far enough above every free-air
sample that noise does not end a loss event.  With Gaussian white
innovations and W = 7 the 0.999 quantile of the index is √(χ²₇(0.999)/7) ≈
1.86.

Choosing the observer gain
--------------------------
Off the sample the index is about 1 whatever the gain.  On the sample, for
a steady oscillation, the innovation's part at the drive frequency is the
equation error A(z)(p − p_fa) of eq. 3.40 passed through 1/C(z) (the error
dynamics, :class:`~afmtool.estimators.observer.InnovationFilters`), whose
gains at resonance are (1 − ρ)·2 sin θ and (1 − r)·2 sin θ::

    |e| ≈ |p − p_fa|·(1 − ρ)/(1 − r) ≈ |p − p_fa|·τ_obs/τ_cant

with p_fa the free-air response to the same dither, ρ = e^{−ω0T/2Q} the
model's pole radius, r the error poles' (:func:`~afmtool.estimators.observer.gain_for_decay`),
τ_obs = −1/ln r and τ_cant = 2Q/(ω0T) samples.  The on-sample contrast grows
with the observer's memory; the latency after the tip leaves grows as
τ_obs·ln(contrast/on) plus about a window.  At Q ≈ 200 the amplitude needs
only a weak interaction to fall to its set point (a frequency shift of
0.2 % brings it to 0.8·A0), so the contrast is set by |p − p_fa|/σ_noise:
with a 30 nm free amplitude, a set point of 0.7·A0 and 0.02 nm of
measurement noise, ``decay_cycles = 1`` reads about 10 on the sample and
detects loss within about one drive period (tests/test_probeloss.py).  The
steady-state Kalman gain weighs the same two noises instead; with the
thermal force of a 2 N/m lever at 300 K (about 0.005 nm per sample as
static deflection) and 0.02 nm of measurement noise its error time constant
is 1 to 2 drive periods.

Everything streams: each update takes a state and returns ``(block, state)``;
chunked runs equal one call bit for bit.

Which detector a capture gets
-----------------------------
:func:`design_detector` (:mod:`afmtool.estimators.detector_design`) chooses
among this module's two indices and the forcing detector of
:mod:`afmtool.estimators.forcing_observer` (the tip-sample force at the
drive, near the information limit) by their performance predicted on the
capture itself, and returns a typed :class:`DetectorDesign`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit

from afmtool.config.samples import sample_count
from afmtool.errors import ConfigError, InputError
from afmtool.estimators._common import as_signal
from afmtool.estimators.decimation import Decimation

# the detector's design (issue 29, item 6): which index, its parameters, its predicted performance
from afmtool.estimators.detector_design import (
    DesignInputs,
    DetectorDesign,
    DetectorOptions,
    IndexKind,
    design_detector,
)
from afmtool.estimators.observer import (
    ObserverDesign,
    ObserverState,
    WindowState,
    _check_signals,
    _predict,
    _window_block_end,
    _window_push,
    _window_resync,
    _window_rms,
)
from afmtool.jit import JIT_OPTIONS

__all__ = [
    "DesignInputs",
    "DetectorDesign",
    "DetectorOptions",
    "IndexKind",
    "design_detector",
    "LOSS_WHEN",
    "Thresholds",
    "check_thresholds",
    "FreeAirCalibration",
    "calibrate_index",
    "index_window",
    "predicted_rms_index",
    "settle_samples",
    "HysteresisStep",
    "hysteresis_update",
    "ReliabilityBlock",
    "ReliabilityState",
    "ReliabilityStep",
    "reliability_update",
]

#: Directions of :func:`hysteresis_update`: loss while the signal is below
#: the thresholds (the reliability index) or above them (the amplitude).
LOSS_WHEN = ("below", "above")

#: Defaults of :func:`calibrate_index`.
DEFAULT_QUANTILE = 0.999
DEFAULT_ON_MARGIN = 1.0
DEFAULT_OFF_RATIO = 2.0


class Thresholds(NamedTuple):
    """Hysteresis thresholds of the switching signal, in index units (dimensionless).

    Attributes
    ----------
    on : float
        Loss is declared when the index falls below ``on``.
    off : float
        Loss ends when the index rises above ``off`` (> ``on``).
    """

    on: float
    off: float


class FreeAirCalibration(NamedTuple):
    """Free-air statistics of the innovation RMS and the thresholds set from them.

    Attributes
    ----------
    level : float
        ρ_fa, the free-air innovation RMS the index is divided by,
        deflection units.
    thresholds : Thresholds
        The switching thresholds (given or automatic), index units.
    samples : int
        Free-air samples the statistics use.
    index_median, index_quantile, index_max : float
        Median, ``quantile`` quantile and maximum of the free-air index.
    quantile : float
        The quantile the automatic ``on`` is based on.
    """

    level: float
    thresholds: Thresholds
    samples: int
    index_median: float
    index_quantile: float
    index_max: float
    quantile: float


def index_window(sample_rate_hz: float, drive_frequency_hz: float, periods: float = 1.0) -> int:
    """Index window W = max(1, round(periods·fs/f_drive)) samples.

    Parameters
    ----------
    sample_rate_hz, drive_frequency_hz : float
        fs and the drive frequency, Hz (0 < f ≤ fs/2).
    periods : float, optional
        Window length in drive periods, > 0; 1 gives
        :func:`~afmtool.estimators.observer.drive_period_window`.
    """
    from afmtool.estimators.observer import drive_period_window

    if not (isinstance(periods, (int, float)) and math.isfinite(periods) and periods > 0):
        raise ConfigError(f"periods={periods!r} must be a finite number > 0")
    one = drive_period_window(sample_rate_hz, drive_frequency_hz)  # validates fs and f
    if periods == 1:
        return one
    return sample_count(periods, sample_rate_hz / drive_frequency_hz, "periods", minimum=1, per="drive period")


def settle_samples(design: ObserverDesign, window_samples: int, residual: float = 1e-6) -> int:
    """Samples after an observer's start before its window RMS is free of the start-up error.

    Parameters
    ----------
    design : ObserverDesign
        The observer; its error poles have radius r < 1.
    window_samples : int
        W of the window RMS.
    residual : float, optional
        Envelope factor the start-up error must have decayed by, in (0, 1).

    Returns
    -------
    int
        ⌈ln(residual)/ln r⌉ + W: the error envelope r^n has fallen by
        ``residual`` and the window holds no earlier sample.
    """
    if not isinstance(design, ObserverDesign):
        raise ConfigError(f"design must be an ObserverDesign, got {type(design).__name__}")
    if not (isinstance(window_samples, (int, np.integer)) and window_samples >= 1):
        raise ConfigError(f"window_samples={window_samples!r} must be an integer >= 1")
    if not (0.0 < residual < 1.0):
        raise ConfigError(f"residual={residual!r} must be in (0, 1)")
    radius = float(np.max(np.abs(design.error_poles)))
    decay = 0 if radius == 0.0 else math.ceil(math.log(residual) / math.log(radius))
    return int(decay + window_samples)


def predicted_rms_index(amplitude_deficit: float, q: float, level: float, error_radius: float,
                        period_samples: float) -> float:
    """The RMS index expected on the sample, from the amplitude the tip-sample force takes away.

    For a steady oscillation the innovation's part at the drive has amplitude
    (module docstring)::

        |e| ≈ ΔA·τ_obs/τ_cant = ΔA·π·τ_obs/Q,    τ_obs = −1/(ln r · fs/f_d) drive periods

    and the index is √(ρ_fa² + |e|²/2)/ρ_fa = √(1 + C²/2) with C = |e|/ρ_fa.
    Measured on the single-tone reference captures the index reads 1.3-1.6×
    this (the impacts add harmonics), so it errs towards "no contrast".

    Parameters
    ----------
    amplitude_deficit : float
        ΔA = A0 − A_sp, deflection units.
    q : float
        Free-air quality factor.
    level : float
        ρ_fa, the free-air innovation RMS, deflection units.
    error_radius : float
        r, the largest modulus of the observer's error poles, in [0, 1).
    period_samples : float
        fs/f_d, samples per drive period.
    """
    if not error_radius < 1.0:
        raise ConfigError(f"error_radius={error_radius!r} must be < 1 (a stable observer)")
    # a dead-beat observer (r = 0) forgets at once: no memory, no build-up of the contrast
    tau_periods = -1.0 / (math.log(error_radius) * period_samples) if error_radius > 0 else 0.0
    contrast = abs(amplitude_deficit) * math.pi * tau_periods / (q * level)
    return math.sqrt(1.0 + 0.5 * contrast * contrast)


def _check_threshold(name: str, value) -> float | None:
    if value is None:
        return None
    if not (isinstance(value, (int, float, np.floating, np.integer)) and math.isfinite(value) and value > 0):
        raise ConfigError(f"{name}={value!r} must be a finite number > 0 (or None for automatic)")
    return float(value)


def check_thresholds(on: float, off: float) -> Thresholds:
    """``Thresholds(on, off)`` after checking 0 < on < off; ConfigError otherwise."""
    on_v = _check_threshold("on", on)
    off_v = _check_threshold("off", off)
    if on_v is None or off_v is None or not on_v < off_v:
        raise ConfigError(f"thresholds on={on!r}, off={off!r} must satisfy 0 < on < off")
    return Thresholds(on_v, off_v)


def calibrate_index(
    free_air_rms,
    *,
    on: float | None = None,
    off: float | None = None,
    quantile: float = DEFAULT_QUANTILE,
    on_margin: float = DEFAULT_ON_MARGIN,
    off_ratio: float = DEFAULT_OFF_RATIO,
) -> FreeAirCalibration:
    """Free-air level of the innovation RMS and the switching thresholds.

    Parameters
    ----------
    free_air_rms : array_like, shape (T,)
        Window RMS of the innovation over a free-air stretch, after the
        observer's start-up transient, deflection units.
    on, off : float, optional
        Thresholds in index units; None sets them automatically (module
        docstring).  Given together they must satisfy 0 < on < off.
    quantile : float, optional
        Quantile of the free-air index behind the automatic ``on``, in (0, 1).
    on_margin : float, optional
        Factor > 0 on that quantile.
    off_ratio : float, optional
        Automatic ``off`` = ``off_ratio`` · on, > 1.

    Returns
    -------
    FreeAirCalibration

    Raises
    ------
    InputError
        If fewer than 16 finite samples are given or their RMS is zero.
    ConfigError
        If a parameter is out of range.

    Notes
    -----
    ρ_fa = √(mean RMS_W²) equals the RMS of the innovation over the stretch
    (every sample enters W windows), so the free-air index has unit mean
    square.
    """
    rms = as_signal("free_air_rms", free_air_rms)
    rms = rms[np.isfinite(rms)]
    if rms.size < 16:
        raise InputError(f"the free-air stretch has {rms.size} usable samples; need at least 16")
    if not (0.0 < quantile < 1.0):
        raise ConfigError(f"quantile={quantile!r} must be in (0, 1)")
    if not (math.isfinite(on_margin) and on_margin > 0):
        raise ConfigError(f"on_margin={on_margin!r} must be > 0")
    if not (math.isfinite(off_ratio) and off_ratio > 1):
        raise ConfigError(f"off_ratio={off_ratio!r} must be > 1")
    on_v = _check_threshold("on", on)
    off_v = _check_threshold("off", off)
    # ρ_fa = √(mean RMS_W²)
    level = math.sqrt(float(np.mean(np.square(rms))))
    if not level > 0:
        raise InputError("the free-air innovation RMS is zero; the index cannot be normalised")
    index = rms / level
    q_value = float(np.quantile(index, quantile))
    if on_v is None:
        on_v = on_margin * q_value
    if off_v is None:
        off_v = off_ratio * on_v
    return FreeAirCalibration(
        level,
        check_thresholds(on_v, off_v),
        int(rms.size),
        float(np.median(index)),
        q_value,
        float(index.max()),
        float(quantile),
    )


# ---------------------------------------------------------------------------
# Hysteresis comparator
# ---------------------------------------------------------------------------


@njit(**JIT_OPTIONS)
def hysteresis_step(x, state, on, off):
    """One step of the loss-when-below comparator (module docstring); returns s(n).

    Shared by :func:`hysteresis_update` and the closed-loop scan simulator.
    ``x`` NaN keeps the state (both comparisons are false).
    """
    if state == 0:
        if x < on:
            return 1
        return 0
    if x > off:
        return 0
    return 1


@njit(**JIT_OPTIONS)
def _hysteresis_kernel(x, sign, on, off, carried, out):
    """s(n) over a chunk; ``sign`` −1 turns loss-when-above into loss-when-below."""
    state = carried[0]
    for i in range(x.shape[0]):
        state = hysteresis_step(sign * x[i], state, sign * on, sign * off)
        out[i] = state
    carried[0] = state


@njit(**JIT_OPTIONS)
def _phasor_push(ring, sums, pos, e, cos_k, sin_k):
    """Put e(k)·e^{−jω_d k} in slot ``pos`` of ring rows 0 (real) and 1 (imaginary); return |Σ_W|."""
    re_sum = _window_push(ring, sums, 0, pos, e * cos_k)
    im_sum = _window_push(ring, sums, 1, pos, -e * sin_k)
    return math.sqrt(re_sum * re_sum + im_sum * im_sum)


@njit(**JIT_OPTIONS)
def _reliability_kernel(  # noqa: PLR0915 - numba kernel: one scalar recursion
        y, g, obs, xhat, ring, sums, counters, inv_level, on, off, carried, first_keep, keep_every,
        phasor, out_switch, out_index, out_decisive):
    """Observer, window RMS, index and switch in one pass over a chunk.

    The observer and window steps are the shared helpers of
    :mod:`afmtool.estimators.observer` in the order of its bank kernel, so
    the RMS is bit for bit ``observer_update``'s.  ``obs`` = [a2, b1, b0,
    bb1, bb2, L1, L2]; ``xhat`` (1, 2), ``ring`` (1, W), ``sums`` (1,),
    ``counters`` [pos, filled, since] and ``carried`` [s] are read at entry
    and written at exit.  ``out_switch`` gets s(n) for every sample,
    ``out_index`` index(n) at the samples first_keep, first_keep +
    keep_every, ..., and ``out_decisive[0]`` the first sample whose index
    sets the switch whatever its state before (below ``on`` or above
    ``off``), −1 if none: up to it the switch only holds its initial state.
    A ``ring`` of two rows makes it the coherent index (module docstring),
    with ``phasor`` = [cos ω_d n0, sin ω_d n0, cos ω_d, sin ω_d] for the
    chunk's first stream sample n0 (:func:`_phasor_push`); its first two
    entries are written back at exit (the phasor rotates on across chunks).
    """
    n_samples = y.shape[0]
    coherent = ring.shape[0] == 2
    # e^{jω_d k}, anchored once per chunk and rotated per sample: over a chunk
    # of 1e7 samples its magnitude drifts by about 1e-9
    cos_k, sin_k, cos_step, sin_step = phasor[0], phasor[1], phasor[2], phasor[3]
    width = ring.shape[1]
    d, b1, b0, bb1, bb2, l1, l2 = obs[0], obs[1], obs[2], obs[3], obs[4], obs[5], obs[6]
    x1 = xhat[0, 0]
    x2 = xhat[0, 1]
    state = carried[0]
    pos = counters[0]
    filled = counters[1]
    since = counters[2]
    inv_count = 1.0 / filled if filled > 0 else 0.0
    next_keep = first_keep
    k = 0
    decisive = -1
    start = 0
    while start < n_samples:
        stop = _window_block_end(start, n_samples, since)
        for i in range(start, stop):
            g_n = g[i]
            e, x1, x2 = _predict(x1, x2, y[i] - d * g_n, g_n, b1, b0, bb1, bb2, l1, l2)
            if filled < width:
                filled += 1
                inv_count = 1.0 / filled
            if coherent:
                # index(n) = |(2/W) Σ_W e(k) e^{−jω_d k}|·(1/ρ_fa)
                v = 2.0 * _phasor_push(ring, sums, pos, e, cos_k, sin_k) * inv_count * inv_level
                cos_k, sin_k = cos_k * cos_step - sin_k * sin_step, sin_k * cos_step + cos_k * sin_step
            else:
                # index(n) = RMS_W(e)(n)·(1/ρ_fa)
                v = _window_rms(_window_push(ring, sums, 0, pos, e * e), inv_count) * inv_level
            pos += 1
            if pos == width:
                pos = 0
            if decisive < 0 and (v < on or v > off):
                decisive = i
            state = hysteresis_step(v, state, on, off)
            out_switch[i] = state
            if i == next_keep:
                out_index[k] = v
                k += 1
                next_keep += keep_every
        since = _window_resync(ring, sums, since + (stop - start))
        start = stop
    xhat[0, 0] = x1
    xhat[0, 1] = x2
    counters[0] = pos
    counters[1] = filled
    counters[2] = since
    carried[0] = state
    phasor[0] = cos_k
    phasor[1] = sin_k
    out_decisive[0] = decisive


class HysteresisStep(NamedTuple):
    """What :func:`hysteresis_update` returns.

    Attributes
    ----------
    switch : numpy.ndarray of int8, shape (T,)
        s(n): 1 = loss.
    state : int
        s of the last sample, the state for the next chunk.
    """

    switch: np.ndarray
    state: int


def _check_state(state) -> int:
    if state not in (0, 1) or isinstance(state, bool):
        raise ConfigError(f"state={state!r} must be 0 or 1")
    return int(state)


def hysteresis_update(state: int, x, on: float, off: float, *, loss_when: str = "below") -> HysteresisStep:
    """Two-threshold comparator over one chunk, with carried state.

    Parameters
    ----------
    state : int
        s before the chunk: 0 (on the sample) or 1 (loss).
    x : array_like, shape (T,)
        The signal (index units for the index, deflection units for the
        amplitude).
    on, off : float
        ``loss_when="below"``: loss starts below ``on`` and ends above
        ``off``, on ≤ off.  ``"above"``: loss starts above ``on`` and ends
        below ``off``, on ≥ off.  on = off is a single threshold.
    loss_when : {"below", "above"}
        Direction (module docstring).

    Returns
    -------
    HysteresisStep

    Raises
    ------
    ConfigError
        If the thresholds are not finite or in the wrong order.
    """
    state = _check_state(state)
    if loss_when not in LOSS_WHEN:
        raise ConfigError(f"loss_when={loss_when!r} must be one of {LOSS_WHEN}")
    if not (math.isfinite(on) and math.isfinite(off)):
        raise ConfigError(f"on={on!r} and off={off!r} must be finite")
    sign = 1.0 if loss_when == "below" else -1.0
    if sign * on > sign * off:
        relation = "<=" if loss_when == "below" else ">="
        raise ConfigError(f"on={on!r} must be {relation} off={off!r} for loss_when={loss_when!r}")
    values = as_signal("x", x)
    out = np.empty(values.shape[0], dtype=np.int8)
    carried = np.array([state], dtype=np.int64)
    _hysteresis_kernel(values, sign, float(on), float(off), carried, out)
    return HysteresisStep(out, int(carried[0]))


# ---------------------------------------------------------------------------
# Observer + index + switch, streaming
# ---------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ReliabilityState:
    """Carried state of the probe-loss detector.

    Attributes
    ----------
    observer : ObserverState
        The free-air observer and its innovation window.
    level : float
        ρ_fa, deflection units.
    thresholds : Thresholds
        Switching thresholds, index units.
    switch : int
        s of the last sample (0 before the first).
    samples_seen : int
        Samples processed so far (fixes which samples are kept and, for the
        coherent index, the phase of the demodulating phasor).
    drive_rad : float
        0 for the RMS index; ω_d·T (rad per sample, in (0, π]) for the
        coherent index at the drive, whose window then has two rows.
    phasor : (float, float) or None
        (cos, sin) of ω_d·samples_seen, rotated on from where the detector
        started (so a chunked run equals one call bit for bit); None anchors
        it at ``samples_seen``.
    """

    observer: ObserverState
    level: float
    thresholds: Thresholds
    switch: int = 0
    samples_seen: int = 0
    drive_rad: float = 0.0
    phasor: tuple[float, float] | None = None

    @classmethod
    def initial(
        cls,
        design: ObserverDesign,
        window_samples: int,
        level: float,
        thresholds: Thresholds | tuple[float, float],
        *,
        drive_rad: float = 0.0,
        samples_seen: int = 0,
    ) -> ReliabilityState:
        """The detector before its first sample (``samples_seen`` samples into the stream).

        Parameters
        ----------
        design : ObserverDesign
            The free-air observer.
        window_samples : int
            W of the index.
        level : float
            ρ_fa, deflection units (1.0 gives the un-normalised statistic).
        thresholds : Thresholds
            Switching thresholds, index units.
        drive_rad : float, optional
            0 (RMS index) or ω_d·T in (0, π] (coherent index).
        samples_seen : int, optional
            Stream position of the first sample the detector will see.
        """
        observer = ObserverState.initial(design, window_samples)
        if drive_rad:  # the coherent index sums the real and imaginary parts: two rows
            observer = dataclasses.replace(observer, window=WindowState.initial(2, window_samples))
        return cls(observer, float(level), thresholds, samples_seen=samples_seen, drive_rad=float(drive_rad))

    def __post_init__(self) -> None:
        if not isinstance(self.observer, ObserverState):
            raise ConfigError(f"observer must be an ObserverState, got {type(self.observer).__name__}")
        if not (isinstance(self.level, float) and math.isfinite(self.level) and self.level > 0):
            raise ConfigError(f"level={self.level!r} must be a finite float > 0")
        object.__setattr__(self, "thresholds", check_thresholds(*self.thresholds))
        object.__setattr__(self, "switch", _check_state(self.switch))
        if not (isinstance(self.samples_seen, (int, np.integer)) and self.samples_seen >= 0):
            raise ConfigError(f"samples_seen={self.samples_seen!r} must be an integer >= 0")
        if not (isinstance(self.drive_rad, float) and 0.0 <= self.drive_rad <= math.pi):
            raise ConfigError(f"drive_rad={self.drive_rad!r} must be a float in [0, pi] (0 = RMS index)")
        rows = self.observer.window.ring.shape[0]
        if rows != (2 if self.drive_rad else 1):
            raise ConfigError(f"the {'coherent' if self.drive_rad else 'RMS'} index needs a window of "
                              f"{2 if self.drive_rad else 1} row(s), got {rows}")


class ReliabilityBlock(NamedTuple):
    """Detector output for one chunk.

    Attributes
    ----------
    switch : numpy.ndarray of int8, shape (T,)
        Switching signal at every sample, 1 = probe loss.
    index : numpy.ndarray
        Reliability index (dimensionless, about 1 in free air) at the kept
        samples n, (n + 1) % keep_every == 0 (n counted from the stream's
        first sample); every sample when keep_every = 1.
    first_decisive : int
        Position in the chunk of the first sample whose index sets the
        switch whatever its state before (below ``on`` or above ``off``);
        −1 if none.  Before it the switch holds the state it entered with,
        so a chunk run from a guessed state is corrected by overwriting
        ``switch[:first_decisive]`` (all of it if −1) with the true one.
    """

    switch: np.ndarray
    index: np.ndarray
    first_decisive: int = -1


class ReliabilityStep(NamedTuple):
    """What :func:`reliability_update` returns: this chunk's output and the next state."""

    block: ReliabilityBlock
    state: ReliabilityState


def _phasor(drive_rad: float, first: int) -> np.ndarray:
    """[cos ω_d n0, sin ω_d n0, cos ω_d, sin ω_d]: where the coherent index's phasor starts a chunk."""
    # ω_d·n0 of a 1e10-sample stream is 1e10 rad, exact to about 1e-6 rad: ample for a magnitude
    anchor = drive_rad * float(first)
    return np.array([math.cos(anchor), math.sin(anchor), math.cos(drive_rad), math.sin(drive_rad)])


def reliability_update(state: ReliabilityState, deflection, dither, *, keep_every: int = 1) -> ReliabilityStep:
    """Reliability index and switching signal over one chunk (ch. 2).

    Parameters
    ----------
    state : ReliabilityState
        From the previous chunk, or built from an ``ObserverState.initial``
        and a :func:`calibrate_index` result.
    deflection : array_like, shape (T,)
        y(n), deflection units.
    dither : array_like, shape (T,)
        g(n), dither units.
    keep_every : int, optional
        Return the index at one sample in ``keep_every`` (the samples n with
        (n + 1) % keep_every == 0, as the lock-in keeps them); the switch is
        returned at every sample.

    Returns
    -------
    ReliabilityStep
        ``(block, state)``; chunked runs equal one call bit for bit.

    Raises
    ------
    InputError
        If the signals are not 1-D or differ in length.
    ConfigError
        If ``state`` or ``keep_every`` is invalid.

    Notes
    -----
    Per sample, one fused loop: the observer step and window RMS of
    :func:`~afmtool.estimators.observer.observer_update` (the same shared
    helpers, so the RMS is the same bit for bit), then
    index(n) = RMS(n)·(1/ρ_fa) and the comparator of
    :func:`hysteresis_update` (loss when below).  Causal: s(n) uses samples
    up to n only.  Nothing of full rate but the int8 switch is written, so
    the pass runs at the speed of the observer alone.
    """
    if not isinstance(state, ReliabilityState):
        raise ConfigError(f"state must be a ReliabilityState, got {type(state).__name__}")
    if not (isinstance(keep_every, (int, np.integer)) and not isinstance(keep_every, bool) and keep_every >= 1):
        raise ConfigError(f"keep_every={keep_every!r} must be an integer >= 1")
    y, g = _check_signals(deflection, dither)
    observer = state.observer
    design = observer.design
    a2, a1, a0 = design.numerator
    b1, b0 = design.denominator
    l1, l2 = design.gain
    # B = [a1 − a2 b1, a0 − a2 b0]
    obs = np.array([a2, b1, b0, a1 - a2 * b1, a0 - a2 * b0, l1, l2])
    xhat = np.array(observer.estimate, dtype=np.float64).reshape(1, 2)
    ring, sums, counters = observer.window._unpack()
    n = y.shape[0]
    decimation = Decimation(int(keep_every))
    first_keep = decimation.first_kept(state.samples_seen)
    n_kept = decimation.count(state.samples_seen, n)
    switch = np.empty(n, dtype=np.int8)
    index = np.empty(n_kept, dtype=np.float64)
    carried = np.array([state.switch], dtype=np.int64)
    decisive = np.empty(1, dtype=np.int64)
    on, off = state.thresholds
    phasor = _phasor(state.drive_rad, state.samples_seen)
    if state.phasor is not None:
        phasor[0], phasor[1] = state.phasor
    _reliability_kernel(y, g, obs, xhat, ring, sums, counters, 1.0 / state.level, on, off, carried,
                        first_keep, int(keep_every), phasor, switch, index, decisive)
    estimate = xhat[0]
    estimate.setflags(write=False)
    new_observer = ObserverState(design, estimate, WindowState._pack(ring, sums, counters))
    new_state = ReliabilityState(new_observer, state.level, state.thresholds, int(carried[0]),
                                 state.samples_seen + n, state.drive_rad, (float(phasor[0]), float(phasor[1])))
    return ReliabilityStep(ReliabilityBlock(switch, index, int(decisive[0])), new_state)
