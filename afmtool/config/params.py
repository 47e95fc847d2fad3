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
    "SECTIONS",  # noqa: F822 - derived from the command specs when first read (module __getattr__ below)
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
    "parse_band",
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


def parse_band(text: str, option: str = "--band") -> tuple[float, float] | None:
    """``"170e3:190e3"`` -> (170000.0, 190000.0) Hz; ``""`` -> None."""
    if not text:
        return None
    low, sep, high = text.partition(":")
    try:
        band = (float(low), float(high))
    except ValueError:
        raise ConfigError(f"{option}={text!r} must look like LOW:HIGH in Hz") from None
    if not sep or not (math.isfinite(band[0]) and math.isfinite(band[1])) or not 0 <= band[0] < band[1]:
        raise ConfigError(f"{option}={text!r} must look like LOW:HIGH with 0 <= LOW < HIGH (Hz)")
    return band


# ----------------------------------------------------------------------------- shared declarations
# Parameters that several commands take, declared once here (the shared groups: the
# free-air model, lock-in and chunking); each class calls the factory where it lists the field,
# so field order, and with it defaults.toml and config.toml, is unchanged.

_DRIVE_HOLD_CHOICES = ("auto", "zoh", "continuous")


def _free_air_segment_field(help_text: str):
    """``free_air``: the off-sample segment START:END (s) of a capture."""
    return field("", help_text, "s", flag="--free-air")


def _free_air_model_file_field(help_text: str):
    """``model``: a free_air.json from ``identify freeair``."""
    return field("", help_text, flag="--model")


def _free_air_f0_field():
    """``f0_hz`` of the f0/Q route (with ``q``; :func:`_check_f0_q`)."""
    return field(
        0.0,
        "Free-air f0 for the f0/Q route (with q; gain and phase fitted at the drive); 0 = off",
        "Hz",
        bounds=">= 0",
        flag="--f0",
    )


def _free_air_q_field():
    """``q`` of the f0/Q route (with ``f0_hz``)."""
    return field(0.0, "Free-air Q for the f0/Q route (with f0_hz); 0 = off", bounds="> 0.5", automatic=0.0, flag="--q")


def _drive_hold_field():
    """``drive_hold``: how the drive reached the cantilever (a DAC's hold or a continuous signal)."""
    return field(
        "auto",
        "How the drive reached the cantilever: DAC hold at the ADC rate, continuous, or told from the free-air phase",
        choices=_DRIVE_HOLD_CHOICES,
        flag="--drive-hold",
    )


def _decimation_field(flag: str | None = "--decimate"):
    """``decimate``: one output sample kept in N (overrides ``rows``)."""
    return field(0, "Keep one output sample in N capture samples; 0 = as --rows says", bounds="[1, 1000000000000000]",
                 automatic=0, flag=flag)


#: ``rows``: what sets the density of the written series (issue 33).
ROW_DENSITIES = ("resolution", "per-period")


def _rows_field(resolution: str, per_period: str = "one row per drive period", flag: str | None = "--rows"):
    """``rows``: series at what the estimator resolves (default) or at the old density."""
    return field(
        "resolution",
        f"Density of the written series: resolution = {resolution} (what the estimator resolves); "
        f"per-period = {per_period}; --decimate N overrides both",
        choices=ROW_DENSITIES,
        flag=flag,
    )


def _lockin_frequency_field(help_text: str):
    """``drive_frequency_hz``: the lock-in's reference frequency."""
    return field(0.0, help_text, "Hz", bounds=">= 0")


def _lockin_lowpass_field():
    """``lockin_lowpass_hz``: the lock-in's low-pass corner."""
    return field(0.0, "Lock-in low-pass corner; 0 = min(f/10, Δf/2)", "Hz", bounds=">= 0")


def _chunk_samples_field(default: int):
    """``chunk_samples``: samples per streamed chunk."""
    return field(default, "Samples per streamed chunk (memory against per-chunk overhead)", bounds=">= 16")


@dataclass(frozen=True)
class FreeAirParams:
    """``afmtool identify freeair``."""

    free_air: str = field("", "Off-sample segment START:END; empty = capture metadata free_air", "s", flag="--free-air")
    route: str = field("segment", "Identification route", choices=("segment", "sweep", "thermal"))
    sweep_method: str = field(
        "record",
        "Sweep route: record (whole-record fit, any sweep rate), h1 or stepped (spectral, need a steady state)",
        choices=("record", "h1", "stepped"),
        flag="--sweep-method",
    )
    drive_hold: str = field(
        "auto",
        "Sweep route: drive held by a DAC at the ADC rate (zoh), continuous, or auto (a hold's half-sample delay)",
        choices=("auto", "zoh", "continuous"),
        flag="--drive-hold",
    )
    temperature_k: float = field(
        295.0,
        "Thermal route: temperature for the equipartition spring constant",
        "K",
        bounds="> 0",
        flag="--temperature",
    )
    band: str = field(
        "", "Thermal route: the band LOW:HIGH to fit; empty = where the peak stands above the floor", "Hz",
        flag="--band",
    )
    averages: int = field(
        0,
        "Thermal route (--psd): periodograms averaged in the spectrum; 0 = the file's '# averages:' comment, "
        "else estimated from its scatter",
        bounds=">= 1",
        automatic=0,
        flag="--averages",
    )
    resolution_hz: float = field(
        0.0,
        "Thermal route (--thermal): Welch resolution fs/nperseg; 0 = the finest that still averages 64 "
        "half-overlapped segments",
        "Hz",
        bounds="> 0",
        automatic=0.0,
        flag="--resolution",
    )

    def validate(self) -> None:
        """Cross-field and format checks; the bounds are checked from the declarations."""
        parse_interval(self.free_air, "free_air")
        parse_band(self.band)


