"""Typed parameter models, one frozen dataclass per command.

Each command resolves its parameters with :func:`afmtool.config.resolve_from`
(packaged defaults, then the user's ``--config`` section, then flags) and
saves the effective values next to its outputs.  Empty strings and zeros
mean "automatic" where a help text says so, because TOML has no null.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from afmtool.config import field
from afmtool.errors import ConfigError

__all__ = [
    "SECTIONS",
    "ReepParams",
    "ProbeLossParams",
    "FreeAirParams",
    "AveragingParams",
    "DesignExcitationParams",
    "TheoryFitParams",
    "TheoryCompareParams",
    "TheoryControllersParams",
    "KalmanBankParams",
    "ObserverTheoryParams",
    "GammaParams",
    "ThermalParams",
    "ElectrostaticFitParams",
    "parse_interval",
    "DecodeParams",
    "parse_bracket_nm",
    "InvolsParams",
    "SpringConstantParams",
]


def parse_interval(text: str, option: str) -> tuple[float, float] | None:
    """``"0.01:0.05"`` -> (0.01, 0.05) seconds; ``""`` -> None."""
    if not text:
        return None
    start, sep, end = text.partition(":")
    try:
        interval = (float(start), float(end))
    except ValueError:
        raise ConfigError(f"{option}={text!r} must look like START:END in seconds") from None
    if not sep or not (math.isfinite(interval[0]) and math.isfinite(interval[1])) or not 0 <= interval[0] < interval[1]:
        raise ConfigError(f"{option}={text!r} must look like START:END with 0 <= START < END (s)")
    return interval


@dataclass(frozen=True)
class FreeAirParams:
    """``afmtool identify freeair``."""

    free_air: str = field("", "Off-sample segment START:END; empty = capture metadata free_air", "s")
    route: str = field(
        "segment", "Identification route", choices=("segment", "sweep", "thermal")
    )
    sweep_method: str = field(
        "record",
        "Sweep route: record (whole-record fit, any sweep rate), h1 or stepped (spectral, need a steady state)",
        choices=("record", "h1", "stepped"),
    )
    drive_hold: str = field(
        "auto",
        "Sweep route: drive held by a DAC at the ADC rate (zoh), continuous, or auto (a hold's half-sample delay)",
        choices=("auto", "zoh", "continuous"),
    )
    temperature_k: float = field(295.0, "Thermal route: temperature for the equipartition spring constant", "K")

    def validate(self) -> None:
        parse_interval(self.free_air, "free_air")
        if self.temperature_k <= 0:
            raise ConfigError(f"temperature_k={self.temperature_k!r} must be > 0")


def _check_f0_q(f0_hz: float, q: float) -> None:
    """The f0/Q route's pair: both 0 (off) or both given, Q > 1/2."""
    if f0_hz < 0 or q < 0 or bool(f0_hz) != bool(q) or (q and not q > 0.5):
        raise ConfigError(f"f0_hz={f0_hz!r} and q={q!r}: give both (f0 > 0, Q > 0.5) or neither")


@dataclass(frozen=True)
class ReepParams:
    """``afmtool reep``: recursive estimation of equivalent parameters (ch. 3)."""

    lam: float = field(0.995, "Forgetting factor λ of the BCEWRLS (eq. 3.39); window 1/(1-λ) samples")
    p0: float = field(1.0e6, "Initial covariance P(0) = P0·I (eq. 3.39)")
    bias_compensation: bool = field(True, "Bias-compensated EWRLS (false: plain EWRLS, for comparison)")
    use_input: bool = field(True, "Use the recorded dither (false: output-only AR(2) tracking)")
    static_offset: bool = field(
        True, "Constant regressor for the static deflection offset of an attractive force (false: eq. 3.40 as is)"
    )
    free_air: str = field("", "Off-sample segment START:END for the free-air model; empty = metadata", "s")
    model: str = field("", "Free-air model file (free_air.json from 'identify freeair'); overrides free_air")
    f0_hz: float = field(0.0, "Free-air f0 for the f0/Q route (with q; gain and phase fitted at the drive); 0 = off", "Hz")
    q: float = field(0.0, "Free-air Q for the f0/Q route (with f0_hz); 0 = off")
    drive_hold: str = field(
        "auto", "How the drive reached the cantilever: DAC hold at the ADC rate, continuous, or told from the free-air phase",
        choices=("auto", "zoh", "continuous"),
    )
    decimate: int = field(0, "Keep one output sample in N; 0 = one per drive period")
    drive_frequency_hz: float = field(0.0, "Lock-in frequency; 0 = metadata drive, else the free-air f0", "Hz")
    lockin_lowpass_hz: float = field(0.0, "Lock-in low-pass corner; 0 = min(f/10, Δf/2)", "Hz")
    bandpass_half_width_hz: float = field(
        5000.0, "Output-only mode: band-pass ±this around the spectral peak before AR(2); 0 = off", "Hz"
    )
    vs: str = field("auto", "Force-curve binning against z_piezo", choices=("auto", "time", "z"))
    z_bin: float = field(0.5, "Force-curve bin width, in the units of z_piezo")
    warmup_windows: float = field(5.0, "Windows 1/(1-λ) left out of summary statistics at the start")
    min_amplitude_fraction: float = field(
        0.01, "Validity: f0', Q' flagged where the amplitude is below this share of the free amplitude; 0 = off"
    )
    max_sigma2_ratio: float = field(
        4.0, "Validity: f0', Q' flagged where sigma^2 exceeds this multiple of its free-air level; 0 = off"
    )
    max_offset_drift: float = field(
        0.1, "Validity: f0', Q' flagged where the static offset's variance over the window exceeds this share "
        "of A^2/2; 0 = off"
    )
    # 1 Mi samples: each chunk costs ~2 ms of hand-offs between the reading, computing and
    # writing threads, 0.6 s per 1e8 samples at 256 Ki; the buffers cost ~100 MB.
    chunk_samples: int = field(1 << 20, "Samples per streamed chunk (memory against per-chunk overhead)")

    def validate(self) -> None:
        if not 0.0 < self.lam < 1.0:
            raise ConfigError(f"lam={self.lam!r} must be in (0, 1)")
        if self.p0 <= 0:
            raise ConfigError(f"p0={self.p0!r} must be > 0")
        if self.decimate < 0:
            raise ConfigError(f"decimate={self.decimate!r} must be >= 0")
        for name in ("drive_frequency_hz", "lockin_lowpass_hz", "bandpass_half_width_hz", "warmup_windows",
                     "min_amplitude_fraction", "max_sigma2_ratio", "max_offset_drift"):
            if getattr(self, name) < 0:
                raise ConfigError(f"{name}={getattr(self, name)!r} must be >= 0")
        if self.z_bin <= 0:
            raise ConfigError(f"z_bin={self.z_bin!r} must be > 0")
        if self.chunk_samples < 16:
            raise ConfigError(f"chunk_samples={self.chunk_samples!r} must be >= 16")
        parse_interval(self.free_air, "free_air")
        _check_f0_q(self.f0_hz, self.q)


