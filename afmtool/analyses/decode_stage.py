"""``decode``'s stream stage: the EKF and the lock-in baseline over the chunks (ch. 7).

:class:`DecodeStage` reads the nominal segment ahead, tunes the EKF on it
(:func:`~afmtool.estimators.ekf_tuning.tune_ekf`), and then runs the EKF
kernel (eqs. 7.11-7.15) and the baseline's lock-in on every chunk, feeding
the innovation's running mean to the bit slicer
(:class:`~afmtool.estimators.bit_stream.BitStreamSlicer`) or, in step
mode, to the step window.  :class:`DecodeKernels` is the same as a pure
function of a chunk, for a split run.  Split out of
:mod:`afmtool.analyses.decode` (issue 29, item 6).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from afmtool.analyses.decode_model import ModelSetup
from afmtool.config.params import DecodeParams, parse_interval
from afmtool.config.samples import interval_samples, sample_count
from afmtool.errors import ConfigError, InputError
from afmtool.estimators.amplitude_baseline import AmplitudeBaseline, SampleHold
from afmtool.estimators.bit_stream import BitStreamSlicer
from afmtool.io.capture import CaptureInfo, Chunk
from afmtool.models.electrostatic import LeverVoltages, actuation_voltage
from afmtool.pipeline import Decimation, Head, read_segment

if TYPE_CHECKING:  # numba and scipy load when a decode runs, not on import
    from afmtool.estimators.lockin import LockIn

__all__ = ["DecodeStage", "DecodeKernels", "DecodeTotals", "PsdBuffer"]

#: Welch segment of the PSD plot, samples.
_PSD_NPERSEG = 4096


def _step_sample(info: CaptureInfo, params: DecodeParams, nominal) -> int | None:
    """The V_phi step's sample in --mode step (auto: when the metadata has vphi_step); None for bits."""
    metadata_time = info.capture_metadata.vphi_step.time_s
    if params.mode == "bits" or (params.mode == "auto" and metadata_time is None):
        return None
    time_s = params.step_time_s or metadata_time or (nominal[1] if nominal is not None else None)
    if time_s is None:
        raise ConfigError("--mode step needs the step's time: --step-time, metadata vphi_step.time_s or a nominal "
                          "segment ending at it")
    return sample_count(time_s, info.sample_rate_hz, "step time")


def _nominal_interval(info: CaptureInfo, params: DecodeParams) -> tuple[float, float] | None:
    interval = parse_interval(params.nominal, "--nominal")
    nominal = info.capture_metadata.nominal  # validated when the capture was opened
    if interval is None and nominal is not None:
        interval = (nominal.start_s, nominal.end_s)
    return interval


def _voltage(data: Mapping[str, np.ndarray], params: DecodeParams, alpha_r: float) -> np.ndarray:
    if params.voltage_channel:
        return data[params.voltage_channel]
    return actuation_voltage(data["v_r"], data["v_sub"], alpha_r)


def _lever_voltages(data: Mapping[str, np.ndarray], params: DecodeParams, alpha_r: float) -> np.ndarray | LeverVoltages:
    """What the EKF kernel forms V from: the voltage channel itself, or V_R, V_sub and α_R (eq. 6.3)."""
    if params.voltage_channel:
        return data[params.voltage_channel]
    return LeverVoltages(data["v_r"], data["v_sub"], alpha_r)


def _actuation_hz(info: CaptureInfo, params: DecodeParams, voltage: np.ndarray) -> tuple[float, str]:
    if params.actuation_hz:
        return params.actuation_hz, "parameter"
    metadata_hz = info.capture_metadata.drive.frequency_hz
    if metadata_hz is not None:
        return metadata_hz, "metadata"
    from afmtool.estimators.filters import welch_psd

    v2 = voltage * voltage
    freqs, power = welch_psd(v2 - v2.mean(), info.sample_rate_hz, min(len(v2), 1 << 14))
    power[freqs < 100.0] = 0.0
    if not power.any():
        raise InputError("the voltage has no AC line to take the actuation frequency from; give --actuation-hz")
    return float(freqs[int(np.argmax(power))]), "strongest line of V^2"


class PsdBuffer:
    """The first ``limit`` samples of the raw deflection and the innovation from ``start`` on."""

    def __init__(self, start: int, limit: int) -> None:
        self.start, self.limit = start, limit
        self.parts: list[tuple[np.ndarray, np.ndarray]] = []
        self.n = 0

    def feed(self, chunk_start: int, deflection: np.ndarray, innovation: np.ndarray) -> None:
        if self.n >= self.limit:
            return
        skip = max(0, self.start - chunk_start)
        take = min(len(deflection) - skip, self.limit - self.n)
        if take > 0:
            self.parts.append((deflection[skip : skip + take].copy(), innovation[skip : skip + take].copy()))
            self.n += take

    def spectra(self, fs: float) -> dict:
        from afmtool.estimators.filters import welch_psd

        if self.n < 2 * _PSD_NPERSEG // 4:
            return {}
        deflection = np.concatenate([d for d, _ in self.parts])
        innovation = np.concatenate([e for _, e in self.parts])
        nperseg = min(_PSD_NPERSEG, self.n)
        freqs, p_defl = welch_psd(deflection, fs, nperseg)
        _, p_innov = welch_psd(innovation, fs, nperseg)
        return {"frequency_hz": freqs, "deflection": p_defl, "innovation": p_innov, "samples": self.n}


