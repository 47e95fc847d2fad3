"""Stepped-sine frequency response: a lock-in per step, and the steps found in the drive.

A stepped sine drives one frequency at a time; each step's settled part is
demodulated at its frequency (batch: :func:`stepped_sine_response`,
streaming: :class:`SteppedSineAccumulator`), giving one bin of a
:class:`~afmtool.estimators.frequency_response.FrequencyResponse` per step
whose ``coherence`` is the line-power fraction.  :func:`detect_segments`
finds the steps from the drive itself when the metadata does not list them.
Split out of :mod:`afmtool.estimators.frequency_response` (issue 29, item 6).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import numpy as np
import scipy.signal

from afmtool.config.samples import MAX_SAMPLES
from afmtool.errors import ConfigError, InputError
from afmtool.estimators.frequency_response import FrequencyResponse
from afmtool.estimators.spectral_checks import check_int, check_positive, checked_signal, frozen, is_real, signal_pair

__all__ = ["SineSegment", "stepped_sine_response", "SteppedSineAccumulator", "detect_segments"]


# --------------------------------------------------------------------------- stepped sine


class SineSegment(NamedTuple):
    """One step of a stepped-sine drive: [start_s, end_s) at ``frequency_hz``."""

    start_s: float
    end_s: float
    frequency_hz: float


def _as_segment(k: int, seg) -> SineSegment:
    if isinstance(seg, Mapping):
        try:
            values = (seg["start_s"], seg["end_s"], seg["frequency_hz"])
        except KeyError as exc:
            raise InputError(f"segments[{k}] lacks {exc.args[0]!r} (needs start_s, end_s, frequency_hz)") from None
    else:
        try:
            values = tuple(seg)
        except TypeError:
            raise InputError(f"segments[{k}]={seg!r} must be a mapping or (start_s, end_s, frequency_hz)") from None
        if len(values) != 3:
            raise InputError(f"segments[{k}]={seg!r} must have 3 values (start_s, end_s, frequency_hz)")
    start, end, freq = values
    for name, value in (("start_s", start), ("end_s", end), ("frequency_hz", freq)):
        if not (is_real(value) and math.isfinite(value)):
            raise InputError(f"segments[{k}].{name}={value!r} must be a finite number")
    if not (0 <= start < end):
        raise InputError(f"segments[{k}] needs 0 <= start_s < end_s, got start_s={start!r}, end_s={end!r}")
    if freq <= 0:
        raise InputError(f"segments[{k}].frequency_hz={freq!r} must be > 0")
    return SineSegment(float(start), float(end), float(freq))


def stepped_sine_response(
    x,
    y,
    sample_rate_hz: float,
    segments: Sequence,
    *,
    settle_fraction: float = 0.5,
    min_periods: int = 10,
) -> FrequencyResponse:
    """Frequency response from a stepped sine by lock-in demodulation of each step.

    Parameters
    ----------
    x, y : array_like
        Input (drive) and output records, 1-D, equal length, finite.
    sample_rate_hz : float
        Sampling rate fs, Hz.
    segments : sequence
        Steps as mappings ``{"start_s", "end_s", "frequency_hz"}`` (capture
        metadata, :meth:`afmtool.sim.excitation.SteppedSine.segments`) or
        :class:`SineSegment`; times in s from the first sample, frequency in
        Hz.  See :func:`detect_segments` when the metadata lacks them.
    settle_fraction : float, optional
        Fraction of each step skipped at its start so that transients decay,
        in [0, 1).  A step of a mode with quality factor Q at f0 needs about
        2Q/(2πf0)·ln(1/ε) s to settle to a relative error ε (for Q = 200 at
        70 kHz and ε = 1e-3, 6 ms).
    min_periods : int, optional
        Fewest drive periods a step's steady-state window may hold.

    Returns
    -------
    FrequencyResponse
        ``method="stepped"``, one point per step, sorted by frequency (stable).

    Notes
    -----
    In each step, the steady-state window is the last N samples of the step
    holding an integer number P = ⌊(1 − settle_fraction)·duration·f⌋ of
    periods, N = round(P·fs/f).  Input and output are demodulated at the
    step frequency over that window (complex demodulation, :class:`_LockInSums`)
    and H = Ŷ/X̂.

    ``coherence`` is the fraction of the output power in the window that is
    at the drive line, γ² = (|Ŷ|²/2)/σ_y², σ_y² the mean-removed output
    power: 1 for a clean sinusoidal response, lower with noise, harmonics or
    unsettled transients.

    Treating the residual y − line as white noise of power σ_y²(1 − γ²), the
    lock-in error of Ŷ has variance 4σ_y²(1 − γ²)/N, so the relative random
    error of |Ŷ| and the phase error are both √((1 − γ²)/(N γ²)); the same
    for X̂ with its own γ_x², and ``magnitude_std`` = |H|·√(ε_x² + ε_y²),
    ``phase_std_rad`` = √(ε_x² + ε_y²).  Residual noise coloured near the
    drive frequency makes these optimistic.

    Raises
    ------
    ConfigError
        For a bad ``sample_rate_hz``, ``settle_fraction`` or ``min_periods``.
    InputError
        For bad records or segments, a segment outside the records, one
        with fewer than ``min_periods`` steady-state periods, or with no
        input at its frequency.
    """
    xa, ya = signal_pair(x, y)
    accumulator = SteppedSineAccumulator(
        sample_rate_hz, segments, settle_fraction=settle_fraction, min_periods=min_periods
    )
    accumulator.add(xa, ya)
    return accumulator.result()


class _StepWindow(NamedTuple):
    """The steady-state window [first, stop) of one step, in samples from the record's start."""

    index: int
    frequency_hz: float
    end_s: float
    first: int
    stop: int