@dataclass(frozen=True)
class ProbeLossParams:
    """``afmtool probeloss``: reliability index, switching signal and amplitude baseline (ch. 2)."""

    free_air: str = field("", "Off-sample segment START:END (model, index level, thresholds, A0); empty = metadata", "s")
    model: str = field("", "Free-air model file (free_air.json from 'identify freeair'); overrides identification")
    f0_hz: float = field(0.0, "Free-air f0 for the f0/Q route (with q; gain and phase fitted at the drive); 0 = off", "Hz")
    q: float = field(0.0, "Free-air Q for the f0/Q route (with f0_hz); 0 = off")
    drive_hold: str = field(
        "auto", "How the drive reached the cantilever: DAC hold at the ADC rate, continuous, or told from the free-air phase",
        choices=("auto", "zoh", "continuous"),
    )
    gain: str = field("decay", "Observer gain: error decay in decay_cycles, or steady-state Kalman", choices=("decay", "kalman"))
    decay_cycles: float = field(1.0, "Decay design: time constant of the observer error", "drive periods")
    process_noise: float = field(0.0, "Kalman design: force noise as the static deflection it causes, rms", "deflection units")
    measurement_noise: float = field(0.0, "Kalman design: measurement noise rms (> 0)", "deflection units")
    window_periods: float = field(1.0, "Reliability-index window (RMS of the innovation)", "drive periods")
    index_level: float = field(0.0, "Free-air innovation RMS the index is divided by; 0 = from the free-air segment",
                               "deflection units")
    on: float = field(0.0, "Loss declared when the index falls below this; 0 = automatic (free-air statistics)")
    off: float = field(0.0, "Loss ends when the index rises above this; 0 = automatic")
    quantile: float = field(0.999, "Automatic on: this quantile of the free-air index")
    off_ratio: float = field(2.0, "Automatic off: off_ratio times on")
    amplitude_upper: float = field(0.0, "Amplitude baseline: loss while the amplitude exceeds A_upper; 0 = automatic",
                                   "deflection units")
    setpoint: float = field(0.0, "Amplitude set point A_sp for the automatic A_upper; 0 = metadata controller",
                            "deflection units")
    upper_fraction: float = field(0.25, "Automatic A_upper = A_sp + upper_fraction·(A0 − A_sp)")
    drive_frequency_hz: float = field(0.0, "Drive frequency; 0 = metadata drive, else the free-air f0", "Hz")
    lockin_lowpass_hz: float = field(0.0, "Lock-in low-pass corner; 0 = min(f/10, Δf/2)", "Hz")
    decimate: int = field(0, "Keep one output sample in N; 0 = one per drive period")
    min_event_periods: float = field(5.0, "Truth scores count events at least this long", "drive periods")
    truth_gap_periods: float = field(1.5, "Truth: no contact for longer than this is probe loss", "drive periods")
    max_events: int = field(1000, "Events listed in report.json (all are counted)")
    # 1 Mi samples, as reep: per-chunk hand-offs cost 0.7 s per 1e8 samples at 256 Ki
    chunk_samples: int = field(1 << 20, "Samples per streamed chunk (memory against per-chunk overhead)")

    def validate(self) -> None:
        parse_interval(self.free_air, "free_air")
        _check_f0_q(self.f0_hz, self.q)
        positive = ("decay_cycles", "window_periods", "quantile", "off_ratio", "min_event_periods", "truth_gap_periods")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name}={getattr(self, name)!r} must be > 0")
        nonnegative = ("process_noise", "measurement_noise", "index_level", "on", "off", "amplitude_upper",
                       "setpoint", "upper_fraction", "drive_frequency_hz", "lockin_lowpass_hz")
        for name in nonnegative:
            if getattr(self, name) < 0:
                raise ConfigError(f"{name}={getattr(self, name)!r} must be >= 0")
        if not self.quantile < 1:
            raise ConfigError(f"quantile={self.quantile!r} must be in (0, 1)")
        if not self.off_ratio > 1:
            raise ConfigError(f"off_ratio={self.off_ratio!r} must be > 1")
        if self.on and self.off and not self.on < self.off:
            raise ConfigError(f"on={self.on!r} must be below off={self.off!r}")
        if self.gain == "kalman" and not self.measurement_noise > 0:
            raise ConfigError("gain='kalman' needs measurement_noise > 0 (and process_noise >= 0)")
        if self.decimate < 0 or self.max_events < 0:
            raise ConfigError("decimate and max_events must be >= 0")
        if self.chunk_samples < 16:
            raise ConfigError(f"chunk_samples={self.chunk_samples!r} must be >= 16")


