"""``afmtool decode``: bits from an electrostatically actuated probe by the EKF innovation (ch. 7).

capture → nominal segment (read ahead) → measurement noise (PSD floor),
ℓ0 (§7.4: innovation RMS minimised on a grid, then golden section), process
noise (mean NIS = 1) → chunks → EKF kernel (eqs. 7.11-7.15) → innovation
and its running mean → clock acquisition on the first ``clock_window_s`` of
the bit stream, then integrate-and-dump with a tracking clock → two-class
threshold → bits.  Beside it, the lock-in amplitude of the deflection at
the actuation frequency is integrated over the same cells: the baseline.
Every filter carries its state across chunks, so the result does not depend
on the chunk size; memory is flat apart from one value per bit.

The voltage is V = α_R·V_R − V_sub from the ``v_r`` and ``v_sub`` channels
(eq. 6.3), or a channel named by ``voltage_channel``.  Model parameters
come from the parameters, ``--electrostatic`` (``identify electrostatic``'s
result) or the capture metadata, and never from the thesis's experiment:
a missing one stops the run with its name (:mod:`afmtool.analyses.decode_model`);
the report says where each came from.  Units: deflection in nm, K_esf in F·m with F = −K_esf·V²/ℓ² (no ½).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from afmtool.analyses.decode_model import ModelSetup, resolve_model
from afmtool.config.params import DecodeParams, parse_bracket_nm, parse_interval
from afmtool.config.samples import interval_samples, sample_count
from afmtool.errors import ConfigError, InputError
from afmtool.estimators.bit_errors import BitErrors, ber_upper_bound, bit_errors
from afmtool.io.capture import CaptureInfo, CaptureReader, Chunk
from afmtool.io.results import ResultWriter
from afmtool.models.electrostatic import LeverVoltages, actuation_voltage
from afmtool.pipeline import Decimation, Head, Split, read_segment, run_stream
from afmtool.report.results import JsonResults

if TYPE_CHECKING:  # numba and scipy load when a decode runs, not on import
    from afmtool.estimators.lockin import LockIn

__all__ = [
    "DecodeResult",
    "run_decode",
    "BitErrors",
    "bit_errors",
    "ber_upper_bound",
    "ModelSetup",
    "resolve_model",
    "SERIES_UNITS",
]

#: Series written, with units: ``t`` and ``innovation`` per sample; the running mean of the
#: innovation (over one actuation period) at the end of each period, ``t_mean`` and ``innovation_mean``.
SERIES_UNITS = {"innovation": "nm", "t_mean": "s", "innovation_mean": "nm"}

#: Hysteresis levels of the transition detector, as shares of the two-class span.
_HYSTERESIS = (0.3, 0.7)
#: Transition smoothing: this share of one bit cell.
_SMOOTH_SHARE = 0.25
#: Welch segment of the PSD plot, samples.
_PSD_NPERSEG = 4096
#: Chunks read ahead in a background thread while the EKF runs on the current one.
_READ_AHEAD = 1
#: Smallest measurement noise the EKF assumes, nm (a noise-free capture would make R = 0).
_MIN_MEASUREMENT_NOISE_NM = 1e-4


# --------------------------------------------------------------------------- result


@dataclass(frozen=True)
class DecodeResult(JsonResults):
    """What :func:`run_decode` found; the command turns it into files and a report."""

    results: dict
    warnings: tuple[str, ...]
    l0_curve_nm: tuple[np.ndarray, np.ndarray] | None  #: (ℓ0, innovation RMS), nm
    psd: dict = field(default_factory=dict)  #: frequency_hz, deflection, innovation (nm²/Hz)
    eye: dict = field(default_factory=dict)  #: x (bit periods), traces (2-D, nm), threshold_nm
    step: object = None  #: StepSeries around the V_phi step (--mode step), for its figure


# --------------------------------------------------------------------------- setup helpers


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


class _Tuning(NamedTuple):
    model: object  # EkfModel
    results: dict
    l0_curve_nm: tuple[np.ndarray, np.ndarray] | None
    warnings: list


def _tune(setup: ModelSetup, params: DecodeParams, fs: float, segment, warmup: int) -> _Tuning:
    """Measurement noise, ℓ0 and process noise: given, or from the nominal segment."""
    from afmtool.estimators.ekf import EkfModel, thermal_force_asd
    from afmtool.estimators.ekf_tuning import estimate_process_noise, innovation_stats

    warnings: list[str] = []
    es = setup.electrostatic
    thermal = thermal_force_asd(es.spring_constant_n_per_m, setup.f0_hz, setup.q, params.temperature_k) \
        if params.temperature_k > 0 else 0.0
    noise: dict = {"thermal_force_asd_n_per_rthz": thermal, "temperature_k": params.temperature_k}
    if segment is None:
        missing = [n for n, v in (("l0_nm", params.l0_nm), ("measurement_noise_nm", params.measurement_noise_nm),
                                  ("process_noise_n_per_rthz", params.process_noise_n_per_rthz)) if not v]
        if missing:
            raise ConfigError(
                f"no nominal segment (give --nominal START:END or capture metadata nominal) to estimate "
                f"{', '.join(missing)}; or give them"
            )
    y, v = segment if segment is not None else (None, None)
    r_nm = _measurement_noise(setup, params, fs, y, noise, warnings)
    q_start = params.process_noise_n_per_rthz or thermal
    if not q_start > 0:
        raise ConfigError("the process noise is 0: give --process-noise or a temperature_k > 0")
    model = EkfModel(setup.f0_hz, setup.q, es, q_start, r_nm)
    if params.l0_nm:
        l0_result: dict = {"estimate_nm": params.l0_nm, "source": "parameter"}
        curve = None
    else:
        model, l0_result, curve = _search_l0(model, params, setup, segment, fs, warmup, warnings)
    if params.process_noise_n_per_rthz:
        noise["process_noise_n_per_rthz"], noise["process_source"] = params.process_noise_n_per_rthz, "parameter"
    else:
        fit = estimate_process_noise(model, y, v, fs, warmup=warmup)
        model = model.with_noise(fit.asd_n_per_rthz, r_nm)
        noise["process_noise_n_per_rthz"] = fit.asd_n_per_rthz
        noise["process_source"] = "mean NIS = 1 on the nominal segment"
        if fit.clamped:
            warnings.append(
                f"process noise: no consistent level in the search range (mean NIS {fit.mean_nis:.3g}); "
                f"using {fit.asd_n_per_rthz:.3g} N/sqrt(Hz)"
            )
    if segment is not None:
        stats = innovation_stats(model, y, v, fs, warmup)
        noise["nominal_innovation_rms_nm"] = stats.rms_nm
        noise["nominal_mean_nis"] = stats.mean_nis
    return _Tuning(model, {"l0": l0_result, "noise": noise}, curve, warnings)


def _measurement_noise(setup: ModelSetup, params: DecodeParams, fs: float, y, noise: dict, warnings: list) -> float:
    """R of the EKF, nm: given, or the PSD floor of the nominal segment (recorded in ``noise``)."""
    from afmtool.estimators.ekf_tuning import estimate_measurement_noise

    if params.measurement_noise_nm:
        r_nm, noise["measurement_source"] = params.measurement_noise_nm, "parameter"
    else:
        if 0.3 * fs < 3.0 * setup.f0_hz:
            raise ConfigError(
                f"the PSD floor above 0.3·fs = {0.3 * fs:g} Hz is not clear of the resonance f0 = {setup.f0_hz:g} Hz; "
                "give --measurement-noise"
            )
        r_nm, noise["measurement_source"] = estimate_measurement_noise(y, fs), "PSD floor of the nominal segment"
        if not r_nm >= _MIN_MEASUREMENT_NOISE_NM:
            warnings.append(
                f"the deflection's noise floor is {r_nm:.3g} nm (a noise-free capture?); the EKF assumes "
                f"{_MIN_MEASUREMENT_NOISE_NM:g} nm"
            )
            r_nm = _MIN_MEASUREMENT_NOISE_NM
    noise["measurement_noise_nm"] = r_nm
    return r_nm


def _search_l0(model, params: DecodeParams, setup: ModelSetup, segment, fs: float, warmup: int,
               warnings: list) -> tuple:
    """ℓ0 by §7.4 on the nominal segment: (model with it, the report's ``l0``, the RMS curve in nm)."""
    from afmtool.estimators.ekf_tuning import estimate_l0

    y, v = segment
    geometric = False
    if params.l0_bracket_nm:
        low, high = parse_bracket_nm(params.l0_bracket_nm)
    else:
        low_m, high_m, geometric = setup.l0_bracket_m()
        low, high = max(low_m, 1.01 * setup.electrostatic.tip_height_m) * 1e9, high_m * 1e9
    search = estimate_l0(
        model, y, v, fs, bracket_m=(low * 1e-9, high * 1e-9), grid_points=params.l0_grid_points, warmup=warmup,
        geometric=geometric,
    )
    l0_result = {
        "estimate_nm": search.l0_m * 1e9,
        "source": "innovation RMS minimum on the nominal segment (§7.4)",
        "rms_at_minimum_nm": search.rms_nm,
        "bracket_nm": [low, high],
        "grid_points": search.grid_points,
        "evaluations": int(search.curve_l0_m.size),
        "unique_minimum": search.unique,
        "process_noise_used_n_per_rthz": model.process_noise_n_per_rthz,
    }
    if not search.unique:
        warnings.append(f"l0: no unique minimum of the innovation RMS: {search.note}")
    return model.with_l0(search.l0_m), l0_result, (search.curve_l0_m * 1e9, search.curve_rms_nm)


def _group_delay_samples(lowpass_hz: float, order: int, fs: float) -> float:
    """Low-frequency group delay of the lock-in's Butterworth low-pass, samples."""
    from afmtool.estimators.filters import butterworth_lowpass_sos, sos_group_delay

    return sos_group_delay(butterworth_lowpass_sos(order, lowpass_hz, fs), lowpass_hz / 100.0, fs)


# --------------------------------------------------------------------------- bit stage


class _BitStage:
    """Clock acquisition on a held window, then the streaming slicer; collects the cells."""

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
        from afmtool.estimators.bitslicer import (
            SlicerConfig,
            SlicerState,
            acquire_clock,
            moving_average,
            slicer_update,
            two_class_threshold,
        )

        params = self.params
        primary_all = np.concatenate([p for p, _ in self.pending])
        aux_all = np.concatenate([a for _, a in self.pending])
        self.pending = []
        # the clock and levels come from exactly the first `window` samples, whatever the chunking
        primary, aux = primary_all[: self.window], aux_all[: self.window]
        period_guess = self.fs / (params.bit_rate_hz or self.rate_max)
        smooth = max(1, int(round(_SMOOTH_SHARE * period_guess)))
        try:
            levels = two_class_threshold(moving_average(primary, smooth)[smooth:])
        except InputError:
            raise InputError(
                f"bit clock: the innovation is constant over the first {len(primary) / self.fs * 1e3:.3g} ms "
                f"of the bit stream (from {self.start / self.fs:g} s); no bits to find"
            ) from None
        span = levels.high_centre - levels.low_centre
        config = SlicerConfig(
            lo=levels.low_centre + _HYSTERESIS[0] * span,
            mid=levels.threshold,
            hi=levels.low_centre + _HYSTERESIS[1] * span,
            smooth=smooth,
            fraction=params.integrate_fraction,
            phase_gain=params.pll_phase_gain,
            rate_gain=0.0 if params.bit_rate_hz else params.pll_rate_gain,
            delay_primary=self.delays[0],
            delay_aux=self.delays[1],
        )
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
        period = self.clock.period_samples
        centres = block.centre_samples
        usable = centres[(centres - period >= 0) & (centres + period <= len(primary) - 1)]
        usable = usable[: params.eye_traces]
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


class _Hold:
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


class _PsdBuffer:
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


# --------------------------------------------------------------------------- run


def run_decode(
    reader: CaptureReader,
    params: DecodeParams,
    writer: ResultWriter,
    *,
    progress: Callable[[int], None] | None = None,
    on_stream_start: Callable[[], None] | None = None,
    split: Split | None = None,
) -> DecodeResult:
    """Decode the bits of a capture, streaming, and write the per-sample series.

    Parameters
    ----------
    reader : CaptureReader
        Needs ``deflection`` (nm) and ``v_sub``, ``v_r`` (V), or the channel
        ``params.voltage_channel`` (V).
    params : DecodeParams
        Effective parameters.
    writer : ResultWriter
        Receives ``t`` and ``innovation`` per sample, ``t_mean`` and
        ``innovation_mean`` once per running-mean window, and
        ``bit_times_s``, ``bits``, ``soft``, ``baseline_soft``,
        ``baseline_bits`` and the ℓ0 curve as whole arrays.
    progress : callable, optional
        Called with the samples read so far.
    on_stream_start : callable, optional
        Called once, when the model is tuned and the stream begins (the
        command starts loading its plotting library then).
    split : Split, optional
        Run the EKF on several chunks at once (:class:`~afmtool.pipeline.Split`);
        the bits are those of the sequential run (``tests/test_split.py``).

    Returns
    -------
    DecodeResult
    """
    from afmtool.io.chunks import require_channels
    from afmtool.io.electrostatic_file import read_electrostatic_file

    info = reader.info
    fs = info.sample_rate_hz
    channels = ("deflection",) + ((params.voltage_channel,) if params.voltage_channel else ("v_sub", "v_r"))
    require_channels(info, channels)  # before the model: a capture of something else is told so first
    setup = resolve_model(info, params, read_electrostatic_file(params.electrostatic) if params.electrostatic else None)
    if setup.f0_hz >= fs / 2:
        raise InputError(f"f0 = {setup.f0_hz:g} Hz is not below the Nyquist frequency {fs / 2:g} Hz")
    decoding = _DecodeStage(info, params, setup, channels)
    (totals,) = run_stream(
        reader, [decoding], writer, channels=channels, chunk_samples=params.chunk_samples, progress=progress,
        prologue=decoding.nominal_prologue, read_ahead=_READ_AHEAD, split=split, on_start=on_stream_start,
    )
    tuning = decoding.tuning
    if tuning.l0_curve_nm is not None:
        writer.put("l0_search/l0_nm", tuning.l0_curve_nm[0], "nm")
        writer.put("l0_search/innovation_rms_nm", tuning.l0_curve_nm[1], "nm")
    results = _common_results(decoding, totals, fs)
    warnings = list(tuning.warnings)
    if decoding.step_window is not None:
        from afmtool.analyses.decode_step import step_results

        series = decoding.step_window.series()
        results["mode"] = "step"
        results["step"] = step_results(series, decoding.step_window.step_sample, fs, decoding.actuation_hz,
                                       setup.f0_hz, setup.q, decoding.mean_window)
        return DecodeResult(results, tuple(warnings), tuning.l0_curve_nm, decoding.psd.spectra(fs), {}, series)
    stage, mean_window = decoding.bits, decoding.mean_window
    decided = _decide(stage, params, mean_window, writer, warnings)
    results.update({"mode": "bits", **decided.results,
                    "baseline": {**decoding.baseline.results(), **decided.baseline_results}})
    results["clock"]["bits_from_s"] = decoding.bits_start / fs
    _compare_truth(reader, results, decided, stage.clock.period_samples, 0.5 * (mean_window - 1))
    eye = {"x": stage.eye_x, "traces": stage.eye_traces, "threshold_nm": decided.threshold_nm}
    eye = eye if stage.eye_traces.size else {}
    return DecodeResult(results, tuple(warnings), tuning.l0_curve_nm, decoding.psd.spectra(fs), eye)


def _common_results(decoding: _DecodeStage, totals, fs: float) -> dict:
    """The model, the nominal segment, the tuning and the EKF's figures: the results of either mode."""
    nominal = decoding.nominal
    return {
        "model": _model_results(decoding.setup, decoding.params),
        "nominal_segment_s": list(nominal) if nominal is not None else None,
        **decoding.tuning.results,
        "ekf": {
            "sample_rate_hz": fs,
            "actuation_hz": decoding.actuation_hz,
            "actuation_source": decoding.actuation_source,
            "mean_window_samples": decoding.mean_window,
            "bit_stream_innovation_rms_nm": totals.bit_stream_rms_nm,
        },
        "n_samples": totals.n_samples,
        "duration_s": totals.n_samples / fs,
    }


def _model_results(setup: ModelSetup, params: DecodeParams) -> dict:
    es = setup.electrostatic
    return {
        "f0_hz": setup.f0_hz,
        "q": setup.q,
        "spring_constant_n_per_m": es.spring_constant_n_per_m,
        "k_esf_f_m": es.k_esf_f_m,
        "alpha_r": es.alpha_r,
        "tip_height_nm": es.tip_height_m * 1e9,
        "l0_guess_nm": es.l0_m * 1e9 if setup.l0_known else None,
        "sources": setup.sources,
        "convention": "F_esf = -K_esf*V^2/(l0 + p)^2 (no 1/2), K_esf in F*m; EKF state [p (nm), dp/dt (nm/s)]",
        "voltage": params.voltage_channel or "alpha_r*v_r - v_sub",
    }


@dataclass(frozen=True)
class _Baseline:
    """The lock-in amplitude baseline: demodulator, decimation and its alignment to the innovation."""

    lockin: LockIn
    keep: int  #: amplitude kept 1 sample in `keep`, held in between
    delay_primary: int  #: samples the innovation mean is delayed by to line up with the amplitude
    delay_aux: int  #: samples the amplitude is delayed by (one of the two is 0)

    @classmethod
    def create(cls, params: DecodeParams, fs: float, actuation_hz: float, mean_window: int) -> _Baseline:
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

    def results(self) -> dict:
        return {
            "method": "lock-in amplitude of the deflection at the actuation frequency, integrated over the same cells",
            "lockin_lowpass_hz": self.lockin.lowpass_hz,
            "lockin_order": self.lockin.order,
            "amplitude_kept_every": self.keep,
            "alignment_delay_samples": self.delay_primary - self.delay_aux,
        }


class _Totals(NamedTuple):
    n_samples: int
    bit_stream_rms_nm: float | None


class _DecodeStage:
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
        self.tuning = _tune(setup, params, fs, segment, warmup)
        self.segment = None
        self.design = discretise(self.tuning.model, fs, self.mean_window)
        if params.bits_from_s >= 0:
            self.bits_start = sample_count(params.bits_from_s, fs, "bits_from_s")
        else:
            self.bits_start = sample_count(nominal[1], fs, "nominal segment END") if nominal is not None else 0
        self.baseline = _Baseline.create(params, fs, self.actuation_hz, self.mean_window)
        self.bits = _BitStage(fs, self.bits_start, params, self.actuation_hz, self.baseline.delay_primary,
                              self.baseline.delay_aux)
        step_sample = _step_sample(self.info, params, nominal)
        self.step_window = None
        if step_sample is not None:
            from afmtool.analyses.decode_step import StepWindow

            self.step_window = StepWindow(step_sample, fs / self.actuation_hz)
        self.psd = _PsdBuffer(self.bits_start, sample_count(params.psd_window_s, fs, "psd_window_s"))
        self.ekf_state = EkfState.initial(self.design, stats_from=self.bits_start)  # sums ε² over the bit stream
        self.lock_state = self.baseline.lockin.initial_state(1)
        self.held = _Hold(self.baseline.keep)
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
            "innovation": innovation.astype(np.float32),
            "t_mean": kept / self.fs,
            "innovation_mean": self.mean_kept.take(mean, chunk.start),
        }
        self.psd.feed(chunk.start, y, innovation)
        held = self.held(chunk.start, n, amplitude)
        if self.step_window is not None:
            self.step_window.feed(chunk.start, y, innovation, held)
        else:
            self.bits.feed(chunk.start, mean, held)
        self.n_total = chunk.start + n
        return columns

    def finish(self) -> _Totals:
        """Close the last bit cell; the sample count and the bit stream's innovation RMS."""
        if self.step_window is None:
            self.bits.finish()
            if self.bits.clock is None:
                raise InputError(f"the bit stream (from {self.bits_start / self.fs:g} s) is empty; check --bits-from")
        from afmtool.estimators.ekf import InnovationSums

        # a split run adds its chunks' sums; a sequential one carries them in the EKF's state
        stats = InnovationSums(*self.split_sums).stats() if self.split_sums[2] else self.ekf_state.stats()
        return _Totals(self.n_total, stats.rms_nm if stats.count else None)


    def _ekf_settle(self, first: Chunk) -> int | None:
        """Samples the EKF needs to forget its start, measured on the first chunk (None: not within it)."""
        from afmtool.estimators.ekf import ekf_forgetting_samples

        volts = _lever_voltages(first.data, self.params, self.setup.electrostatic.alpha_r)
        return ekf_forgetting_samples(self.design, first.data["deflection"], volts)


