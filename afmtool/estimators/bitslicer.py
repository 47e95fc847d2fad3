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
from afmtool.jit import JIT_OPTIONS

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

# Slots of the carried slicer state (SlicerState.vector).
(
    _CELL_END,  # b_k + T: end of the current cell, samples of the delayed primary
    _PERIOD,  # T: the clock's period, samples
    _PRIMARY_SUM,  # Σ primary over the integrated part of the current cell
    _AUX_SUM,  # Σ aux over the same samples
    _INTEGRATED,  # samples integrated so far in the current cell
    _LOGIC_LEVEL,  # hysteresis output: 1, 0, or -1 before the first flip
    _SMOOTH_SUM,  # Σ of the moving-average ring
    _SMOOTH_POS,  # next slot of the moving-average ring
    _SMOOTH_FILL,  # samples in the moving-average ring (≤ its length)
    _PREVIOUS_SMOOTHED,  # s[n−1] (NaN before the first sample)
    _LAST_MID_CROSSING,  # τ of the latest crossing of `mid`, samples (NaN before one)
    _SAMPLE,  # n: samples of the delayed primary seen so far
    _DELAY_POS_PRIMARY,  # next slot of the primary's delay ring
    _DELAY_POS_AUX,  # next slot of the aux's delay ring
    _STARTED,  # 1 once the delay rings hold the first sample
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
        vector[_CELL_END] = next_boundary
        vector[_PERIOD] = period
        vector[_LOGIC_LEVEL] = -1.0
        vector[_LAST_MID_CROSSING] = math.nan
        vector[_PREVIOUS_SMOOTHED] = math.nan
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
        return float(self.vector[_CELL_END])


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
def _delayed(ring, position, value):
    """Push ``value`` into a delay ring; (the value written len(ring) − 1 samples ago, next position)."""
    ring[position] = value
    position += 1
    if position == ring.shape[0]:
        position = 0
    return ring[position], position


@njit(**JIT_OPTIONS)
def _hysteresis(logic_level, smoothed, level_low, level_high):
    """(new level, flipped): 1 above ``level_high``, 0 below ``level_low``, else held; -1 is no level yet."""
    if logic_level != 1.0 and smoothed > level_high:
        return 1.0, logic_level == 0.0
    if logic_level != 0.0 and smoothed < level_low:
        return 0.0, logic_level == 1.0
    return logic_level, False


@njit(**JIT_OPTIONS)
def _slicer_kernel(  # noqa: PLR0915 - numba kernel: one scalar recursion, the equations line by line
    primary, aux, coefficients, locked, state, smooth_ring, delay_ring_primary, delay_ring_aux,
    out_centres, out_soft_primary, out_soft_aux, out_transitions,
):
    """Delay, smooth, detect transitions, track the clock and integrate cells, per sample.

    The equations are the module docstring's, one above each line.  Returns
    (cells written, transitions written).  Sample indices are those of the
    delayed streams, counted from the stream start.  The procedural twin
    is ``tests/naive_slicer.py``.
    """
    level_low = coefficients[0]
    level_mid = coefficients[1]
    level_high = coefficients[2]
    integrate_fraction = coefficients[3]
    phase_gain = coefficients[4]  # k_p
    rate_gain = coefficients[5]  # k_i
    cell_end = state[_CELL_END]
    period = state[_PERIOD]
    primary_sum = state[_PRIMARY_SUM]
    aux_sum = state[_AUX_SUM]
    integrated = state[_INTEGRATED]
    logic_level = state[_LOGIC_LEVEL]
    smooth_sum = state[_SMOOTH_SUM]
    smooth_pos = int(state[_SMOOTH_POS])
    smooth_fill = int(state[_SMOOTH_FILL])
    previous_smoothed = state[_PREVIOUS_SMOOTHED]
    last_mid_crossing = state[_LAST_MID_CROSSING]
    sample = int(state[_SAMPLE])
    delay_pos_primary = int(state[_DELAY_POS_PRIMARY])
    delay_pos_aux = int(state[_DELAY_POS_AUX])
    started = state[_STARTED]
    smooth_length = smooth_ring.shape[0]
    # the centred moving average's delay: (L − 1)/2
    smooth_delay = 0.5 * (smooth_length - 1)
    # the integrated part of a cell: phase u in [(1 − fraction)/2, (1 + fraction)/2)
    integrate_from = 0.5 * (1.0 - integrate_fraction)
    integrate_until = 0.5 * (1.0 + integrate_fraction)
    n_cells = 0
    n_transitions = 0
    for i in range(primary.shape[0]):
        if started == 0.0:
            # the delay rings start full of the first sample: x[n − D] = x[0] for n < D
            delay_ring_primary[:] = primary[i]
            delay_ring_aux[:] = aux[i]
            started = 1.0
        # p[n] = primary[n − D_p], a[n] = aux[n − D_a]
        primary_delayed, delay_pos_primary = _delayed(delay_ring_primary, delay_pos_primary, primary[i])
        aux_delayed, delay_pos_aux = _delayed(delay_ring_aux, delay_pos_aux, aux[i])
        # s[n] = (1/L) Σ_{j<L} p[n − j]  (fewer terms while the ring fills)
        if smooth_fill < smooth_length:
            smooth_fill += 1
        else:
            smooth_sum -= smooth_ring[smooth_pos]
        smooth_ring[smooth_pos] = primary_delayed
        smooth_sum += primary_delayed
        smooth_pos += 1
        if smooth_pos == smooth_length:
            smooth_pos = 0
        smoothed = smooth_sum / smooth_fill
        # τ_mid = n − 1 + (s[n−1] − mid)/(s[n−1] − s[n]) − (L − 1)/2: the crossing of mid, interpolated
        crosses = (previous_smoothed - level_mid) * (smoothed - level_mid) <= 0.0
        if previous_smoothed == previous_smoothed and crosses and previous_smoothed != smoothed:
            last_mid_crossing = (sample - 1 + (previous_smoothed - level_mid) / (previous_smoothed - smoothed)
                                 - smooth_delay)
        previous_smoothed = smoothed
        # hysteresis: level ← 1 when s > hi, 0 when s < lo; a change of level is a transition at τ_mid
        logic_level, flipped = _hysteresis(logic_level, smoothed, level_low, level_high)
        if flipped and last_mid_crossing == last_mid_crossing:
            if n_transitions < out_transitions.shape[0]:
                out_transitions[n_transitions] = last_mid_crossing
                n_transitions += 1
            if locked:
                cell_start = cell_end - period
                # e = τ − (b_k + T·round((τ − b_k)/T)): the transition's distance from the nearest boundary
                timing_error = last_mid_crossing - (
                    cell_start + period * math.floor((last_mid_crossing - cell_start) / period + 0.5)
                )
                # b ← b + k_p·e
                cell_end += phase_gain * timing_error
                # T ← T + k_i·e
                period += rate_gain * timing_error
        if locked:
            cell_start = cell_end - period
            if sample >= cell_start:
                # u = (n − b_k)/T: the phase within the cell
                cell_phase = (sample - cell_start) / period
                if integrate_from <= cell_phase < integrate_until:
                    # Σp += p[n], Σa += a[n], N += 1 over the central fraction of the cell
                    primary_sum += primary_delayed
                    aux_sum += aux_delayed
                    integrated += 1.0
                if sample + 1 >= cell_end:
                    if n_cells < out_centres.shape[0]:
                        # centre b_k + T/2; soft values Σp/N and Σa/N (NaN for a cell with no samples)
                        out_centres[n_cells] = cell_end - 0.5 * period
                        out_soft_primary[n_cells] = primary_sum / integrated if integrated > 0 else math.nan
                        out_soft_aux[n_cells] = aux_sum / integrated if integrated > 0 else math.nan
                        n_cells += 1
                    primary_sum = 0.0
                    aux_sum = 0.0
                    integrated = 0.0
                    # b_{k+1} = b_k + T
                    cell_end += period
        sample += 1
    state[_CELL_END] = cell_end
    state[_PERIOD] = period
    state[_PRIMARY_SUM] = primary_sum
    state[_AUX_SUM] = aux_sum
    state[_INTEGRATED] = integrated
    state[_LOGIC_LEVEL] = logic_level
    state[_SMOOTH_SUM] = smooth_sum
    state[_SMOOTH_POS] = smooth_pos
    state[_SMOOTH_FILL] = smooth_fill
    state[_PREVIOUS_SMOOTHED] = previous_smoothed
    state[_LAST_MID_CROSSING] = last_mid_crossing
    state[_SAMPLE] = sample
    state[_DELAY_POS_PRIMARY] = delay_pos_primary
    state[_DELAY_POS_AUX] = delay_pos_aux
    state[_STARTED] = started
    return n_cells, n_transitions


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
    smooth_ring = state.smooth_ring.copy()
    delay_ring_primary = state.delay_primary.copy()
    delay_ring_aux = state.delay_aux.copy()
    period = max(float(vector[_PERIOD]), 1.0)
    capacity = int(p.size / (0.5 * period)) + 2 if state.locked else 0
    centres = np.empty(capacity)
    soft_primary = np.empty(capacity)
    soft_aux = np.empty(capacity)
    transitions = np.empty(p.size + 1)
    n_cells, n_transitions = _slicer_kernel(
        p, a, config.coefficients(), state.locked, vector, smooth_ring, delay_ring_primary, delay_ring_aux,
        centres, soft_primary, soft_aux, transitions,
    )
    shift = float(config.delay_primary)
    # copies, not views: a caller that keeps the cells of every chunk would otherwise
    # keep each chunk's whole buffers (twice the cells, and a sample per transition slot)
    block = SlicerBlock(centres[:n_cells] - shift, soft_primary[:n_cells].copy(), soft_aux[:n_cells].copy(),
                        transitions[:n_transitions] - shift)
    return SlicerStep(block, SlicerState(vector, smooth_ring, delay_ring_primary, delay_ring_aux, state.locked))


def moving_average(x, length: int) -> np.ndarray:
    """Causal moving average over ``length`` samples (shorter at the start), as the slicer smooths."""
    x = np.asarray(x, dtype=np.float64)
    if not (isinstance(length, (int, np.integer)) and length >= 1):
        raise ConfigError(f"length={length!r} must be an integer >= 1")
    c = np.concatenate(([0.0], np.cumsum(x)))
    idx = np.arange(1, x.size + 1)
    lo = np.maximum(idx - length, 0)
    return (c[idx] - c[lo]) / (idx - lo)