def _check_f0_q(f0_hz: float, q: float) -> None:
    """The f0/Q route's pair: both 0 (off) or both given, Q > 1/2."""
    if f0_hz < 0 or q < 0 or bool(f0_hz) != bool(q) or (q and not q > 0.5):
        raise ConfigError(f"f0_hz={f0_hz!r} and q={q!r}: give both (f0 > 0, Q > 0.5) or neither")


@dataclass(frozen=True)
class ReepParams:
    """``afmtool reep``: recursive estimation of equivalent parameters (ch. 3)."""

    window_us: float = field(
        400.0,
        "Forgetting window 1/(1-λ) of the BCEWRLS (eq. 3.39) in time: the thesis's λ = 0.995 at 500 kHz; "
        "λ = 1 - 1/(window · REEP's rate)",
        "µs",
        bounds="> 0",
        flag="--window-us",
    )
    lam: float = field(
        0.0,
        "Forgetting factor λ per capture sample instead of window_us (window 1/(1-λ) samples); 0 = from window_us",
        bounds="(0, 1)",
        automatic=0.0,
        flag="--lambda",
    )
    samples_per_period: float = field(
        5.0,
        "REEP's rate: deflection and dither pass one anti-alias filter and are decimated by D = floor(fs/(N·f0)), "
        "so that the regression sees N to 2N samples per period at any oversampling; 0 = the capture's rate",
        "samples per period",
        bounds=">= 3",
        automatic=0.0,
        flag="--samples-per-period",
    )
    p0: float = field(1.0e6, "Initial covariance P(0) = P0·I (eq. 3.39)", bounds="> 0")
    bias_compensation: bool = field(
        True, "Bias-compensated EWRLS (false: plain EWRLS, for comparison)", flag="--no-bias-compensation"
    )
    use_input: bool = field(True, "Use the recorded dither (false: output-only AR(2) tracking)", flag="--no-input")
    static_offset: bool = field(
        True,
        "Constant regressor for the static deflection offset of an attractive force (false: eq. 3.40 as is)",
        flag="--no-static-offset",
    )
    free_air: str = _free_air_segment_field("Off-sample segment START:END for the free-air model; empty = metadata")
    model: str = _free_air_model_file_field(
        "Free-air model file (free_air.json from 'identify freeair'); overrides free_air"
    )
    f0_hz: float = _free_air_f0_field()
    q: float = _free_air_q_field()
    drive_hold: str = _drive_hold_field()
    rows: str = _rows_field("at least 8 rows per forgetting window (50 us at 400 us)")
    decimate: int = _decimation_field()
    drive_frequency_hz: float = _lockin_frequency_field("Lock-in frequency; 0 = metadata drive, else the free-air f0")
    lockin_lowpass_hz: float = _lockin_lowpass_field()
    bandpass_half_width_hz: float = field(
        5000.0, "Output-only mode: band-pass ±this around the spectral peak before AR(2); 0 = off", "Hz", bounds=">= 0"
    )
    vs: str = field("auto", "Force-curve binning against z_piezo", choices=("auto", "time", "z"), flag="--vs")
    z_bin: float = field(0.5, "Force-curve bin width, in the units of z_piezo", bounds="> 0", flag="--z-bin")
    spring_constant_n_per_m: float = field(
        0.0, "Spring constant k for the interaction quantities (e.g. identify freeair --psd); 0 = metadata "
        "cantilever.spring_constant_n_per_m", "N/m", bounds=">= 0", flag="--spring-constant",
    )
    warmup_windows: float = field(
        5.0, "Windows 1/(1-λ) flagged as not converged at the start (and left out of the summaries)", bounds=">= 0"
    )
    min_amplitude_fraction: float = field(
        0.01,
        "Validity: f0', Q' flagged where the amplitude is below this share of the free amplitude; 0 = off",
        bounds=">= 0",
    )
    max_offset_drift: float = field(
        0.1,
        "Validity: f0', Q' flagged where the static offset's variance over the window exceeds this share "
        "of A^2/2; 0 = off",
        bounds=">= 0",
    )
    # 1 Mi samples: each chunk costs ~2 ms of hand-offs between the reading, computing and
    # writing threads, 0.6 s per 1e8 samples at 256 Ki; the buffers cost ~100 MB.
    chunk_samples: int = _chunk_samples_field(1 << 20)

    def validate(self) -> None:
        """Cross-field and format checks; the bounds are checked from the declarations."""
        parse_interval(self.free_air, "free_air")
        _check_f0_q(self.f0_hz, self.q)


