"""The phases of a drive that was not recorded, from the deflection it caused.

An instrument that does not record its dither still says what it drove: the
lines' frequencies F_i (Hz) and amplitudes A_i (V) (``--drive``).  What it
does not say is each line's phase relative to the capture's first sample.
On the free-air segment the deflection is

    p(t) = Σ_i A_i·|G(jω_i)|·cos(ω_i t + φ_i + ∠G(jω_i)) + noise,

with G the free-air response of eq. 3.1.  A linear least-squares fit of p on
cos ω_i t and sin ω_i t gives each line's complex amplitude D_i; G is then
found from the magnitudes alone, and φ_i = ∠D_i − ∠G(jω_i).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from afmtool.errors import ConfigError, InputError

__all__ = ["DriveLine", "DrivePhaseFit", "parse_drive_lines", "line_amplitudes", "fit_drive_phases", "synthesize_drive"]


class DriveLine(NamedTuple):
    """One line of the dither: frequency (Hz), amplitude (V) and phase (rad) at t = 0."""

    frequency_hz: float
    amplitude_v: float
    phase_rad: float = 0.0


class DrivePhaseFit(NamedTuple):
    """The fitted lines and the second-order response their magnitudes imply.

    Attributes
    ----------
    lines : tuple of DriveLine
        With their fitted phases.
    f0_hz, q, gain : float
        G(s) = gain·ω0² / (s² + (ω0/Q)s + ω0²) from the lines' magnitudes
        (``gain`` in deflection units per V); from the metadata when fewer
        than three lines.
    response_source : str
        ``"line magnitudes"`` or ``"metadata cantilever f0_hz, q"``.
    deflection_amplitudes : tuple of float
        |D_i|, deflection units.
    """

    lines: tuple[DriveLine, ...]
    f0_hz: float
    q: float
    gain: float
    response_source: str
    deflection_amplitudes: tuple[float, ...]


def parse_drive_lines(text: str) -> tuple[DriveLine, ...]:
    """``"71000:0.05,70000:0.025"`` → lines (Hz, V), for ``--drive``."""
    lines = []
    for item in text.split(","):
        freq, sep, amp = item.partition(":")
        try:
            line = DriveLine(float(freq), float(amp))
        except ValueError:
            raise ConfigError(f"--drive item {item.strip()!r} must look like FREQUENCY_HZ:AMPLITUDE_V") from None
        if not sep or not (math.isfinite(line.frequency_hz) and line.frequency_hz > 0):
            raise ConfigError(f"--drive item {item.strip()!r} must look like FREQUENCY_HZ:AMPLITUDE_V, frequency > 0")
        if not (math.isfinite(line.amplitude_v) and line.amplitude_v > 0):
            raise ConfigError(f"--drive item {item.strip()!r}: the amplitude must be > 0")
        lines.append(line)
    frequencies = [line.frequency_hz for line in lines]
    if len(set(frequencies)) != len(frequencies):
        raise ConfigError(f"--drive {text!r} names a frequency twice")
    return tuple(lines)


def line_amplitudes(x: np.ndarray, sample_rate_hz: float, start_sample: int, frequencies_hz) -> np.ndarray:
    """Complex amplitudes D_i with x[n] ≈ Re Σ D_i·exp(jω_i t_n) + c, t_n = (start_sample + n)/fs.

    Linear least squares on [cos ω_i t, sin ω_i t, 1]: unlike a per-line
    DFT it does not leak one line into another on a short segment.
    """
    x = np.asarray(x, dtype=np.float64)
    t = (start_sample + np.arange(x.size)) / sample_rate_hz
    omega = 2.0 * np.pi * np.asarray(frequencies_hz, dtype=np.float64)
    phase = np.outer(t, omega)
    design = np.column_stack([np.cos(phase), np.sin(phase), np.ones_like(t)])
    coef, *_ = np.linalg.lstsq(design, x, rcond=None)
    k = omega.size
    # c·cos + s·sin = Re[(c − j s)·exp(jωt)]
    return coef[:k] - 1j * coef[k : 2 * k]


def _response_from_magnitudes(f: np.ndarray, magnitude: np.ndarray) -> tuple[float, float, float]:
    """(f0, Q, gain) of a second-order low-pass through |H(f_i)| (≥ 3 lines).

    1/|H|² = (1/g²)·[(1 − f²/f0²)² + f²/(f0²Q²)] = α + β f² + γ f⁴ is linear
    in (α, β, γ): g = α^(−1/2), f0 = (α/γ)^(1/4), 1/Q² = 2 + β f0²/α.
    """
    scale = float(np.max(f))
    u = (f / scale) ** 2  # scaled, for a well-conditioned fit
    design = np.column_stack([np.ones_like(u), u, u * u])
    (alpha, beta, gamma), *_ = np.linalg.lstsq(design, 1.0 / magnitude**2, rcond=None)
    inv_q2 = 2.0 + beta * math.sqrt(alpha / gamma) / alpha if alpha > 0 and gamma > 0 else math.nan
    if not (alpha > 0 and gamma > 0 and inv_q2 > 0):
        raise InputError(
            "the drive lines' deflection amplitudes do not fit a second-order resonance; "
            "give lines around the resonance, or metadata cantilever f0_hz and q"
        )
    f0 = scale * (alpha / gamma) ** 0.25
    return f0, 1.0 / math.sqrt(inv_q2), 1.0 / math.sqrt(alpha)


def fit_drive_phases(
    deflection: np.ndarray,
    sample_rate_hz: float,
    start_sample: int,
    lines: tuple[DriveLine, ...],
    *,
    f0_hz: float | None = None,
    q: float | None = None,
) -> DrivePhaseFit:
    """Each drive line's phase at t = 0 from the free-air deflection.

    Parameters
    ----------
    deflection : ndarray
        Free-air segment of the deflection (any length unit).
    sample_rate_hz : float
    start_sample : int
        Index of the segment's first sample in the capture (t = 0 at sample 0).
    lines : tuple of DriveLine
        Frequencies (Hz) and amplitudes (V); phases are ignored.
    f0_hz, q : float, optional
        Free-air resonance, used only with fewer than three lines.

    Returns
    -------
    DrivePhaseFit

    Notes
    -----
    With D_i the deflection's complex amplitude at ω_i (least squares,
    :func:`line_amplitudes`) and G(jω) = g/(1 − (ω/ω0)² + jω/(ω0 Q)) (eq. 3.1),
    |D_i|/A_i = |G(jω_i)| fixes g, ω0, Q from three or more lines, and

        φ_i = ∠D_i − ∠G(jω_i),   ∠G(jω) = −atan2(ω/(ω0Q), 1 − (ω/ω0)²).

    A pure delay between the drive and the deflection cannot be told from a
    phase of the drive; it ends up in φ_i, so the synthesised dither and the
    free-air model identified from it describe the deflection exactly as a
    delay-free pair.
    """
    fs = float(sample_rate_hz)
    frequencies = np.array([line.frequency_hz for line in lines])
    amplitudes = np.array([line.amplitude_v for line in lines])
    if np.any(frequencies >= fs / 2):
        raise ConfigError(f"--drive lines must be below the Nyquist frequency {fs / 2:g} Hz")
    if len(deflection) < 4 * len(lines) + 8:
        raise InputError(f"the free-air segment ({len(deflection)} samples) is too short to fit the drive phases")
    d = line_amplitudes(deflection, fs, start_sample, frequencies)
    magnitude = np.abs(d) / amplitudes
    if np.any(magnitude <= 0):
        raise InputError("a drive line has no response in the deflection on the free-air segment")
    if len(lines) >= 3:
        f0, qf, gain = _response_from_magnitudes(frequencies, magnitude)
        source = "line magnitudes"
    elif f0_hz and q:
        f0, qf = float(f0_hz), float(q)
        u = frequencies / f0
        gain = float(np.mean(magnitude * np.hypot(1 - u * u, u / qf)))
        source = "metadata cantilever f0_hz, q"
    else:
        raise InputError(
            f"--drive gives {len(lines)} line(s): fitting their phases needs three lines around the resonance, "
            "or metadata cantilever f0_hz and q"
        )
    u = frequencies / f0
    response_phase = -np.arctan2(u / qf, 1.0 - u * u)
    phases = np.angle(d) - response_phase
    fitted = tuple(DriveLine(float(f), float(a), float(p)) for f, a, p in zip(frequencies, amplitudes, phases))
    return DrivePhaseFit(fitted, float(f0), float(qf), float(gain), source, tuple(float(v) for v in np.abs(d)))


def synthesize_drive(lines: tuple[DriveLine, ...], sample_rate_hz: float, start_sample: int, n: int) -> np.ndarray:
    """g[k] = Σ_i A_i cos(ω_i t_k + φ_i), t_k = (start_sample + k)/fs: the dither as the ADC would sample it (V)."""
    index = start_sample + np.arange(n, dtype=np.float64)
    out = np.zeros(n)
    for line in lines:
        # cycles reduced to [0, 1) before the 2π keeps the cosine's argument small on long captures
        cycles = np.mod(index * (line.frequency_hz / sample_rate_hz), 1.0)
        out += line.amplitude_v * np.cos(2.0 * np.pi * cycles + line.phase_rad)
    return out