_FORCE_SETS = ("attractive", "attractive-repulsive", "repulsive", "repulsive-q38", "ch4-default")


@dataclass(frozen=True)
class AveragingParams:
    """``afmtool theory averaging``: ωe, Qe and the steady state along a force curve (ch. 4)."""

    f0_hz: float = field(80318.0, "Free-air resonant frequency", "Hz")
    q: float = field(168.0, "Free-air quality factor")
    force_set: str = field("attractive", "Piecewise-linear force parameters (thesis sets)", choices=_FORCE_SETS)
    force: str = field("", "Custom force d=...,wa2=...,wb2=...,ca=...,cb=... (nm, 1/s^2, 1/s); overrides force_set")
    q_values: str = field("", "Several free-air Q overlaid in one figure, e.g. 50,100,200,400 (Figs. 4.2-4.5)")
    free_amplitude_nm: float = field(20.0, "Free-air oscillation amplitude at the drive", "nm")
    drive_offset_hz: float = field(0.0, "Drive frequency minus f0", "Hz")
    separation_from_nm: float = field(30.0, "Force curve start (largest separation)", "nm")
    separation_to_nm: float = field(0.0, "Force curve turn (smallest separation)", "nm")
    points: int = field(601, "Separations along each leg")

    def validate(self) -> None:
        for name in ("f0_hz", "q", "free_amplitude_nm"):
            if getattr(self, name) <= 0:
                raise ConfigError(f"{name}={getattr(self, name)!r} must be > 0")
        if self.separation_to_nm >= self.separation_from_nm:
            raise ConfigError("separation_to_nm must be below separation_from_nm")
        if self.points < 2:
            raise ConfigError(f"points={self.points!r} must be >= 2")


@dataclass(frozen=True)
class TheoryCompareParams:
    """``afmtool theory compare``: REEP output beside averaging theory (§3.4.3)."""

    force_set: str = field("", "Force parameters; empty = the capture's metadata force", choices=("",) + _FORCE_SETS)
    force: str = field("", "Custom force d=...,wa2=...,wb2=...,ca=...,cb=... (nm, 1/s^2, 1/s); overrides force_set")
    amplitude_fraction: float = field(0.6, "Compare where the amplitude is above this share of the free amplitude")
    tolerance: float = field(0.25, "Pass when the worst error is within this share of the theory's change")
    separation: str = field("auto", "Separation from /truth or from z_piezo; auto = /truth when present",
                            choices=("auto", "truth", "z-piezo"))
    z_sensitivity: float = field(0.0, "z_piezo sensitivity; 0 = from the channel's length units", "nm/unit")
    contact_z: str = field("", "z_piezo reading at contact (l = 0); empty = aligned on the approach amplitude")

    def validate(self) -> None:
        if self.contact_z:
            try:
                float(self.contact_z)
            except ValueError:
                raise ConfigError(f"contact_z={self.contact_z!r} must be a number") from None
        if not 0 < self.amplitude_fraction < 1:
            raise ConfigError(f"amplitude_fraction={self.amplitude_fraction!r} must be in (0, 1)")
        if self.tolerance <= 0:
            raise ConfigError(f"tolerance={self.tolerance!r} must be > 0")


@dataclass(frozen=True)
class TheoryControllersParams:
    """``afmtool theory controllers``: low, high and switching z-controller gains on the grating (ch. 2)."""

    line_rates_hz: str = field("4,8,12,30", "Line rates of the table, comma-separated", "Hz")
    lines: int = field(2, "Raster lines per table run (a trace and a retrace each)")
    seed: int = field(1, "Simulation seed (the same surface, noise and seed for the three controllers)")
    tolerance: float = field(1.2, "Pass: switching loss area <= this x the high gain's, peak force <= this x the low's")
    figure_line_rate_hz: float = field(12.0, "Line rate of the height images", "Hz")
    figure_lines: int = field(16, "Raster lines of the height images")
    figure_pixels: int = field(48, "Pixels per line of the height images")

    def rates(self) -> tuple[float, ...]:
        """The line rates as numbers, Hz."""
        try:
            rates = tuple(float(v) for v in self.line_rates_hz.split(","))
        except ValueError:
            raise ConfigError(f"line_rates_hz={self.line_rates_hz!r} must be comma-separated numbers") from None
        return rates

    def validate(self) -> None:
        if not all(rate > 0 for rate in self.rates()):
            raise ConfigError(f"line_rates_hz={self.line_rates_hz!r} must all be > 0")
        for name in ("lines", "figure_lines", "figure_pixels"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name}={getattr(self, name)!r} must be >= 1")
        if self.figure_line_rate_hz <= 0:
            raise ConfigError(f"figure_line_rate_hz={self.figure_line_rate_hz!r} must be > 0")
        if self.tolerance < 1:
            raise ConfigError(f"tolerance={self.tolerance!r} must be >= 1")


