"""``decode``'s baseline: the lock-in amplitude of the deflection at the actuation frequency.

The classical reading of a bit (a larger or smaller oscillation amplitude)
beside the EKF's: the amplitude is demodulated by a lock-in
(:class:`~afmtool.estimators.lockin.LockIn`), kept one sample in ``keep``
and held in between (:class:`SampleHold`), and delayed against the
innovation's running mean (or the mean against it) so the two line up
over the same bit cells.  Moved out of :mod:`afmtool.analyses.decode`
(issue 29, item 6).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from afmtool.config.params import DecodeParams
from afmtool.estimators.decimation import Decimation
from afmtool.records.decode import BaselineRecord

if TYPE_CHECKING:  # numba and scipy load when a decode runs, not on import
    from afmtool.estimators.bitslicer import TwoClass
    from afmtool.estimators.lockin import LockIn

__all__ = ["AmplitudeBaseline", "SampleHold"]


def _group_delay_samples(lowpass_hz: float, order: int, fs: float) -> float:
    """Low-frequency group delay of the lock-in's Butterworth low-pass, samples."""
    from afmtool.estimators.filters import butterworth_lowpass_sos, sos_group_delay

    return sos_group_delay(butterworth_lowpass_sos(order, lowpass_hz, fs), lowpass_hz / 100.0, fs)


@dataclass(frozen=True)
class AmplitudeBaseline:
    """The lock-in amplitude baseline: demodulator, decimation and its alignment to the innovation."""

    lockin: LockIn
    keep: int  #: amplitude kept 1 sample in `keep`, held in between
    delay_primary: int  #: samples the innovation mean is delayed by to line up with the amplitude
    delay_aux: int  #: samples the amplitude is delayed by (one of the two is 0)

    @classmethod
    def create(cls, params: DecodeParams, fs: float, actuation_hz: float, mean_window: int) -> AmplitudeBaseline:
        from afmtool.estimators.lockin import LockIn

        rate = params.bit_rate_hz or params.bit_rate_max_hz or actuation_hz / 2
        lowpass_hz = params.baseline_lowpass_hz or min(rate / 2, actuation_hz / 4)
        lockin = LockIn(actuation_hz, fs, lowpass_hz)
        # band-limited to the low-pass: keep ≥ 16 samples per low-pass period, hold in between
        keep = int(min(max(fs / (16.0 * lowpass_hz), 1.0), 8.0))
        # the amplitude lags by the low-pass group delay and half the hold; the mean by half its window
        lag = _group_delay_samples(lowpass_hz, lockin.order, fs) + 0.5 * (keep - 1) - 0.5 * (mean_window - 1)
        if lag > 0:
            return cls(lockin, keep, int(round(lag)), 0)
        return cls(lockin, keep, 0, int(round(-lag)))

    def record(self, levels: TwoClass) -> BaselineRecord:
        """The report's ``baseline``: the lock-in, and ``levels``, the two classes of its cell amplitudes."""
        return BaselineRecord(
            method="lock-in amplitude of the deflection at the actuation frequency, integrated over the same cells",
            lockin_lowpass_hz=self.lockin.lowpass_hz, lockin_order=self.lockin.order, amplitude_kept_every=self.keep,
            alignment_delay_samples=self.delay_primary - self.delay_aux, threshold_nm=levels.threshold,
            separation=levels.separation, estimated_ber_gaussian=levels.estimated_error_rate,
        )


class SampleHold:
    """Sample-and-hold of a signal kept at capture indices n with (n + 1) % keep == 0 (LockIn's rule)."""

    def __init__(self, keep: int) -> None:
        self.keep = keep
        self.last = 0.0

    def __call__(self, start: int, n: int, kept: np.ndarray) -> np.ndarray:
        first = Decimation(self.keep).first_kept(start)
        out = np.empty(n)
        out[: min(first, n)] = self.last
        if kept.size:
            # every kept value fills `keep` samples, the last one what is left of the chunk
            whole = (n - first) // self.keep
            out[first : first + whole * self.keep].reshape(whole, self.keep)[:] = kept[:whole, None]
            out[first + whole * self.keep :] = kept[-1]
            self.last = float(kept[-1])
        return out
