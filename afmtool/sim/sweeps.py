"""Wide-band sweeps: a repeated linear chirp, and stepped sines on a logarithmic grid.

:class:`RepeatedChirp` sweeps start → stop again and again.  For an H1
estimate over several decades this matters: a single linear chirp passes
the lowest decades in its first milliseconds, where the first Welch
segment's window is nearly zero, so those bins get almost no weight.
Repeating the sweep puts every frequency in the middle of some segment.

:class:`~afmtool.sim.excitation.SteppedSine` holds every step equally long,
which over three decades wastes time at high frequency or starves the low
ones of periods.  :class:`LogSteppedSine` gives step k the dwell
max(c/f_k, ``min_dwell_s``) with c (periods) chosen so the steps fill the
sweep duration: every low-frequency step then holds the same number of
periods.  Phase is continuous across steps; values are in the drive's units.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from afmtool.errors import ConfigError

__all__ = ["RepeatedChirp", "LogSteppedSine", "log_stepped_sine"]


@dataclass(frozen=True)
class RepeatedChirp:
    """Linear sweeps from ``start_hz`` to ``end_hz`` repeated every ``period_s``, continuous phase.

    Within sweep k (t in [kT, (k+1)T)) the phase advances as
    2π(f_s·τ + (f_e − f_s)τ²/(2T)), τ = t − kT, so each sweep adds
    (f_s + f_e)·T/2 cycles; the frequency jumps back to f_s at each restart.

    Parameters
    ----------
    amplitude : float
        Amplitude (drive units), ≥ 0.
    start_hz, end_hz : float
        Sweep limits, Hz, > 0.
    period_s : float
        Duration T of one sweep, s, > 0.
    """

    amplitude: float
    start_hz: float
    end_hz: float
    period_s: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.amplitude) and self.amplitude >= 0):
            raise ConfigError(f"amplitude={self.amplitude!r} must be a finite number >= 0")
        for name in ("start_hz", "end_hz", "period_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"{name}={value!r} must be a finite number > 0")

    @property
    def max_frequency_hz(self) -> float:
        return float(max(self.start_hz, self.end_hz))

    def phase_rad(self, t_s) -> np.ndarray:
        """Unwrapped phase, rad (t ≥ 0)."""
        t = np.asarray(t_s, dtype=np.float64)
        k = np.floor(t / self.period_s)
        tau = t - k * self.period_s
        rate = (self.end_hz - self.start_hz) / self.period_s
        per_sweep = 0.5 * (self.start_hz + self.end_hz) * self.period_s
        return 2.0 * np.pi * (k * per_sweep + self.start_hz * tau + 0.5 * rate * tau * tau)

    def __call__(self, t_s) -> np.ndarray:
        return self.amplitude * np.sin(self.phase_rad(t_s))

    def to_metadata(self) -> dict:
        return {
            "kind": "repeated-chirp",
            "frequency_hz": float(0.5 * (self.start_hz + self.end_hz)),
            "amplitude": float(self.amplitude),
            "start_hz": float(self.start_hz),
            "end_hz": float(self.end_hz),
            "sweep_period_s": float(self.period_s),
        }


@dataclass(frozen=True)
class LogSteppedSine:
    """Sines at ``frequencies_hz[k]`` held for ``dwells_s[k]`` in turn, continuous phase.

    Parameters
    ----------
    amplitude : float
        Amplitude (drive units), ≥ 0.
    frequencies_hz : tuple of float
        Step frequencies, Hz, > 0.
    dwells_s : tuple of float
        Step durations, s, > 0; same length.
    """

    amplitude: float
    frequencies_hz: tuple[float, ...]
    dwells_s: tuple[float, ...]

    def __post_init__(self) -> None:
        if not (math.isfinite(self.amplitude) and self.amplitude >= 0):
            raise ConfigError(f"amplitude={self.amplitude!r} must be a finite number >= 0")
        if not (len(self.frequencies_hz) == len(self.dwells_s) >= 1):
            raise ConfigError(
                f"frequencies_hz and dwells_s need one length >= 1, got {len(self.frequencies_hz)} and "
                f"{len(self.dwells_s)}"
            )
        for k, (f, d) in enumerate(zip(self.frequencies_hz, self.dwells_s)):
            if not (math.isfinite(f) and f > 0):
                raise ConfigError(f"frequencies_hz[{k}]={f!r} must be a finite number > 0")
            if not (math.isfinite(d) and d > 0):
                raise ConfigError(f"dwells_s[{k}]={d!r} must be a finite number > 0")

    @property
    def max_frequency_hz(self) -> float:
        return float(max(self.frequencies_hz))

    @property
    def duration_s(self) -> float:
        return float(sum(self.dwells_s))

    def _starts(self) -> np.ndarray:
        return np.concatenate(([0.0], np.cumsum(self.dwells_s)[:-1]))

    def segments(self) -> list[dict[str, float]]:
        """``[{"start_s", "end_s", "frequency_hz"}, ...]`` (capture metadata)."""
        starts = self._starts()
        return [
            {"start_s": float(s), "end_s": float(s + d), "frequency_hz": float(f)}
            for s, d, f in zip(starts, self.dwells_s, self.frequencies_hz)
        ]

    def phase_rad(self, t_s) -> np.ndarray:
        """Unwrapped phase, rad: cycles of the finished steps plus f_k·(t − start_k)."""
        t = np.asarray(t_s, dtype=np.float64)
        starts = self._starts()
        freqs = np.asarray(self.frequencies_hz)
        index = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(freqs) - 1)
        start_cycles = np.concatenate(([0.0], np.cumsum(freqs[:-1] * np.asarray(self.dwells_s[:-1]))))
        return 2.0 * np.pi * (start_cycles[index] + freqs[index] * (t - starts[index]))

    def __call__(self, t_s) -> np.ndarray:
        return self.amplitude * np.sin(self.phase_rad(t_s))

    def to_metadata(self) -> dict:
        return {
            "kind": "log-stepped",
            "frequency_hz": float(self.frequencies_hz[len(self.frequencies_hz) // 2]),
            "amplitude": float(self.amplitude),
        }


def log_stepped_sine(
    amplitude: float, start_hz: float, stop_hz: float, steps_per_decade: int, duration_s: float, min_dwell_s: float
) -> LogSteppedSine:
    """Log-spaced steps from ``start_hz`` to ``stop_hz`` filling ``duration_s``.

    Step k (frequency f_k = start·10^(k/steps_per_decade), the last one
    ``stop_hz``) lasts max(c/f_k, ``min_dwell_s``), with c found by bisection
    so that the dwells sum to ``duration_s``.

    Raises
    ------
    ConfigError
        For bad arguments, or a duration shorter than the minimum dwells.
    """
    for name, value in (("start_hz", start_hz), ("stop_hz", stop_hz), ("duration_s", duration_s),
                        ("min_dwell_s", min_dwell_s)):
        if not (math.isfinite(value) and value > 0):
            raise ConfigError(f"{name}={value!r} must be a finite number > 0")
    if not stop_hz > start_hz:
        raise ConfigError(f"stop_hz={stop_hz!r} must exceed start_hz={start_hz!r}")
    if not (isinstance(steps_per_decade, int) and steps_per_decade >= 1):
        raise ConfigError(f"steps_per_decade={steps_per_decade!r} must be an integer >= 1")
    n = int(math.floor(math.log10(stop_hz / start_hz) * steps_per_decade + 1e-9)) + 1
    freqs = start_hz * 10.0 ** (np.arange(n) / steps_per_decade)
    if freqs[-1] < stop_hz * (1 - 1e-9):
        freqs = np.append(freqs, stop_hz)
    if duration_s < min_dwell_s * freqs.size:
        raise ConfigError(
            f"duration_s={duration_s!r} is shorter than {freqs.size} steps of min_dwell_s={min_dwell_s!r}"
        )

    def total(c: float) -> float:
        return float(np.sum(np.maximum(c / freqs, min_dwell_s)))

    lo, hi = 0.0, duration_s * freqs[0]
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if total(mid) < duration_s else (lo, mid)
    dwells = np.maximum(hi / freqs, min_dwell_s)
    dwells *= duration_s / dwells.sum()  # exact sum (the bisection leaves ~1e-16 relative)
    return LogSteppedSine(float(amplitude), tuple(freqs.tolist()), tuple(dwells.tolist()))