@dataclass(frozen=True)
class ProbeLossParams:
    """``afmtool probeloss``: reliability index, switching signal and amplitude baseline (ch. 2)."""

    free_air: str = _free_air_segment_field(
        "Off-sample segment START:END (model, index level, thresholds, A0); empty = metadata"
    )
    model: str = _free_air_model_file_field(
        "Free-air model file (free_air.json from 'identify freeair'); overrides identification"
    )
    f0_hz: float = _free_air_f0_field()
    q: float = _free_air_q_field()
    drive_hold: str = _drive_hold_field()
    gain: str = field(
        "decay", "Observer gain: error decay in decay_cycles, or steady-state Kalman", choices=("decay", "kalman")
    )
    decay_cycles: float = field(
        0.0,
        "Decay design of the rms and coherent indices: time constant of the observer error; 0 = 1",
        "drive periods",
        bounds=">= 0",
        flag="--decay-cycles",
    )
    process_noise: float = field(
        0.0,
        "Kalman design: force noise as the static deflection it causes, rms",
        "deflection units",
        bounds=">= 0",
        flag="--process-noise",
    )
    measurement_noise: float = field(
        0.0, "Kalman design: measurement noise rms (> 0)", "deflection units", bounds=">= 0", flag="--measurement-noise"
    )
    index: str = field(
        "auto",
        "Reliability index: the innovation's window RMS (thesis), its amplitude at the drive demodulated over "
        "the window (coherent), or the tip-sample force at the drive by a Kalman filter on the free-air model "
        "(forcing, near the information limit); auto = the one predicted fastest at precision >= 0.9 on this "
        "capture (report.json: detectability)",
        choices=("auto", "rms", "coherent", "forcing"),
        flag="--index",
    )
    window_periods: float = field(
        0.0, "Window of the rms or coherent index; 0 = 1 (rms) or 1.5 (coherent)", "drive periods", bounds=">= 0",
        flag="--window-periods",
    )
    latency_periods: float = field(
        0.0,
        "Latency the detector aims at: the most precise design predicted within it; 0 = the fastest predicted "
        "at precision >= 0.9",
        "drive periods",
        bounds=">= 0",
        flag="--latency-periods",
    )
    index_level: float = field(
        0.0,
        "Free-air innovation RMS the index is divided by; 0 = from the free-air segment",
        "deflection units",
        bounds=">= 0",
        flag="--index-level",
    )
    on: float = field(
        0.0,
        "Loss declared when the index falls below this; 0 = automatic (free-air statistics)",
        bounds=">= 0",
        flag="--on",
    )
    off: float = field(0.0, "Loss ends when the index rises above this; 0 = automatic", bounds=">= 0", flag="--off")
    quantile: float = field(0.999, "Automatic on: this quantile of the free-air index", bounds="(0, 1)")
    off_ratio: float = field(2.0, "Automatic off: off_ratio times on", bounds="> 1")
    amplitude_upper: float = field(
        0.0,
        "Amplitude baseline: loss while the amplitude exceeds A_upper; 0 = automatic",
        "deflection units",
        bounds=">= 0",
        flag="--amplitude-upper",
    )
    setpoint: float = field(
        0.0,
        "Amplitude set point A_sp for the automatic A_upper; 0 = metadata controller",
        "deflection units",
        bounds=">= 0",
        flag="--setpoint",
    )
    upper_fraction: float = field(0.25, "Automatic A_upper = A_sp + upper_fraction·(A0 − A_sp)", bounds=">= 0")
    drive_frequency_hz: float = _lockin_frequency_field("Drive frequency; 0 = metadata drive, else the free-air f0")
    lockin_lowpass_hz: float = _lockin_lowpass_field()
    rows: str = _rows_field("one row per index window (the RMS or coherent index's window, the forcing filter's "
                            "memory); events use every sample")
    decimate: int = _decimation_field()
    min_event_periods: float = field(5.0, "Truth scores count events at least this long", "drive periods", bounds="> 0")
    truth_gap_periods: float = field(
        1.5, "Truth: no contact for longer than this is probe loss", "drive periods", bounds="> 0"
    )
    max_events: int = field(1000, "Events listed in report.json (all are counted)", bounds=">= 0")
    # 1 Mi samples, as reep: per-chunk hand-offs cost 0.7 s per 1e8 samples at 256 Ki
    chunk_samples: int = _chunk_samples_field(1 << 20)

    def validate(self) -> None:
        """Cross-field and format checks; the bounds are checked from the declarations."""
        parse_interval(self.free_air, "free_air")
        _check_f0_q(self.f0_hz, self.q)
        if self.on and self.off and not self.on < self.off:
            raise ConfigError(f"on={self.on!r} must be below off={self.off!r}")
        if self.gain == "kalman" and not self.measurement_noise > 0:
            raise ConfigError("gain='kalman' needs measurement_noise > 0 (and process_noise >= 0)")


_FORCE_SETS = ("attractive", "attractive-repulsive", "repulsive", "repulsive-q38", "ch4-default")


@dataclass(frozen=True)
class AveragingParams:
    """``afmtool theory averaging``: ωe, Qe and the steady state along a force curve (ch. 4)."""

    f0_hz: float = field(80318.0, "Free-air resonant frequency", "Hz", bounds="> 0", flag="--f0")
    q: float = field(168.0, "Free-air quality factor", bounds="> 0")
    force_set: str = field(
        "attractive", "Piecewise-linear force parameters (thesis sets)", choices=_FORCE_SETS, flag="--force-set"
    )
    force: str = field(
        "", "Custom force d=...,wa2=...,wb2=...,ca=...,cb=... (nm, 1/s^2, 1/s); overrides force_set", flag="--force"
    )
    q_values: str = field("", "Several free-air Q overlaid in one figure, e.g. 50,100,200,400 (Figs. 4.2-4.5)")
    free_amplitude_nm: float = field(
        20.0, "Free-air oscillation amplitude at the drive", "nm", bounds="> 0", flag="--free-amplitude"
    )
    drive_offset_hz: float = field(0.0, "Drive frequency minus f0", "Hz")
    separation_from_nm: float = field(30.0, "Force curve start (largest separation)", "nm")
    separation_to_nm: float = field(0.0, "Force curve turn (smallest separation)", "nm")
    points: int = field(601, "Separations along each leg", bounds=">= 2")

    def validate(self) -> None:
        """Cross-field checks; the bounds are checked from the declarations."""
        if self.separation_to_nm >= self.separation_from_nm:
            raise ConfigError("separation_to_nm must be below separation_from_nm")


