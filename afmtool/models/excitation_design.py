"""The three-sine REEP excitation of §3.3.2, designed for one identified cantilever.

REEP identifies the two denominator coefficients of eq. 3.40 with the
numerator fixed; the thesis excites five parameters' worth of richness with
three sines, ``g(t) = A sin ω_d t + B sin((ω_d + Δω)t + φ_+) + B sin((ω_d − Δω)t + φ_−)``:
a main line at (or near) the resonance, which sets the tapping amplitude, and
two side lines ±Δf away that the high-Q cantilever attenuates.

The free-air response is, with G(s) = k_g ω0²/(s² + (ω0/Q)s + ω0²) the
identified model (:class:`afmtool.models.free_air.FreeAirModel`),

.. math:: p(t) = \\sum_k |G(j\\omega_k)| A_k \\sin(\\omega_k t + \\varphi_k + \\angle G(j\\omega_k))
          = \\mathrm{Im}\\,[E(t)\\,e^{j\\omega_d t}],

with the complex envelope E(t) = Σ_k R_k exp(j((ω_k − ω_d)t + ψ_k)),
R_k = |G(jω_k)|A_k and ψ_k = φ_k + ∠G(jω_k).  The side lines make E(t)
beat around the main line's R_d e^{jψ_d}; the largest excursion is exactly

.. math:: \\beta = \\max_t |E(t) - R_d e^{j\\psi_d}| / R_d = (R_+ + R_-)/R_d

whatever the phases (§3.3.2 writes the in-phase case, where all of β is an
amplitude change ±2B|G(ω_d+Δω)|/|G(ω_d)|).  Design rule: A from the requested
amplitude, A = a / |G(jω_d)|; then B = min(s_max A, β_tol R_d/(|G_+| + |G_−|)):
the thesis's B = A/2 where the cantilever attenuates the side lines enough,
scaled down at low Q (docs/conventions.md, "Comparing REEP with averaging theory").

Phases: the side-line sum is put in quadrature with the main line's response,
(ψ_+ + ψ_−)/2 = ψ_d + π/2.  Then the beat is mostly a phase swing of the tip
oscillation and its amplitude changes only by |R_+ − R_−|/R_d to first order,
and, because ∠G(ω_d ± Δω) ≈ ∠G(ω_d) ∓ π/2, the drive's own side lines are
near quadrature too, which keeps the DAC's crest factor low
(peak ≈ √(A² + 4B²) instead of A + 2B).  Sine phases throughout: a line is
A·sin(2πft + φ), as in :mod:`afmtool.sim.excitation`.

A loop for an arbitrary waveform generator is periodic only if every line
is a whole number of cycles long: L samples at f_dac need f_k L / f_dac
integer.  The side offset is rounded to a whole number N_b of samples per
beat (Δf = f_dac/N_b) and the loop holds M beats, M chosen so that the
frequency grid f_dac/(M N_b) is at most ``resolution_hz``; the main line is
rounded to that grid.  The exported lines are the rounded ones.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from afmtool.errors import ConfigError

__all__ = [
    "DEFAULT_OFFSET_BANDWIDTHS",
    "ExcitationDesign",
    "ExcitationLine",
    "default_offset_hz",
    "design_three_sine",
    "dither_samples",
    "free_air_response",
    "response_envelope",
]

#: Default side-line offset in resonance bandwidths f0/Q: 20 f0/Q gives the thesis's
#: Δf ≈ 6 kHz at f0 ≈ 70 kHz, Q ≈ 225 (§3.3.2), where |G(f0 ± Δf)|/|G(f0)| ≈ 1/40.
DEFAULT_OFFSET_BANDWIDTHS = 20.0

#: The default offset is at most this share of f0: the side lines stay near the
#: resonance, where the one-mode model of eq. 3.40 holds, and the lock-in low-pass
#: min(f_d/10, Δf/2) keeps its corner.
MAX_OFFSET_SHARE_OF_F0 = 0.1

#: Longest loop the sample-file export writes, samples.
MAX_LOOP_SAMPLES = 1 << 24


@dataclass(frozen=True)
class ExcitationLine:
    """One line of the dither, ``amplitude_v·sin(2π frequency_hz t + phase_rad)``.

    ``response_nm`` and ``response_phase_rad`` are the predicted free-air
    deflection line |G|·A and φ + ∠G (model deflection units, usually nm).
    """

    role: str
    frequency_hz: float
    amplitude_v: float
    phase_rad: float
    response_nm: float
    response_phase_rad: float


@dataclass(frozen=True)
class ExcitationDesign:
    """A designed three-sine excitation and what it does to the free cantilever.

    Attributes
    ----------
    lines : tuple of ExcitationLine
        Main, lower and upper line, in that order (frequencies on the loop grid).
    offset_hz : float
        Side-line offset Δf after rounding to whole samples per beat, Hz.
    offset_reason : str
        Where Δf came from (the default rule, or given).
    side_scale : float
        B/A.
    beat : float
        β = (R_+ + R_−)/R_d, the largest relative excursion of the response envelope.
    amplitude_beat : float
        max |(|E(t)| − R_d)| / R_d: the relative swing of the response amplitude alone.
    phase_swing_rad : float
        max |arg E(t) − ψ_d|, rad.
    beat_tolerance : float
        The β the design was held under.
    dac_rate_hz : float
        Rate of the sample file, Hz.
    loop_samples : int
        Samples in one loop (M·N_b).
    loop_beats : int
        Beat periods M in one loop.
    """

    lines: tuple[ExcitationLine, ...]
    offset_hz: float
    offset_reason: str
    side_scale: float
    beat: float
    amplitude_beat: float
    phase_swing_rad: float
    beat_tolerance: float
    dac_rate_hz: float
    loop_samples: int
    loop_beats: int

    @property
    def main(self) -> ExcitationLine:
        return self.lines[0]

    @property
    def loop_s(self) -> float:
        return self.loop_samples / self.dac_rate_hz

    @property
    def peak_v(self) -> float:
        """Largest |u| over one loop, V."""
        return float(np.max(np.abs(dither_samples(self))))


def _finite_positive(name: str, value: float) -> float:
    if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
        raise ConfigError(f"{name}={value!r} must be a finite number > 0")
    return float(value)


def default_offset_hz(f0_hz: float, q: float) -> tuple[float, str]:
    """Δf = min(20·f0/Q, f0/10) and the sentence that explains it."""
    wide = DEFAULT_OFFSET_BANDWIDTHS * f0_hz / q
    cap = MAX_OFFSET_SHARE_OF_F0 * f0_hz
    if wide <= cap:
        return wide, (
            f"default: {DEFAULT_OFFSET_BANDWIDTHS:g} resonance bandwidths f0/Q = {f0_hz / q:.4g} Hz, far enough out "
            "that the cantilever attenuates the side lines about 40-fold (the thesis's 6 kHz at f0 = 70 kHz, "
            "Q = 225, §3.3.2)"
        )
    return cap, (
        f"default: {DEFAULT_OFFSET_BANDWIDTHS:g}·f0/Q = {wide:.4g} Hz would leave the resonance region, so capped at "
        f"f0/10 = {cap:.4g} Hz; at this low Q the side lines are scaled down to hold the beat tolerance"
    )


def free_air_response(frequency_hz, f0_hz: float, q: float, gain: float) -> np.ndarray:
    """G(j2πf) = gain·ω0²/(ω0² − ω² + jω0ω/Q): deflection per dither unit (continuous drive)."""
    w = 2.0 * np.pi * np.asarray(frequency_hz, dtype=np.float64)
    w0 = 2.0 * np.pi * f0_hz
    return gain * w0**2 / (w0**2 - w**2 + 1j * w0 * w / q)


def _loop_grid(drive_hz: float, offset_hz: float, dac_rate_hz: float, resolution_hz: float) -> tuple[int, int]:
    """(samples per beat N_b, beats per loop M) for the loop grid (module docstring)."""
    per_beat = max(2, round(dac_rate_hz / offset_hz))
    beats = max(1, math.ceil((dac_rate_hz / per_beat) / resolution_hz))
    if per_beat * beats > MAX_LOOP_SAMPLES:
        raise ConfigError(
            f"a loop with a {resolution_hz:g} Hz frequency grid at {dac_rate_hz:g} Hz needs {per_beat * beats} "
            f"samples (> {MAX_LOOP_SAMPLES}); give a coarser --resolution or a lower --dac-rate"
        )
    return per_beat, beats


def _design_request(f0_hz, q, gain, amplitude_nm, dac_rate_hz, drive_hz, offset_hz, beat_tolerance, max_side_scale,
                    resolution_hz) -> tuple:
    """The checked arguments of :func:`design_three_sine`, defaults filled in, and why Δf is what it is."""
    f0_hz, q, amplitude_nm = (_finite_positive(n, v) for n, v in
                              (("f0_hz", f0_hz), ("q", q), ("amplitude_nm", amplitude_nm)))
    if not (isinstance(gain, (int, float)) and math.isfinite(gain) and gain != 0):
        raise ConfigError(f"the model's gain={gain!r} must be a finite non-zero number")
    dac_rate_hz = _finite_positive("dac_rate_hz", dac_rate_hz)
    beat_tolerance = _finite_positive("beat_tolerance", beat_tolerance)
    max_side_scale = _finite_positive("max_side_scale", max_side_scale)
    drive_hz = f0_hz if not drive_hz else _finite_positive("drive_hz", drive_hz)
    if offset_hz:
        offset_hz, reason = _finite_positive("offset_hz", offset_hz), "given (--offset)"
    else:
        offset_hz, reason = default_offset_hz(f0_hz, q)
    if offset_hz >= drive_hz:
        raise ConfigError(f"the side-line offset {offset_hz:g} Hz must be below the drive frequency {drive_hz:g} Hz")
    if 2.0 * (drive_hz + offset_hz) >= dac_rate_hz:
        raise ConfigError(
            f"--dac-rate {dac_rate_hz:g} Hz must exceed twice the upper line {drive_hz + offset_hz:g} Hz"
        )
    resolution_hz = _finite_positive("resolution_hz", resolution_hz) if resolution_hz else f0_hz / (100.0 * q)
    return (f0_hz, q, amplitude_nm, dac_rate_hz, beat_tolerance, max_side_scale, drive_hz, offset_hz, reason,
            resolution_hz)


def design_three_sine(
    f0_hz: float,
    q: float,
    gain: float,
    amplitude_nm: float,
    *,
    dac_rate_hz: float,
    drive_hz: float | None = None,
    offset_hz: float | None = None,
    beat_tolerance: float = 0.05,
    max_side_scale: float = 0.5,
    resolution_hz: float | None = None,
) -> ExcitationDesign:
    """Design the three-sine REEP dither (§3.3.2) for a free-air model.

    Parameters
    ----------
    f0_hz, q, gain : float
        The free-air model: resonance (Hz), quality factor, DC gain
        (deflection units per dither volt, e.g. nm/V).
    amplitude_nm : float
        Requested free-air response amplitude at the main line, in the
        model's deflection units (nm for a model identified on nm data).
    dac_rate_hz : float
        Sample rate of the exported loop, Hz; above 2·(f_d + Δf).
    drive_hz : float, optional
        Main line, Hz; default f0.
    offset_hz : float, optional
        Side-line offset Δf, Hz; default :func:`default_offset_hz`.
    beat_tolerance : float
        Largest allowed β = (R_+ + R_−)/R_d, the envelope's relative excursion.
    max_side_scale : float
        Largest B/A (the thesis's 1/2).
    resolution_hz : float, optional
        Frequency grid of the loop, Hz; default f0/(100 Q), which moves the
        main line by at most 1/200 of a bandwidth.

    Returns
    -------
    ExcitationDesign
    """
    (f0_hz, q, amplitude_nm, dac_rate_hz, beat_tolerance, max_side_scale, drive_hz, offset_hz, reason,
     resolution_hz) = _design_request(f0_hz, q, gain, amplitude_nm, dac_rate_hz, drive_hz, offset_hz, beat_tolerance,
                                      max_side_scale, resolution_hz)

    per_beat, beats = _loop_grid(drive_hz, offset_hz, dac_rate_hz, resolution_hz)
    grid_hz = dac_rate_hz / (per_beat * beats)
    offset_q = dac_rate_hz / per_beat  # = beats · grid
    drive_q = max(1, round(drive_hz / grid_hz)) * grid_hz
    freqs = np.array([drive_q, drive_q - offset_q, drive_q + offset_q])
    g = free_air_response(freqs, f0_hz, q, gain)
    mags, angles = np.abs(g), np.angle(g)

    main_v = amplitude_nm / mags[0]
    response_main = amplitude_nm
    side_v = min(max_side_scale * main_v, beat_tolerance * response_main / (mags[1] + mags[2]))
    # side responses in quadrature with the main one: ψ_- + ψ_+ = 2ψ_d + π, with φ_- = φ_+
    side_phase = _wrap(0.5 * (2.0 * angles[0] + math.pi - angles[1] - angles[2]))
    phases = np.array([0.0, side_phase, side_phase])
    amps = np.array([main_v, side_v, side_v])
    roles = ("main", "lower", "upper")
    lines = tuple(
        ExcitationLine(roles[k], float(freqs[k]), float(amps[k]), float(phases[k]), float(mags[k] * amps[k]),
                       float(_wrap(phases[k] + angles[k])))
        for k in range(3)
    )
    beat = float((lines[1].response_nm + lines[2].response_nm) / response_main)
    partial = ExcitationDesign(lines, float(offset_q), reason, float(side_v / main_v), beat, 0.0, 0.0,
                               beat_tolerance, dac_rate_hz, per_beat * beats, beats)
    t = np.arange(4096) / (4096 * offset_q)  # one beat period, finely
    envelope = response_envelope(partial, t)
    relative = envelope / (response_main * np.exp(1j * lines[0].response_phase_rad))
    return ExcitationDesign(
        lines, float(offset_q), reason, float(side_v / main_v), beat,
        float(np.max(np.abs(np.abs(relative) - 1.0))), float(np.max(np.abs(np.angle(relative)))),
        beat_tolerance, dac_rate_hz, per_beat * beats, beats,
    )


def _wrap(angle: float) -> float:
    return float((angle + math.pi) % (2.0 * math.pi) - math.pi)


def response_envelope(design: ExcitationDesign, t_s) -> np.ndarray:
    """Complex envelope E(t) of the predicted free-air response about the main line (module docstring)."""
    t = np.asarray(t_s, dtype=np.float64)
    main_hz = design.main.frequency_hz
    out = np.zeros(t.shape, dtype=np.complex128)
    for line in design.lines:
        out += line.response_nm * np.exp(1j * (2.0 * np.pi * (line.frequency_hz - main_hz) * t
                                               + line.response_phase_rad))
    return out


def dither_samples(design: ExcitationDesign, t_s=None) -> np.ndarray:
    """u(t) = Σ A_k sin(2π f_k t + φ_k), V; default one loop at the DAC rate.

    The phase 2π f_k t is reduced with the loop grid's integer cycle counts,
    so a long loop keeps full float64 accuracy and sample L equals sample 0.
    """
    if t_s is not None:
        t = np.asarray(t_s, dtype=np.float64)
        return sum(line.amplitude_v * np.sin(2.0 * np.pi * line.frequency_hz * t + line.phase_rad)
                   for line in design.lines)
    n = np.arange(design.loop_samples, dtype=np.int64)
    out = np.zeros(design.loop_samples)
    for line in design.lines:
        cycles = round(line.frequency_hz * design.loop_s)  # whole cycles per loop, exact by construction
        phase = 2.0 * np.pi * ((n * cycles) % design.loop_samples) / design.loop_samples
        out += line.amplitude_v * np.sin(phase + line.phase_rad)
    return out