def _step_windows(steps: Sequence[SineSegment], fs: float, settle_fraction: float, min_periods: int) -> list:
    """Each step's steady-state window (see :func:`stepped_sine_response`, Notes), checked."""
    windows = []
    for k, (start, end, freq) in enumerate(steps):
        if freq >= fs / 2:
            raise InputError(f"segments[{k}].frequency_hz={freq!r} is not below the Nyquist frequency {fs / 2:g} Hz")
        if not (math.isfinite(start) and math.isfinite(end) and 0 <= start < end and end * fs <= MAX_SAMPLES):
            raise InputError(f"segments[{k}]: {start!r}..{end!r} s must be finite, 0 <= start < end, within {MAX_SAMPLES:.0e} samples")
        stop = int(math.floor(end * fs + 1e-9))
        steady_s = (1.0 - settle_fraction) * (end - start)
        periods = int(math.floor(steady_s * freq + 1e-9))
        n = int(round(periods * fs / freq))
        if periods < min_periods or n > stop:
            raise InputError(
                f"segments[{k}] ({freq:g} Hz) holds {periods} steady-state periods, fewer than {min_periods=}"
            )
        windows.append(_StepWindow(k, freq, end, stop - n, stop))
    return windows


class _LockInSums:
    """Lock-in sums of one channel over one step window, added chunk by chunk.

    The lock-in of a window of N samples is Ŷ = (2/N) Σ_n (y[n] − ȳ) e[n],
    e[n] = e^{−j2πf n/fs} with n the absolute sample index (so input and
    output share the phase reference): for y = A sin(2πf n/fs + φ) over an
    integer number of periods, Ŷ = A·e^{j(φ − π/2)}, and the line power is
    |Ŷ|²/2.  The mean-removed power is σ² = Σ(y − ȳ)²/N.  With v = y − K
    (K the window's first sample, against cancellation in σ²) and the sums
    S1 = Σv, S2 = Σv², P = Σv·e, E = Σe:  Ŷ = (2/N)(P − (S1/N)·E) and
    σ² = S2/N − (S1/N)².
    """

    __slots__ = ("shift", "s1", "s2", "p", "e", "n")

    def __init__(self) -> None:
        self.shift: float | None = None
        self.s1 = self.s2 = 0.0
        self.p = self.e = 0j
        self.n = 0

    def add(self, values: np.ndarray, phasor: np.ndarray) -> None:
        if self.shift is None:
            self.shift = float(values[0])
        shifted = values - self.shift
        self.s1 += float(np.sum(shifted))
        self.s2 += float(np.dot(shifted, shifted))
        # two real dots: numpy's float-by-complex dot takes a slow generic loop (50x slower here)
        self.p += complex(float(np.dot(shifted, phasor.real)), float(np.dot(shifted, phasor.imag)))
        self.e += complex(np.sum(phasor))
        self.n += values.size

    def lock_in(self) -> tuple[complex, float]:
        """(Ŷ, σ²) of the whole window."""
        mean = self.s1 / self.n
        amplitude = 2.0 * (self.p - mean * self.e) / self.n
        power = max(self.s2 / self.n - mean * mean, 0.0)
        return complex(amplitude), power


