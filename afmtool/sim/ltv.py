"""Scenario ``ltv``: a linear time-varying second-order discrete plant with known (f0, Q) truth.

The plant is eq. 3.40 with time-varying denominator and a fixed numerator,

.. math::

    p(n) + b_1(n)p(n-1) + b_0(n)p(n-2) = a_2 g(n) + a_1 g(n-1) + a_0 g(n-2) + w(n),

where (b1(n), b0(n)) come from the prescribed f0(t_n), Q(t_n) through the
pole map z = e^{sT} (:func:`~afmtool.models.discretisation.discrete_denominator`)
and (a2, a1, a0) is the numerator of the **free-air** model for the way the
dither reaches the cantilever (``drive_hold``, :mod:`afmtool.models.discretisation`),
times the dither gain: by default a continuous dither, for which the
line-matched numerator makes the sampled response equal G(jω) exactly at
the drive's main line (free-air phase −90° at resonance) and to < 0.1 % at
side lines ±6 kHz away; with ``drive_hold="zoh"`` the zero-order-hold
numerator, exact at every frequency for a dither a DAC holds per sample.  Keeping the numerator fixed while the poles move is
the structure of eq. 5.13 (c1, c0 fixed, ωe and Qe varying), which
docs/conventions.md identifies as the physically right one.  w(n) is optional white
process noise (nm); white measurement noise is added to the recorded
deflection only.

With constant parameters the recursion is computed with
``scipy.signal.lfilter``; with ``drive_hold="zoh"`` it equals the exact
discrete-time (ZOH) response of G(s) = ω0²/(s² + (ω0/Q)s + ω0²) to the
sampled dither.  With varying
parameters it is the numba kernel :func:`_ltv_kernel`.

Parameter profile
-----------------
f0 and Q move from (``f0_hz``, ``q``) to (``step_f0_hz``, ``step_q``) at
``step_time_s``, linearly over ``ramp_s`` (0 = a step).  With
``step_repeat_s`` > 0 they then switch back and forth every
``step_repeat_s`` (a square wave of steps or ramps).  Equal start and step
values, or ``step_time_s`` ≥ ``duration_s``, give a constant plant.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy import signal

from afmtool.config.samples import sample_count
from afmtool.errors import ConfigError
from afmtool.io.capture import ChannelSpec
from afmtool.jit import JIT_OPTIONS
from afmtool.models.cantilever import Cantilever
from afmtool.models.discretisation import DiscreteNumerator, discrete_denominator, sampled_numerator
from afmtool.sim import SimulatedCapture, param, validate_parameters
from afmtool.sim.excitation import DRIVE_KINDS, LinearChirp, MultiSine, SteppedSine, build_dither, drive_metadata, sine

__all__ = ["LtvParams", "parameter_profile", "ltv_recursion", "simulate_ltv"]


@dataclass(frozen=True)
class LtvParams:
    """Parameters of the ``ltv`` scenario (defaults: the REEP acceptance test of §3.3)."""

    duration_s: float = param(0.05, "capture length", "s", minimum=0, exclusive_minimum=True)
    sample_rate_hz: float = param(500e3, "sample rate", "Hz", minimum=0, exclusive_minimum=True)
    f0_hz: float = param(70000.0, "free-air resonant frequency f0 (before the step)", "Hz", minimum=0,
                         exclusive_minimum=True)
    q: float = param(200.0, "free-air quality factor Q (before the step)", "", minimum=0.5, exclusive_minimum=True)
    step_time_s: float = param(0.02, "time f0 and Q start to change", "s", minimum=0)
    step_f0_hz: float = param(69800.0, "f0 after the step", "Hz", minimum=0, exclusive_minimum=True)
    step_q: float = param(150.0, "Q after the step", "", minimum=0.5, exclusive_minimum=True)
    ramp_s: float = param(0.0, "duration of each change (0 = a step)", "s", minimum=0)
    step_repeat_s: float = param(0.0, "if > 0, switch back and forth every step_repeat_s", "s", minimum=0)
    drive: str = param("three-sine", "dither type", "", choices=DRIVE_KINDS)
    drive_hold: str = param(
        "continuous", "how the plant sees the dither: a continuous signal, or held per sample (a DAC at the "
        "sample rate)", "", choices=("continuous", "zoh"),
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
    process_noise_nm: float = param(0.0, "rms white equation noise w(n)", "nm", minimum=0)
    measurement_noise_nm: float = param(0.05, "rms white noise added to the recorded deflection", "nm", minimum=0)
    initial_state: str = param(
        "steady", "start in the free-air steady state of the dither or at rest", "", choices=("steady", "rest")
    )

    def __post_init__(self) -> None:
        validate_parameters(self)
        nyquist = self.sample_rate_hz / 2
        for name in ("f0_hz", "step_f0_hz"):
            if getattr(self, name) >= nyquist:
                raise ConfigError(f"{name}={getattr(self, name)!r} must be below sample_rate_hz/2 = {nyquist:g}")
        if self.duration_s * self.sample_rate_hz < 2:
            raise ConfigError(f"duration_s={self.duration_s!r} gives fewer than 2 samples")
        if self.step_repeat_s > 0 and self.ramp_s > self.step_repeat_s:
            raise ConfigError(f"ramp_s={self.ramp_s!r} must not exceed step_repeat_s={self.step_repeat_s!r}")
        top_hz = self.dither()[0].max_frequency_hz
        if top_hz >= nyquist:
            raise ConfigError(f"the dither reaches {top_hz:g} Hz, above sample_rate_hz/2 = {nyquist:g}")

    def numerator(self) -> DiscreteNumerator:
        """Free-air numerator for ``drive_hold`` times the dither gain (nm of deflection per V of dither).

        Continuous: matched at the drive's main (or sweep-centre) line.
        """
        match_hz = self.f0_hz + self.drive_offset_hz
        a2, a1, a0 = sampled_numerator(self.f0_hz, self.q, self.sample_rate_hz, self.drive_hold, match_hz=match_hz)
        gain = self.dither_gain_nm_per_v
        return DiscreteNumerator(gain * a2, gain * a1, gain * a0)

    def free_air_response(self, f_hz: np.ndarray) -> np.ndarray:
        """Discrete free-air response H(e^{j2πf/fs}) from dither (V) to deflection (nm)."""
        b1, b0 = discrete_denominator(self.f0_hz, self.q, self.sample_rate_hz)
        z_inv = np.exp(-2j * np.pi * np.asarray(f_hz, dtype=np.float64) / self.sample_rate_hz)
        a2, a1, a0 = self.numerator()
        return (a2 + a1 * z_inv + a0 * z_inv**2) / (1.0 + b1 * z_inv + b0 * z_inv**2)

    def dither(self) -> tuple[MultiSine | LinearChirp | SteppedSine, float, float]:
        """The dither (V), its main/centre frequency (Hz) and main-line amplitude (V).

        The amplitude makes the free-air *discrete* steady-state deflection at
        f_c = f0 + ``drive_offset_hz`` equal ``amplitude_nm``.
        """
        center_hz = self.f0_hz + self.drive_offset_hz
        if not 0 < center_hz < self.sample_rate_hz / 2:
            raise ConfigError(f"drive_offset_hz={self.drive_offset_hz!r} puts the drive at {center_hz:g} Hz")
        amplitude_v = self.amplitude_nm / abs(complex(self.free_air_response(center_hz)))
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


def parameter_profile(t_s: np.ndarray, step_time_s: float, ramp_s: float, step_repeat_s: float) -> np.ndarray:
    """Fraction s(t) ∈ [0, 1] of the way from the initial to the stepped parameters.

    s = 0 before ``step_time_s``; change k (k = 0, 1, …, at step_time_s +
    k·step_repeat_s, only k = 0 when step_repeat_s = 0) moves s linearly
    over ``ramp_s`` to 1 for even k and to 0 for odd k.
    """
    t = np.asarray(t_s, dtype=np.float64)
    tau = t - step_time_s
    if step_repeat_s > 0:
        k = np.floor(np.maximum(tau, 0.0) / step_repeat_s)
        local = tau - k * step_repeat_s
    else:
        k = np.zeros_like(tau)
        local = tau
    target = np.where(k % 2 == 0, 1.0, 0.0)
    if ramp_s > 0:
        frac = np.clip(local / ramp_s, 0.0, 1.0)
    else:
        frac = (local >= 0).astype(np.float64)
    s = (1.0 - target) + (2.0 * target - 1.0) * frac
    return np.where(tau < 0, 0.0, s)


@njit(**JIT_OPTIONS)
def _ltv_kernel(u, b1, b0, p1, p2, out):
    """p(n) = u(n) − b1(n)p(n−1) − b0(n)p(n−2), from p(−1) = p1, p(−2) = p2."""
    for n in range(u.shape[0]):
        p = u[n] - b1[n] * p1 - b0[n] * p2
        out[n] = p
        p2 = p1
        p1 = p
    return out


def ltv_recursion(
    u: np.ndarray, b1: np.ndarray, b0: np.ndarray, p_minus1: float = 0.0, p_minus2: float = 0.0
) -> np.ndarray:
    """Solve p(n) + b1(n)p(n−1) + b0(n)p(n−2) = u(n) (eq. 3.40 with time-varying AR part).

    Parameters
    ----------
    u : numpy.ndarray
        Right-hand side u(n) (numerator output plus process noise), nm.
    b1, b0 : numpy.ndarray
        AR coefficients per sample, same length as ``u``.
    p_minus1, p_minus2 : float
        p(−1) and p(−2), nm.

    Returns
    -------
    numpy.ndarray
        p(n), nm.  Constant coefficients use ``scipy.signal.lfilter``.
    """
    u = np.ascontiguousarray(u, dtype=np.float64)
    b1 = np.ascontiguousarray(b1, dtype=np.float64)
    b0 = np.ascontiguousarray(b0, dtype=np.float64)
    if not (u.shape == b1.shape == b0.shape and u.ndim == 1):
        raise ConfigError(f"u, b1 and b0 must be 1-D of equal length, got {u.shape}, {b1.shape}, {b0.shape}")
    if u.size and np.all(b1 == b1[0]) and np.all(b0 == b0[0]):
        den = [1.0, b1[0], b0[0]]
        zi = signal.lfiltic([1.0], den, y=[p_minus1, p_minus2])
        return signal.lfilter([1.0], den, u, zi=zi)[0]
    return _ltv_kernel(u, b1, b0, float(p_minus1), float(p_minus2), np.empty_like(u))


def _initial_history(params: LtvParams, excitation) -> tuple[float, float]:
    """Free-air steady state p(−1), p(−2) (sweeps: a sine at their initial frequency and phase)."""
    if isinstance(excitation, MultiSine):
        lines = excitation
    else:
        freqs = getattr(excitation, "frequencies_hz", None)
        f_start = freqs[0] if freqs is not None else excitation.start_hz
        lines = sine(excitation.amplitude, f_start, float(excitation.phase_rad(np.array([0.0]))[0]))
    response = params.free_air_response(np.asarray(lines.frequencies_hz))
    period = 1.0 / params.sample_rate_hz
    return lines.steady_state(response, -period)[0], lines.steady_state(response, -2 * period)[0]


def _ltv_metadata(params: LtvParams, center_hz: float, amplitude_v: float, numerator) -> dict:
    """The capture metadata of :func:`simulate_ltv`: cantilever, drive, numerator and noise."""
    a2, a1, a0 = numerator
    cantilever = Cantilever(params.f0_hz, params.q)
    drive = drive_metadata(params, center_hz, amplitude_v)
    metadata = {
        "scenario": "ltv",
        "cantilever": {"f0_hz": float(cantilever.f0_hz), "q": float(cantilever.q)},
        "drive": drive,
        "numerator": {
            "a2": float(a2),
            "a1": float(a1),
            "a0": float(a0),
            "note": f"free-air {params.drive_hold} numerator x dither gain; input dither (V), output deflection (nm)",
        },
        "noise": {
            "process_noise_nm": float(params.process_noise_nm),
            "measurement_noise_nm": float(params.measurement_noise_nm),
        },
    }
    return metadata


def simulate_ltv(params: LtvParams, seed: int) -> SimulatedCapture:
    """Linear time-varying discrete cantilever with prescribed f0(t), Q(t) and a fixed numerator.

    Parameters
    ----------
    params : LtvParams
        Scenario parameters.
    seed : int
        Seed of ``numpy.random.default_rng`` (process then measurement noise).

    Returns
    -------
    SimulatedCapture
        Channels ``dither`` (V) and ``deflection`` (nm); truth ``f0_hz``,
        ``q``, ``b1``, ``b0`` (the coefficients used to compute p(n)) and
        ``deflection_clean``.
    """
    fs = params.sample_rate_hz
    n = sample_count(params.duration_s, fs, "duration_s")
    t = np.arange(n) / fs
    excitation, center_hz, amplitude_v = params.dither()
    rng = np.random.default_rng(seed)
    process = params.process_noise_nm * rng.standard_normal(n)
    measurement = params.measurement_noise_nm * rng.standard_normal(n)

    s = parameter_profile(t, params.step_time_s, params.ramp_s, params.step_repeat_s)
    f0 = params.f0_hz + s * (params.step_f0_hz - params.f0_hz)
    q = params.q + s * (params.step_q - params.q)
    b1, b0 = discrete_denominator(f0, q, fs)

    dither = excitation(t)
    if params.initial_state == "steady":
        g_hist = excitation(np.array([-2.0, -1.0]) / fs)
        p1, p2 = _initial_history(params, excitation)
    else:
        g_hist = np.zeros(2)
        p1 = p2 = 0.0
    g_ext = np.concatenate((g_hist, dither))
    a2, a1, a0 = params.numerator()
    # u(n) = a2·g(n) + a1·g(n−1) + a0·g(n−2) + w(n)
    u = a2 * g_ext[2:] + a1 * g_ext[1:-1] + a0 * g_ext[:-2] + process
    clean = ltv_recursion(u, b1, b0, p1, p2)

    changes = bool(np.any(s != 0.0))
    metadata = _ltv_metadata(params, center_hz, amplitude_v, (a2, a1, a0))
    if params.drive == "stepped":
        metadata["segments"] = excitation.segments()
    free_end = params.step_time_s if changes else n / fs
    free_samples = int(math.floor(free_end * fs + 1e-9))
    if free_samples >= 1:
        metadata["free_air"] = {"start_s": 0.0, "end_s": min(free_samples, n) / fs}
    truth = {"f0_hz": f0, "q": q, "b1": np.asarray(b1), "b0": np.asarray(b0), "deflection_clean": clean}
    channels = (ChannelSpec("dither", "V"), ChannelSpec("deflection", "nm"))
    data = {"dither": dither, "deflection": clean + measurement}
    return SimulatedCapture(fs, channels, data, metadata, truth)
