"""Scenario ``tapping``: a driven one-mode cantilever meeting the piecewise-linear tip-sample force.

The model is eq. 3.1 in per-unit-mass form with the force of eq. 4.1/6.2
in the convention of :mod:`afmtool.models.forces`:

.. math::

    \\ddot p + (\\omega_0/Q)\\dot p + \\omega_0^2 p
        = \\omega_0^2 g(t) + F(p, \\dot p; l(t)) + \\eta(t),

with p the deflection (nm, positive away from the sample), g = gain·dither
the dither forcing (nm), l(t) the separation program (nm) and η a thermal
(Langevin) acceleration (nm/s²).  It is integrated with the classical
fixed-step fourth-order Runge-Kutta method, ``substeps`` steps per sample;
g and l are evaluated analytically at every stage time (no interpolation).

Thermal noise
-------------
The thermal force of a mode with damping c = mω0/Q has the one-sided PSD
S_F = 4k_B·T·mω0/Q (N²/Hz); per unit mass S_η = 4k_B·T·ω0³/(Qk) (m²/s⁴/Hz,
using m = k/ω0²), which gives k⟨p²⟩ = k_B·T.  In the simulation η is held
constant over each sample period T_s at an independent N(0, σ²) value.  That
piecewise-constant process has the one-sided PSD 2σ²T_s·sinc²(fT_s), so

.. math:: \\sigma^2 = \\frac{S_\\eta f_s}{2\\,\\mathrm{sinc}^2(f_0/f_s)}

makes its PSD equal S_η at the resonance f0, where the cantilever responds
(sinc x = sin πx/(πx)).  White measurement noise of rms
``measurement_noise_nm`` is added to the recorded deflection only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit

from afmtool.config.samples import sample_count
from afmtool.errors import ConfigError
from afmtool.io.capture import ChannelSpec
from afmtool.jit import JIT_OPTIONS
from afmtool.models.cantilever import Cantilever
from afmtool.models.forces import THESIS_FORCE_SETS, PiecewiseLinearForce, force_per_mass
from afmtool.sim import SimulatedCapture, param, validate_parameters
from afmtool.sim.excitation import DRIVE_KINDS, LinearChirp, MultiSine, SteppedSine, build_dither, drive_metadata, sine
from afmtool.sim.separation import ConstantSeparation, ForceCurve, LineScan, SeparationSteps

__all__ = [
    "PROGRAMS",
    "FORCE_SET_CHOICES",
    "TappingParams",
    "RK4Result",
    "integrate_rk4",
    "thermal_accel_rms",
    "simulate_tapping",
]

#: Boltzmann constant, J/K.
K_BOLTZMANN = 1.380649e-23
#: Separation programs the scenario offers.
PROGRAMS = ("constant", "force-curve", "steps", "line-scan")
#: Force choices: a thesis set, "custom" (the d_nm ... c_b_per_s fields) or "none".
FORCE_SET_CHOICES = (*THESIS_FORCE_SETS, "custom", "none")
_DEFAULT_FORCE = THESIS_FORCE_SETS["attractive"]
_CUSTOM_FIELDS = ("d_nm", "omega_a2_per_s2", "omega_b2_per_s2", "c_a_per_s", "c_b_per_s")
_DEFAULT_CHUNK_SAMPLES = 1 << 16


@dataclass(frozen=True)
class TappingParams:
    """Parameters of the ``tapping`` scenario (defaults: §3.4.3, attractive set, amplitude force curve)."""

    duration_s: float = param(0.05, "capture length", "s", minimum=0, exclusive_minimum=True)
    sample_rate_hz: float = param(
        500e3, "sample rate of the recorded channels", "Hz", minimum=0, exclusive_minimum=True
    )
    substeps: int = param(8, "RK4 steps per sample period (raise for stiff repulsive sets)", "", minimum=1)
    f0_hz: float = param(80318.0, "free-air resonant frequency f0", "Hz", minimum=0, exclusive_minimum=True)
    q: float = param(168.0, "free-air quality factor Q", "", minimum=0.5, exclusive_minimum=True)
    spring_constant_n_per_m: float = param(
        2.0, "spring constant k (sets the thermal noise level)", "N/m", minimum=0, exclusive_minimum=True
    )
    drive: str = param("three-sine", "dither type", "", choices=DRIVE_KINDS)
    drive_file: str = param(
        "", "play a designed dither: lines.json or excitation.wav of 'afmtool design excitation' (replaces drive and "
        "amplitude_nm); '' = off", "",
    )
    drive_hold: str = param(
        "continuous", "how the plant sees the dither: a continuous signal at every RK4 stage, or held per sample "
        "(a DAC at the sample rate)", "", choices=("continuous", "zoh"),
    )
    amplitude_nm: float = param(
        25.0,
        "free-air steady-state deflection amplitude of the main line (sweeps: at their centre frequency)",
        "nm",
        minimum=0,
    )
    drive_offset_hz: float = param(0.0, "main-line (or sweep-centre) frequency minus f0", "Hz")
    sideband_offset_hz: float = param(
        6000.0, "three-sine side-line offset Δf", "Hz", minimum=0, exclusive_minimum=True
    )
    sideband_scale: float = param(0.5, "three-sine side-line amplitude / main-line amplitude", "", minimum=0)
    sweep_span_hz: float = param(
        10000.0, "full span of the chirp / stepped sweep, centred on the drive frequency", "Hz", minimum=0,
        exclusive_minimum=True,
    )
    sweep_steps: int = param(11, "number of stepped-sine segments over the capture", "", minimum=1)
    dither_gain_nm_per_v: float = param(
        1.0, "forcing g per volt of dither (g = gain·dither)", "nm/V", minimum=0, exclusive_minimum=True
    )
    program: str = param("force-curve", "separation program l(t)", "", choices=PROGRAMS)
    separation_nm: float = param(
        40.0, "initial separation l (constant, force-curve start/end, line-scan over height 0)", "nm"
    )
    turn_separation_nm: float = param(5.0, "force-curve: closest separation", "nm")
    free_air_fraction: float = param(
        0.2, "force-curve / line-scan: share of the capture held at separation_nm first", "", minimum=0, maximum=1
    )
    dwell_fraction: float = param(
        0.0, "force-curve: share of the capture held at turn_separation_nm", "", minimum=0, maximum=1
    )
    step_levels_nm: tuple[float, ...] = param(
        (40.0, 20.0, 15.0, 10.0), "steps: separations, each held for an equal share of the capture", "nm"
    )
    topography_height_nm: float = param(5.0, "line-scan: height of the square features", "nm")
    topography_features: int = param(4, "line-scan: number of raised features along the line", "", minimum=1)
    scan_size_m: float = param(1e-6, "line-scan: length of the line", "m", minimum=0, exclusive_minimum=True)
    force_set: str = param(
        "attractive", "tip-sample force: a thesis set, 'custom' (fields below) or 'none'", "",
        choices=FORCE_SET_CHOICES,
    )
    d_nm: float = param(_DEFAULT_FORCE.d_nm, "custom force: attractive range d", "nm", minimum=0)
    omega_a2_per_s2: float = param(_DEFAULT_FORCE.omega_a2, "custom force: ω_a²", "1/s^2", minimum=0)
    omega_b2_per_s2: float = param(_DEFAULT_FORCE.omega_b2, "custom force: ω_b²", "1/s^2", minimum=0)
    c_a_per_s: float = param(_DEFAULT_FORCE.c_a, "custom force: c_a", "1/s", minimum=0)
    c_b_per_s: float = param(_DEFAULT_FORCE.c_b, "custom force: c_b", "1/s", minimum=0)
    temperature_k: float = param(300.0, "thermal-noise temperature (0 disables)", "K", minimum=0)
    measurement_noise_nm: float = param(0.05, "rms white noise added to the recorded deflection", "nm", minimum=0)
    initial_state: str = param(
        "steady", "start in the free-air steady state of the dither or at rest", "", choices=("steady", "rest")
    )

    def __post_init__(self) -> None:
        validate_parameters(self)
        nyquist = self.sample_rate_hz / 2
        if self.f0_hz >= nyquist:
            raise ConfigError(f"f0_hz={self.f0_hz!r} must be below sample_rate_hz/2 = {nyquist:g}")
        if self.duration_s * self.sample_rate_hz < 2:
            raise ConfigError(f"duration_s={self.duration_s!r} gives fewer than 2 samples")
        if self.program == "force-curve":
            if not self.turn_separation_nm < self.separation_nm:
                raise ConfigError(
                    f"turn_separation_nm={self.turn_separation_nm!r} must be below separation_nm={self.separation_nm!r}"
                )
            if not self.free_air_fraction + self.dwell_fraction < 1:
                raise ConfigError(
                    f"free_air_fraction={self.free_air_fraction!r} + dwell_fraction={self.dwell_fraction!r} "
                    "must be below 1 to leave time for the ramps"
                )
        if self.program == "line-scan" and not self.free_air_fraction < 1:
            raise ConfigError(f"free_air_fraction={self.free_air_fraction!r} must be below 1 to leave time to scan")
        if self.program == "steps" and not self.step_levels_nm:
            raise ConfigError("step_levels_nm=() needs at least one level")
        top_hz = self.dither()[0].max_frequency_hz  # also validates the drive frequencies
        if top_hz >= nyquist:
            raise ConfigError(f"the dither reaches {top_hz:g} Hz, above sample_rate_hz/2 = {nyquist:g}")
        if self.force_set != "custom":
            for name in _CUSTOM_FIELDS:
                default = getattr(TappingParams, name)
                if getattr(self, name) != default:
                    raise ConfigError(
                        f"{name}={getattr(self, name)!r} is only used with force_set='custom' "
                        f"(force_set={self.force_set!r})"
                    )

    def dither(self) -> tuple[MultiSine | LinearChirp | SteppedSine, float, float]:
        """The dither (V), its main/centre frequency (Hz) and main-line amplitude (V).

        The amplitude is ``amplitude_nm / (gain·|G(f_c)|)`` so that the free-air
        steady-state deflection at f_c = f0 + ``drive_offset_hz`` is ``amplitude_nm``;
        a held dither (``drive_hold="zoh"``) is also divided by sinc(f_c/fs), the
        staircase's fundamental.
        """
        if self.drive_file:
            from afmtool.sim.excitation import load_designed_drive

            lines = load_designed_drive(self.drive_file)
            main = int(np.argmax(lines.amplitudes))
            return lines, float(lines.frequencies_hz[main]), float(lines.amplitudes[main])
        center_hz = self.f0_hz + self.drive_offset_hz
        if not center_hz > 0:
            raise ConfigError(f"drive_offset_hz={self.drive_offset_hz!r} puts the drive at {center_hz:g} Hz")
        response = abs(complex(self.cantilever().frequency_response(center_hz)))
        if self.drive_hold == "zoh":
            response *= float(np.sinc(center_hz / self.sample_rate_hz))
        amplitude_v = self.amplitude_nm / (self.dither_gain_nm_per_v * response)
        excitation = build_dither(
            self.drive,
            amplitude=amplitude_v,
            center_hz=center_hz,
            sideband_offset_hz=self.sideband_offset_hz,
            sideband_scale=self.sideband_scale,
            sweep_span_hz=self.sweep_span_hz,
            sweep_steps=self.sweep_steps,
            duration_s=self.duration_s,
        )
        return excitation, center_hz, amplitude_v

    def cantilever(self) -> Cantilever:
        return Cantilever(self.f0_hz, self.q, self.spring_constant_n_per_m)

    def force(self) -> PiecewiseLinearForce:
        """The tip-sample force; ``force_set="none"`` is all-zero parameters (d = 0)."""
        if self.force_set == "custom":
            return PiecewiseLinearForce(
                self.d_nm, self.omega_a2_per_s2, self.omega_b2_per_s2, self.c_a_per_s, self.c_b_per_s
            )
        if self.force_set == "none":
            return PiecewiseLinearForce(0.0, 0.0, 0.0, 0.0, 0.0)
        return THESIS_FORCE_SETS[self.force_set]


# --------------------------------------------------------------------------- kernel


@njit(**JIT_OPTIONS)
def _rk4_kernel(g_half, g_held, l_half, accel_noise, nsub, dt, w0q, w0sq, d, wa2, wb2, ca, cb, p0, v0, out_p,
                out_contact):
    """Integrate n sample periods with ``nsub`` RK4 steps each.

    ``g_half[j]`` and ``l_half[j]`` hold g and l at t_start + j·dt/2
    (length 2·nsub·n + 1); ``accel_noise[i]`` is η over sample period i.
    A non-empty ``g_held`` (length n) replaces g by ``g_held[i]`` at every
    stage of period i (a zero-order-held dither: it jumps at the sample
    instants, where the half-step grid point is shared by two periods).
    Writes p(t_i) to ``out_p[i]`` and 1 to ``out_contact[i]`` when
    p + l < d at any step boundary in [t_i, t_{i+1}).  Returns the state
    (p, v) at the end.
    """
    half = 0.5 * dt
    sixth = dt / 6.0
    p = p0
    v = v0
    held = g_held.shape[0] > 0
    for i in range(out_p.shape[0]):
        out_p[i] = p
        eta = accel_noise[i]
        touched = 0
        base = 2 * nsub * i
        for k in range(nsub):
            j = base + 2 * k
            l0 = l_half[j]
            l1 = l_half[j + 1]
            l2 = l_half[j + 2]
            if held:
                fg0 = w0sq * g_held[i] + eta
                fg1 = fg0
                fg2 = fg0
            else:
                fg0 = w0sq * g_half[j] + eta
                fg1 = w0sq * g_half[j + 1] + eta
                fg2 = w0sq * g_half[j + 2] + eta
            if p + l0 < d:
                touched = 1
            # k1 = f(t, y)
            a1 = fg0 - w0sq * p - w0q * v + force_per_mass(p, v, l0, d, wa2, wb2, ca, cb)
            # k2 = f(t + h/2, y + h/2·k1)
            p2 = p + half * v
            v2 = v + half * a1
            a2 = fg1 - w0sq * p2 - w0q * v2 + force_per_mass(p2, v2, l1, d, wa2, wb2, ca, cb)
            # k3 = f(t + h/2, y + h/2·k2)
            p3 = p + half * v2
            v3 = v + half * a2
            a3 = fg1 - w0sq * p3 - w0q * v3 + force_per_mass(p3, v3, l1, d, wa2, wb2, ca, cb)
            # k4 = f(t + h, y + h·k3)
            p4 = p + dt * v3
            v4 = v + dt * a3
            a4 = fg2 - w0sq * p4 - w0q * v4 + force_per_mass(p4, v4, l2, d, wa2, wb2, ca, cb)
            # y += h/6·(k1 + 2k2 + 2k3 + k4)
            p = p + sixth * (v + 2.0 * v2 + 2.0 * v3 + v4)
            v = v + sixth * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
        out_contact[i] = touched
    return p, v


class RK4Result(NamedTuple):
    """Output of :func:`integrate_rk4`."""

    deflection_nm: np.ndarray  #: p at each sample instant t_i, nm
    contact: np.ndarray  #: uint8, 1 when p + l < d during [t_i, t_{i+1})
    p_end_nm: float  #: p after the last period, nm
    v_end_nm_per_s: float  #: ṗ after the last period, nm/s


def integrate_rk4(
    g_half: np.ndarray,
    l_half: np.ndarray,
    accel_noise: np.ndarray,
    *,
    substeps: int,
    sample_rate_hz: float,
    cantilever: Cantilever,
    force: PiecewiseLinearForce,
    p0_nm: float = 0.0,
    v0_nm_per_s: float = 0.0,
    g_held: np.ndarray | None = None,
) -> RK4Result:
    """Integrate p̈ + (ω0/Q)ṗ + ω0²p = ω0²g + F(p, ṗ; l) + η over n sample periods (RK4).

    Parameters
    ----------
    g_half, l_half : numpy.ndarray
        Forcing g (nm) and separation l (nm) at the half-step grid
        t_0 + j·T_s/(2·substeps), j = 0 … 2·substeps·n.
    accel_noise : numpy.ndarray
        η (nm/s²) held over each of the n sample periods.
    substeps : int
        RK4 steps per sample period.
    sample_rate_hz : float
        f_s = 1/T_s, Hz.
    cantilever : Cantilever
        Free-air ω0 and Q.
    force : PiecewiseLinearForce
        Tip-sample force per unit mass.
    p0_nm, v0_nm_per_s : float
        State at t_0.
    g_held : numpy.ndarray, optional
        Forcing g (nm) held over each of the n sample periods (a
        zero-order-held dither); ``g_half`` then only sets the grid length.

    Returns
    -------
    RK4Result
    """
    n = accel_noise.shape[0]
    if not (isinstance(substeps, int) and substeps >= 1):
        raise ConfigError(f"substeps={substeps!r} must be an integer >= 1")
    expected = 2 * substeps * n + 1
    if g_half.shape != (expected,) or l_half.shape != (expected,):
        raise ConfigError(
            f"g_half and l_half need {expected} values for {n} samples, got {g_half.shape} and {l_half.shape}"
        )
    out_p = np.empty(n)
    out_contact = np.zeros(n, dtype=np.uint8)
    w0 = cantilever.omega0_rad_s
    held = np.empty(0) if g_held is None else np.ascontiguousarray(g_held, dtype=np.float64)
    if held.size and held.shape != (n,):
        raise ConfigError(f"g_held needs {n} values, got {held.shape}")
    p_end, v_end = _rk4_kernel(
        np.ascontiguousarray(g_half, dtype=np.float64),
        held,
        np.ascontiguousarray(l_half, dtype=np.float64),
        np.ascontiguousarray(accel_noise, dtype=np.float64),
        substeps,
        1.0 / (sample_rate_hz * substeps),
        w0 / cantilever.q,
        w0 * w0,
        *force.as_args(),
        float(p0_nm),
        float(v0_nm_per_s),
        out_p,
        out_contact,
    )
    return RK4Result(out_p, out_contact, float(p_end), float(v_end))


def thermal_accel_rms(cantilever: Cantilever, temperature_k: float, sample_rate_hz: float) -> float:
    """σ of the per-sample thermal acceleration η, nm/s² (module docstring).

    σ² = S_η·f_s / (2·sinc²(f0/f_s)), S_η = 4k_B·T·ω0³/(Q·k) in m²/s⁴/Hz,
    converted to nm²/s⁴/Hz.
    """
    w0 = cantilever.omega0_rad_s
    psd_nm2 = 4.0 * K_BOLTZMANN * temperature_k * w0**3 / (cantilever.q * cantilever.spring_constant_n_per_m) * 1e18
    hold = np.sinc(cantilever.f0_hz / sample_rate_hz)
    return float(math.sqrt(psd_nm2 * sample_rate_hz / 2.0) / hold)


# --------------------------------------------------------------------------- scenario


def _topography(params: TappingParams) -> tuple[np.ndarray, np.ndarray]:
    """Square features: feature k covers [(k + 1/4)/n, (k + 3/4)/n] of the line."""
    positions = np.linspace(0.0, params.scan_size_m, 8192 * params.topography_features + 1)
    phase = (positions / params.scan_size_m * params.topography_features) % 1.0
    heights = np.where((phase >= 0.25) & (phase < 0.75), params.topography_height_nm, 0.0)
    return positions, heights


def _program(params: TappingParams):
    if params.program == "constant":
        return ConstantSeparation(params.separation_nm)
    free_air_s = params.free_air_fraction * params.duration_s
    if params.program == "force-curve":
        dwell_s = params.dwell_fraction * params.duration_s
        ramp = (params.duration_s - free_air_s - dwell_s) / 2
        return ForceCurve(params.separation_nm, params.turn_separation_nm, free_air_s, ramp, ramp, dwell_s)
    if params.program == "steps":
        return SeparationSteps(params.step_levels_nm, params.duration_s / len(params.step_levels_nm))
    positions, heights = _topography(params)
    return LineScan(params.separation_nm, positions, heights, free_air_s, params.duration_s - free_air_s)


def _program_channels(program, t: np.ndarray, separation: np.ndarray, channels: list, data: dict, truth: dict) -> None:
    """What the separation program adds: z_piezo (force curve, steps), the ramp direction, the topography."""
    if isinstance(program, ForceCurve):
        sampled = program.sample(t)
        channels.append(ChannelSpec("z_piezo", "nm"))
        data["z_piezo"] = sampled.z_piezo_nm
        truth["ramp_direction"] = sampled.direction
    elif isinstance(program, LineScan):
        truth["topography_nm"] = program.height_nm(t)
    elif isinstance(program, SeparationSteps):
        # the piezo moves the sample by the steps: z_piezo = l(t) − l(0), as on a force curve
        channels.append(ChannelSpec("z_piezo", "nm"))
        data["z_piezo"] = separation - separation[0]


def _initial_state(excitation, cantilever: Cantilever, gain: float, hold_fs: float | None = None) -> tuple[float, float]:
    """Free-air steady state at t = 0 (sweeps: that of a sine at their initial frequency and phase).

    With ``hold_fs`` (a dither held per sample at that rate) each line's
    fundamental lags T/2 and is scaled by sinc(f/fs).
    """
    if isinstance(excitation, MultiSine):
        lines = excitation
    else:
        t0 = np.array([0.0])
        freqs = getattr(excitation, "frequencies_hz", None)
        f_start = freqs[0] if freqs is not None else excitation.start_hz
        lines = sine(excitation.amplitude, f_start, float(excitation.phase_rad(t0)[0]))
    freqs = np.asarray(lines.frequencies_hz)
    response = gain * cantilever.frequency_response(freqs)
    if hold_fs is not None:
        response = response * np.sinc(freqs / hold_fs) * np.exp(-1j * np.pi * freqs / hold_fs)
    return lines.steady_state(response, 0.0)


def _drive_metadata(params: TappingParams, excitation, center_hz: float, amplitude_v: float) -> dict:
    drive = drive_metadata(params, center_hz, amplitude_v)
    if params.drive_file:  # a designed drive: its lines, as an instrument would record them
        drive.update(kind="designed", source=params.drive_file, lines=[
            {"frequency_hz": f, "amplitude_v": a, "phase_deg": math.degrees(p)}
            for a, f, p in zip(excitation.amplitudes, excitation.frequencies_hz, excitation.phases_rad)
        ])
        drive.pop("free_amplitude_nm", None)
        drive.pop("sideband_scale", None)
        others = [f for f in excitation.frequencies_hz if f != center_hz]
        drive["sideband_offset_hz"] = float(min(abs(f - center_hz) for f in others)) if others else 0.0
    if params.drive == "chirp":
        drive["start_hz"] = float(excitation.start_hz)
        drive["end_hz"] = float(excitation.end_hz)
    return drive


def _integrate_in_chunks(params: TappingParams, excitation, program, accel_noise: np.ndarray, start_state,
                         chunk_samples: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """RK4 over the whole capture, ``chunk_samples`` at a time: (deflection, contact, dither, separation).

    The drive and the separation are evaluated on the half-step grid of the
    sub-steps (a continuous drive, not held, unless ``drive_hold="zoh"``);
    the state (p, v) is carried from chunk to chunk, so the result does not
    depend on the chunk size.
    """
    fs = params.sample_rate_hz
    nsub = params.substeps
    n = accel_noise.shape[0]
    cantilever = params.cantilever()
    force = params.force()
    gain = params.dither_gain_nm_per_v
    p, v = start_state
    clean = np.empty(n)
    contact = np.empty(n, dtype=np.uint8)
    dither = np.empty(n)
    separation = np.empty(n)
    per_sample = 2 * nsub
    half_step_s = 1.0 / (per_sample * fs)
    for start in range(0, n, chunk_samples):
        stop = min(start + chunk_samples, n)
        t_half = np.arange(per_sample * start, per_sample * stop + 1) * half_step_s
        dither_half = excitation(t_half)
        l_half = program(t_half)
        held = gain * dither_half[:-1:per_sample] if params.drive_hold == "zoh" else None
        result = integrate_rk4(
            gain * dither_half,
            l_half,
            accel_noise[start:stop],
            substeps=nsub,
            sample_rate_hz=fs,
            cantilever=cantilever,
            force=force,
            p0_nm=p,
            v0_nm_per_s=v,
            g_held=held,
        )
        clean[start:stop] = result.deflection_nm
        contact[start:stop] = result.contact
        dither[start:stop] = dither_half[:-1:per_sample]
        separation[start:stop] = l_half[:-1:per_sample]
        p, v = result.p_end_nm, result.v_end_nm_per_s
    return clean, contact, dither, separation


def simulate_tapping(params: TappingParams, seed: int, *, chunk_samples: int = _DEFAULT_CHUNK_SAMPLES) -> SimulatedCapture:
    """Tapping-mode cantilever with the piecewise-linear force, RK4 with sub-steps.

    Parameters
    ----------
    params : TappingParams
        Scenario parameters.
    seed : int
        Seed of ``numpy.random.default_rng`` (thermal then measurement noise).
    chunk_samples : int, optional
        Samples integrated per kernel call (bounds memory; the result does
        not depend on it).

    Returns
    -------
    SimulatedCapture
        Channels ``dither`` (V), ``deflection`` (nm) and, for the
        force-curve and steps programs, ``z_piezo`` (nm, l(t) − l(0): positive = sample
        farther from the tip).  Truth: ``separation_nm``, ``contact``
        (uint8, p + l < d during the sample period), ``deflection_clean``,
        plus ``ramp_direction`` (force curve: −1 approach, +1 retract) or
        ``topography_nm`` (line scan).
    """
    if not (isinstance(chunk_samples, int) and chunk_samples >= 1):
        raise ConfigError(f"chunk_samples={chunk_samples!r} must be an integer >= 1")
    fs = params.sample_rate_hz
    nsub = params.substeps
    n = sample_count(params.duration_s, fs, "duration_s")
    cantilever = params.cantilever()
    force = params.force()
    gain = params.dither_gain_nm_per_v
    excitation, center_hz, amplitude_v = params.dither()
    program = _program(params)

    rng = np.random.default_rng(seed)
    sigma_eta = thermal_accel_rms(cantilever, params.temperature_k, fs)
    accel_noise = sigma_eta * rng.standard_normal(n)
    measurement = params.measurement_noise_nm * rng.standard_normal(n)

    if params.initial_state == "steady":
        p, v = _initial_state(excitation, cantilever, gain, fs if params.drive_hold == "zoh" else None)
    else:
        p, v = 0.0, 0.0
    clean, contact, dither, separation = _integrate_in_chunks(params, excitation, program, accel_noise, (p, v),
                                                              chunk_samples)
    per_sample = 2 * nsub
    half_step_s = 1.0 / (per_sample * fs)

    t = np.arange(n) * (per_sample * half_step_s)
    channels = [ChannelSpec("dither", "V"), ChannelSpec("deflection", "nm")]
    data = {"dither": dither, "deflection": clean + measurement}
    truth = {"separation_nm": separation, "contact": contact, "deflection_clean": clean}
    _program_channels(program, t, separation, channels, data, truth)

    metadata = {
        "scenario": "tapping",
        "cantilever": cantilever.to_metadata(),
        "drive": _drive_metadata(params, excitation, center_hz, amplitude_v),
        "force": {"set": params.force_set, **force.to_metadata()},
        "separation": {"program": params.program, "initial_nm": float(separation[0])},
        "noise": {
            "temperature_k": float(params.temperature_k),
            "thermal_accel_rms_nm_per_s2": sigma_eta,
            "measurement_noise_nm": float(params.measurement_noise_nm),
        },
        "integrator": {"method": "rk4", "substeps": nsub},
    }
    if params.drive == "stepped":
        metadata["segments"] = excitation.segments()
    hold_samples = min(n, int(math.floor(min(program.initial_hold_s, params.duration_s) * fs + 1e-9)))
    if hold_samples >= 1 and not contact[:hold_samples].any():
        metadata["free_air"] = {"start_s": 0.0, "end_s": hold_samples / fs}
    return SimulatedCapture(fs, tuple(channels), data, metadata, truth)