class SteppedSineAccumulator:
    """Streaming stepped-sine response: per-step lock-in sums accumulated over chunks.

    Feed the input and output records in chunks of any size with
    :meth:`add`; :meth:`result` gives :func:`stepped_sine_response` of the
    concatenated records (to rounding: the sums run in another order).
    Memory is O(number of steps), whatever the record length.

    Parameters
    ----------
    sample_rate_hz, segments, settle_fraction, min_periods
        As in :func:`stepped_sine_response`.

    Raises
    ------
    ConfigError
        For a bad ``sample_rate_hz``, ``settle_fraction`` or ``min_periods``.
    InputError
        For bad segments, a step at or above the Nyquist frequency or with
        fewer than ``min_periods`` steady-state periods; for bad chunks (in
        :meth:`add`); for a step ending after the records (in :meth:`result`).
    """

    def __init__(
        self, sample_rate_hz: float, segments: Sequence, *, settle_fraction: float = 0.5, min_periods: int = 10
    ) -> None:
        fs = check_positive("sample_rate_hz", sample_rate_hz)
        if not (is_real(settle_fraction) and 0 <= settle_fraction < 1):
            raise ConfigError(f"settle_fraction={settle_fraction!r} must be a number in [0, 1)")
        min_periods = check_int("min_periods", min_periods, 1)
        if isinstance(segments, (str, bytes, Mapping)) or not isinstance(segments, Sequence) or not segments:
            raise InputError("segments must be a non-empty list of {start_s, end_s, frequency_hz}")
        steps = [_as_segment(k, seg) for k, seg in enumerate(segments)]
        self._fs = fs
        self._windows = _step_windows(steps, fs, settle_fraction, min_periods)
        self._first = np.array([w.first for w in self._windows], dtype=np.int64)
        self._stop = np.array([w.stop for w in self._windows], dtype=np.int64)
        self._sums = [(_LockInSums(), _LockInSums()) for _ in self._windows]
        self._n_samples = 0

    @property
    def n_samples(self) -> int:
        """Samples added so far."""
        return self._n_samples

    def add(self, x_chunk, y_chunk) -> None:
        """Accumulate the next chunk of input and output samples (any length ≥ 0)."""
        xc, yc = signal_pair(x_chunk, y_chunk)
        lo, hi = self._n_samples, self._n_samples + xc.size
        for k in np.flatnonzero((self._first < hi) & (self._stop > lo)):
            window = self._windows[k]
            a, b = max(window.first, lo), min(window.stop, hi)
            # time is absolute (sample index) so input and output share the phase reference
            phasor = np.exp(-2j * np.pi * window.frequency_hz / self._fs * np.arange(a, b))
            sx, sy = self._sums[k]
            sx.add(xc[a - lo : b - lo], phasor)
            sy.add(yc[a - lo : b - lo], phasor)
        self._n_samples = hi

    def result(self) -> FrequencyResponse:
        """The response of every step (see :func:`stepped_sine_response`).

        Raises
        ------
        InputError
            If a step ends after the samples added so far, or its input has
            no component at its frequency.
        """
        duration = self._n_samples / self._fs
        rows = []
        for window, (sx, sy) in zip(self._windows, self._sums):
            k, freq = window.index, window.frequency_hz
            if window.end_s > duration * (1 + 1e-12) or window.stop > self._n_samples:
                raise InputError(f"segments[{k}] ends at {window.end_s!r} s, after the records end ({duration:g} s)")
            n = window.stop - window.first
            x_amp, x_power = sx.lock_in()
            y_amp, y_power = sy.lock_in()
            if abs(x_amp) == 0 or x_power == 0:
                raise InputError(f"segments[{k}]: the input has no component at {freq:g} Hz")
            gx = min(abs(x_amp) ** 2 / 2 / x_power, 1.0)
            gy = min(abs(y_amp) ** 2 / 2 / y_power, 1.0) if y_power > 0 else 0.0
            # relative lock-in errors of X̂ and Ŷ (stepped_sine_response, Notes); gx > 0 here
            rel = math.sqrt((1 - gx) / (n * gx) + ((1 - gy) / (n * gy) if gy > 0 else math.inf))
            rows.append((freq, y_amp / x_amp, gy, rel))
        rows.sort(key=lambda r: r[0])
        freq = np.array([r[0] for r in rows])
        response = np.array([r[1] for r in rows], dtype=np.complex128)
        rel = np.array([r[3] for r in rows])
        return FrequencyResponse(
            frequency_hz=frozen(freq),
            response=frozen(response),
            coherence=frozen(np.array([r[2] for r in rows])),
            magnitude_std=frozen(np.abs(response) * rel),
            phase_std_rad=frozen(rel),
            method="stepped",
        )