@dataclass(frozen=True)
class KalmanBankParams:
    """``afmtool kalman-bank``: validate REEP by a bank of Kalman filters and an adaptive observer (§3.4.2)."""

    n_filters: int = field(5, "Filters spread over the approach when neither at_z nor models is given")
    at_z: str = field("", "Design points z1,z2,... (z_piezo units); models from REEP there; empty = automatic")
    models: str = field("", "Bank models f0_hz:q,f0_hz:q,... instead of REEP's; empty = from REEP")
    design_leg: str = field("approach", "Force-curve leg the design points and verdict refer to", choices=("approach", "retract"))
    reep: str = field("", "REEP output folder or reep.h5 to use; empty = run REEP internally")
    free_air: str = field("", "Off-sample segment START:END for the free-air model; empty = metadata", "s")
    model: str = field("", "Free-air model file (free_air.json); overrides free_air")
    f0_hz: float = field(0.0, "Free-air f0 for the f0/Q route (with q; gain and phase fitted at the drive); 0 = off", "Hz")
    q: float = field(0.0, "Free-air Q for the f0/Q route (with f0_hz); 0 = off")
    drive_hold: str = field(
        "auto", "How the drive reached the cantilever: DAC hold at the ADC rate, continuous, or told from the free-air phase",
        choices=("auto", "zoh", "continuous"),
    )
    lam: float = field(0.995, "Internal REEP: forgetting factor λ (eq. 3.39)")
    noise_ratio: float = field(
        0.03, "Kalman gains: process-noise rms (as static deflection) over measurement-noise rms, σ_w/σ_v"
    )
    rms_window_periods: float = field(10.0, "Innovation RMS window, in drive periods")
    z_bin: float = field(0.5, "Bin width of RMS against z, in the units of z_piezo")
    min_amplitude_fraction: float = field(
        0.25, "Automatic design points: only where REEP's amplitude is above this share of the free amplitude"
    )
    onset_fraction: float = field(
        0.1, "Automatic design points: start where the model has moved this share of its change along the leg"
    )
    z_tolerance_bins: int = field(0, "Verdict: a filter's RMS minimum may lie this many z bins from its design bin")
    rms_tolerance: float = field(
        0.01, "Verdict: or its RMS at the design bin may exceed its minimum by at most this share (flat minima)"
    )
    adaptive_fraction: float = field(0.9, "Verdict: share of the time the adaptive observer must have the least RMS")
    f0_scale: float = field(1.0, "Multiply every bank model's f0 by this: a negative control that must fail")
    drive_frequency_hz: float = field(0.0, "Drive frequency; 0 = metadata drive, else the free-air f0", "Hz")
    decimate: int = field(0, "Keep one output sample in N; 0 = one per drive period")
    warmup_windows: float = field(5.0, "REEP windows 1/(1-λ) left out of the statistics at the start")
    chunk_samples: int = field(1 << 18, "Samples per streamed chunk (memory against per-chunk overhead)")

    def validate(self) -> None:
        positive = ("lam", "noise_ratio", "rms_window_periods", "z_bin", "adaptive_fraction", "f0_scale")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name}={getattr(self, name)!r} must be > 0")
        if not self.lam < 1.0:
            raise ConfigError(f"lam={self.lam!r} must be in (0, 1)")
        if self.n_filters < 1:
            raise ConfigError(f"n_filters={self.n_filters!r} must be >= 1")
        if self.at_z and self.models:
            raise ConfigError("give at_z or models, not both")
        for name in ("min_amplitude_fraction", "onset_fraction", "adaptive_fraction"):
            if not 0 <= getattr(self, name) <= 1:
                raise ConfigError(f"{name}={getattr(self, name)!r} must be in [0, 1]")
        for name in ("z_tolerance_bins", "rms_tolerance", "drive_frequency_hz", "decimate", "warmup_windows"):
            if getattr(self, name) < 0:
                raise ConfigError(f"{name}={getattr(self, name)!r} must be >= 0")
        if self.chunk_samples < 16:
            raise ConfigError(f"chunk_samples={self.chunk_samples!r} must be >= 16")
        parse_interval(self.free_air, "free_air")
        _check_f0_q(self.f0_hz, self.q)