@dataclass(frozen=True)
class TheoryCompareParams:
    """``afmtool theory compare``: REEP output beside averaging theory (§3.4.3)."""

    force_set: str = field(
        "", "Force parameters; empty = the capture's metadata force", choices=("",) + _FORCE_SETS, flag="--force-set"
    )
    force: str = field(
        "", "Custom force d=...,wa2=...,wb2=...,ca=...,cb=... (nm, 1/s^2, 1/s); overrides force_set", flag="--force"
    )
    fit: str = field(
        "", "The output folder of 'theory fit' on this REEP run: its fitted force and contact point", flag="--fit"
    )
    amplitude_fraction: float = field(
        0.3, "Compare where the amplitude is above this share of the free amplitude", bounds="(0, 1)"
    )
    tolerance: float = field(
        0.1,
        "Model floor: averaging theory is expected to hold to this share of its own shift from free air (eq. C.1)",
        bounds="> 0",
    )
    bin_nm: float = field(1.0, "Width of the separation bins whose medians are compared", "nm", bounds="> 0",
                          flag="--bin")
    separation: str = field(
        "auto",
        "Separation from /truth, from z_piezo, or (with --fit) the fitted contact point; auto = /truth when present",
        choices=("auto", "truth", "z-piezo"),
        flag="--separation",
    )
    z_sensitivity: float = field(
        0.0, "z_piezo sensitivity; 0 = from the channel's length units", "nm/unit", flag="--z-sensitivity"
    )
    contact_z: str = field(
        "", "z_piezo reading at contact (l = 0); empty = aligned on the approach amplitude", flag="--contact-z"
    )

    def validate(self) -> None:
        """Format checks; the bounds are checked from the declarations."""
        if self.contact_z:
            try:
                contact_z = float(self.contact_z)
            except ValueError:
                raise ConfigError(f"contact_z={self.contact_z!r} must be a number") from None
            if not math.isfinite(contact_z):
                raise ConfigError(f"contact_z={self.contact_z!r} must be a finite number")


@dataclass(frozen=True)
class TheoryControllersParams:
    """``afmtool theory controllers``: low, high and switching z-controller gains on the grating (ch. 2)."""

    line_rates_hz: str = field("4,8,12,30", "Line rates of the table, comma-separated", "Hz", flag="--line-rates")
    lines: int = field(2, "Raster lines per table run (a trace and a retrace each)", bounds=">= 1", flag="--lines")
    seed: int = field(
        1, "Simulation seed (the same surface, noise and seed for the three controllers)", bounds=">= 0", flag="--seed"
    )
    tolerance: float = field(
        1.2, "Pass: switching loss area <= this x the high gain's, peak force <= this x the low's", bounds=">= 1"
    )
    figure_line_rate_hz: float = field(12.0, "Line rate of the height images", "Hz", bounds="> 0")
    figure_lines: int = field(16, "Raster lines of the height images", bounds=">= 1", flag="--figure-lines")
    figure_pixels: int = field(48, "Pixels per line of the height images", bounds=">= 1")

    def rates(self) -> tuple[float, ...]:
        """The line rates as numbers, Hz."""
        try:
            rates = tuple(float(v) for v in self.line_rates_hz.split(","))
        except ValueError:
            raise ConfigError(f"line_rates_hz={self.line_rates_hz!r} must be comma-separated numbers") from None
        return rates

    def validate(self) -> None:
        """Format checks; the bounds are checked from the declarations."""
        if not all(math.isfinite(rate) and rate > 0 for rate in self.rates()):
            raise ConfigError(f"line_rates_hz={self.line_rates_hz!r} must all be finite and > 0")


#: The fields of ``[kalman-bank.reep]`` that kalman-bank sets from its own section.
_BANK_OWNED_REEP_FIELDS = ("free_air", "model", "f0_hz", "q", "drive_hold", "rows", "decimate", "drive_frequency_hz",
                           "vs", "z_bin", "chunk_samples")


@dataclass(frozen=True)
class KalmanBankParams:
    """``afmtool kalman-bank``: validate REEP by a bank of Kalman filters and an adaptive observer (§3.4.2)."""

    n_filters: int = field(
        5, "Filters spread over the approach when neither at_z nor models is given", bounds=">= 1", flag="--n-filters"
    )
    at_z: str = field(
        "", "Design points z1,z2,... (z_piezo units); models from REEP there; empty = automatic", flag="--at-z"
    )
    models: str = field("", "Bank models f0_hz:q,f0_hz:q,... instead of REEP's; empty = from REEP", flag="--models")
    design_leg: str = field(
        "approach", "Force-curve leg the design points and verdict refer to", choices=("approach", "retract")
    )
    reep_run: str = field("", "REEP output folder or reep.h5 to use; empty = run REEP internally", flag="--reep")
    free_air: str = _free_air_segment_field("Off-sample segment START:END for the free-air model; empty = metadata")
    model: str = _free_air_model_file_field("Free-air model file (free_air.json); overrides free_air")
    f0_hz: float = _free_air_f0_field()
    q: float = _free_air_q_field()
    drive_hold: str = _drive_hold_field()
    noise_ratio: float = field(
        0.03,
        "Kalman gains: process-noise rms (as static deflection) over measurement-noise rms, σ_w/σ_v",
        bounds="> 0",
        flag="--noise-ratio",
    )
    rms_window_periods: float = field(
        10.0, "Innovation RMS window, in drive periods", bounds="> 0", flag="--window-periods"
    )
    z_bin: float = field(0.5, "Bin width of RMS against z, in the units of z_piezo", bounds="> 0", flag="--z-bin")
    min_amplitude_fraction: float = field(
        0.25,
        "Automatic design points: only where REEP's amplitude is above this share of the free amplitude",
        bounds="[0, 1]",
    )
    onset_fraction: float = field(
        0.1,
        "Automatic design points: start where the model has moved this share of its change along the leg",
        bounds="[0, 1]",
    )
    z_tolerance_bins: int = field(
        0, "Verdict: a filter's RMS minimum may lie this many z bins from its design bin", bounds=">= 0"
    )
    rms_tolerance: float = field(
        0.01,
        "Verdict: or its RMS at the design bin may exceed its minimum by at most this share (flat minima)",
        bounds=">= 0",
    )
    adaptive_fraction: float = field(
        0.9, "Verdict: share of the time the adaptive observer must have the least RMS", bounds="(0, 1]"
    )
    f0_scale: float = field(
        1.0,
        "Multiply every bank model's f0 by this: a negative control that must fail",
        bounds="> 0",
        flag="--f0-scale",
    )
    drive_frequency_hz: float = _lockin_frequency_field("Drive frequency; 0 = metadata drive, else the free-air f0")
    rows: str = _rows_field("REEP's rows (at least 8 per REEP window, finer than the RMS window at the defaults), "
                            "the RMS of every observer beside them")
    decimate: int = _decimation_field(flag=None)
    chunk_samples: int = _chunk_samples_field(1 << 18)
    reep: ReepParams = field(
        ReepParams(),
        "REEP inside kalman-bank (pass 1 and the adaptive observer): window, rate, P0, offset regressor, bias "
        "compensation, warm-up; the free-air route, drive, decimation, z bin and chunking are kalman-bank's own",
    )

    def validate(self) -> None:
        """Cross-field and format checks; the bounds are checked from the declarations."""
        if self.at_z and self.models:
            raise ConfigError("give at_z or models, not both")
        parse_interval(self.free_air, "free_air")
        _check_f0_q(self.f0_hz, self.q)
        for name in _BANK_OWNED_REEP_FIELDS:
            if getattr(self.reep, name) != getattr(ReepParams, name):
                raise ConfigError(f"[kalman-bank.reep] {name}: kalman-bank sets it; give it in [kalman-bank]")
        if not self.reep.use_input:
            raise ConfigError("[kalman-bank.reep] use_input = false: the bank's observers need the dither")


