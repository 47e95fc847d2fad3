"""Bit detection on a stream: transitions, bit clock, integrate-and-dump, two-class threshold (§7.6).

The detector works on a "primary" signal in which the bits are levels (the
running mean of the EKF innovation, :mod:`afmtool.estimators.ekf`) and can
integrate an "aux" signal over the same bit cells (the lock-in amplitude of
the baseline), each through its own integer delay so the two line up.

Transitions
    The primary is smoothed by a moving average of ``smooth`` samples
    (centred: delay (smooth − 1)/2).  A transition is a hysteresis flip of
    the smoothed signal across ``lo``/``hi``; its time is the most recent
    crossing of ``mid`` (linearly interpolated), so rising and falling
    edges are timed alike.

Clock (:func:`acquire_clock`)
    From the transition times τ_k of an acquisition window: the bit rate
    (given, or the lowest strong peak of |Σ_k e^{−j2πfτ_k}| over a range of
    rates: transitions of a random NRZ stream sit on the cell boundaries,
    so their impulse train has lines at the bit rate and its harmonics,
    none below), then the boundary phase, refined by least squares on
    τ_k ≈ b0 + m_k·T.

Integrate-and-dump with tracking (:func:`slicer_update`)
    Cell k spans [b_k, b_k + T) in samples; the soft value is the mean of
    the signal over its central ``fraction``·T.  Every transition nudges the
    clock: with e = τ − (nearest boundary), b ← b + k_p·e and T ← T + k_i·e
    (a second-order digital PLL; k_i = 0 holds a given rate).

Threshold (:func:`two_class_threshold`)
    1-D two-means (Lloyd) on the soft values; the threshold is the midpoint
    of the two centres, and the separation in pooled standard deviations
    gives a Gaussian estimate of the bit error rate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit

from afmtool.errors import ConfigError, InputError
from afmtool.estimators._common import JIT_OPTIONS

__all__ = [
    "TwoClass",
    "two_class_threshold",
    "BitClock",
    "acquire_clock",
    "SlicerConfig",
    "SlicerState",
    "SlicerBlock",
    "SlicerStep",
    "slicer_update",
    "moving_average",
]

#: Fewest transitions from which a clock is acquired.
MIN_TRANSITIONS = 8

# Slots of the carried slicer state.
(
    _NEXT, _PERIOD, _ACC_P, _ACC_A, _CNT, _LEVEL,
    _SSUM, _SPOS, _SFILL, _PREV_S, _LAST_MID,
    _N, _DPOS_P, _DPOS_A, _STARTED,
    _STATE_LEN,
) = range(16)


# --------------------------------------------------------------------------- threshold


class TwoClass(NamedTuple):
    """Result of :func:`two_class_threshold` (units of the input)."""

    threshold: float  #: midpoint of the two centres
    low_centre: float
    high_centre: float
    low_std: float
    high_std: float
    low_count: int
    high_count: int
    separation: float  #: (high − low)/(low_std + high_std): half-distance over pooled σ
    estimated_error_rate: float  #: Gaussian estimate ½·erfc(separation/√2)


def two_class_threshold(values, *, max_iterations: int = 100) -> TwoClass:
    """Two-class clustering of 1-D values by two-means (Lloyd's algorithm).

    Starts from the 10th and 90th percentiles; each pass assigns every
    value to the nearer centre (threshold = midpoint) and moves each centre
    to its class mean, until the assignment no longer changes.

    Parameters
    ----------
    values : array_like
        Finite values (NaN are ignored); at least two distinct ones.
    max_iterations : int, optional
        Cap on the passes.

    Returns
    -------
    TwoClass
    """
    x = np.asarray(values, dtype=np.float64).ravel()
    x = x[np.isfinite(x)]
    if x.size < 2 or x.min() == x.max():
        raise InputError(f"two-class threshold needs at least two distinct finite values, got {x.size}")
    low, high = np.percentile(x, [10.0, 90.0])
    if low == high:
        low, high = float(x.min()), float(x.max())
    assigned = None
    for _ in range(max_iterations):
        threshold = 0.5 * (low + high)
        is_high = x >= threshold
        if assigned is not None and np.array_equal(is_high, assigned):
            break
        assigned = is_high
        if is_high.all() or not is_high.any():
            break
        low, high = float(x[~is_high].mean()), float(x[is_high].mean())
    threshold = 0.5 * (low + high)
    is_high = x >= threshold
    lows, highs = x[~is_high], x[is_high]
    low_std = float(lows.std()) if lows.size > 1 else 0.0
    high_std = float(highs.std()) if highs.size > 1 else 0.0
    spread = low_std + high_std
    separation = (high - low) / spread if spread > 0 else math.inf
    estimate = 0.5 * math.erfc(separation / math.sqrt(2.0)) if math.isfinite(separation) else 0.0
    return TwoClass(
        float(threshold), float(low), float(high), low_std, high_std, int(lows.size), int(highs.size),
        float(separation), float(estimate),
    )


# --------------------------------------------------------------------------- clock


class BitClock(NamedTuple):
    """A bit clock in samples of the primary stream."""

    period_samples: float  #: T = f_s/rate
    first_boundary: float  #: a cell boundary, samples from the stream start
    rate_hz: float
    recovered: bool  #: True when the rate came from the transitions
    transitions: int  #: transitions used
    line_strength: float  #: |Σ e^{−j2πfτ}|/N at the rate, 0 … 1 (1: all on the grid)
    rms_jitter_samples: float  #: rms of τ_k − (b0 + m_k T) after the fit


def _line(times: np.ndarray, freq_per_sample: np.ndarray) -> np.ndarray:
    """|Σ_k e^{−j2π f τ_k}|/N for each frequency (cycles per sample)."""
    centred = times - times.mean()
    phase = np.exp(-2j * np.pi * np.outer(freq_per_sample, centred))
    return np.abs(phase.sum(axis=1)) / times.size


def _recover_rate(times: np.ndarray, fs: float, rate_range_hz: tuple[float, float]) -> float:
    low, high = rate_range_hz
    span = times[-1] - times[0]
    if span <= 0:
        raise InputError("the transitions span no time; cannot recover the bit rate")
    step = 1.0 / (4.0 * span)  # cycles per sample: a quarter of the line width
    grid = np.arange(low / fs, high / fs + step, step)
    strength = np.concatenate([_line(times, part) for part in np.array_split(grid, max(1, grid.size // 2048))])
    interior = np.flatnonzero(
        (strength[1:-1] >= strength[:-2]) & (strength[1:-1] >= strength[2:])
    ) + 1
    if interior.size == 0:
        interior = np.array([int(np.argmax(strength))])
    strong = interior[strength[interior] >= 0.5 * strength.max()]
    k = int(strong.min())  # lowest strong line: the bit rate, not a harmonic
    a, b = grid[max(k - 1, 0)], grid[min(k + 1, grid.size - 1)]
    # golden-section refinement of the peak
    ratio = (math.sqrt(5.0) - 1.0) / 2.0
    c, d = b - ratio * (b - a), a + ratio * (b - a)
    fc, fd = _line(times, np.array([c]))[0], _line(times, np.array([d]))[0]
    for _ in range(60):
        if fc > fd:
            b, d, fd = d, c, fc
            c = b - ratio * (b - a)
            fc = _line(times, np.array([c]))[0]
        else:
            a, c, fc = c, d, fd
            d = a + ratio * (b - a)
            fd = _line(times, np.array([d]))[0]
    return 0.5 * (a + b) * fs


def acquire_clock(
    transitions_samples,
    sample_rate_hz: float,
    *,
    rate_hz: float = 0.0,
    rate_range_hz: tuple[float, float] = (1e3, 200e3),
) -> BitClock:
    """Bit rate and phase from transition times (module docstring).

    Parameters
    ----------
    transitions_samples : array_like
        Transition times τ_k, in (fractional) samples, increasing.
    sample_rate_hz : float
        f_s, Hz.
    rate_hz : float, optional
        The bit rate, Hz, if known (> 0); else it is recovered within
        ``rate_range_hz``.
    rate_range_hz : (float, float), optional
        Search range of the recovered rate, Hz.

    Returns
    -------
    BitClock

    Raises
    ------
    InputError
        Fewer than :data:`MIN_TRANSITIONS` transitions.
    """
    times = np.asarray(transitions_samples, dtype=np.float64)
    if times.size < MIN_TRANSITIONS:
        raise InputError(
            f"found {times.size} bit transitions in the clock acquisition window; need at least {MIN_TRANSITIONS}"
        )
    fs = float(sample_rate_hz)
    recovered = not rate_hz > 0
    if recovered:
        low, high = rate_range_hz
        if not 0 < low < high < fs / 2:
            raise ConfigError(f"rate_range_hz={rate_range_hz!r} must satisfy 0 < low < high < sample_rate_hz/2")
        rate_hz = _recover_rate(times, fs, rate_range_hz)
    period = fs / rate_hz
    # phase of the line: boundaries at b0 + m·T
    phasor = np.exp(-2j * np.pi * times / period).sum()
    b0 = (-np.angle(phasor) / (2 * np.pi)) % 1.0 * period
    for _ in range(2):  # least-squares refinement, outliers (|r| > T/4) left out
        m = np.rint((times - b0) / period)
        resid = times - (b0 + m * period)
        keep = np.abs(resid) <= period / 4
        if keep.sum() < MIN_TRANSITIONS:
            break
        if recovered:
            slope, intercept = np.polyfit(m[keep], times[keep], 1)
            period, b0 = float(slope), float(intercept)
        else:
            b0 = float(b0 + resid[keep].mean())
    m = np.rint((times - b0) / period)
    resid = times - (b0 + m * period)
    keep = np.abs(resid) <= period / 4
    strength = float(np.abs(np.exp(-2j * np.pi * (times - b0) / period).sum()) / times.size)
    return BitClock(
        float(period), float(b0), fs / float(period), recovered, int(times.size), strength,
        float(np.sqrt(np.mean(resid[keep] ** 2))) if keep.any() else math.nan,
    )


# --------------------------------------------------------------------------- slicer


@dataclass(frozen=True)
class SlicerConfig:
    """Fixed settings of the integrate-and-dump slicer.

    Parameters
    ----------
    lo, mid, hi : float
        Hysteresis levels and transition level of the smoothed primary.
    smooth : int
        Moving-average length for transition detection, samples (≥ 1).
    fraction : float
        Share of each cell integrated, centred, in (0, 1].
    phase_gain, rate_gain : float
        PLL gains k_p (≥ 0, < 1) and k_i (≥ 0) per transition.
    delay_primary, delay_aux : int
        Delays (samples, ≥ 0) applied to the primary and the aux signal.
    """

    lo: float
    mid: float
    hi: float
    smooth: int
    fraction: float
    phase_gain: float
    rate_gain: float
    delay_primary: int = 0
    delay_aux: int = 0

    def __post_init__(self) -> None:
        finite = math.isfinite(self.lo) and math.isfinite(self.hi)
        if not (finite and self.lo <= self.mid <= self.hi and self.lo < self.hi):
            raise ConfigError(
                f"levels lo={self.lo!r}, mid={self.mid!r}, hi={self.hi!r} must be finite, lo <= mid <= hi, lo < hi"
            )
        if not (isinstance(self.smooth, (int, np.integer)) and self.smooth >= 1):
            raise ConfigError(f"smooth={self.smooth!r} must be an integer >= 1")
        if not 0 < self.fraction <= 1:
            raise ConfigError(f"fraction={self.fraction!r} must be in (0, 1]")
        if not 0 <= self.phase_gain < 1:
            raise ConfigError(f"phase_gain={self.phase_gain!r} must be in [0, 1)")
        if not 0 <= self.rate_gain < 1:
            raise ConfigError(f"rate_gain={self.rate_gain!r} must be in [0, 1)")
        for name in ("delay_primary", "delay_aux"):
            value = getattr(self, name)
            if not (isinstance(value, (int, np.integer)) and value >= 0):
                raise ConfigError(f"{name}={value!r} must be an integer >= 0")

    def coefficients(self) -> np.ndarray:
        return np.array([self.lo, self.mid, self.hi, self.fraction, self.phase_gain, self.rate_gain])


@dataclass(frozen=True)
class SlicerState:
    """Carried slicer state: scalars, smoothing ring and the two delay lines.

    Build with :meth:`unlocked` (transitions only, for clock acquisition)
    or :meth:`locked` (integrate cells of a clock).
    """

    vector: np.ndarray
    smooth_ring: np.ndarray
    delay_primary: np.ndarray
    delay_aux: np.ndarray
    locked: bool

    @classmethod
    def _new(cls, config: SlicerConfig, next_boundary: float, period: float, locked: bool) -> SlicerState:
        vector = np.zeros(_STATE_LEN)
        vector[_NEXT] = next_boundary
        vector[_PERIOD] = period
        vector[_LEVEL] = -1.0
        vector[_LAST_MID] = math.nan
        vector[_PREV_S] = math.nan
        return cls(
            vector, np.zeros(config.smooth), np.zeros(config.delay_primary + 1), np.zeros(config.delay_aux + 1),
            locked,
        )

    @classmethod
    def unlocked(cls, config: SlicerConfig) -> SlicerState:
        """Detect transitions only."""
        return cls._new(config, math.inf, 1.0, False)

    @classmethod
    def locked_to(cls, config: SlicerConfig, clock: BitClock, start: float = 0.0) -> SlicerState:
        """Integrate the cells of ``clock``, the first one starting at the first boundary ≥ ``start``.

        ``clock`` and ``start`` are in samples of the primary stream; cells
        never start before both delay lines have filled.
        """
        period = clock.period_samples
        # the kernel counts samples of the delayed primary: primary index + delay_primary
        boundary = clock.first_boundary + config.delay_primary
        start = max(float(start) + config.delay_primary, float(max(config.delay_primary, config.delay_aux)))
        first = boundary + math.ceil((start - boundary) / period) * period
        return cls._new(config, first + period, period, True)

    @property
    def period_samples(self) -> float:
        return float(self.vector[_PERIOD])

    @property
    def next_boundary(self) -> float:
        """End of the current cell, samples of the (delayed) stream."""
        return float(self.vector[_NEXT])


class SlicerBlock(NamedTuple):
    """Cells completed in one chunk, and transitions seen."""

    centre_samples: np.ndarray  #: cell centres, samples of the primary stream (its delay removed)
    soft_primary: np.ndarray  #: mean of the primary over the integrated part of each cell
    soft_aux: np.ndarray  #: the same for the aux signal
    transitions_samples: np.ndarray  #: transition times, samples of the primary stream


class SlicerStep(NamedTuple):
    block: SlicerBlock
    state: SlicerState


@njit(**JIT_OPTIONS)
def _slicer_kernel(  # noqa: C901, PLR0915 - numba kernel: one scalar recursion
    primary, aux, coef, locked, state, sring, dring_p, dring_a, out_c, out_p, out_a, out_t
):
    """Delay, smooth, detect transitions, track the clock and integrate cells, per sample.

    Returns (cells written, transitions written).  Sample indices are those
    of the delayed streams, counted from the stream start.
    """
    lo = coef[0]
    mid = coef[1]
    hi = coef[2]
    frac = coef[3]
    kp = coef[4]
    ki = coef[5]
    nxt = state[_NEXT]
    period = state[_PERIOD]
    acc_p = state[_ACC_P]
    acc_a = state[_ACC_A]
    cnt = state[_CNT]
    level = state[_LEVEL]
    ssum = state[_SSUM]
    spos = int(state[_SPOS])
    sfill = int(state[_SFILL])
    prev_s = state[_PREV_S]
    last_mid = state[_LAST_MID]
    n = int(state[_N])
    dpos_p = int(state[_DPOS_P])
    dpos_a = int(state[_DPOS_A])
    started = state[_STARTED]
    slen = sring.shape[0]
    dlen_p = dring_p.shape[0]
    dlen_a = dring_a.shape[0]
    half_smooth = 0.5 * (slen - 1)
    lo_frac = 0.5 * (1.0 - frac)
    hi_frac = 0.5 * (1.0 + frac)
    n_cells = 0
    n_trans = 0
    for i in range(primary.shape[0]):
        # delay lines: the value written dlen − 1 samples ago (the first value before that)
        if started == 0.0:
            for j in range(dlen_p):
                dring_p[j] = primary[i]
            for j in range(dlen_a):
                dring_a[j] = aux[i]
            started = 1.0
        dring_p[dpos_p] = primary[i]
        dpos_p += 1
        if dpos_p == dlen_p:
            dpos_p = 0
        pd = dring_p[dpos_p]
        dring_a[dpos_a] = aux[i]
        dpos_a += 1
        if dpos_a == dlen_a:
            dpos_a = 0
        ad = dring_a[dpos_a]
        # s = moving average of the delayed primary over `slen` samples
        if sfill < slen:
            sfill += 1
        else:
            ssum -= sring[spos]
        sring[spos] = pd
        ssum += pd
        spos += 1
        if spos == slen:
            spos = 0
        s = ssum / sfill
        # most recent crossing of `mid`, interpolated, in delayed-primary samples
        if prev_s == prev_s and (prev_s - mid) * (s - mid) <= 0.0 and prev_s != s:
            last_mid = n - 1 + (prev_s - mid) / (prev_s - s) - half_smooth
        prev_s = s
        # hysteresis: a flip is a transition, timed at the last mid crossing
        flipped = False
        if level != 1.0 and s > hi:
            flipped = level == 0.0
            level = 1.0
        elif level != 0.0 and s < lo:
            flipped = level == 1.0
            level = 0.0
        if flipped and last_mid == last_mid:
            if n_trans < out_t.shape[0]:
                out_t[n_trans] = last_mid
                n_trans += 1
            if locked:
                # e = τ − nearest boundary; b ← b + k_p e; T ← T + k_i e
                cell_start = nxt - period
                e = last_mid - (cell_start + period * math.floor((last_mid - cell_start) / period + 0.5))
                nxt += kp * e
                period += ki * e
        if locked:
            cell_start = nxt - period
            if n >= cell_start:
                u = (n - cell_start) / period
                if lo_frac <= u < hi_frac:
                    acc_p += pd
                    acc_a += ad
                    cnt += 1.0
                if n + 1 >= nxt:
                    if n_cells < out_c.shape[0]:
                        out_c[n_cells] = nxt - 0.5 * period
                        out_p[n_cells] = acc_p / cnt if cnt > 0 else math.nan
                        out_a[n_cells] = acc_a / cnt if cnt > 0 else math.nan
                        n_cells += 1
                    acc_p = 0.0
                    acc_a = 0.0
                    cnt = 0.0
                    nxt += period
        n += 1
    state[_NEXT] = nxt
    state[_PERIOD] = period
    state[_ACC_P] = acc_p
    state[_ACC_A] = acc_a
    state[_CNT] = cnt
    state[_LEVEL] = level
    state[_SSUM] = ssum
    state[_SPOS] = spos
    state[_SFILL] = sfill
    state[_PREV_S] = prev_s
    state[_LAST_MID] = last_mid
    state[_N] = n
    state[_DPOS_P] = dpos_p
    state[_DPOS_A] = dpos_a
    state[_STARTED] = started
    return n_cells, n_trans


def slicer_update(config: SlicerConfig, state: SlicerState, primary, aux=None) -> SlicerStep:
    """Run the slicer over one chunk of the primary (and aux) signal.

    Parameters
    ----------
    config : SlicerConfig
        Levels, smoothing, fraction, gains and delays.
    state : SlicerState
        Carried state (not modified).
    primary : array_like
        The signal whose levels are the bits.
    aux : array_like, optional
        A second signal integrated over the same cells (zeros if omitted).

    Returns
    -------
    SlicerStep
        Completed cells (centre in samples of the primary stream, counted
        from the stream start, the primary delay removed), their soft values,
        the transitions, and the new state.  Chunked and single-call runs
        give the same cells.
    """
    p = np.ascontiguousarray(primary, dtype=np.float64)
    a = np.zeros_like(p) if aux is None else np.ascontiguousarray(aux, dtype=np.float64)
    if p.ndim != 1 or a.shape != p.shape:
        raise ConfigError(f"primary and aux must be 1-D of one length, got {p.shape} and {a.shape}")
    if state.smooth_ring.shape[0] != config.smooth or state.delay_primary.shape[0] != config.delay_primary + 1:
        raise ConfigError("the slicer state was built for another configuration")
    vector = state.vector.copy()
    sring = state.smooth_ring.copy()
    dring_p = state.delay_primary.copy()
    dring_a = state.delay_aux.copy()
    period = max(float(vector[_PERIOD]), 1.0)
    capacity = int(p.size / (0.5 * period)) + 2 if state.locked else 0
    out_c = np.empty(capacity)
    out_p = np.empty(capacity)
    out_a = np.empty(capacity)
    out_t = np.empty(p.size + 1)
    n_cells, n_trans = _slicer_kernel(
        p, a, config.coefficients(), state.locked, vector, sring, dring_p, dring_a, out_c, out_p, out_a, out_t
    )
    shift = float(config.delay_primary)
    # copies, not views: a caller that keeps the cells of every chunk would otherwise
    # keep each chunk's whole out_* buffers (twice the cells, and a sample per transition slot)
    block = SlicerBlock(out_c[:n_cells] - shift, out_p[:n_cells].copy(), out_a[:n_cells].copy(), out_t[:n_trans] - shift)
    return SlicerStep(block, SlicerState(vector, sring, dring_p, dring_a, state.locked))


def moving_average(x, length: int) -> np.ndarray:
    """Causal moving average over ``length`` samples (shorter at the start), as the slicer smooths."""
    x = np.asarray(x, dtype=np.float64)
    if not (isinstance(length, (int, np.integer)) and length >= 1):
        raise ConfigError(f"length={length!r} must be an integer >= 1")
    c = np.concatenate(([0.0], np.cumsum(x)))
    idx = np.arange(1, x.size + 1)
    lo = np.maximum(idx - length, 0)
    return (c[idx] - c[lo]) / (idx - lo)