@dataclass(frozen=True)
class ObserverTheoryParams:
    """``afmtool theory observer``: A_e², sensitivities, SNR and transients of an observer design (ch. 5)."""

    f0_hz: float = field(80318.0, "Nominal (free-air) plant resonance f0", "Hz")
    q: float = field(168.0, "Nominal plant quality factor")
    gain: float = field(1.0, "Numerator DC gain: c0 = gain·ω0², c1 = 0 (eq. 5.13), deflection per dither unit")
    model: str = field("", "Free-air model file (free_air.json); overrides f0_hz, q and gain")
    f0_low_hz: float = field(0.0, "End of the force-curve direction (on-sample f0'); 0 = from reep or averaging theory", "Hz")
    q_low: float = field(0.0, "End of the force-curve direction (on-sample Q'); 0 = as f0_low_hz")
    reep: str = field("", "REEP output folder or reep.h5: the direction ends at its lowest usable amplitude")
    force_set: str = field("attractive", "Averaging theory direction: thesis force set", choices=_FORCE_SETS)
    setpoint_fraction: float = field(0.3, "Direction end: amplitude as a share of the free amplitude")
    free_amplitude_nm: float = field(20.0, "Free-air deflection amplitude at the drive", "nm")
    drive_frequency_hz: float = field(0.0, "Drive frequency ω/2π; 0 = f0_hz", "Hz")
    cycles: str = field("4,50", "Observer gains: error time constants in drive periods (aggressive, sluggish)")
    observers: str = field("", "Directional plots: observer models f0_hz:q,...; empty = free-air and direction end")
    grid_points: int = field(41, "Points per axis of the 2-D observer-model maps")
    grid_margin: float = field(0.5, "Maps extend this share of the direction's span beyond its ends")
    line_points: int = field(101, "Points along the force-curve direction")
    spring_constant_n_per_m: float = field(2.0, "Spring constant k, for the thermal noise η", "N/m")
    temperature_k: float = field(300.0, "Temperature of the thermal noise η", "K")
    measurement_asd: float = field(1.0e-4, "Measurement noise ν, one-sided amplitude spectral density", "nm/sqrt(Hz)")
    recommend: bool = field(False, "Also pick the model and gain of greatest sensitivity whose transients settle in time")
    max_cycles: float = field(10.0, "Recommend: the error must settle (below residual) within this many drive periods")
    residual: float = field(0.36787944117144233, "Settled: the step response stays below this share of the step (1/e)")
    sample_rate_hz: float = field(500e3, "Recommend: also give the discrete observer (eq. 3.40) at this rate", "Hz")
    drive_hold: str = field(
        "continuous", "Recommend: the discrete observer's numerator for a continuous drive or one a DAC holds per sample",
        choices=("continuous", "zoh"),
    )

    def validate(self) -> None:
        for name in ("f0_hz", "q", "gain", "free_amplitude_nm", "spring_constant_n_per_m", "max_cycles", "sample_rate_hz"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name}={getattr(self, name)!r} must be > 0")
        for name in ("f0_low_hz", "q_low", "drive_frequency_hz", "temperature_k", "measurement_asd", "grid_margin"):
            if getattr(self, name) < 0:
                raise ConfigError(f"{name}={getattr(self, name)!r} must be >= 0")
        if self.q <= 0.5:
            raise ConfigError(f"q={self.q!r} must be > 0.5 (an under-damped mode)")
        if not 0 < self.setpoint_fraction < 1:
            raise ConfigError(f"setpoint_fraction={self.setpoint_fraction!r} must be in (0, 1)")
        if not 0 < self.residual < 1:
            raise ConfigError(f"residual={self.residual!r} must be in (0, 1)")
        if self.grid_points < 3 or self.line_points < 3:
            raise ConfigError("grid_points and line_points must be >= 3")


@dataclass(frozen=True)
class GammaParams:
    """``afmtool identify gamma``: Γ_IR,ts with the feed-through removed (eqs. 6.15, 6.16)."""

    method: str = field(
        "auto", "Frequency responses: H1 (chirp/broadband), stepped sines, or auto (stepped if both captures "
        "carry segments metadata)", choices=("auto", "h1", "stepped"),
    )
    nperseg: int = field(0, "H1 segment length in samples; 0 = largest power of two <= n/16")
    min_coherence: float = field(0.9, "Usable band: coherence of Gamma_IR,V and Gamma_ts,V at least this")
    settle_fraction: float = field(0.5, "Stepped sines: share of each step skipped before the lock-in")
    min_periods: int = field(4, "Stepped sines: fewest drive periods per step after settling")
    roll_off_start_factor: float = field(2.0, "Roll-off fitted from this multiple of the bandwidth ...")
    roll_off_stop_factor: float = field(10.0, "... to this multiple (or the top of the usable band)")
    chunk_samples: int = field(1 << 18, "Samples per streamed chunk (H1 streams; stepped sines are held)")

    def validate(self) -> None:
        if self.nperseg != 0 and self.nperseg < 16:
            raise ConfigError(f"nperseg={self.nperseg!r} must be 0 (auto) or >= 16")
        if not 0 <= self.min_coherence <= 1:
            raise ConfigError(f"min_coherence={self.min_coherence!r} must be in [0, 1]")
        if not 0 <= self.settle_fraction < 1:
            raise ConfigError(f"settle_fraction={self.settle_fraction!r} must be in [0, 1)")
        if self.min_periods < 1:
            raise ConfigError(f"min_periods={self.min_periods!r} must be >= 1")
        if not 0 < self.roll_off_start_factor < self.roll_off_stop_factor:
            raise ConfigError(
                f"roll_off_start_factor={self.roll_off_start_factor!r} must be > 0 and below "
                f"roll_off_stop_factor={self.roll_off_stop_factor!r}"
            )
        if self.chunk_samples < 16:
            raise ConfigError(f"chunk_samples={self.chunk_samples!r} must be >= 16")