@dataclass(frozen=True)
class DecodeKernels:
    """The EKF and the baseline lock-in as a pure function of a chunk: :class:`_DecodeStage`'s
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


class _Decided(NamedTuple):
    bits: np.ndarray
    baseline_bits: np.ndarray
    centres: np.ndarray  #: cell centres, samples of the innovation running mean
    threshold_nm: float
    results: dict  #: "clock" and "bits"
    baseline_results: dict


def _decide(stage: _BitStage, params: DecodeParams, mean_window: int, writer, warnings: list) -> _Decided:
    """Two-class thresholds, bits, and the per-bit arrays of decode.h5."""
    from afmtool.estimators.bitslicer import two_class_threshold

    centres, soft, soft_aux = stage.take_arrays()
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
    bit_times = (centres - 0.5 * (mean_window - 1)) / stage.fs
    writer.put("bit_times_s", bit_times, "s", {"meaning": "centre of each decoded cell, running-mean delay removed"})
    writer.put("bits", bits, "", {"polarity": params.polarity})
    writer.put("soft", soft, "nm", {"meaning": "innovation running mean averaged over the integrated part of the cell"})
    writer.put("baseline_soft", soft_aux, "nm", {"meaning": "lock-in amplitude averaged over the same cells"})
    writer.put("baseline_bits", base_bits, "", {"polarity": "1 = larger amplitude"})
    clock = stage.clock
    results = {
        "clock": {
            "rate_hz": clock.rate_hz,
            "recovered": clock.recovered,
            "period_samples": clock.period_samples,
            "final_period_samples": stage.state.period_samples,
            "acquisition_transitions": clock.transitions,
            "line_strength": clock.line_strength,
            "rms_jitter_samples": clock.rms_jitter_samples,
        },
        "bits": {
            "count": int(bits.size),
            "ones": int(bits.sum()),
            "incomplete_cells": int((~finite).sum()),
            "detector": f"integrate-and-dump over the central {params.integrate_fraction:g} of each cell",
            "threshold_nm": levels.threshold,
            "centres_nm": [levels.low_centre, levels.high_centre],
            "std_nm": [levels.low_std, levels.high_std],
            "separation": levels.separation,
            "estimated_ber_gaussian": levels.estimated_error_rate,
        },
    }
    baseline = {
        "threshold_nm": base_levels.threshold,
        "separation": base_levels.separation,
        "estimated_ber_gaussian": base_levels.estimated_error_rate,
    }
    return _Decided(bits, base_bits, centres, levels.threshold, results, baseline)


def _compare_truth(
    reader: CaptureReader, results: dict, decided: _Decided, period: float, latency_known: float
) -> None:
    """BER and confusion counts of the decoder and the baseline when /truth has the bits."""
    bits, base_bits, centres = decided.bits, decided.baseline_bits, decided.centres
    names = reader.info.truth_names
    if not {"bit", "bit_index"} <= set(names):
        return
    truth = reader.truth()
    truth_bit, truth_index = truth["bit"], truth["bit_index"]
    truth_results: dict = {}
    if "l0_nm" in truth and truth["l0_nm"].size:
        l0_true = float(truth["l0_nm"][0])
        truth_results["l0_nm"] = l0_true
        estimate = results["l0"]["estimate_nm"]
        truth_results["l0_error_percent"] = 100.0 * (estimate / l0_true - 1.0)
    max_lag = int(math.ceil(2 * period + latency_known))
    ekf = bit_errors(bits, centres, truth_bit, truth_index, max_lag=max_lag)
    base = bit_errors(base_bits, centres, truth_bit, truth_index, max_lag=max_lag + int(math.ceil(period)),
                      allow_inversion=True)
    fs = reader.info.sample_rate_hz
    for key, found in (("decoder", ekf), ("baseline", base)):
        truth_results[key] = {
            "ber": found.ber,
            "ber_upper_95": ber_upper_bound(found.errors, found.compared) if found.compared else None,
            "errors": found.errors,
            "compared": found.compared,
            "latency_s": found.lag_samples / fs,
            "confusion": found.confusion,
        }
    truth_results["baseline"]["inverted"] = base.inverted
    truth_results["alignment"] = "latency (0 to 2 bit periods) with the fewest errors, per decoder"
    if ekf.compared and base.compared:
        # with no decoder error the ratio is bounded below, by the one-sided 95 % upper bound of its BER
        bound = ekf.ber if ekf.errors else ber_upper_bound(0, ekf.compared)
        truth_results["baseline_to_decoder_ber_ratio"] = base.ber / bound if bound > 0 else None
        truth_results["ratio_is_lower_bound"] = ekf.errors == 0
    results["truth"] = truth_results
    del truth
