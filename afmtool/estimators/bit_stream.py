"""The bit stream of ``decode``: clock acquisition, the streaming slicer, and the two-class decision (§7.6).

:class:`BitStreamSlicer` holds the first ``clock_window_s`` of the bit
stream, detects its transitions, acquires the clock
(:func:`~afmtool.estimators.bitslicer.acquire_clock`) and from then on
runs the tracking integrate-and-dump slicer chunk by chunk, collecting one
soft value per cell.  :func:`decide_bits` thresholds the soft values into
bits (two-means, :func:`~afmtool.estimators.bitslicer.two_class_threshold`).
Moved out of :mod:`afmtool.analyses.decode` (issue 29, item 6).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from afmtool.config.params import DecodeParams
from afmtool.config.samples import sample_count
from afmtool.errors import InputError
from afmtool.records.decode import BitsRecord, ClockRecord

if TYPE_CHECKING:
    from afmtool.estimators.bitslicer import TwoClass

__all__ = ["BitStreamSlicer", "BitDecision", "decide_bits"]

#: Hysteresis levels of the transition detector, as shares of the two-class span.
HYSTERESIS = (0.3, 0.7)
#: Transition smoothing: this share of one bit cell.
SMOOTH_SHARE = 0.25


class BitStreamSlicer:
    """Clock acquisition on a held window, then the streaming slicer; collects the cells.

    ``primary`` is the signal whose levels are the bits (the innovation's
    running mean), ``aux`` a second signal integrated over the same cells
    (the baseline's amplitude); each is delayed by its own ``delays`` entry
    (samples) so the two line up.
    """

    def __init__(self, fs: float, start: int, params: DecodeParams, actuation_hz: float,
                 delay_primary: int, delay_aux: int) -> None:
        self.fs = fs
        self.start = start
        self.params = params
        self.rate_max = params.bit_rate_max_hz or actuation_hz
        self.delays = (delay_primary, delay_aux)
        self.window = sample_count(params.clock_window_s, fs, "clock_window_s", minimum=1)
        self.pending: list[tuple[np.ndarray, np.ndarray]] = []
        self.pending_n = 0
        self.config = None
        self.state = None
        self.clock = None
        self.centres: list[np.ndarray] = []
        self.soft: list[np.ndarray] = []
        self.aux: list[np.ndarray] = []
        self.eye_x = np.linspace(-1.0, 1.0, 81)
        self.eye_traces = np.empty((0, self.eye_x.size))

    def feed(self, chunk_start: int, primary: np.ndarray, aux: np.ndarray) -> None:
        skip = max(0, self.start - chunk_start)
        if skip >= len(primary):
            return
        primary, aux = primary[skip:], aux[skip:]
        if self.state is None:
            self.pending.append((primary, aux))
            self.pending_n += len(primary)
            if self.pending_n >= self.window:
                self._acquire()
            return
        self._slice(primary, aux)

    def finish(self) -> None:
        if self.state is None and self.pending_n:
            self._acquire()

    def _slice(self, primary: np.ndarray, aux: np.ndarray):
        from afmtool.estimators.bitslicer import slicer_update

        step = slicer_update(self.config, self.state, primary, aux)
        self.state = step.state
        self.centres.append(step.block.centre_samples + self.start)
        self.soft.append(step.block.soft_primary)
        self.aux.append(step.block.soft_aux)
        return step.block

    def _acquire(self) -> None:
        from afmtool.estimators.bitslicer import SlicerState, acquire_clock, slicer_update

        params = self.params
        primary_all = np.concatenate([p for p, _ in self.pending])
        aux_all = np.concatenate([a for _, a in self.pending])
        self.pending = []
        # the clock and levels come from exactly the first `window` samples, whatever the chunking
        primary, aux = primary_all[: self.window], aux_all[: self.window]
        config = self._slicer_config(primary)
        found = slicer_update(config, SlicerState.unlocked(config), primary, aux).block.transitions_samples
        try:
            self.clock = acquire_clock(
                found, self.fs, rate_hz=params.bit_rate_hz, rate_range_hz=(params.bit_rate_min_hz, self.rate_max)
            )
        except InputError as exc:
            raise InputError(
                f"bit clock: {exc} in the first {len(primary) / self.fs * 1e3:.3g} ms of the bit stream "
                f"(from {self.start / self.fs:g} s); check --bits-from, --clock-window or --bit-rate"
            ) from None
        self.config = config
        self.state = SlicerState.locked_to(config, self.clock)
        block = self._slice(primary, aux)
        if primary_all.size > primary.size:
            self._slice(primary_all[primary.size :], aux_all[primary.size :])
        self._eye(primary, block.centre_samples)

    def _slicer_config(self, primary: np.ndarray):
        """Levels and smoothing of the slicer from the acquisition window's two classes."""
        from afmtool.estimators.bitslicer import SlicerConfig, moving_average, two_class_threshold

        params = self.params
        period_guess = self.fs / (params.bit_rate_hz or self.rate_max)
        smooth = max(1, int(round(SMOOTH_SHARE * period_guess)))
        try:
            levels = two_class_threshold(moving_average(primary, smooth)[smooth:])
        except InputError:
            raise InputError(
                f"bit clock: the innovation is constant over the first {len(primary) / self.fs * 1e3:.3g} ms "
                f"of the bit stream (from {self.start / self.fs:g} s); no bits to find"
            ) from None
        span = levels.high_centre - levels.low_centre
        return SlicerConfig(
            lo=levels.low_centre + HYSTERESIS[0] * span,
            mid=levels.threshold,
            hi=levels.low_centre + HYSTERESIS[1] * span,
            smooth=smooth,
            fraction=params.integrate_fraction,
            phase_gain=params.pll_phase_gain,
            rate_gain=0.0 if params.bit_rate_hz else params.pll_rate_gain,
            delay_primary=self.delays[0],
            delay_aux=self.delays[1],
        )

    def _eye(self, primary: np.ndarray, centres: np.ndarray) -> None:
        """The eye diagram's traces: the primary around the acquisition window's cell centres."""
        period = self.clock.period_samples
        usable = centres[(centres - period >= 0) & (centres + period <= len(primary) - 1)]
        usable = usable[: self.params.eye_traces]
        grid = usable[:, None] + self.eye_x[None, :] * period
        self.eye_traces = np.interp(grid.ravel(), np.arange(len(primary)), primary).reshape(grid.shape)

    def take_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The cells' centres, soft values and aux values, each joined into one array.

        The per-chunk parts are dropped as each array is joined, so the peak
        is the parts plus one joined array, not twice everything (36 MB per
        copy at 1e8 samples of 30 kbit/s).  Call once.
        """
        joined = []
        for name in ("centres", "soft", "aux"):
            parts = getattr(self, name)
            setattr(self, name, [])
            joined.append(np.concatenate(parts) if parts else np.empty(0))
            del parts
        return joined[0], joined[1], joined[2]


class BitDecision(NamedTuple):
    """The bits of the decoder and of the baseline, and what the report says about them."""

    bits: np.ndarray
    baseline_bits: np.ndarray
    centres: np.ndarray  #: cell centres, samples of the innovation running mean
    soft: np.ndarray  #: the decoder's soft value per cell, nm
    baseline_soft: np.ndarray  #: the baseline's amplitude per cell, nm
    bit_times_s: np.ndarray  #: cell centres, s, the running mean's delay removed
    threshold_nm: float
    clock_record: ClockRecord  #: the report's ``clock``
    bits_record: BitsRecord  #: the report's ``bits``
    baseline_levels: TwoClass  #: the two classes of the baseline's cell amplitudes


def decide_bits(slicer: BitStreamSlicer, params: DecodeParams, mean_window: int, warnings: list) -> BitDecision:
    """Two-class thresholds and the bits of the decoder and the baseline (one call, after the stream)."""
    from afmtool.estimators.bitslicer import two_class_threshold

    centres, soft, soft_aux = slicer.take_arrays()
    finite = np.isfinite(soft)
    if finite.sum() < 2:
        raise InputError(f"only {int(finite.sum())} complete bit cells were decoded")
    if (~finite).any():
        warnings.append(f"{int((~finite).sum())} bit cells had no samples to integrate (clock jumps); their bits are 0")
    levels = two_class_threshold(soft)
    one_low = params.polarity == "negative"
    bits = ((soft < levels.threshold) if one_low else (soft >= levels.threshold)).astype(np.uint8)
    base_levels = two_class_threshold(soft_aux)
    base_bits = (soft_aux >= base_levels.threshold).astype(np.uint8)
    bit_times = (centres - 0.5 * (mean_window - 1)) / slicer.fs
    clock = slicer.clock
    clock_record = ClockRecord(
        rate_hz=clock.rate_hz, recovered=clock.recovered, period_samples=clock.period_samples,
        final_period_samples=slicer.state.period_samples, acquisition_transitions=clock.transitions,
        line_strength=clock.line_strength, rms_jitter_samples=clock.rms_jitter_samples,
        bits_from_s=slicer.start / slicer.fs,
    )
    bits_record = BitsRecord(
        count=int(bits.size), ones=int(bits.sum()), incomplete_cells=int((~finite).sum()),
        detector=f"integrate-and-dump over the central {params.integrate_fraction:g} of each cell",
        threshold_nm=levels.threshold, centres_nm=(levels.low_centre, levels.high_centre),
        std_nm=(levels.low_std, levels.high_std), separation=levels.separation,
        estimated_ber_gaussian=levels.estimated_error_rate,
    )
    return BitDecision(bits, base_bits, centres, soft, soft_aux, bit_times, levels.threshold, clock_record,
                       bits_record, base_levels)