@dataclass(frozen=True)
class DecodeParams:
    """``afmtool decode``: EKF bit decoder for electrostatically actuated probes (ch. 7)."""

    voltage_channel: str = field("", "Channel holding the lever-sample voltage V; empty = alpha_r*v_r - v_sub (eq. 6.3)")
    nominal: str = field("", "Nominal (bit-free) segment START:END for l0 and noise; empty = metadata nominal", "s")
    f0_hz: float = field(0.0, "Resonant frequency f0; 0 = metadata cantilever.f0_hz", "Hz")
    q: float = field(0.0, "Quality factor Q; 0 = metadata cantilever.q")
    spring_constant_n_per_m: float = field(0.0, "Spring constant k; 0 = metadata, else eq. 7.10's 0.1404", "N/m")
    k_esf_f_m: float = field(0.0, "K_esf (no-1/2 convention); 0 = metadata electrostatic, else 1.66e-21", "F*m")
    alpha_r: float = field(0.0, "alpha_R of V = alpha_R*V_R - V_sub; 0 = metadata electrostatic, else 0.2549")
    tip_height_nm: float = field(0.0, "Tip height t_h; 0 = metadata electrostatic, else 768.3", "nm")
    l0_nm: float = field(0.0, "Lever-sample separation l0; 0 = estimate on the nominal segment (§7.4)", "nm")
    l0_bracket_nm: str = field("", "l0 search bracket LOW:HIGH; empty = 0.75-1.33 x the guess (metadata or 1081.8)", "nm")
    l0_grid_points: int = field(41, "Coarse grid points of the l0 search before golden-section refinement")
    process_noise_n_per_rthz: float = field(
        0.0, "Force-noise ASD of the EKF; 0 = estimate on the nominal segment (mean NIS = 1)", "N/sqrt(Hz)"
    )
    measurement_noise_nm: float = field(0.0, "Rms measurement noise; 0 = estimate from the PSD floor of the nominal segment", "nm")
    temperature_k: float = field(300.0, "Thermal force noise used for the l0 search when the process noise is estimated", "K")
    warmup_s: float = field(2e-4, "Start of the nominal segment left out of the innovation statistics", "s")
    actuation_hz: float = field(0.0, "Actuation frequency; 0 = metadata drive, else the strongest line of V^2", "Hz")
    mean_window: int = field(0, "Running mean of the innovation, samples; 0 = one actuation period")
    bit_rate_hz: float = field(0.0, "Bit rate; 0 = recover the clock from the transitions", "Hz")
    bit_rate_min_hz: float = field(1000.0, "Clock recovery: lowest bit rate searched", "Hz")
    bit_rate_max_hz: float = field(0.0, "Clock recovery: highest bit rate searched; 0 = the actuation frequency", "Hz")
    bits_from_s: float = field(-1.0, "Start of the bit stream; < 0 = the end of the nominal segment (or 0)", "s")
    clock_window_s: float = field(0.005, "Clock acquisition window at the start of the bit stream", "s")
    integrate_fraction: float = field(0.7, "Share of each bit cell integrated (centred)")
    polarity: str = field(
        "negative", "Innovation sign of a 1 bit (a raised sample attracts more: negative)", choices=("negative", "positive")
    )
    pll_phase_gain: float = field(0.05, "Clock tracking: share of each transition's phase error corrected")
    pll_rate_gain: float = field(0.001, "Clock tracking: rate correction per transition (recovered rates only)")
    baseline_lowpass_hz: float = field(0.0, "Lock-in baseline low-pass; 0 = min(bit rate/2, actuation/4)", "Hz")
    psd_window_s: float = field(0.02, "Stretch of the bit stream used for the PSD comparison plot", "s")
    eye_traces: int = field(200, "Bit cells drawn in the eye diagram")
    # 1 Mi samples: each chunk costs ~2 ms of hand-offs between the reading, computing and
    # writing threads, 0.6 s per 1e8 samples at 256 Ki; the buffers cost ~100 MB.
    chunk_samples: int = field(1 << 20, "Samples per streamed chunk (memory against per-chunk overhead)")

    def validate(self) -> None:
        parse_interval(self.nominal, "nominal")
        for name in (
            "f0_hz", "q", "spring_constant_n_per_m", "k_esf_f_m", "alpha_r", "tip_height_nm", "l0_nm",
            "process_noise_n_per_rthz", "measurement_noise_nm", "temperature_k", "warmup_s", "actuation_hz",
            "bit_rate_hz", "bit_rate_max_hz", "baseline_lowpass_hz", "mean_window",
        ):
            if not getattr(self, name) >= 0:
                raise ConfigError(f"{name}={getattr(self, name)!r} must be >= 0")
        for name in ("bit_rate_min_hz", "clock_window_s", "psd_window_s"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name}={getattr(self, name)!r} must be > 0")
        if 0 < self.q <= 0.5:
            raise ConfigError(f"q={self.q!r} must be > 0.5 (an under-damped mode)")
        if self.bit_rate_max_hz and self.bit_rate_max_hz <= self.bit_rate_min_hz:
            raise ConfigError(f"bit_rate_max_hz={self.bit_rate_max_hz!r} must exceed bit_rate_min_hz={self.bit_rate_min_hz!r}")
        if self.l0_grid_points < 5:
            raise ConfigError(f"l0_grid_points={self.l0_grid_points!r} must be >= 5")
        if self.l0_bracket_nm:
            parse_bracket_nm(self.l0_bracket_nm)
        if not 0 < self.integrate_fraction <= 1:
            raise ConfigError(f"integrate_fraction={self.integrate_fraction!r} must be in (0, 1]")
        if not 0 <= self.pll_phase_gain < 1 or not 0 <= self.pll_rate_gain < 1:
            raise ConfigError("pll_phase_gain and pll_rate_gain must be in [0, 1)")
        if self.eye_traces < 1:
            raise ConfigError(f"eye_traces={self.eye_traces!r} must be >= 1")
        if self.chunk_samples < 16:
            raise ConfigError(f"chunk_samples={self.chunk_samples!r} must be >= 16")


