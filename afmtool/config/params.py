"""Typed parameter models, one frozen dataclass per command.

Each command resolves its parameters with :func:`afmtool.config.resolve_from`
(packaged defaults, then the user's ``--config`` section, then flags) and
saves the effective values next to its outputs.  Empty strings and zeros
mean "automatic" where a help text says so, because TOML has no null.
"""

from __future__ import annotations

from dataclasses import dataclass

from afmtool.config import field
from afmtool.errors import ConfigError

__all__ = ["SECTIONS", "ReepParams", "FreeAirParams", "AveragingParams", "TheoryCompareParams", "parse_interval"]


def parse_interval(text: str, option: str) -> tuple[float, float] | None:
    """``"0.01:0.05"`` -> (0.01, 0.05) seconds; ``""`` -> None."""
    if not text:
        return None
    start, sep, end = text.partition(":")
    try:
        interval = (float(start), float(end))
    except ValueError:
        raise ConfigError(f"{option}={text!r} must look like START:END in seconds") from None
    if not sep or not 0 <= interval[0] < interval[1]:
        raise ConfigError(f"{option}={text!r} must look like START:END with 0 <= START < END (s)")
    return interval


@dataclass(frozen=True)
class FreeAirParams:
    """``afmtool identify freeair``."""

    free_air: str = field("", "Off-sample segment START:END; empty = capture metadata free_air", "s")
    route: str = field(
        "segment", "Identification route", choices=("segment", "sweep", "thermal")
    )
    sweep_method: str = field("h1", "Sweep route: H1 (broadband/chirp) or stepped sines", choices=("h1", "stepped"))
    temperature_k: float = field(295.0, "Thermal route: temperature for the equipartition spring constant", "K")

    def validate(self) -> None:
        parse_interval(self.free_air, "free_air")
        if self.temperature_k <= 0:
            raise ConfigError(f"temperature_k={self.temperature_k!r} must be > 0")


@dataclass(frozen=True)
class ReepParams:
    """``afmtool reep``: recursive estimation of equivalent parameters (ch. 3)."""

    lam: float = field(0.995, "Forgetting factor λ of the BCEWRLS (eq. 3.39); window 1/(1-λ) samples")
    p0: float = field(1.0e6, "Initial covariance P(0) = P0·I (eq. 3.39)")
    bias_compensation: bool = field(True, "Bias-compensated EWRLS (false: plain EWRLS, for comparison)")
    use_input: bool = field(True, "Use the recorded dither (false: output-only AR(2) tracking)")
    free_air: str = field("", "Off-sample segment START:END for the free-air model; empty = metadata", "s")
    model: str = field("", "Free-air model file (free_air.json from 'identify freeair'); overrides free_air")
    decimate: int = field(0, "Keep one output sample in N; 0 = one per drive period")
    drive_frequency_hz: float = field(0.0, "Lock-in frequency; 0 = metadata drive, else the free-air f0", "Hz")
    lockin_lowpass_hz: float = field(0.0, "Lock-in low-pass corner; 0 = min(f/10, Δf/2)", "Hz")
    bandpass_half_width_hz: float = field(
        5000.0, "Output-only mode: band-pass ±this around the spectral peak before AR(2); 0 = off", "Hz"
    )
    vs: str = field("auto", "Force-curve binning against z_piezo", choices=("auto", "time", "z"))
    z_bin: float = field(0.5, "Force-curve bin width, in the units of z_piezo")
    warmup_windows: float = field(5.0, "Windows 1/(1-λ) left out of summary statistics at the start")
    chunk_samples: int = field(1 << 18, "Samples per streamed chunk (memory against per-chunk overhead)")

    def validate(self) -> None:
        if not 0.0 < self.lam < 1.0:
            raise ConfigError(f"lam={self.lam!r} must be in (0, 1)")
        if self.p0 <= 0:
            raise ConfigError(f"p0={self.p0!r} must be > 0")
        if self.decimate < 0:
            raise ConfigError(f"decimate={self.decimate!r} must be >= 0")
        for name in ("drive_frequency_hz", "lockin_lowpass_hz", "bandpass_half_width_hz", "warmup_windows"):
            if getattr(self, name) < 0:
                raise ConfigError(f"{name}={getattr(self, name)!r} must be >= 0")
        if self.z_bin <= 0:
            raise ConfigError(f"z_bin={self.z_bin!r} must be > 0")
        if self.chunk_samples < 16:
            raise ConfigError(f"chunk_samples={self.chunk_samples!r} must be >= 16")
        parse_interval(self.free_air, "free_air")


_FORCE_SETS = ("attractive", "attractive-repulsive", "repulsive", "repulsive-q38", "ch4-default")


@dataclass(frozen=True)
class AveragingParams:
    """``afmtool theory averaging``: ωe, Qe and the steady state along a force curve (ch. 4)."""

    f0_hz: float = field(80318.0, "Free-air resonant frequency", "Hz")
    q: float = field(168.0, "Free-air quality factor")
    force_set: str = field("attractive", "Piecewise-linear force parameters (thesis sets)", choices=_FORCE_SETS)
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
    amplitude_fraction: float = field(0.6, "Compare where the amplitude is above this share of the free amplitude")
    tolerance: float = field(0.25, "Pass when the worst error is within this share of the theory's change")

    def validate(self) -> None:
        if not 0 < self.amplitude_fraction < 1:
            raise ConfigError(f"amplitude_fraction={self.amplitude_fraction!r} must be in (0, 1)")
        if self.tolerance <= 0:
            raise ConfigError(f"tolerance={self.tolerance!r} must be > 0")


#: Config-file section -> parameter model.
SECTIONS: dict[str, type] = {
    "identify.freeair": FreeAirParams,
    "reep": ReepParams,
    "theory.averaging": AveragingParams,
    "theory.compare": TheoryCompareParams,
}