#: A step's unwrapped phase may depart from a straight line by this much (rms, rad);
#: more means the frequency is not constant (e.g. a chirp).
_STEP_PHASE_RMS_RAD = 0.1
#: Blocks on each side of a candidate step boundary whose medians are compared.
_STEP_WINDOW_BLOCKS = 4


def detect_segments(
    x,
    sample_rate_hz: float,
    *,
    min_segment_s: float = 1e-3,
    tolerance_hz: float | None = None,
) -> tuple[SineSegment, ...]:
    """Find the steps of a stepped-sine drive from its instantaneous frequency.

    Parameters
    ----------
    x : array_like
        The drive (input) record, 1-D, finite.
    sample_rate_hz : float
        Sampling rate fs, Hz.
    min_segment_s : float, optional
        Shortest step to find, s.  The record is examined in blocks of
        ``min_segment_s/8``; steps shorter than 4 blocks
        (``min_segment_s/2``) are not reported.
    tolerance_hz : float, optional
        Smallest frequency step to detect, Hz.  Default: 10 robust standard
        deviations of the step statistic (Notes), and at least 1e-6·fs.

    Returns
    -------
    tuple of SineSegment
        In time order.  Adjacent steps share their boundary, placed by a
        change-point fit of the two steps' phase lines
        (:func:`_step_boundaries`); the first step starts at 0 and the last ends at the record's
        end when the drive runs up to them.  The frequency of a step is the
        slope of a straight-line fit to its unwrapped phase (away from its
        edges), Hz.  Empty if there is no stepped sine (e.g. a chirp).

    Notes
    -----
    The instantaneous frequency is f_i[n] = (φ[n+1] − φ[n])·fs/2π with φ the
    unwrapped phase of the analytic signal (:func:`scipy.signal.hilbert`) of
    the mean-removed drive (mirrored at both ends against edge ringing),
    reduced to one value f_b per block, the least-squares slope of the phase
    over the block.  At
    each block edge k the step statistic is
    d_k = median(f_b[k…k+3]) − median(f_b[k−4…k−1]); a boundary is where
    |d_k| exceeds the tolerance and is the largest within ±3 blocks.  The
    medians ignore the ringing of f_i after a step (the Hilbert transform's
    Gibbs oscillation).  Blocks whose envelope is below 0.2× the median
    envelope (no drive) also end a step.  A candidate step is rejected if its
    unwrapped phase departs from a straight line by more than 0.1 rad rms
    (so the drive needs a signal-to-noise ratio of ≳ 25 dB), or
    the medians of its two halves differ by more than the tolerance (the
    frequency drifts: a chirp).  Touching steps whose fitted frequencies
    differ by less than a quarter of the tolerance are merged (a cut caused
    by ringing near the record's ends).  The whole record is held in memory.

    Raises
    ------
    ConfigError
        For a bad ``sample_rate_hz``, ``min_segment_s`` or ``tolerance_hz``.
    InputError
        For a bad record or one shorter than 8 × ``min_segment_s``/8 blocks.
    """
    fs = check_positive("sample_rate_hz", sample_rate_hz)
    min_segment_s = check_positive("min_segment_s", min_segment_s)
    if tolerance_hz is not None:
        tolerance_hz = check_positive("tolerance_hz", tolerance_hz)
    xa = checked_signal("x", x)
    block = max(8, int(min_segment_s * fs / 8))
    if xa.size < 8 * block:
        raise InputError(f"the record has {xa.size} samples, shorter than {min_segment_s=} s at {fs:g} Hz")
    analytic, phase = _analytic_drive(xa)
    f_block, driven = _block_frequencies(phase, analytic, block, fs)
    stat = _step_statistic(f_block)
    if tolerance_hz is None:
        tolerance_hz = max(10.0 * 1.4826 * float(np.median(np.abs(stat[1:f_block.size]))), 1e-6 * fs)
    cuts = _step_cuts(stat, f_block.size, tolerance_hz)
    steps = _fitted_steps(cuts, driven, phase, f_block, block, fs, tolerance_hz)
    if not steps:
        return ()
    return _step_boundaries(steps, phase, np.abs(analytic), driven, block, fs)