def parse_bracket_nm(text: str) -> tuple[float, float]:
    """``"900:1300"`` -> (900.0, 1300.0) nm, 0 < LOW < HIGH."""
    low, sep, high = text.partition(":")
    try:
        bracket = (float(low), float(high))
    except ValueError:
        raise ConfigError(f"l0_bracket_nm={text!r} must look like LOW:HIGH in nm") from None
    if not sep or not 0 < bracket[0] < bracket[1]:
        raise ConfigError(f"l0_bracket_nm={text!r} must look like LOW:HIGH with 0 < LOW < HIGH (nm)")
    return bracket


@dataclass(frozen=True)
class ThermalParams:
    """``afmtool identify thermal``: g(T), K_TP, K_TP(t_s), C(jω) and H(jω) (§6.5.2, §6.6.2)."""

    breakdown_temperature_c: float = field(550.0, "Breakdown temperature T_k of the sensor (the I-V knee)", "degC")
    room_temperature_c: float = field(25.0, "Room temperature T_r (the sensor at zero power)", "degC")
    g_order: int = field(2, "Degree of the polynomial fit of g(T)")
    g_table_bins: int = field(40, "Temperature bins of the g(T) table")
    knee_fit_fraction: float = field(0.5, "The knee is fitted on V_R >= this share of the largest V_R")
    z_bin_nm: float = field(10.0, "Bin width of the K_TP(t_s) table", "nm")
    method: str = field(
        "auto", "V_R sweep: H1, stepped sines, or auto (stepped if the capture has segments)",
        choices=("auto", "h1", "stepped"),
    )
    nperseg: int = field(0, "V_R sweep, H1 segment length; 0 = largest power of two <= n/16")
    min_coherence: float = field(0.9, "V_R sweep: bins with a lower coherence are left out of the summaries")
    settle_fraction: float = field(0.5, "Stepped sines: share of each step skipped before the lock-in")
    min_periods: int = field(4, "Stepped sines: fewest drive periods per step after settling")
    chunk_samples: int = field(1 << 18, "Samples per streamed chunk")

    def validate(self) -> None:
        if not self.breakdown_temperature_c > self.room_temperature_c:
            raise ConfigError(
                f"breakdown_temperature_c={self.breakdown_temperature_c!r} must exceed "
                f"room_temperature_c={self.room_temperature_c!r}"
            )
        if not 1 <= self.g_order <= 6:
            raise ConfigError(f"g_order={self.g_order!r} must be in 1..6")
        if self.g_table_bins < 2:
            raise ConfigError(f"g_table_bins={self.g_table_bins!r} must be >= 2")
        if not 0 < self.knee_fit_fraction < 1:
            raise ConfigError(f"knee_fit_fraction={self.knee_fit_fraction!r} must be in (0, 1)")
        if self.z_bin_nm <= 0:
            raise ConfigError(f"z_bin_nm={self.z_bin_nm!r} must be > 0")
        if self.nperseg != 0 and self.nperseg < 16:
            raise ConfigError(f"nperseg={self.nperseg!r} must be 0 (auto) or >= 16")
        if not 0 <= self.min_coherence <= 1:
            raise ConfigError(f"min_coherence={self.min_coherence!r} must be in [0, 1]")
        if not 0 <= self.settle_fraction < 1:
            raise ConfigError(f"settle_fraction={self.settle_fraction!r} must be in [0, 1)")
        if self.min_periods < 1:
            raise ConfigError(f"min_periods={self.min_periods!r} must be >= 1")
        if self.chunk_samples < 16:
            raise ConfigError(f"chunk_samples={self.chunk_samples!r} must be >= 16")


@dataclass(frozen=True)
class ElectrostaticFitParams:
    """``afmtool identify electrostatic``: eq. 6.6 (optical) or eq. 6.7 (thermal) by nonlinear least squares."""

    sensor: str = field(
        "auto", "Which curve to fit: optical deflection (eq. 6.6), thermal current through K_TP (eq. 6.7), or auto "
        "(optical if the capture has deflection)", choices=("auto", "optical", "thermal"),
    )
    v_r_v: float = field(0.0, "Sensor voltage V_R; 0 = the mean of the capture's v_r channel", "V")
    spring_constant_n_per_m: float = field(
        0.0, "Spring constant k if known (then K_esf is reported); 0 = unknown: only K_esf/k is identifiable", "N/m"
    )
    snap_margin: float = field(0.05, "Drop this share of the V_sub range just before snap-in")
    rank_tolerance: float = field(1e-7, "Relative singular value below which a combination is not identifiable")
    max_relative_std: float = field(0.1, "Parameters with a larger relative standard deviation are flagged")

    def validate(self) -> None:
        if self.spring_constant_n_per_m < 0:
            raise ConfigError(f"spring_constant_n_per_m={self.spring_constant_n_per_m!r} must be >= 0")
        if not 0 <= self.snap_margin < 1:
            raise ConfigError(f"snap_margin={self.snap_margin!r} must be in [0, 1)")
        if not 0 < self.rank_tolerance < 1:
            raise ConfigError(f"rank_tolerance={self.rank_tolerance!r} must be in (0, 1)")
        if self.max_relative_std <= 0:
            raise ConfigError(f"max_relative_std={self.max_relative_std!r} must be > 0")