@dataclass(frozen=True)
class ObserverTheoryParams:
    """``afmtool theory observer``: A_e², sensitivities, SNR and transients of an observer design (ch. 5)."""

    f0_hz: float = field(80318.0, "Nominal (free-air) plant resonance f0", "Hz", bounds="> 0", flag="--f0")
    q: float = field(168.0, "Nominal plant quality factor", bounds="> 0.5", flag="--q")
    gain: float = field(
        1.0, "Numerator DC gain: c0 = gain·ω0², c1 = 0 (eq. 5.13), deflection per dither unit", bounds="> 0"
    )
    model: str = field("", "Free-air model file (free_air.json); overrides f0_hz, q and gain", flag="--model")
    f0_low_hz: float = field(
        0.0,
        "End of the force-curve direction (on-sample f0'); 0 = from reep or averaging theory",
        "Hz",
        bounds=">= 0",
        flag="--f0-low",
    )
    q_low: float = field(
        0.0, "End of the force-curve direction (on-sample Q'); 0 = as f0_low_hz", bounds=">= 0", flag="--q-low"
    )
    reep: str = field(
        "", "REEP output folder or reep.h5: the direction ends at its lowest usable amplitude", flag="--reep"
    )
    force_set: str = field(
        "attractive", "Averaging theory direction: thesis force set", choices=_FORCE_SETS, flag="--force-set"
    )
    setpoint_fraction: float = field(0.3, "Direction end: amplitude as a share of the free amplitude", bounds="(0, 1)")
    free_amplitude_nm: float = field(20.0, "Free-air deflection amplitude at the drive", "nm", bounds="> 0")
    drive_frequency_hz: float = field(0.0, "Drive frequency ω/2π; 0 = f0_hz", "Hz", bounds=">= 0")
    cycles: str = field(
        "4,50", "Observer gains: error time constants in drive periods (aggressive, sluggish)", flag="--cycles"
    )
    observers: str = field(
        "", "Directional plots: observer models f0_hz:q,...; empty = free-air and direction end", flag="--observers"
    )
    grid_points: int = field(41, "Points per axis of the 2-D observer-model maps", bounds=">= 3")
    grid_margin: float = field(0.5, "Maps extend this share of the direction's span beyond its ends", bounds=">= 0")
    line_points: int = field(101, "Points along the force-curve direction", bounds=">= 3")
    spring_constant_n_per_m: float = field(2.0, "Spring constant k, for the thermal noise η", "N/m", bounds="> 0")
    temperature_k: float = field(300.0, "Temperature of the thermal noise η", "K", bounds=">= 0")
    measurement_asd: float = field(
        1.0e-4, "Measurement noise ν, one-sided amplitude spectral density", "nm/sqrt(Hz)", bounds=">= 0"
    )
    recommend: bool = field(
        False,
        "Also pick the model and gain of greatest sensitivity whose transients settle in time",
        flag="--recommend",
    )
    max_cycles: float = field(
        10.0,
        "Recommend: the error must settle (below residual) within this many drive periods",
        bounds="> 0",
        flag="--max-cycles",
    )
    residual: float = field(
        0.36787944117144233, "Settled: the step response stays below this share of the step (1/e)", bounds="(0, 1)"
    )
    sample_rate_hz: float = field(
        500e3, "Recommend: also give the discrete observer (eq. 3.40) at this rate", "Hz", bounds="> 0"
    )
    drive_hold: str = field(
        "continuous",
        "Recommend: the discrete observer's numerator for a continuous drive or one a DAC holds per sample",
        choices=("continuous", "zoh"),
    )