class DecodeTotals(NamedTuple):
    n_samples: int
    bit_stream_rms_nm: float | None


class DecodeStage:
    """The EKF and the lock-in baseline as a :mod:`afmtool.pipeline` stage.

    ``nominal_prologue`` reads the nominal segment ahead; ``prepare`` tunes
    the EKF on it (ℓ0, noise) and sets the clock, the baseline and the PSD
    buffer up; ``step`` runs the EKF here and the lock-in on the side
    thread (both kernels release the GIL); ``finish`` returns the totals.
    """

    def __init__(self, info: CaptureInfo, params: DecodeParams, setup: ModelSetup, channels: tuple[str, ...]) -> None:
        self.info = info
        self.params = params
        self.setup = setup
        self.channels = channels
        self.fs = info.sample_rate_hz
        self.nominal = _nominal_interval(info, params)
        self.segment = None
        self.n_total = 0

    def nominal_prologue(self, chunks: Iterator[Chunk]) -> Iterator[Chunk]:
        """Read the nominal segment ahead (when there is one); hand the whole stream on."""
        if self.nominal is not None:
            fs, alpha_r = self.fs, self.setup.electrostatic.alpha_r
            start, end = interval_samples(self.nominal, fs, "nominal segment", self.info.n_samples)
            held, chunks = read_segment(chunks, self.channels, start, end)
            self.segment = (held["deflection"], _voltage(held, self.params, alpha_r))
            del held
        return chunks

    def prepare(self, head: Head) -> None:
        """Actuation, tuning (ℓ0, noise), the EKF design, the clock, baseline and PSD buffer."""
        from afmtool.estimators.ekf import EkfState, discretise
        from afmtool.estimators.ekf_tuning import tune_ekf

        params, fs, setup, segment, nominal = self.params, self.fs, self.setup, self.segment, self.nominal
        probe = segment[1] if segment is not None else _voltage(head.first.data, params, setup.electrostatic.alpha_r)
        self.actuation_hz, self.actuation_source = _actuation_hz(self.info, params, probe)
        if not 0 < self.actuation_hz < fs / 2:
            raise InputError(
                f"actuation frequency {self.actuation_hz:g} Hz is not below the Nyquist frequency {fs / 2:g} Hz"
            )
        self.mean_window = params.mean_window or sample_count(1.0 / self.actuation_hz, fs, "actuation period", minimum=1)
        warmup = sample_count(params.warmup_s, fs, "warmup_s")
        if segment is not None and warmup >= len(segment[0]) // 2:
            raise ConfigError(
                f"warmup_s={params.warmup_s!r} leaves too little of the {len(segment[0])}-sample nominal segment"
            )
        self.tuning = tune_ekf(setup.electrostatic, setup.f0_hz, setup.q, params, fs, segment, warmup,
                               setup.l0_bracket_m())
        self.segment = None
        self.design = discretise(self.tuning.model, fs, self.mean_window)
        if params.bits_from_s >= 0:
            self.bits_start = sample_count(params.bits_from_s, fs, "bits_from_s")
        else:
            self.bits_start = sample_count(nominal[1], fs, "nominal segment END") if nominal is not None else 0
        self.baseline = AmplitudeBaseline.create(params, fs, self.actuation_hz, self.mean_window)
        self.bits = BitStreamSlicer(fs, self.bits_start, params, self.actuation_hz, self.baseline.delay_primary,
                              self.baseline.delay_aux)
        step_sample = _step_sample(self.info, params, nominal)
        self.step_window = None
        if step_sample is not None:
            from afmtool.analyses.decode_step import StepWindow

            self.step_window = StepWindow(step_sample, fs / self.actuation_hz)
        self.psd = PsdBuffer(self.bits_start, sample_count(params.psd_window_s, fs, "psd_window_s"))
        self.ekf_state = EkfState.initial(self.design, stats_from=self.bits_start)  # sums ε² over the bit stream
        self.lock_state = self.baseline.lockin.initial_state(1)
        self.held = SampleHold(self.baseline.keep)
        self.mean_kept = Decimation(self.design.mean_window)
        self.side = head.side
        self.split_sums = [0.0, 0.0, 0]
        self.ekf_settle = self._ekf_settle(head.first)

    def step(self, chunk: Chunk) -> dict[str, np.ndarray]:
        """The innovation per sample and its running mean at the end of each window."""
        from afmtool.estimators.ekf import ekf_update

        y = chunk.data["deflection"]
        demodulating = self.side.submit(self.baseline.lockin.process, (y,), self.lock_state, self.baseline.keep)
        step = ekf_update(
            self.design, self.ekf_state, y, _lever_voltages(chunk.data, self.params, self.setup.electrostatic.alpha_r)
        )
        self.ekf_state = step.state
        (demod,), self.lock_state = demodulating.result()
        return self.account(chunk, (step.block, demod.amplitude, None))

    def kernels(self) -> DecodeKernels | None:
        """The EKF and the baseline lock-in as :class:`DecodeKernels`, for a split run (None if the EKF did not settle)."""
        from afmtool.estimators.split_lead import sos_lead

        lockin_lead = sos_lead(self.baseline.lockin.sos)
        if self.ekf_settle is None or lockin_lead is None:
            return None
        lead = max(2 * self.ekf_settle + self.design.mean_window, lockin_lead)
        return DecodeKernels(self.design, self.params, self.setup.electrostatic.alpha_r, self.baseline.lockin,
                             self.baseline.keep, self.bits_start, lead)

    def account(self, chunk: Chunk, estimate) -> dict[str, np.ndarray]:
        """Everything after the kernels, in capture order: columns, PSD buffer, bit cells, statistics."""
        (innovation, mean), amplitude, sums = estimate
        y = chunk.data["deflection"]
        n = len(y)
        if sums is not None:  # a split run: the chunk's statistics, added up here
            self.split_sums = [a + b for a, b in zip(self.split_sums, sums)]
        kept = self.mean_kept.kept_index(chunk.start, n)
        # Per sample, t = n / sample_rate_hz (a root attribute of decode.h5), and float32: its
        # resolution (~1e-7 of the value) is far below the measurement noise, and at 1e8 samples
        # a float64 series with its t column was 1.6 GB to write.
        columns = {
            "t_mean": kept / self.fs,
            "innovation_mean": self.mean_kept.take(mean, chunk.start),
        }
        if self.params.rows == "per-period":  # the innovation at every sample, as before issue 33
            columns["innovation"] = innovation.astype(np.float32)
        self.psd.feed(chunk.start, y, innovation)
        held = self.held(chunk.start, n, amplitude)
        if self.step_window is not None:
            self.step_window.feed(chunk.start, y, innovation, held)
        else:
            self.bits.feed(chunk.start, mean, held)
        self.n_total = chunk.start + n
        return columns

    def finish(self) -> DecodeTotals:
        """Close the last bit cell; the sample count and the bit stream's innovation RMS."""
        if self.step_window is None:
            self.bits.finish()
            if self.bits.clock is None:
                raise InputError(f"the bit stream (from {self.bits_start / self.fs:g} s) is empty; check --bits-from")
        from afmtool.estimators.ekf import InnovationSums

        # a split run adds its chunks' sums; a sequential one carries them in the EKF's state
        stats = InnovationSums(*self.split_sums).stats() if self.split_sums[2] else self.ekf_state.stats()
        return DecodeTotals(self.n_total, stats.rms_nm if stats.count else None)


    def _ekf_settle(self, first: Chunk) -> int | None:
        """Samples the EKF needs to forget its start, measured on the first chunk (None: not within it)."""
        from afmtool.estimators.ekf import ekf_forgetting_samples

        volts = _lever_voltages(first.data, self.params, self.setup.electrostatic.alpha_r)
        return ekf_forgetting_samples(self.design, first.data["deflection"], volts)