@dataclass(frozen=True)
class InvolsParams:
    """``afmtool identify invols``: the InvOLS from the contact part of a force curve on a hard sample."""

    leg: str = field("approach", "Which part of the curve to fit", choices=("approach", "retract", "all"))
    skip_fraction: float = field(0.1, "Share of the contact z range next to the contact point left out of the fit")
    z_channel: str = field("z_piezo", "Channel holding the z-piezo position (a length, or V with --z-sensitivity)")
    deflection_channel: str = field("deflection", "Channel holding the deflection (V, or a length)")

    def validate(self) -> None:
        if not 0 <= self.skip_fraction < 1:
            raise ConfigError(f"skip_fraction={self.skip_fraction!r} must be in [0, 1)")


@dataclass(frozen=True)
class SpringConstantParams:
    """``afmtool identify freeair --psd``: the spring constant, thermal (Butt–Jaschke) and Sader."""

    detection: str = field(
        "optical-lever", "How the spectrum's deflection was measured: optical lever calibrated by a static force "
        "curve (factor 0.817) or the tip's displacement itself, e.g. an interferometer (0.971)",
        choices=("optical-lever", "displacement"),
    )
    length_um: float = field(0.0, "Sader: plan-view length L of the rectangular cantilever; 0 = no Sader value", "um")
    width_um: float = field(0.0, "Sader: plan-view width b; 0 = no Sader value", "um")
    fluid: str = field("air", "Sader: the fluid around the cantilever", choices=("air", "water"))
    fluid_density_kg_per_m3: float = field(0.0, "Sader: fluid density; 0 = that of the fluid at 25 degC", "kg/m^3")
    fluid_viscosity_pa_s: float = field(0.0, "Sader: fluid viscosity; 0 = that of the fluid at 25 degC", "Pa s")

    def validate(self) -> None:
        for name in ("length_um", "width_um", "fluid_density_kg_per_m3", "fluid_viscosity_pa_s"):
            if getattr(self, name) < 0:
                raise ConfigError(f"{name}={getattr(self, name)!r} must be >= 0")
        if (self.length_um > 0) != (self.width_um > 0):
            raise ConfigError("the Sader method needs both length_um and width_um (--length, --width)")


@dataclass(frozen=True)
class DesignExcitationParams:
    """``afmtool design excitation``: the three-sine REEP dither of §3.3.2 for one cantilever."""

    amplitude_nm: float = field(20.0, "Free-air response amplitude at the main line (model deflection units)", "nm")
    dac_rate_hz: float = field(2.0e6, "Sample rate of the exported loop (a whole number of Hz)", "Hz")
    drive_frequency_hz: float = field(0.0, "Main line; 0 = the model's f0", "Hz")
    offset_hz: float = field(0.0, "Side-line offset; 0 = min(20 f0/Q, f0/10)", "Hz")
    beat_tolerance: float = field(0.05, "Largest relative excursion of the response envelope (side lines / main)")
    max_side_scale: float = field(0.5, "Largest side-line amplitude as a share of the main line's (thesis: 1/2)")
    resolution_hz: float = field(0.0, "Frequency grid of the loop; 0 = f0/(100 Q)", "Hz")

    def validate(self) -> None:
        for name in ("amplitude_nm", "dac_rate_hz", "beat_tolerance", "max_side_scale"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name}={getattr(self, name)!r} must be > 0")
        for name in ("drive_frequency_hz", "offset_hz", "resolution_hz"):
            if getattr(self, name) < 0:
                raise ConfigError(f"{name}={getattr(self, name)!r} must be >= 0")
        if self.dac_rate_hz != int(self.dac_rate_hz):
            raise ConfigError(f"dac_rate_hz={self.dac_rate_hz!r} must be a whole number of Hz (a WAV header holds an integer)")


@dataclass(frozen=True)
class TheoryFitParams:
    """``afmtool theory fit``: force parameters fitted to REEP's approach (ch. 4)."""

    amplitude_fraction: float = field(0.3, "Fit where the amplitude is above this share of the free amplitude")
    max_relative_std: float = field(0.1, "A parameter with a larger relative standard deviation is not identified")
    z_sensitivity: float = field(0.0, "z_piezo sensitivity; 0 = from the channel's length units", "nm/unit")
    skip_s: float = field(5e-3, "Leave out REEP's start-up", "s")
    max_samples: int = field(3000, "Fit at most this many (evenly thinned) approach samples")

    def validate(self) -> None:
        if not 0 <= self.amplitude_fraction < 1:
            raise ConfigError(f"amplitude_fraction={self.amplitude_fraction!r} must be in [0, 1)")
        if self.max_relative_std <= 0:
            raise ConfigError(f"max_relative_std={self.max_relative_std!r} must be > 0")
        if self.max_samples < 20:
            raise ConfigError(f"max_samples={self.max_samples!r} must be >= 20")


#: Config-file section -> parameter model.
SECTIONS: dict[str, type] = {
    "identify.freeair": FreeAirParams,
    "identify.gamma": GammaParams,
    "identify.thermal": ThermalParams,
    "identify.electrostatic": ElectrostaticFitParams,
    "reep": ReepParams,
    "probeloss": ProbeLossParams,
    "decode": DecodeParams,
    "theory.averaging": AveragingParams,
    "theory.compare": TheoryCompareParams,
    "theory.controllers": TheoryControllersParams,
    "kalman-bank": KalmanBankParams,
    "theory.observer": ObserverTheoryParams,
    "identify.invols": InvolsParams,
    "identify.spring_constant": SpringConstantParams,
    "design.excitation": DesignExcitationParams,
    "theory.fit": TheoryFitParams,
}