@dataclass(frozen=True)
class GammaParams:
    """``afmtool identify gamma``: Γ_IR,ts with the feed-through removed (eqs. 6.15, 6.16)."""

    method: str = field(
        "auto",
        "Frequency responses: H1 (chirp/broadband), stepped sines, or auto (stepped if both captures "
        "carry segments metadata)",
        choices=("auto", "h1", "stepped"),
    )
    nperseg: int = field(
        0, "H1 segment length in samples; 0 = largest power of two <= n/16", bounds=">= 16", automatic=0
    )
    min_coherence: float = field(
        0.9,
        "Usable band: coherence of Gamma_IR,V and Gamma_ts,V at least this",
        bounds="[0, 1]",
        flag="--min-coherence",
    )
    settle_fraction: float = field(0.5, "Stepped sines: share of each step skipped before the lock-in", bounds="[0, 1)")
    min_periods: int = field(4, "Stepped sines: fewest drive periods per step after settling", bounds=">= 1")
    roll_off_start_factor: float = field(2.0, "Roll-off fitted from this multiple of the bandwidth ...", bounds="> 0")
    roll_off_stop_factor: float = field(10.0, "... to this multiple (or the top of the usable band)", bounds="> 0")
    chunk_samples: int = field(
        1 << 18, "Samples per streamed chunk (H1 streams; stepped sines are held)", bounds=">= 16"
    )

    def validate(self) -> None:
        """Cross-field checks; the bounds are checked from the declarations."""
        if not self.roll_off_start_factor < self.roll_off_stop_factor:
            raise ConfigError(
                f"roll_off_start_factor={self.roll_off_start_factor!r} must be below "
                f"roll_off_stop_factor={self.roll_off_stop_factor!r}"
            )


@dataclass(frozen=True)
class DecodeParams:
    """``afmtool decode``: EKF bit decoder for electrostatically actuated probes (ch. 7)."""

    voltage_channel: str = field(
        "",
        "Channel holding the lever-sample voltage V; empty = alpha_r*v_r - v_sub (eq. 6.3)",
        flag="--voltage-channel",
    )
    nominal: str = field(
        "", "Nominal (bit-free) segment START:END for l0 and noise; empty = metadata nominal", "s", flag="--nominal"
    )
    f0_hz: float = field(0.0, "Resonant frequency f0; 0 = metadata cantilever.f0_hz", "Hz", bounds=">= 0")
    q: float = field(0.0, "Quality factor Q; 0 = metadata cantilever.q", bounds="> 0.5", automatic=0.0)
    electrostatic: str = field(
        "",
        "electrostatic.json (or its folder) from 'identify electrostatic': K_esf/k, alpha_R, l0 (and t_h, k) of "
        "eqs. 6.6/6.7; parameters given here win, the capture metadata fills the rest",
        flag="--electrostatic",
    )
    spring_constant_n_per_m: float = field(
        0.0, "Spring constant k; 0 = --electrostatic, else metadata cantilever", "N/m", bounds=">= 0"
    )
    k_esf_f_m: float = field(
        0.0, "K_esf (no-1/2 convention); 0 = --electrostatic (K_esf/k times k), else metadata", "F*m", bounds=">= 0"
    )
    alpha_r: float = field(
        -1.0,
        "alpha_R of V = alpha_R*V_R - V_sub (eq. 6.3); 0 = the lever at ground (V = -V_sub); -1 = --electrostatic, "
        "else metadata",
        bounds=">= 0",
        automatic=-1.0,
        flag="--alpha-r",
    )
    tip_height_nm: float = field(
        0.0, "Tip height t_h; 0 = --electrostatic, else metadata, else none (the separation is not clamped)", "nm",
        bounds=">= 0",
    )
    l0_nm: float = field(
        0.0, "Lever-sample separation l0; 0 = estimate on the nominal segment (§7.4)", "nm", bounds=">= 0", flag="--l0"
    )
    l0_bracket_nm: str = field(
        "", "l0 search bracket LOW:HIGH; empty = 0.75-1.33 x the guess (--electrostatic or metadata l0), else "
        "1.05 t_h (or 100 nm) to 20 um on a geometric grid", "nm"
    )
    l0_grid_points: int = field(
        41, "Coarse grid points of the l0 search before golden-section refinement", bounds=">= 5"
    )
    process_noise_n_per_rthz: float = field(
        0.0,
        "Force-noise ASD of the EKF; 0 = estimate on the nominal segment (mean NIS = 1)",
        "N/sqrt(Hz)",
        bounds=">= 0",
        flag="--process-noise",
    )
    measurement_noise_nm: float = field(
        0.0,
        "Rms measurement noise; 0 = estimate from the PSD floor of the nominal segment",
        "nm",
        bounds=">= 0",
        flag="--measurement-noise",
    )
    temperature_k: float = field(
        300.0, "Thermal force noise used for the l0 search when the process noise is estimated", "K", bounds=">= 0"
    )
    warmup_s: float = field(
        2e-4, "Start of the nominal segment left out of the innovation statistics", "s", bounds=">= 0"
    )
    actuation_hz: float = field(
        0.0,
        "Actuation frequency; 0 = metadata drive, else the strongest line of V^2",
        "Hz",
        bounds=">= 0",
        flag="--actuation-hz",
    )
    mean_window: int = field(
        0, "Running mean of the innovation, samples; 0 = one actuation period", bounds="[1, 10000000]", automatic=0
    )
    bit_rate_hz: float = field(
        0.0, "Bit rate; 0 = recover the clock from the transitions", "Hz", bounds=">= 0", flag="--bit-rate"
    )
    bit_rate_min_hz: float = field(1000.0, "Clock recovery: lowest bit rate searched", "Hz", bounds="> 0")
    bit_rate_max_hz: float = field(
        0.0, "Clock recovery: highest bit rate searched; 0 = the actuation frequency", "Hz", bounds=">= 0"
    )
    bits_from_s: float = field(
        -1.0, "Start of the bit stream; < 0 = the end of the nominal segment (or 0)", "s", flag="--bits-from"
    )
    clock_window_s: float = field(
        0.005, "Clock acquisition window at the start of the bit stream", "s", bounds="> 0", flag="--clock-window"
    )
    integrate_fraction: float = field(0.7, "Share of each bit cell integrated (centred)", bounds="(0, 1]")
    polarity: str = field(
        "negative",
        "Innovation sign of a 1 bit (a raised sample attracts more: negative)",
        choices=("negative", "positive"),
        flag="--polarity",
    )
    pll_phase_gain: float = field(
        0.05, "Clock tracking: share of each transition's phase error corrected", bounds="[0, 1)"
    )
    pll_rate_gain: float = field(
        0.001, "Clock tracking: rate correction per transition (recovered rates only)", bounds="[0, 1)"
    )
    baseline_lowpass_hz: float = field(
        0.0, "Lock-in baseline low-pass; 0 = min(bit rate/2, actuation/4)", "Hz", bounds=">= 0"
    )
    psd_window_s: float = field(0.02, "Stretch of the bit stream used for the PSD comparison plot", "s", bounds="> 0")
    mode: str = field(
        "auto",
        "What the capture holds: bits read back, or a step in the surface potential V_phi (§7.7: step response of "
        "the deflection, its amplitude and the EKF innovation); auto = step when the metadata has vphi_step",
        choices=("auto", "bits", "step"),
        flag="--mode",
    )
    step_time_s: float = field(
        0.0, "Time of the V_phi step; 0 = metadata vphi_step.time_s, else the end of the nominal segment", "s",
        bounds=">= 0", flag="--step-time",
    )
    rows: str = _rows_field(
        "the innovation's running mean once per actuation period (bits are never faster than the actuation), no "
        "per-sample innovation", per_period="also the innovation at every sample (float32)",
    )
    eye_traces: int = field(200, "Bit cells drawn in the eye diagram", bounds=">= 1")
    # 1 Mi samples: each chunk costs ~2 ms of hand-offs between the reading, computing and
    # writing threads, 0.6 s per 1e8 samples at 256 Ki; the buffers cost ~100 MB.
    chunk_samples: int = _chunk_samples_field(1 << 20)

    def validate(self) -> None:
        """Cross-field and format checks; the bounds are checked from the declarations."""
        parse_interval(self.nominal, "nominal")
        if self.bit_rate_max_hz and self.bit_rate_max_hz <= self.bit_rate_min_hz:
            raise ConfigError(
                f"bit_rate_max_hz={self.bit_rate_max_hz!r} must exceed bit_rate_min_hz={self.bit_rate_min_hz!r}"
            )
        if self.l0_bracket_nm:
            parse_bracket_nm(self.l0_bracket_nm)