def _analytic_drive(xa: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The analytic signal of the mean-removed drive and its unwrapped phase φ[n], rad."""
    # mirror the record at both ends so the FFT's wrap-around jump, whose
    # Hilbert ringing decays only as 1/distance, lies a record away
    pad = xa.size - 1
    analytic = scipy.signal.hilbert(np.pad(xa - xa.mean(), pad, mode="reflect"))[pad : pad + xa.size]
    return analytic, np.unwrap(np.angle(analytic))


def _block_frequencies(phase: np.ndarray, analytic: np.ndarray, block: int, fs: float) -> tuple[np.ndarray, np.ndarray]:
    """Per block: the frequency f_b (Hz) and whether the drive is on (envelope > 0.2× its median)."""
    inst = np.diff(phase) * fs / (2 * np.pi)
    n_blocks = inst.size // block
    # block frequency: least-squares slope of the phase over the block (noise
    # σ_φ·√12/(2π·T_b·√N_b) Hz), which also averages the ripple of f_i
    centred_t = np.arange(block) - (block - 1) / 2.0
    blocks = phase[: n_blocks * block].reshape(n_blocks, block)
    f_block = (blocks @ centred_t) / float(centred_t @ centred_t) * fs / (2 * np.pi)
    e_block = np.median(np.abs(analytic)[: n_blocks * block].reshape(n_blocks, block), axis=1)
    return f_block, e_block > 0.2 * np.median(e_block)


def _step_statistic(f_block: np.ndarray) -> np.ndarray:
    """d_k = median(f_b[k…k+3]) − median(f_b[k−4…k−1]) at each block edge k (0 at the record's ends), Hz."""
    n_blocks, m = f_block.size, _STEP_WINDOW_BLOCKS
    stat = np.zeros(n_blocks + 1)  # stat[k]: step between blocks k−1 and k
    for k in range(1, n_blocks):
        stat[k] = np.median(f_block[k : k + m]) - np.median(f_block[max(0, k - m) : k])
    return stat


def _step_cuts(stat: np.ndarray, n_blocks: int, tolerance_hz: float) -> list[int]:
    """Block edges where |d_k| exceeds the tolerance and is the largest within ±3 blocks, with 0 and n_blocks."""
    m = _STEP_WINDOW_BLOCKS
    size = np.abs(stat)
    cuts = {0, n_blocks}
    for k in range(1, n_blocks):
        near = size[max(1, k - m + 1) : min(n_blocks, k + m)]
        if size[k] > tolerance_hz and size[k] == near.max() and not any(c in cuts for c in range(k - m + 1, k)):
            cuts.add(k)
    return sorted(cuts)


def _fitted_steps(cuts, driven, phase, f_block, block, fs, tolerance_hz) -> list:
    """[first block, end block, (frequency Hz, phase at t = 0 rad)] of each accepted step, touching equal ones merged."""
    steps = []
    for a0, b0 in zip(cuts[:-1], cuts[1:]):
        for a, b in _driven_runs(driven, a0, b0):
            line = _step_line(phase, f_block, a, b, block, fs, tolerance_hz)
            if line is None:
                continue
            if steps and steps[-1][1] == a and abs(steps[-1][2][0] - line[0]) < tolerance_hz / 4:
                # a spurious cut (ringing near the record's ends): same frequency on both sides
                a = steps.pop()[0]
                line = _step_line(phase, f_block, a, b, block, fs, tolerance_hz)
            steps.append([a, b, line])
    return steps


def _driven_runs(driven: np.ndarray, a0: int, b0: int) -> list[tuple[int, int]]:
    """Maximal runs [a, b) of driven blocks inside [a0, b0)."""
    runs, start = [], None
    for k in range(a0, b0):
        if driven[k] and start is None:
            start = k
        elif not driven[k] and start is not None:
            runs.append((start, k))
            start = None
    if start is not None:
        runs.append((start, b0))
    return runs


def _step_line(phase, f_block, a: int, b: int, block: int, fs: float, tolerance_hz: float):
    """(frequency Hz, phase offset rad) of blocks [a, b) from a line fit φ ≈ φ0 + 2πf·t, or None if not a step."""
    if b - a < 4:
        return None
    half = (a + b) // 2
    if abs(np.median(f_block[a:half]) - np.median(f_block[half:b])) > tolerance_hz:
        return None
    core = slice((a + 1) * block, (b - 1) * block)
    t = np.arange(core.start, core.stop) / fs
    slope, offset = np.polyfit(t, phase[core], 1)
    if np.sqrt(np.mean((phase[core] - slope * t - offset) ** 2)) > _STEP_PHASE_RMS_RAD:
        return None
    return float(slope / (2 * np.pi)), float(offset)


def _step_boundaries(
    steps, phase: np.ndarray, envelope: np.ndarray, driven: np.ndarray, block: int, fs: float
) -> tuple[SineSegment, ...]:
    """Sample boundaries of the steps from their block edges.

    Where step A meets step B, the boundary c (first sample of B) minimises
    Σ_{n<c} (φ[n] − L_A[n])² + Σ_{n≥c} (φ[n] − L_B[n])² over ±2 blocks,
    L_A and L_B the steps' phase lines: a change-point fit that holds with or
    without phase continuity at the step.  Next to a gap without drive, the
    edge is where the envelope crosses half its median over the step.
    """
    n = phase.size
    edges = [[a * block, b * block] for a, b, _ in steps]
    for i, (a, b, _) in enumerate(steps):
        level = 0.5 * float(np.median(envelope[a * block : b * block]))
        if a > 0 and not driven[a - 1]:
            lo = max(edges[i][0] - block, 0)
            above = np.flatnonzero(envelope[lo : edges[i][0] + block] >= level)
            edges[i][0] = lo + int(above[0]) if above.size else edges[i][0]
        if b < driven.size and not driven[b]:
            lo = edges[i][1] - block
            above = np.flatnonzero(envelope[lo : min(edges[i][1] + block, n)] >= level)
            edges[i][1] = lo + int(above[-1]) + 1 if above.size else edges[i][1]
    if np.all(driven[: steps[0][0]]):
        edges[0][0] = 0
    if np.all(driven[steps[-1][1] :]):
        edges[-1][1] = n
    for i in range(len(steps) - 1):
        if steps[i][1] != steps[i + 1][0]:
            continue
        lo, hi = max(edges[i][1] - 2 * block, 0), min(edges[i][1] + 2 * block, n)
        t = np.arange(lo, hi) / fs
        (f_a, p_a), (f_b, p_b) = steps[i][2], steps[i + 1][2]
        err_a = (phase[lo:hi] - p_a - 2 * np.pi * f_a * t) ** 2
        err_b = (phase[lo:hi] - p_b - 2 * np.pi * f_b * t) ** 2
        # cost[c] for c = lo … hi: samples before c on line A, from c on line B
        cost = np.concatenate(([0.0], np.cumsum(err_a))) + np.concatenate((np.cumsum(err_b[::-1])[::-1], [0.0]))
        edges[i][1] = edges[i + 1][0] = lo + int(np.argmin(cost))
    return tuple(SineSegment(start / fs, stop / fs, step[2][0]) for (start, stop), step in zip(edges, steps))