@dataclass(frozen=True)
class DecodeKernels:
    """The EKF and the baseline lock-in as a pure function of a chunk: :class:`DecodeStage`'s
    :class:`~afmtool.pipeline.ChunkKernels`.

    The EKF starts from its prior (eq. 7.14) a lead ahead, twice the
    samples it was measured to need to forget its start
    (:func:`~afmtool.estimators.ekf.ekf_forgetting_samples`) plus one
    running-mean window; its innovation statistics are returned as sums
    for the stage to add up.
    """

    design: object
    params: DecodeParams
    alpha_r: float
    lockin: LockIn
    every: int
    bits_start: int
    lead_samples: int

    @property
    def alignment(self) -> int:
        return self.every

    def estimate(self, lead: Chunk | None, chunk: Chunk):
        """``(EkfBlock, amplitude, InnovationSums)`` of ``chunk``."""
        from afmtool.estimators.ekf import ekf_from_prior

        def signals(part: Chunk):
            return part.data["deflection"], _lever_voltages(part.data, self.params, self.alpha_r)

        block, sums = ekf_from_prior(self.design, signals(lead) if lead is not None else None, signals(chunk),
                                     stats_from=self.bits_start - chunk.start)
        lock_state = self.lockin.initial_state(1, lead.start if lead is not None else chunk.start)
        amplitude = None
        for part in (lead, chunk):
            if part is not None:
                (demod,), lock_state = self.lockin.process((part.data["deflection"],), lock_state, self.every)
                amplitude = demod.amplitude
        return block, amplitude, sums