def parse_bracket_nm(text: str) -> tuple[float, float]:
    """``"900:1300"`` -> (900.0, 1300.0) nm, 0 < LOW < HIGH."""
    low, sep, high = text.partition(":")
    try:
        bracket = (float(low), float(high))
    except ValueError:
        raise ConfigError(f"l0_bracket_nm={text!r} must look like LOW:HIGH in nm") from None
    if not sep or not (math.isfinite(bracket[1]) and 0 < bracket[0] < bracket[1]):
        raise ConfigError(f"l0_bracket_nm={text!r} must look like LOW:HIGH with 0 < LOW < HIGH (nm)")
    return bracket


@dataclass(frozen=True)
class ThermalParams:
    """``afmtool identify thermal``: g(T), K_TP, K_TP(t_s), C(jω) and H(jω) (§6.5.2, §6.6.2)."""

    breakdown_temperature_c: float = field(
        550.0,
        "Breakdown temperature T_k of the sensor (the I-V knee)",
        "degC",
        bounds=">= -273.15",
        flag="--breakdown-temperature",
    )
    room_temperature_c: float = field(
        25.0, "Room temperature T_r (the sensor at zero power)", "degC", bounds=">= -273.15", flag="--room-temperature"
    )
    g_order: int = field(2, "Degree of the polynomial fit of g(T)", bounds="[1, 6]")
    g_table_bins: int = field(40, "Temperature bins of the g(T) table", bounds=">= 2")
    knee_fit_fraction: float = field(0.5, "The knee is fitted on V_R >= this share of the largest V_R", bounds="(0, 1)")
    z_bin_nm: float = field(10.0, "Bin width of the K_TP(t_s) table", "nm", bounds="> 0")
    method: str = field(
        "auto",
        "V_R sweep: H1, stepped sines, or auto (stepped if the capture has segments)",
        choices=("auto", "h1", "stepped"),
    )
    nperseg: int = field(
        0, "V_R sweep, H1 segment length; 0 = largest power of two <= n/16", bounds=">= 16", automatic=0
    )
    min_coherence: float = field(
        0.9, "V_R sweep: bins with a lower coherence are left out of the summaries", bounds="[0, 1]"
    )
    settle_fraction: float = field(0.5, "Stepped sines: share of each step skipped before the lock-in", bounds="[0, 1)")
    min_periods: int = field(4, "Stepped sines: fewest drive periods per step after settling", bounds=">= 1")
    chunk_samples: int = field(1 << 18, "Samples per streamed chunk", bounds=">= 16")

    def validate(self) -> None:
        """Cross-field checks; the bounds are checked from the declarations."""
        if not self.breakdown_temperature_c > self.room_temperature_c:
            raise ConfigError(
                f"breakdown_temperature_c={self.breakdown_temperature_c!r} must exceed "
                f"room_temperature_c={self.room_temperature_c!r}"
            )


