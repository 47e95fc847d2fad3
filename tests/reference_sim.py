"""An independent reference simulator of a driven cantilever, for tests only.

Written from the physics alone: it imports nothing from ``afmtool`` (only
numpy, scipy, numba, h5py, json, dataclasses and math), so that estimator
tests can be scored against a truth that does not share afmtool's
conventions, discretisations or code.

Equation of motion
------------------
One mode, per unit mass, deflection p in nm (positive away from the sample):

.. math::

    \\ddot p + \\frac{\\omega_0(t)}{Q(t)}\\dot p + \\omega_0(t)^2 p
        = \\omega_{0,\\mathrm{free}}^2\\, k_g\\, u(t) + F(p, \\dot p; l(t)),

with u(t) the drive (V), k_g the drive gain (nm/V: the static deflection
per volt), ω0,free = 2π·f0 the free-air resonance and ω0(t), Q(t) optional
prescribed time-varying values (``f0_of_t``, ``q_of_t``; the forcing keeps
its free-air scale, as the drive's force per unit mass does not change when
the tip-sample interaction shifts the resonance).  The free-air transfer
function from u to p is therefore

.. math:: G(s) = \\frac{k_g\\,\\omega_0^2}{s^2 + (\\omega_0/Q)s + \\omega_0^2},

|G(jω0)| = k_g·Q and arg G(jω0) = −90°.

Tip-sample force (eq. 4.1 in the docs/conventions.md sign convention)
----------------------------------------------------------
The force is positive upward, the sample surface sits at p = −l, the
tip-sample separation is t_s = p + l, attraction is negative for
0 ≤ t_s < d, repulsion is added for t_s < 0 and dissipation opposes the
velocity:

.. math::

    F = \\begin{cases}
        0 & t_s \\ge d\\\\
        -\\omega_a^2 (d - t_s) - c_a \\dot p & 0 \\le t_s < d\\\\
        -\\omega_a^2 (d - t_s) - \\omega_b^2 t_s - (c_a + c_b)\\dot p & t_s < 0.
    \\end{cases}

Integration and the drive
-------------------------
Classical fixed-step RK4, ``oversample`` steps per sample period (≥ 32 by
default).  A *continuous* drive (``hold="continuous"``: a function
generator, or a fast DAC behind its reconstruction filter) is evaluated
analytically at every RK4 stage time t, t + h/2, t + h; it is never
interpolated from the samples (a linear interpolation would scale a line at
f by sinc²(f/fs)).  A *held* drive (``hold="zoh"``: a DAC at the ADC's own
rate) is u(t_i) over the whole interval [t_i, t_{i+1}).  The ``dither``
channel records u(t_i) in both cases: the ADC samples what the DAC or
generator puts out.

Ground truth
------------
``/truth`` holds ``deflection_clean`` (nm, before measurement noise),
``f0_hz`` and ``q`` per sample (the ω0(t), Q(t) of the equation), and with a
separation program ``separation_nm`` (l at t_i); with a force ``contact``
(uint8: 1 when t_s = p + l < d at any RK4 step boundary in [t_i, t_{i+1})).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import h5py
import numpy as np
from numba import njit

__all__ = [
    "Sine",
    "MultiSine",
    "LinearChirp",
    "SteppedSine",
    "PiecewiseLinearForce",
    "Capture",
    "three_sine",
    "drive_voltage",
    "free_air_response",
    "simulate",
    "write_capture_h5",
    "SeparationSteps",
    "loss_program",
    "thermal_record",
]

_CHUNK_SAMPLES = 8192
_DEFLECTION_SCALE = {"nm": 1.0, "um": 1e-3, "µm": 1e-3, "m": 1e-9}


# --------------------------------------------------------------------------- drives


@dataclass(frozen=True)
class Sine:
    """u(t) = A·cos(2πf·t + φ), V."""

    frequency_hz: float
    amplitude_v: float
    phase_rad: float = 0.0


@dataclass(frozen=True)
class MultiSine:
    """A sum of :class:`Sine` lines (e.g. REEP's three-sine dither)."""

    lines: tuple[Sine, ...]


@dataclass(frozen=True)
class LinearChirp:
    """u(t) = A·cos(2π(f_s·τ + ½k·τ²)), τ = t − t_start, k = (f_e − f_s)/(t_end − t_start).

    Zero outside [t_start, t_end]; ``t_end=None`` means the end of the capture
    (:func:`simulate` fills it in).
    """

    f_start_hz: float
    f_end_hz: float
    amplitude_v: float
    t_start_s: float = 0.0
    t_end_s: float | None = None


@dataclass(frozen=True)
class SteppedSine:
    """Sines at ``frequencies_hz[k]`` over [k·dwell, (k+1)·dwell), phase-continuous; zero after."""

    frequencies_hz: tuple[float, ...]
    dwell_s: float
    amplitude_v: float

    def segments(self) -> list[dict]:
        """The capture-metadata ``segments`` list (start_s, end_s, frequency_hz)."""
        return [
            {"start_s": k * self.dwell_s, "end_s": (k + 1) * self.dwell_s, "frequency_hz": float(f)}
            for k, f in enumerate(self.frequencies_hz)
        ]


def three_sine(center_hz: float, offset_hz: float, amplitude_v: float, side_scale: float = 0.5) -> MultiSine:
    """Main line at ``center_hz`` and side lines at ±``offset_hz`` scaled by ``side_scale``."""
    side = side_scale * amplitude_v
    return MultiSine(
        (Sine(center_hz, amplitude_v), Sine(center_hz - offset_hz, side), Sine(center_hz + offset_hz, side))
    )


def drive_voltage(drive, t: np.ndarray) -> np.ndarray:
    """The drive u(t) in V at arbitrary times ``t`` (s), analytically.

    Parameters
    ----------
    drive : Sine, MultiSine, LinearChirp or SteppedSine
        The drive.
    t : array_like
        Times, s.

    Returns
    -------
    numpy.ndarray
        u(t), V, the shape of ``t``.
    """
    t = np.asarray(t, dtype=np.float64)
    if isinstance(drive, Sine):
        return drive.amplitude_v * np.cos(2.0 * np.pi * drive.frequency_hz * t + drive.phase_rad)
    if isinstance(drive, MultiSine):
        out = np.zeros_like(t)
        for line in drive.lines:
            out += drive_voltage(line, t)
        return out
    if isinstance(drive, LinearChirp):
        if drive.t_end_s is None:
            raise ValueError("LinearChirp.t_end_s is None: give the chirp an end time")
        span = drive.t_end_s - drive.t_start_s
        if not span > 0:
            raise ValueError(f"LinearChirp needs t_end_s > t_start_s, got {drive.t_start_s}, {drive.t_end_s}")
        rate = (drive.f_end_hz - drive.f_start_hz) / span
        tau = t - drive.t_start_s
        phase = 2.0 * np.pi * (drive.f_start_hz * tau + 0.5 * rate * tau * tau)
        inside = (tau >= 0.0) & (t <= drive.t_end_s)
        return np.where(inside, drive.amplitude_v * np.cos(phase), 0.0)
    if isinstance(drive, SteppedSine):
        freqs = np.asarray(drive.frequencies_hz, dtype=np.float64)
        k = np.floor(t / drive.dwell_s).astype(np.int64)
        inside = (k >= 0) & (k < freqs.size)
        kc = np.clip(k, 0, freqs.size - 1)
        # phase-continuous: the phase accumulated over the earlier segments
        start_phase = np.concatenate(([0.0], np.cumsum(2.0 * np.pi * freqs * drive.dwell_s)))[:-1]
        phase = start_phase[kc] + 2.0 * np.pi * freqs[kc] * (t - kc * drive.dwell_s)
        return np.where(inside, drive.amplitude_v * np.cos(phase), 0.0)
    raise TypeError(f"unknown drive {drive!r}")


def _drive_lines_at_zero(drive) -> list[Sine]:
    """The drive near t = 0 as sine lines (for the initial steady state)."""
    if isinstance(drive, Sine):
        return [drive]
    if isinstance(drive, MultiSine):
        return list(drive.lines)
    if isinstance(drive, LinearChirp):
        return [Sine(drive.f_start_hz, drive.amplitude_v)] if drive.t_start_s == 0.0 else []
    if isinstance(drive, SteppedSine):
        return [Sine(drive.frequencies_hz[0], drive.amplitude_v)]
    raise TypeError(f"unknown drive {drive!r}")


def _drive_metadata(drive) -> dict:
    if isinstance(drive, Sine):
        return {"kind": "sine", "frequency_hz": drive.frequency_hz, "amplitude_v": drive.amplitude_v,
                "sideband_offset_hz": 0.0}
    if isinstance(drive, MultiSine):
        main = max(drive.lines, key=lambda line: line.amplitude_v)
        meta = {"kind": "multi-sine", "frequency_hz": main.frequency_hz, "amplitude_v": main.amplitude_v,
                "lines_hz": [line.frequency_hz for line in drive.lines],
                "lines_v": [line.amplitude_v for line in drive.lines]}
        offsets = sorted({round(abs(line.frequency_hz - main.frequency_hz), 9) for line in drive.lines} - {0.0})
        if len(drive.lines) == 3 and len(offsets) == 1:
            meta["kind"] = "three-sine"
            meta["sideband_offset_hz"] = offsets[0]
            meta["sideband_scale"] = min(line.amplitude_v for line in drive.lines) / main.amplitude_v
        return meta
    if isinstance(drive, LinearChirp):
        return {"kind": "chirp", "frequency_hz": 0.5 * (drive.f_start_hz + drive.f_end_hz),
                "amplitude_v": drive.amplitude_v, "start_hz": drive.f_start_hz, "end_hz": drive.f_end_hz,
                "t_start_s": drive.t_start_s, "t_end_s": drive.t_end_s}
    return {"kind": "stepped", "frequency_hz": float(np.median(drive.frequencies_hz)),
            "amplitude_v": drive.amplitude_v}


# --------------------------------------------------------------------------- force


@dataclass(frozen=True)
class PiecewiseLinearForce:
    """Eq. 4.1 per unit mass in the docs/conventions.md convention (module docstring).

    ``d_nm`` attractive range (nm), ``wa2``/``wb2`` attractive/repulsive
    stiffness per unit mass (1/s²), ``ca``/``cb`` damping per unit mass (1/s).
    """

    d_nm: float
    wa2: float
    wb2: float
    ca: float
    cb: float

    def __call__(self, p, v, l):
        """F/m in nm/s² at deflection p (nm), velocity v (nm/s), separation l (nm)."""
        p, v, l = np.broadcast_arrays(np.asarray(p, float), np.asarray(v, float), np.asarray(l, float))
        ts = p + l
        out = np.where(ts < self.d_nm, -self.wa2 * (self.d_nm - ts) - self.ca * v, 0.0)
        return out + np.where(ts < 0.0, -self.wb2 * ts - self.cb * v, 0.0)


#: The thesis's §3.4.3 "predominant attractive" set (f0 = 80,318 Hz, Q = 168), eq. 4.1 magnitudes.
ATTRACTIVE_SET = PiecewiseLinearForce(4.0, 0.31e6**2, 3.03e6**2, 0.042e6, 0.0)


# --------------------------------------------------------------------------- separation programs


@dataclass(frozen=True)
class SeparationSteps:
    """l(t) (nm): ``levels_nm[k]`` from ``edges_s[k]`` to ``edges_s[k+1]`` (the last level holds on)."""

    edges_s: tuple[float, ...]
    levels_nm: tuple[float, ...]

    def __call__(self, t):
        t = np.asarray(t, dtype=np.float64)
        k = np.clip(np.searchsorted(np.asarray(self.edges_s), t, side="right") - 1, 0, len(self.levels_nm) - 1)
        return np.asarray(self.levels_nm)[k]


def loss_program(free_s: float, on_s: float, losses_s, on_nm: float, off_nm: float) -> tuple[SeparationSteps, float]:
    """Free air for ``free_s``, then on the sample (``on_nm``) for ``on_s`` between losses of ``losses_s`` each.

    Returns the program and the capture length that ends with an on-sample
    stretch.  During a loss the sample is at ``off_nm`` (beyond the free
    amplitude plus the force range, so the tip is truly off).
    """
    edges = [0.0, free_s]
    levels = [off_nm, on_nm]
    for loss in losses_s:
        edges += [edges[-1] + on_s, edges[-1] + on_s + loss]
        levels += [off_nm, on_nm]
    return SeparationSteps(tuple(edges), tuple(levels)), edges[-1] + on_s


# --------------------------------------------------------------------------- capture


@dataclass(frozen=True)
class Capture:
    """A simulated capture: channels with units, ground truth and capture metadata."""

    sample_rate_hz: float
    channels: dict[str, np.ndarray]
    units: dict[str, str]
    truth: dict[str, np.ndarray]
    metadata: dict = field(default_factory=dict)

    @property
    def t(self) -> np.ndarray:
        """Sample times t_i = i/fs, s."""
        n = next(iter(self.channels.values())).size
        return np.arange(n) / self.sample_rate_hz


def free_air_response(frequency_hz, f0_hz: float, q: float, gain_nm_per_v: float = 1.0) -> np.ndarray:
    """G(jω) = k_g·ω0²/(ω0² − ω² + jωω0/Q), nm/V (continuous drive, module docstring)."""
    w = 2.0 * np.pi * np.asarray(frequency_hz, dtype=np.float64)
    w0 = 2.0 * np.pi * f0_hz
    return gain_nm_per_v * w0 * w0 / (w0 * w0 - w * w + 1j * w * w0 / q)


@njit(cache=True)
def _rk4(forcing, held, w0sq, w0q, sep, d, wa2, wb2, ca, cb, nsub, h, p, v, out_p, out_contact):  # noqa: PLR0915 - numba kernel: one scalar recursion
    """RK4 over n sample periods, ``nsub`` steps each.

    ``forcing``, ``w0sq``, ``w0q`` and ``sep`` are sampled on the half-step
    grid (length 2·nsub·n + 1): index 2k is a step start, 2k + 1 its
    midpoint.  With ``held`` (length n, else empty) the forcing is
    ``held[i]`` at every stage of sample interval i instead: a held input
    jumps at t_{i+1}, where the grid point is shared by two intervals.
    Returns the final (p, v).
    """
    half = 0.5 * h
    use_held = held.shape[0] > 0
    for i in range(out_p.shape[0]):
        out_p[i] = p
        touched = 0
        for k in range(nsub):
            j = 2 * (i * nsub + k)
            if use_held:
                g0 = held[i]
                g1 = held[i]
                g2 = held[i]
            else:
                g0 = forcing[j]
                g1 = forcing[j + 1]
                g2 = forcing[j + 2]
            if p + sep[j] < d:
                touched = 1
            # stage 1 at t
            ts = p + sep[j]
            f = 0.0
            if ts < d:
                f = -wa2 * (d - ts) - ca * v
                if ts < 0.0:
                    f += -wb2 * ts - cb * v
            a1 = g0 - w0sq[j] * p - w0q[j] * v + f
            # stage 2 at t + h/2
            p2 = p + half * v
            v2 = v + half * a1
            ts = p2 + sep[j + 1]
            f = 0.0
            if ts < d:
                f = -wa2 * (d - ts) - ca * v2
                if ts < 0.0:
                    f += -wb2 * ts - cb * v2
            a2 = g1 - w0sq[j + 1] * p2 - w0q[j + 1] * v2 + f
            # stage 3 at t + h/2
            p3 = p + half * v2
            v3 = v + half * a2
            ts = p3 + sep[j + 1]
            f = 0.0
            if ts < d:
                f = -wa2 * (d - ts) - ca * v3
                if ts < 0.0:
                    f += -wb2 * ts - cb * v3
            a3 = g1 - w0sq[j + 1] * p3 - w0q[j + 1] * v3 + f
            # stage 4 at t + h
            p4 = p + h * v3
            v4 = v + h * a3
            ts = p4 + sep[j + 2]
            f = 0.0
            if ts < d:
                f = -wa2 * (d - ts) - ca * v4
                if ts < 0.0:
                    f += -wb2 * ts - cb * v4
            a4 = g2 - w0sq[j + 2] * p4 - w0q[j + 2] * v4 + f
            p = p + h / 6.0 * (v + 2.0 * v2 + 2.0 * v3 + v4)
            v = v + h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
        out_contact[i] = touched
    return p, v


def _steady_state(lines, f0_hz, q, gain, forcing_w0sq, sample_rate_hz, hold) -> tuple[float, float]:
    """Free-air (p, ṗ) at t = 0 in the periodic steady state of the drive lines.

    Continuous drive: p = Re Σ G(jω)·A·e^{jφ}.  Held drive: the state x_i at
    the sample instants obeys x_{i+1} = Φx_i + Γu_i exactly (Φ = e^{AT}), so
    for u_i = Re(U e^{jωT i}) the steady state is Re((e^{jωT}I − Φ)⁻¹ΓU).
    """
    if not lines:
        return 0.0, 0.0
    w0 = 2.0 * np.pi * f0_hz
    if hold == "continuous":
        p = 0.0
        v = 0.0
        for line in lines:
            w = 2.0 * np.pi * line.frequency_hz
            response = forcing_w0sq * gain / (w0 * w0 - w * w + 1j * w * w0 / q)
            phasor = response * line.amplitude_v * np.exp(1j * line.phase_rad)
            p += phasor.real
            v += (1j * w * phasor).real
        return float(p), float(v)
    from scipy.linalg import expm

    period = 1.0 / sample_rate_hz
    a = np.array([[0.0, 1.0], [-w0 * w0, -w0 / q]])
    b = np.array([0.0, forcing_w0sq * gain])
    big = np.zeros((3, 3))
    big[:2, :2] = a * period
    big[:2, 2] = b * period
    e = expm(big)
    phi, gamma = e[:2, :2], e[:2, 2]
    state = np.zeros(2)
    for line in lines:
        z = np.exp(1j * 2.0 * np.pi * line.frequency_hz * period)
        x = np.linalg.solve(z * np.eye(2) - phi, gamma * line.amplitude_v * np.exp(1j * line.phase_rad))
        state += x.real
    return float(state[0]), float(state[1])


def _as_function(value, name: str) -> Callable[[np.ndarray], np.ndarray] | None:
    if value is None:
        return None
    if callable(value):
        return value
    if isinstance(value, (int, float)) and math.isfinite(value):
        constant = float(value)
        return lambda t: np.full(np.shape(t), constant)
    raise ValueError(f"{name}={value!r} must be a number or a callable t -> value")


def simulate(  # noqa: C901, PLR0915 - the whole independent simulator, read top to bottom
    *,
    f0_hz: float,
    q: float,
    gain_nm_per_v: float,
    sample_rate_hz: float,
    duration_s: float,
    drive,
    hold: str = "continuous",
    noise_nm: float = 0.0,
    seed: int = 0,
    oversample: int = 32,
    force: PiecewiseLinearForce | None = None,
    separation_nm=None,
    f0_of_t: Callable[[np.ndarray], np.ndarray] | None = None,
    q_of_t: Callable[[np.ndarray], np.ndarray] | None = None,
    start_at_steady_state: bool = True,
    free_air_s: float | None = None,
    record_z_piezo: bool = False,
    deflection_units: str = "nm",
    extra_metadata: dict | None = None,
) -> Capture:
    """Integrate the driven cantilever (module docstring) and sample it.

    Parameters
    ----------
    f0_hz, q : float
        Free-air resonance f0 (Hz) and quality factor Q (> 1/2).
    gain_nm_per_v : float
        Drive gain k_g: static deflection per volt of drive, nm/V.
    sample_rate_hz, duration_s : float
        ADC rate fs (Hz) and capture length (s).
    drive : Sine, MultiSine, LinearChirp or SteppedSine
        The drive u(t), V.
    hold : {"continuous", "zoh"}
        How the plant sees the drive: analytically at every RK4 stage, or
        held at u(t_i) over each sample interval.
    noise_nm : float
        Rms of white measurement noise added to the recorded deflection, nm.
    seed : int
        Seed of ``numpy.random.default_rng`` for the measurement noise.
    oversample : int
        RK4 steps per sample period (≥ 32 unless a test says why).
    force : PiecewiseLinearForce, optional
        Tip-sample force; needs ``separation_nm``.
    separation_nm : float or callable, optional
        Rest separation l (nm), a constant or a function of t (s).
    f0_of_t, q_of_t : callable, optional
        Prescribed ω0(t)/(2π) (Hz) and Q(t); default the free-air values.
    start_at_steady_state : bool
        Start in the free-air periodic steady state of the drive at t = 0
        (chirps: of a sine at their start frequency), else at rest.
    free_air_s : float, optional
        End of the metadata ``free_air`` segment (s).  Default: the whole
        capture without a force, else the samples before the first contact
        (none when the capture starts in contact); 0 omits it.
    record_z_piezo : bool
        Add a ``z_piezo`` channel (nm) = l(t) − l(0): positive = sample
        farther from the tip.
    deflection_units : {"nm", "um", "m"}
        Units the deflection channel is written in.
    extra_metadata : dict, optional
        Merged into the capture metadata (e.g. ``controller``, ``scan``).

    Returns
    -------
    Capture
        Channels ``dither`` (V) and ``deflection``; truth as the module
        docstring lists.
    """
    if hold not in ("continuous", "zoh"):
        raise ValueError(f"hold={hold!r} must be 'continuous' or 'zoh'")
    if not (f0_hz > 0 and q > 0.5 and sample_rate_hz > 2 * f0_hz and duration_s > 0):
        raise ValueError(f"need f0_hz > 0, q > 0.5, fs > 2 f0, duration > 0: {f0_hz=}, {q=}, {sample_rate_hz=}")
    if not (isinstance(oversample, int) and oversample >= 1):
        raise ValueError(f"oversample={oversample!r} must be an integer >= 1")
    if force is not None and separation_nm is None:
        raise ValueError("a force needs separation_nm")
    if deflection_units not in _DEFLECTION_SCALE:
        raise ValueError(f"deflection_units={deflection_units!r} must be one of {sorted(_DEFLECTION_SCALE)}")
    if isinstance(drive, LinearChirp) and drive.t_end_s is None:
        drive = replace(drive, t_end_s=duration_s)

    fs = float(sample_rate_hz)
    n = int(round(duration_s * fs))
    w0_free = 2.0 * np.pi * f0_hz
    sep_fn = _as_function(separation_nm, "separation_nm")
    f0_fn = _as_function(f0_of_t, "f0_of_t")
    q_fn = _as_function(q_of_t, "q_of_t")
    d, wa2, wb2, ca, cb = (
        (force.d_nm, force.wa2, force.wb2, force.ca, force.cb) if force is not None else (0.0, 0.0, 0.0, 0.0, 0.0)
    )
    if force is not None and d == 0.0 and wb2 == 0.0:
        force = None

    f0_start = float(f0_fn(np.zeros(1))[0]) if f0_fn else f0_hz
    q_start = float(q_fn(np.zeros(1))[0]) if q_fn else q
    if start_at_steady_state:
        p, v = _steady_state(_drive_lines_at_zero(drive), f0_start, q_start, gain_nm_per_v, w0_free**2, fs, hold)
    else:
        p, v = 0.0, 0.0

    per_sample = 2 * oversample
    h = 1.0 / (fs * oversample)
    clean = np.empty(n)
    contact = np.zeros(n, dtype=np.uint8)
    dither = np.empty(n)
    sep_samples = np.zeros(n)
    f0_samples = np.empty(n)
    q_samples = np.empty(n)
    for start in range(0, n, _CHUNK_SAMPLES):
        stop = min(start + _CHUNK_SAMPLES, n)
        t_half = np.arange(per_sample * start, per_sample * stop + 1) / (per_sample * fs)
        t_samples = np.arange(start, stop) / fs
        u_samples = drive_voltage(drive, t_samples)
        if hold == "continuous":
            u_half = drive_voltage(drive, t_half)
            held = np.empty(0)
        else:
            u_half = np.empty(0)
            held = w0_free**2 * gain_nm_per_v * u_samples
        f0_half = f0_fn(t_half) if f0_fn else np.full(t_half.shape, f0_hz)
        q_half = q_fn(t_half) if q_fn else np.full(t_half.shape, q)
        w0_half = 2.0 * np.pi * np.asarray(f0_half, dtype=np.float64)
        sep_half = np.asarray(sep_fn(t_half), dtype=np.float64) if sep_fn else np.full(t_half.shape, np.inf)
        p, v = _rk4(
            np.ascontiguousarray(w0_free**2 * gain_nm_per_v * u_half),
            np.ascontiguousarray(held),
            np.ascontiguousarray(w0_half * w0_half),
            np.ascontiguousarray(w0_half / np.asarray(q_half, dtype=np.float64)),
            np.ascontiguousarray(sep_half),
            d, wa2, wb2, ca, cb, oversample, h, p, v,
            clean[start:stop], contact[start:stop],
        )
        dither[start:stop] = u_samples
        f0_samples[start:stop] = f0_half[:-1:per_sample]
        q_samples[start:stop] = q_half[:-1:per_sample]
        if sep_fn:
            sep_samples[start:stop] = sep_half[:-1:per_sample]

    rng = np.random.default_rng(seed)
    measured = clean + noise_nm * rng.standard_normal(n)
    scale = _DEFLECTION_SCALE[deflection_units]
    channels = {"dither": dither, "deflection": measured * scale}
    units = {"dither": "V", "deflection": deflection_units}
    truth = {"deflection_clean": clean, "f0_hz": f0_samples, "q": q_samples}
    if sep_fn:
        truth["separation_nm"] = sep_samples
        if record_z_piezo:
            channels["z_piezo"] = sep_samples - sep_samples[0]
            units["z_piezo"] = "nm"
    if force is not None:
        truth["contact"] = contact

    drive_meta = _drive_metadata(drive)
    drive_meta.update(dither_gain_nm_per_v=float(gain_nm_per_v), hold=hold)
    main_hz = drive_meta["frequency_hz"]
    drive_meta["free_amplitude_nm"] = float(abs(free_air_response(main_hz, f0_hz, q, gain_nm_per_v)) * drive_meta[
        "amplitude_v"])
    metadata = {
        "scenario": "reference_sim",
        "simulator": "tests/reference_sim.py (independent of afmtool)",
        "cantilever": {"f0_hz": float(f0_hz), "q": float(q)},
        "drive": drive_meta,
        "noise": {"measurement_noise_nm": float(noise_nm)},
        "integrator": {"method": "rk4", "substeps": oversample, "hold": hold},
    }
    if isinstance(drive, SteppedSine):
        metadata["segments"] = drive.segments()
    if force is not None:
        metadata["force"] = {"d_nm": d, "omega_a2_per_s2": wa2, "omega_b2_per_s2": wb2, "c_a_per_s": ca,
                             "c_b_per_s": cb}
    if free_air_s is None:
        touched = np.flatnonzero(contact) if force is not None else np.empty(0, dtype=np.int64)
        free_samples = int(touched[0]) if touched.size else n
        free_end = free_samples / fs
    else:
        free_end = float(free_air_s)
    if free_end > 0:
        metadata["free_air"] = {"start_s": 0.0, "end_s": min(free_end, n / fs)}
    if extra_metadata:
        metadata.update(extra_metadata)
    return Capture(fs, channels, units, truth, metadata)


def write_capture_h5(path, capture: Capture) -> Path:
    """Write ``capture`` in afmtool's HDF5 capture layout with h5py directly.

    Root attribute ``sample_rate_hz``, root attribute ``metadata`` (JSON),
    ``/channels/<name>`` float64 datasets with a ``units`` attribute, and
    ``/truth/<name>``.
    """
    path = Path(path)
    with h5py.File(path, "w") as h5:
        h5.attrs["sample_rate_hz"] = float(capture.sample_rate_hz)
        h5.attrs["metadata"] = json.dumps(capture.metadata)
        group = h5.create_group("channels", track_order=True)
        for name, values in capture.channels.items():
            ds = group.create_dataset(name, data=np.asarray(values, dtype=np.float64))
            ds.attrs["units"] = capture.units[name]
        truth = h5.create_group("truth")
        for name, values in capture.truth.items():
            truth.create_dataset(name, data=np.asarray(values))
    return path


# --------------------------------------------------------------------------- thermal noise

#: Boltzmann constant, J/K (exact, SI 2019).
_K_B = 1.380649e-23


@njit(cache=True)
def _ar_state(phi, chol, white, p, v, out):
    """x_{i+1} = Φ·x_i + L·ξ_i (ξ ~ N(0, I₂)); out[i] = p at sample i."""
    for i in range(out.shape[0]):
        out[i] = p
        e0 = white[i, 0]
        e1 = white[i, 1]
        w0 = chol[0, 0] * e0
        w1 = chol[1, 0] * e0 + chol[1, 1] * e1
        p_next = phi[0, 0] * p + phi[0, 1] * v + w0
        v = phi[1, 0] * p + phi[1, 1] * v + w1
        p = p_next
    return p, v


def thermal_record(
    *,
    f0_hz: float,
    q: float,
    spring_constant_n_per_m: float,
    temperature_k: float,
    sample_rate_hz: float,
    duration_s: float,
    noise_nm: float = 0.0,
    seed: int = 0,
    deflection_units: str = "nm",
) -> Capture:
    """A thermal-noise time record: the first mode driven by white thermal force, sampled exactly.

    The mode, per unit mass, p̈ + (ω0/Q)ṗ + ω0²p = w(t), with white force
    noise E[w(t)w(s)] = q_c·δ(t − s).  Its stationary variance is
    ⟨p²⟩ = q_c·Q/(2ω0³), and equipartition, k⟨p²⟩ = k_B·T, fixes
    q_c = 2k_B·T·ω0³/(k·Q).  The state x = (p, ṗ) is sampled exactly: over a
    sample period T, x_{i+1} = Φx_i + w_i with Φ = e^{AT} and w_i ~ N(0, Q_d),
    Q_d = ∫₀ᵀ e^{As} G q_c Gᵀ e^{Aᵀs} ds by Van Loan's matrix exponential, so no
    integration error enters at any rate; the start is drawn from the
    stationary distribution (⟨p²⟩ = k_B·T/k, ⟨ṗ²⟩ = ω0²·k_B·T/k).  White
    measurement noise of rms ``noise_nm`` is added.  Channel ``deflection``
    only (no drive); metadata carries f0, Q, k and T.
    """
    from scipy.linalg import expm

    if deflection_units not in _DEFLECTION_SCALE:
        raise ValueError(f"deflection_units={deflection_units!r} must be one of {sorted(_DEFLECTION_SCALE)}")
    w0 = 2.0 * np.pi * f0_hz
    period = 1.0 / sample_rate_hz
    variance_nm2 = _K_B * temperature_k / spring_constant_n_per_m * 1e18
    q_c = 2.0 * variance_nm2 * w0**3 / q  # nm²/s³
    a = np.array([[0.0, 1.0], [-w0 * w0, -w0 / q]])
    van_loan = np.zeros((4, 4))
    van_loan[:2, :2] = -a * period
    van_loan[:2, 2:] = np.array([[0.0, 0.0], [0.0, q_c]]) * period
    van_loan[2:, 2:] = a.T * period
    e = expm(van_loan)
    phi = e[2:, 2:].T
    q_d = phi @ e[:2, 2:]
    q_d = 0.5 * (q_d + q_d.T)
    chol = np.linalg.cholesky(q_d)
    n = int(round(duration_s * sample_rate_hz))
    rng = np.random.default_rng(seed)
    p0 = math.sqrt(variance_nm2) * rng.standard_normal()
    v0 = w0 * math.sqrt(variance_nm2) * rng.standard_normal()
    clean = np.empty(n)
    _ar_state(phi, chol, rng.standard_normal((n, 2)), p0, v0, clean)
    measured = clean + noise_nm * rng.standard_normal(n)
    metadata = {
        "scenario": "reference_sim thermal record",
        "simulator": "tests/reference_sim.py (independent of afmtool)",
        "cantilever": {"f0_hz": float(f0_hz), "q": float(q), "spring_constant_n_per_m": float(spring_constant_n_per_m)},
        "thermal": {"temperature_k": float(temperature_k)},
        "noise": {"measurement_noise_nm": float(noise_nm)},
    }
    return Capture(float(sample_rate_hz), {"deflection": measured * _DEFLECTION_SCALE[deflection_units]},
                   {"deflection": deflection_units}, {"deflection_clean": clean}, metadata)