@dataclass(frozen=True)
class ElectrostaticFitParams:
    """``afmtool identify electrostatic``: eq. 6.6 (optical) or eq. 6.7 (thermal) by nonlinear least squares."""

    sensor: str = field(
        "auto",
        "Which curve to fit: optical deflection (eq. 6.6), thermal current through K_TP (eq. 6.7), or auto "
        "(optical if the capture has deflection)",
        choices=("auto", "optical", "thermal"),
        flag="--sensor",
    )
    v_r_v: float = field(0.0, "Sensor voltage V_R; 0 = the mean of the capture's v_r channel", "V", flag="--v-r")
    spring_constant_n_per_m: float = field(
        0.0,
        "Spring constant k if known (then K_esf is reported); 0 = unknown: only K_esf/k is identifiable",
        "N/m",
        bounds=">= 0",
        flag="--spring-constant",
    )
    snap_margin: float = field(0.05, "Drop this share of the V_sub range just before snap-in", bounds="[0, 1)")
    rank_tolerance: float = field(
        1e-7, "Relative singular value below which a combination is not identifiable", bounds="(0, 1)"
    )
    max_relative_std: float = field(
        0.1, "Parameters with a larger relative standard deviation are flagged", bounds="> 0"
    )


@dataclass(frozen=True)
class InvolsParams:
    """``afmtool identify invols``: the InvOLS from the contact part of a force curve on a hard sample."""

    leg: str = field("approach", "Which part of the curve to fit", choices=("approach", "retract", "all"), flag="--leg")
    skip_fraction: float = field(
        0.1, "Share of the contact z range next to the contact point left out of the fit", bounds="[0, 1)"
    )
    z_channel: str = field(
        "z_piezo", "Channel holding the z-piezo position (a length, or V with --z-sensitivity)", flag="--z-channel"
    )
    deflection_channel: str = field(
        "deflection", "Channel holding the deflection (V, or a length)", flag="--deflection-channel"
    )


@dataclass(frozen=True)
class SpringConstantParams:
    """``afmtool identify freeair --psd``: the spring constant, thermal (Butt–Jaschke) and Sader."""

    detection: str = field(
        "optical-lever",
        "How the spectrum's deflection was measured: optical lever calibrated by a static force "
        "curve (factor 0.817) or the tip's displacement itself, e.g. an interferometer (0.971)",
        choices=("optical-lever", "displacement"),
        flag="--detection",
    )
    length_um: float = field(
        0.0,
        "Sader: plan-view length L of the rectangular cantilever; 0 = no Sader value",
        "um",
        bounds=">= 0",
        flag="--length",
    )
    width_um: float = field(0.0, "Sader: plan-view width b; 0 = no Sader value", "um", bounds=">= 0", flag="--width")
    fluid: str = field("air", "Sader: the fluid around the cantilever", choices=("air", "water"), flag="--fluid")
    fluid_density_kg_per_m3: float = field(
        0.0, "Sader: fluid density; 0 = that of the fluid at 25 degC", "kg/m^3", bounds=">= 0"
    )
    fluid_viscosity_pa_s: float = field(
        0.0, "Sader: fluid viscosity; 0 = that of the fluid at 25 degC", "Pa s", bounds=">= 0"
    )

    def validate(self) -> None:
        """Cross-field checks; the bounds are checked from the declarations."""
        if (self.length_um > 0) != (self.width_um > 0):
            raise ConfigError("the Sader method needs both length_um and width_um (--length, --width)")


@dataclass(frozen=True)
class DesignExcitationParams:
    """``afmtool design excitation``: the three-sine REEP dither of §3.3.2 for one cantilever."""

    amplitude_nm: float = field(
        20.0,
        "Free-air response amplitude at the main line (model deflection units)",
        "nm",
        bounds="> 0",
        flag="--amplitude",
    )
    dac_rate_hz: float = field(
        2.0e6, "Sample rate of the exported loop (a whole number of Hz)", "Hz", bounds="> 0", flag="--dac-rate"
    )
    drive_frequency_hz: float = field(
        0.0, "Main line; 0 = the model's f0", "Hz", bounds=">= 0", flag="--drive-frequency"
    )
    offset_hz: float = field(0.0, "Side-line offset; 0 = min(20 f0/Q, f0/10)", "Hz", bounds=">= 0", flag="--offset")
    beat_tolerance: float = field(
        0.03,
        "Largest relative excursion of the response envelope (side lines / main); kalman-bank warns above 0.03",
        bounds="> 0",
        flag="--beat-tolerance",
    )
    max_side_scale: float = field(
        0.5, "Largest side-line amplitude as a share of the main line's (thesis: 1/2)", bounds="> 0"
    )
    resolution_hz: float = field(
        0.0, "Frequency grid of the loop; 0 = f0/(100 Q)", "Hz", bounds=">= 0", flag="--resolution"
    )

    def validate(self) -> None:
        """Format checks; the bounds are checked from the declarations."""
        if self.dac_rate_hz != int(self.dac_rate_hz):
            raise ConfigError(
                f"dac_rate_hz={self.dac_rate_hz!r} must be a whole number of Hz (a WAV header holds an integer)"
            )


@dataclass(frozen=True)
class TheoryFitParams:
    """``afmtool theory fit``: force parameters fitted to REEP's approach (ch. 4)."""

    amplitude_fraction: float = field(
        0.3, "Fit where the amplitude is above this share of the free amplitude", bounds="[0, 1)"
    )
    max_relative_std: float = field(
        0.1, "A parameter with a larger relative standard deviation is not identified", bounds="> 0"
    )
    z_sensitivity: float = field(
        0.0, "z_piezo sensitivity; 0 = from the channel's length units", "nm/unit", flag="--z-sensitivity"
    )
    skip_s: float = field(5e-3, "Leave out REEP's start-up", "s", bounds=">= 0")
    max_samples: int = field(3000, "Fit at most this many (evenly thinned) approach samples", bounds=">= 20")


def __getattr__(name: str):
    """``SECTIONS``: config-file section -> parameter model, derived from the command specs.

    Looked up when first read, not at import: the specs (:mod:`afmtool.config.commands`)
    name the models defined here, so this module cannot import them while it loads.
    """
    if name == "SECTIONS":
        from afmtool.config.commands import sections

        globals()["SECTIONS"] = sections()  # once: later reads find the module attribute
        return globals()["SECTIONS"]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
