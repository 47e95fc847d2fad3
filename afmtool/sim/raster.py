"""Scenario ``raster``: a closed-loop tapping-mode scan (thesis ch. 2).

One numba kernel steps, per sample period T = 1/fs, everything an
amplitude-feedback AFM runs:

* the cantilever of eq. 2.5 in per-unit-mass form with the piecewise-linear
  tip-sample force of :mod:`afmtool.models.forces` and a thermal
  acceleration η (as in :mod:`afmtool.sim.tapping`),

  .. math:: \\ddot p + (\\omega_0/Q)\\dot p + \\omega_0^2 p = \\omega_0^2 g + F(p, \\dot p; l) + \\eta,

* the z-piezo, a second-order actuator driven by the controller output u,

  .. math:: \\ddot z + (\\omega_p/Q_p)\\dot z + \\omega_p^2 z = \\omega_p^2 u,

  with the separation l(t) = z(t) − h(x(t), y) (nm): z > 0 moves the sample
  away from the tip, h is the topography under the tip (up = toward it);
  both integrated together by RK4 with ``substeps`` steps per sample;
* the instrument, at each sample n, on the measured y(n) = p(t_n) + v(n):
  the lock-in amplitude A(n) (complex demodulation at the drive frequency,
  Butterworth low-pass: the equations of :mod:`afmtool.estimators.lockin`),
  the free-air observer and its window RMS (the shared helpers of
  :mod:`afmtool.estimators.observer`), the reliability index
  index(n) = RMS(n)/ρ_fa and the switching signal s(n) (the comparator of
  :mod:`afmtool.estimators.reliability`), and a PI controller on the
  amplitude error,

  .. math:: e_A(n) = A_{sp} - A(n),\\quad u_I(n) = u_I(n-1) + K_I T e_A(n),\\quad u(n) = u_I(n) + K_P e_A(n),

  whose gains (K_P, K_I) are the low pair, the high pair, or — in
  ``switching`` mode — the high pair while s(n) = 1 (probe loss) and the
  low pair otherwise (§2.4, Fig. 2.1).  By default (``switch_rule =
  "loss-approaching"``) the high pair also needs e_A < 0, the error of a
  tip that is off the sample and must be approached: after the tip is
  crushed on a rising edge it can ring down free of the sample with an
  amplitude below the set point, the index rightly reads "no interaction",
  and a high gain would then retract the sample and launch the tip into a
  long loss (``switch_rule = "loss"`` is the thesis's rule as written).
  The integrator carries the piezo position, so a switch of K_I changes the
  rate, never the position, and at a switch of K_P the integrator takes up
  the change of the proportional term (bumpless transfer: u is continuous).

The controller output u is held over each sample period (the FPGA's DAC).
The dither g reaches the plant as a continuous signal evaluated at every RK4
stage (``drive_hold="continuous"``, the default: a function generator) or
held over each sample period (``"zoh"``: a DAC at the sample rate, as on the
thesis's FPGA); the in-loop observer runs on the free-air model discretised
for that hold (:mod:`afmtool.models.discretisation`), so it fits the
free-air cantilever to the noise either way.

Time line
---------
``free_air_s`` with the sample ``retract_nm`` beyond the free amplitude (the
free-air segment, written to metadata ``free_air``; the in-loop index is
normalised and its thresholds set on it, :func:`~afmtool.estimators.reliability.calibrate_index`),
then ``engage_s`` at the first pixel: the sample approaches at
``engage_rate_nm_per_s`` until the amplitude falls to the set point, and PI
control takes over from there (the integrator starts at the reached z), then
``lines`` raster lines, each a trace then a retrace over ``scan_size_m``
at ``line_rate_hz`` (metadata ``scan`` with ``start_s``); a nonzero
``duration_s`` cuts the capture there.  Lines are ``scan_size_m/pixels_per_line``
apart (square pixels), the first at ``y_offset_m``.

Topographies
------------
``grating``: square pits ``grating_depth_nm`` deep on a ``grating_pitch_m``
square lattice, each half a pitch wide, walls sloped over
``grating_wall_m`` (a calibration grating: 20 nm, 3.5 µm).  ``dna``:
``dna_strands`` straight strands ``dna_height_nm`` high (1.4 nm) with a
Gaussian cross-section of FWHM ``dna_width_m`` (tip-broadened), at
seeded random positions and angles, on a flat surface.  ``flat``: h = 0.

Defaults, and why
-----------------
The cantilever is the AC240 of §2.5 (f0 = 70,720 Hz, Q = 210, k = 2 N/m)
at 500 kHz, driven at f0 with small side lines so that the free-air model
can be identified from the free-air hold (three-sine, side lines at 0.2 of
the main one: the lock-in's beat stays below 0.1 nm).  At Q ≈ 200 the
amplitude falls to the set point under a weak interaction, and the index's
on-sample contrast is about |p − p_fa|·τ_obs/τ_cant over the noise
(:mod:`afmtool.estimators.reliability`), hence a 30 nm free amplitude, a set
point of 0.7·A0 and 0.02 nm of measurement noise (40 fm/√Hz over 250 kHz);
the in-loop observer forgets in one drive period.  The force is the ch. 4
set (short-range attraction with damping, stiff repulsion).  The z-piezo
(15 kHz, Q = 1) stands for a fast z-actuator: a landing after probe loss
indents the sample by about the piezo's lag, v_z/(Q_p·ω_p), so a slow
piezo turns every fast re-approach into a force spike whatever switches
the gain.

Controller gains, tuned as §2.4-2.5 has it.  The low pair (K_I = 600/s,
K_P = 0.1) is gentle on the sample and slow enough to lose the grating's
pits at 4-12 Hz.  The high pair is tuned from the loop's stability limit,
in the manner of Ziegler and Nichols: along (K_I, K_P) = s·(1500/s, 0.5)
the loop on a flat sample is stable up to s ≈ 2.3 and oscillates in a limit
cycle (z rms ≈ 0.4 nm) from s ≈ 2.4 (the ultimate gain); the default s = 1
is 0.43 of it (Ziegler-Nichols PI: 0.45), which approaches about 2.5 times
faster than the low pair after probe loss and rings on the rising edges.
The ratio K_P/K_I = 1/3000 s puts the PI zero near the amplitude's own
pole 1/τ = ω0/2Q, so the pair winds up little while the tip is pressed on a
rising edge (an integral-dominated pair with the same approach rate, e.g.
K_I = 3000/s with K_P = 0.1, overshoots after each rising edge and loses
more than the low pair at 12 Hz and above).  Nearer the limit (s ≥ 1.2)
the high gain's ringing keeps the tip in light, intermittent contact, which
the reliability index reads as probe loss (the index's per-event precision
on the ch. 2 captures falls below 0.95), so the default stays at the
Ziegler-Nichols margin.  At the top of each rising edge the constant high
gain overshoots and pulls the sample off the tip (the amplitude grows back
only at the free-air rate ω0/2Q of eq. 2.1 while the integrator keeps
retracting); the switching gain, on its low pair there, does not.  That
lift-off is the high gain's edge ringing of §2.5, not probe loss in the
sense of §2.2 (the surface falling away), and ``afmtool theory
controllers`` reports the two apart (:func:`afmtool.analyses.controllers.classify_loss`,
docs/ch2_table.json): in probe loss the high gain is the least of the
three, the switching gain a drive period or so per pit behind it.

Truth
-----
``topography_nm`` (h under the tip at t_n), ``contact`` (uint8, p + l < d at
a step boundary in the sample period, as in ``tapping``), ``force_n`` (the
tip-sample force of largest magnitude over the period's step boundaries, N,
positive = repulsive), ``separation_nm`` (l at t_n) and ``switch`` (uint8,
the in-loop switching signal).  Channels: ``dither`` (V), ``deflection``
(nm), ``z_piezo`` (nm, the controller output u: the height image) and
``amplitude`` (nm, the in-loop lock-in amplitude).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit

from afmtool.config.samples import sample_count
from afmtool.errors import ConfigError
from afmtool.estimators.observer import (
    ObserverDesign,
    _predict,
    _window_block_end,
    _window_push,
    _window_resync,
    _window_rms,
)
from afmtool.estimators.reliability import (
    FreeAirCalibration,
    calibrate_index,
    hysteresis_step,
    index_window,
    settle_samples,
)
from afmtool.io.capture import ChannelSpec
from afmtool.jit import JIT_OPTIONS
from afmtool.models.cantilever import Cantilever
from afmtool.models.forces import THESIS_FORCE_SETS, PiecewiseLinearForce, force_per_mass
from afmtool.models.free_air import FreeAirModel
from afmtool.sim import SimulatedCapture, param, register_scenario, validate_parameters
from afmtool.sim.excitation import MultiSine, sine, three_sine
from afmtool.sim.tapping import thermal_accel_rms

__all__ = [
    "CONTROLLERS",
    "TOPOGRAPHIES",
    "RasterParams",
    "RasterRun",
    "run_raster",
    "simulate_raster",
    "capture_from_run",
    "topography_nm",
]

#: Controller modes: constant low gain, constant high gain, or switched by the index.
CONTROLLERS = ("low", "high", "switching")
#: Sample surfaces.
TOPOGRAPHIES = ("grating", "dna", "flat")
_CONTROLLER_CODE = {"low": 0, "high": 1, "switching": 2}
_DEFAULT_CHUNK_SAMPLES = 1 << 16
#: The lock-in oscillator is recomputed exactly every this many samples, as in
#: :mod:`afmtool.estimators.lockin`, so the in-loop amplitude equals LockIn's.
_LOCKIN_RESYNC = 4096
#: Residual of the observer's start-up transient below which the in-loop
#: calibration starts (relative to the initial error).
_SETTLE_RESIDUAL = 1e-6


@dataclass(frozen=True)
class RasterParams:
    """Parameters of the ``raster`` scenario (defaults: the ch. 2 grating experiment, reduced)."""

    controller: str = param("switching", "z-controller gains: low, high, or switched by the index", "",
                            choices=CONTROLLERS)
    topography: str = param("grating", "sample surface", "", choices=TOPOGRAPHIES)
    line_rate_hz: float = param(8.0, "lines per second (a trace and a retrace each)", "Hz",
                                minimum=0, exclusive_minimum=True)
    lines: int = param(4, "raster lines", "", minimum=1)
    duration_s: float = param(0.0, "capture length; 0 = through the last line (shorter cuts the run)", "s",
                              minimum=0)
    pixels_per_line: int = param(64, "pixels per line (images; line spacing = scan_size_m/pixels)", "", minimum=1)
    scan_size_m: float = param(10e-6, "scan length along x", "m", minimum=0, exclusive_minimum=True)
    y_offset_m: float = param(1.3e-6, "y of the first line (the grating's first pit row spans 0.875-2.625 um)", "m")
    sample_rate_hz: float = param(500e3, "sample rate of the instrument and recorded channels", "Hz",
                                  minimum=0, exclusive_minimum=True)
    substeps: int = param(8, "RK4 steps per sample period", "", minimum=1)
    free_air_s: float = param(0.01, "free-air hold before the engage (the free_air segment)", "s",
                              minimum=0, exclusive_minimum=True)
    engage_s: float = param(0.012, "engage at the first pixel: approach until A <= A_sp, then PI", "s",
                            minimum=0, exclusive_minimum=True)
    engage_rate_nm_per_s: float = param(5000.0, "engage: approach rate of the sample", "nm/s",
                                        minimum=0, exclusive_minimum=True)
    retract_nm: float = param(30.0, "free-air hold: sample this far beyond the free amplitude", "nm",
                              minimum=0, exclusive_minimum=True)
    f0_hz: float = param(70720.0, "free-air resonant frequency f0 (AC240, ch. 2)", "Hz",
                         minimum=0, exclusive_minimum=True)
    q: float = param(210.0, "free-air quality factor Q", "", minimum=0.5, exclusive_minimum=True)
    spring_constant_n_per_m: float = param(2.0, "spring constant k (thermal noise, forces in N)", "N/m",
                                           minimum=0, exclusive_minimum=True)
    drive: str = param("three-sine", "dither: a sine at f0, or with small side lines for identification", "",
                       choices=("sine", "three-sine"))
    drive_hold: str = param("continuous", "how the plant sees the dither: a continuous signal, or held per sample "
                            "(a DAC at the sample rate)", "", choices=("continuous", "zoh"))
    sideband_offset_hz: float = param(6000.0, "three-sine side-line offset", "Hz", minimum=0, exclusive_minimum=True)
    sideband_scale: float = param(0.2, "three-sine side-line / main-line amplitude", "", minimum=0)
    amplitude_nm: float = param(30.0, "free amplitude A0 at the drive frequency", "nm", minimum=0,
                                exclusive_minimum=True)
    dither_gain_nm_per_v: float = param(1.0, "forcing g per volt of dither", "nm/V", minimum=0,
                                        exclusive_minimum=True)
    setpoint_ratio: float = param(0.7, "amplitude set point A_sp / A0", "", minimum=0, maximum=1,
                                  exclusive_minimum=True)
    force_set: str = param("ch4-default", "tip-sample force (thesis sets, f0 80 kHz per unit mass)", "",
                           choices=tuple(THESIS_FORCE_SETS))
    ki_low_per_s: float = param(600.0, "low gain: integral gain K_I (nm of z per nm of amplitude error per s)",
                                "1/s", minimum=0)
    kp_low: float = param(0.1, "low gain: proportional gain K_P", "", minimum=0)
    ki_high_per_s: float = param(1500.0, "high gain: integral gain K_I (0.43 of the on-sample stability limit)", "1/s",
                                 minimum=0)
    kp_high: float = param(0.5, "high gain: proportional gain K_P (0.43 of the on-sample stability limit)", "",
                           minimum=0)
    switch_rule: str = param(
        "loss-approaching", "switching: high gain while the index reads loss and A > A_sp, or whenever it reads loss",
        "", choices=("loss-approaching", "loss"),
    )
    piezo_f0_hz: float = param(15000.0, "z-piezo resonance", "Hz", minimum=0, exclusive_minimum=True)
    piezo_q: float = param(1.0, "z-piezo quality factor", "", minimum=0.5, exclusive_minimum=True)
    lockin_lowpass_hz: float = param(0.0, "lock-in low-pass corner; 0 = min(f0/10, side-line offset/2)", "Hz",
                                     minimum=0)
    lockin_order: int = param(4, "lock-in Butterworth order", "", minimum=1)
    observer_decay_cycles: float = param(1.0, "in-loop observer: error time constant, drive periods", "",
                                         minimum=0, exclusive_minimum=True)
    window_periods: float = param(1.0, "index window, drive periods", "", minimum=0, exclusive_minimum=True)
    index_on: float = param(0.0, "loss declared when the index falls below this; 0 = automatic", "", minimum=0)
    index_off: float = param(0.0, "loss ends when the index rises above this; 0 = automatic", "", minimum=0)
    grating_depth_nm: float = param(20.0, "grating: pit depth", "nm", minimum=0)
    grating_pitch_m: float = param(3.5e-6, "grating: pitch", "m", minimum=0, exclusive_minimum=True)
    grating_wall_m: float = param(100e-9, "grating: lateral width of the sloped pit walls", "m", minimum=0)
    dna_height_nm: float = param(1.4, "dna: strand height", "nm", minimum=0)
    dna_width_m: float = param(10e-9, "dna: strand FWHM (tip-broadened)", "m", minimum=0, exclusive_minimum=True)
    dna_strands: int = param(6, "dna: number of strands", "", minimum=0)
    temperature_k: float = param(300.0, "thermal-noise temperature (0 disables)", "K", minimum=0)
    measurement_noise_nm: float = param(0.02, "rms white noise on the measured deflection", "nm", minimum=0)

    def __post_init__(self) -> None:
        validate_parameters(self)
        nyquist = self.sample_rate_hz / 2
        if self.f0_hz >= nyquist:
            raise ConfigError(f"f0_hz={self.f0_hz!r} must be below sample_rate_hz/2 = {nyquist:g}")
        if self.drive == "three-sine":
            if self.sideband_offset_hz >= self.f0_hz:
                raise ConfigError(f"sideband_offset_hz={self.sideband_offset_hz!r} must be below f0_hz")
            if self.f0_hz + self.sideband_offset_hz >= nyquist:
                raise ConfigError("f0_hz + sideband_offset_hz must be below sample_rate_hz/2")
        if self.lockin_lowpass_hz >= nyquist:
            raise ConfigError(f"lockin_lowpass_hz={self.lockin_lowpass_hz!r} must be below sample_rate_hz/2")
        if (self.index_on == 0) != (self.index_off == 0):
            raise ConfigError("index_on and index_off must be given together (or both 0 = automatic)")
        if self.index_on and not self.index_on < self.index_off:
            raise ConfigError(f"index_on={self.index_on!r} must be below index_off={self.index_off!r}")
        if self.free_air_s * self.sample_rate_hz < 200:
            raise ConfigError(f"free_air_s={self.free_air_s!r} gives fewer than 200 free-air samples")

    # ------------------------------------------------------------------ derived

    @property
    def setpoint_nm(self) -> float:
        """A_sp, nm."""
        return self.setpoint_ratio * self.amplitude_nm

    @property
    def line_period_s(self) -> float:
        return 1.0 / self.line_rate_hz

    @property
    def scan_start_s(self) -> float:
        return self.free_air_s + self.engage_s

    @property
    def scan_end_s(self) -> float:
        """End of the last line, s."""
        return self.scan_start_s + self.lines * self.line_period_s

    @property
    def capture_s(self) -> float:
        """Length of the capture: ``duration_s``, or through the last line when it is 0, s."""
        return self.duration_s or self.scan_end_s

    @property
    def line_spacing_m(self) -> float:
        return self.scan_size_m / self.pixels_per_line

    def cantilever(self) -> Cantilever:
        return Cantilever(self.f0_hz, self.q, self.spring_constant_n_per_m)

    def force(self) -> PiecewiseLinearForce:
        return THESIS_FORCE_SETS[self.force_set]

    def lowpass_hz(self) -> float:
        """The lock-in corner: given, or :func:`~afmtool.estimators.lockin.default_lowpass_hz`."""
        from afmtool.estimators.lockin import default_lowpass_hz

        if self.lockin_lowpass_hz:
            return self.lockin_lowpass_hz
        return default_lowpass_hz(self.f0_hz, self.sideband_offset_hz if self.drive == "three-sine" else None)

    def dither(self) -> tuple[MultiSine, float]:
        """The dither (V) and its main-line amplitude (V) for a free amplitude ``amplitude_nm`` at f0.

        The amplitude is ``amplitude_nm / (gain·|G(f0)|)``, with a held
        dither (``drive_hold="zoh"``) also divided by sinc(f0/fs): the
        staircase's fundamental is the sine scaled by sinc(f0/fs).
        """
        response = abs(complex(self.cantilever().frequency_response(self.f0_hz)))
        if self.drive_hold == "zoh":
            response *= np.sinc(self.f0_hz / self.sample_rate_hz)
        amplitude_v = self.amplitude_nm / (self.dither_gain_nm_per_v * response)
        if self.drive == "sine":
            return sine(amplitude_v, self.f0_hz), amplitude_v
        return three_sine(amplitude_v, self.f0_hz, self.sideband_offset_hz, self.sideband_scale), amplitude_v

    def free_air_model(self) -> FreeAirModel:
        """The true free-air model (dither V to deflection nm), as the in-loop observer uses it.

        Discretised at the sample rate for the way the plant sees the dither
        (:mod:`afmtool.models.discretisation`), so that ``probeloss --model``
        runs the in-loop observer exactly.
        """
        from afmtool.models.discretisation import discrete_denominator, sampled_numerator

        fs = self.sample_rate_hz
        unit = sampled_numerator(self.f0_hz, self.q, fs, self.drive_hold, match_hz=self.f0_hz)
        gain = self.dither_gain_nm_per_v
        return FreeAirModel(
            self.f0_hz, self.q, gain, source="given", sample_rate_hz=fs,
            numerator=tuple(gain * a for a in unit),
            denominator=tuple(float(b) for b in discrete_denominator(self.f0_hz, self.q, fs)),
        )


# --------------------------------------------------------------------------- topography


def _ramp(distance_inside, wall):
    """0 outside, rising linearly to 1 over ``wall`` inside (a step when wall = 0)."""
    if wall <= 0:
        return (distance_inside > 0).astype(np.float64)
    return np.clip(distance_inside / wall, 0.0, 1.0)


def _dna_strands(params: RasterParams, seed: int) -> np.ndarray:
    """(n, 3): a point (x, y) on each strand (m) and its direction angle (rad), seeded."""
    rng = np.random.default_rng([seed, 0x0D4A])
    height = params.lines * params.line_spacing_m
    xs = rng.uniform(0.1, 0.9, params.dna_strands) * params.scan_size_m
    ys = params.y_offset_m + rng.uniform(0.0, 1.0, params.dna_strands) * height
    angles = rng.uniform(0.15 * math.pi, 0.85 * math.pi, params.dna_strands)  # never parallel to x
    return np.column_stack([xs, ys, angles])


def topography_nm(params: RasterParams, x_m: np.ndarray, y_m: np.ndarray, strands: np.ndarray | None = None):
    """Height h(x, y) of the sample surface, nm (up = toward the tip).

    Parameters
    ----------
    params : RasterParams
        Topography kind and its parameters.
    x_m, y_m : array_like
        Lateral positions, m (broadcast).
    strands : numpy.ndarray, optional
        The ``dna`` strands, from the scenario's seed.
    """
    x = np.asarray(x_m, dtype=np.float64)
    y = np.asarray(y_m, dtype=np.float64)
    if params.topography == "flat":
        return np.zeros(np.broadcast(x, y).shape)
    if params.topography == "grating":
        pitch = params.grating_pitch_m
        quarter = 0.25 * pitch
        # distance inside the pit along x and y (pit: [pitch/4, 3·pitch/4) in each)
        fx = np.mod(x, pitch)
        fy = np.mod(y, pitch)
        inside_x = np.minimum(fx - quarter, 3 * quarter - fx)
        inside_y = np.minimum(fy - quarter, 3 * quarter - fy)
        depth = np.minimum(_ramp(inside_x, params.grating_wall_m), _ramp(inside_y, params.grating_wall_m))
        return -params.grating_depth_nm * depth
    sigma = params.dna_width_m / (2.0 * math.sqrt(2.0 * math.log(2.0)))
    out = np.zeros(np.broadcast(x, y).shape)
    for x0, y0, angle in strands if strands is not None else ():
        # distance from the line through (x0, y0) with direction angle
        distance = (x - x0) * math.sin(angle) - (y - y0) * math.cos(angle)
        out = np.maximum(out, params.dna_height_nm * np.exp(-0.5 * (distance / sigma) ** 2))
    return out


def _scan_position(params: RasterParams, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tip position (x, y), m, at times ``t_s``: at the first pixel until the scan starts."""
    elapsed = np.maximum(np.asarray(t_s, dtype=np.float64) - params.scan_start_s, 0.0)
    phase = elapsed / params.line_period_s
    line = np.minimum(np.floor(phase), params.lines - 1)
    fraction = np.where(phase >= params.lines, 1.0, phase - line)
    position = np.where(fraction < 0.5, 2.0 * fraction, 2.0 - 2.0 * fraction)
    return position * params.scan_size_m, params.y_offset_m + line * params.line_spacing_m


# --------------------------------------------------------------------------- kernel


@njit(**JIT_OPTIONS)
def _rotor_at(n, cycles_per_sample):
    """The lock-in reference e^{−j2πfn/fs} exactly as LockIn's kernel holds it at sample n."""
    two_pi = 2.0 * math.pi
    step = complex(math.cos(two_pi * cycles_per_sample), -math.sin(two_pi * cycles_per_sample))
    synced = n - n % _LOCKIN_RESYNC
    frac = (synced * cycles_per_sample) % 1.0
    rotor = complex(math.cos(two_pi * frac), -math.sin(two_pi * frac))
    for _ in range(n - synced):
        rotor *= step
    return rotor


@njit(**JIT_OPTIONS)
def _derivatives(p, v, z, w, g_acc, eta, u, h, w0q, w0sq, wpq, wpsq, d, wa2, wb2, ca, cb):
    """(ṗ, v̇, ż, ẇ) of the cantilever and the piezo at one RK4 stage; also F/m."""
    force = force_per_mass(p, v, z - h, d, wa2, wb2, ca, cb)
    # p̈ = ω0²g + η − ω0²p − (ω0/Q)ṗ + F/m
    a = g_acc + eta - w0sq * p - w0q * v + force
    # z̈ = ωp²(u − z) − (ωp/Qp)ż
    b = wpsq * (u - z) - wpq * w
    return a, b, force


@njit(**JIT_OPTIONS)
def _plant_period(plant, g_row, eta, u, h_half, base, nsub, dt, w0q, w0sq, wpq, wpsq, d, wa2, wb2, ca, cb):
    """Integrate one sample period with ``nsub`` RK4 steps; η and u held.

    ``g_row[j]`` is the dither forcing ω0²·gain·g at t_n + j·dt/2
    (j = 0 … 2·nsub): the continuous dither at each stage time, or the
    sample's value throughout for a held one.

    Returns (contact, force extreme per unit mass, closest tip-surface
    separation t_s = p + l, nm) over the step boundaries.
    """
    half = 0.5 * dt
    sixth = dt / 6.0
    p, v, z, w = plant[0], plant[1], plant[2], plant[3]
    touched = 0
    extreme = 0.0
    closest = math.inf
    for k in range(nsub):
        j = base + 2 * k
        h0 = h_half[j]
        h1 = h_half[j + 1]
        h2 = h_half[j + 2]
        ts = p + z - h0
        closest = min(closest, ts)
        if ts < d:
            touched = 1
        # k1 = f(t, y)
        a1, b1, f1 = _derivatives(p, v, z, w, g_row[2 * k], eta, u, h0, w0q, w0sq, wpq, wpsq, d, wa2, wb2, ca, cb)
        if abs(f1) > abs(extreme):
            extreme = f1
        # k2 = f(t + h/2, y + h/2·k1)
        p2, v2, z2, w2 = p + half * v, v + half * a1, z + half * w, w + half * b1
        a2, b2, _ = _derivatives(p2, v2, z2, w2, g_row[2 * k + 1], eta, u, h1, w0q, w0sq, wpq, wpsq, d, wa2, wb2, ca, cb)
        # k3 = f(t + h/2, y + h/2·k2)
        p3, v3, z3, w3 = p + half * v2, v + half * a2, z + half * w2, w + half * b2
        a3, b3, _ = _derivatives(p3, v3, z3, w3, g_row[2 * k + 1], eta, u, h1, w0q, w0sq, wpq, wpsq, d, wa2, wb2, ca, cb)
        # k4 = f(t + h, y + h·k3)
        p4, v4, z4, w4 = p + dt * v3, v + dt * a3, z + dt * w3, w + dt * b3
        a4, b4, _ = _derivatives(p4, v4, z4, w4, g_row[2 * k + 2], eta, u, h2, w0q, w0sq, wpq, wpsq, d, wa2, wb2, ca, cb)
        # y += h/6·(k1 + 2k2 + 2k3 + k4)
        p = p + sixth * (v + 2.0 * v2 + 2.0 * v3 + v4)
        v = v + sixth * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
        z = z + sixth * (w + 2.0 * w2 + 2.0 * w3 + w4)
        w = w + sixth * (b1 + 2.0 * b2 + 2.0 * b3 + b4)
    plant[0], plant[1], plant[2], plant[3] = p, v, z, w
    return touched, extreme, closest


@njit(**JIT_OPTIONS)
def _demodulate(y, rotor, sos, zi):
    """One lock-in sample: mix with the rotor, run the SOS cascade (DF2T); returns the filtered value."""
    v = y * rotor
    for s in range(sos.shape[0]):
        out = sos[s, 0] * v + zi[0, s, 0]
        zi[0, s, 0] = sos[s, 1] * v - sos[s, 4] * out + zi[0, s, 1]
        zi[0, s, 1] = sos[s, 2] * v - sos[s, 5] * out
        v = out
    return v


@njit(**JIT_OPTIONS)
def _raster_kernel(  # noqa: PLR0915 - numba kernel: one scalar recursion
    start, dither, g_rows, eta, noise, h_half, gain, nsub, dt, period,
    w0q, w0sq, wpq, wpsq, d, wa2, wb2, ca, cb,
    obs, xhat, ring, sums, counters,
    cal, sos, zi, cycles_per_sample,
    ctl, schedule, plant, carried,
    out_y, out_u, out_amp, out_rms, out_switch, out_contact, out_force, out_sep, out_gap,
):
    """Closed loop over one chunk of samples [start, start + T) (module docstring).

    ``dither`` holds g(t_n) (what the ADC records and the observer sees);
    ``g_rows[i]`` the forcing ω0²·gain·g over sample period i at the RK4
    half-step times (see :func:`_plant_period`).

    ``obs`` = [a2, b1, b0, bb1, bb2, l1, l2] (observer model and gain);
    ``xhat``, ``ring``, ``sums``, ``counters`` the observer's carried state
    (the layout of :class:`~afmtool.estimators.observer.BankState`, one row);
    ``cal`` = [1/ρ_fa (NaN before calibration), on, off];
    ``ctl`` = [A_sp, K_I low, K_P low, K_I high, K_P high, mode, high gain in either direction];
    ``schedule`` = [first approach sample, first sample the amplitude is trusted, z retracted,
    approach per sample]; ``plant`` = [p, v, z, ż]; ``carried`` = [u_I, u, switch, engaged, K_P in use].
    """
    n_samples = dither.shape[0]
    width = ring.shape[1]
    a2, b1, b0, bb1, bb2, l1, l2 = obs[0], obs[1], obs[2], obs[3], obs[4], obs[5], obs[6]
    inv_level, on, off = cal[0], cal[1], cal[2]
    setpoint, ki_lo, kp_lo, ki_hi, kp_hi, mode = ctl[0], ctl[1], ctl[2], ctl[3], ctl[4], ctl[5]
    any_direction = ctl[6] != 0.0
    n_engage, n_lockin, z_far, approach_step = schedule[0], schedule[1], schedule[2], schedule[3]
    u_int, u, switch, engaged = carried[0], carried[1], int(carried[2]), int(carried[3])
    kp_prev = carried[4]
    two_pi = 2.0 * math.pi
    step = complex(math.cos(two_pi * cycles_per_sample), -math.sin(two_pi * cycles_per_sample))
    rotor = _rotor_at(start, cycles_per_sample)
    pos = counters[0]
    filled = counters[1]
    since = counters[2]
    inv_count = 1.0 / filled if filled > 0 else 0.0
    begin = 0
    while begin < n_samples:
        stop = _window_block_end(begin, n_samples, since)
        for i in range(begin, stop):
            n = start + i
            g_n = dither[i]
            # measured deflection y(n) = p(t_n) + v(n)
            y = plant[0] + noise[i]
            out_y[i] = y
            # observer (eq. 2.10 sampled) and its window RMS
            e, x1, x2 = _predict(xhat[0, 0], xhat[0, 1], y - a2 * g_n, g_n, b1, b0, bb1, bb2, l1, l2)
            xhat[0, 0] = x1
            xhat[0, 1] = x2
            if filled < width:
                filled += 1
                inv_count = 1.0 / filled
            rms = _window_rms(_window_push(ring, sums, 0, pos, e * e), inv_count)
            pos += 1
            if pos == width:
                pos = 0
            out_rms[i] = rms
            # switching signal on the index (NaN before calibration keeps s = 0)
            switch = hysteresis_step(rms * inv_level, switch, on, off)
            out_switch[i] = switch
            # lock-in amplitude A(n) = 2|LP[y e^{−jωn}]|
            if n % _LOCKIN_RESYNC == 0:
                frac = (n * cycles_per_sample) % 1.0
                rotor = complex(math.cos(two_pi * frac), -math.sin(two_pi * frac))
            amp = 2.0 * abs(_demodulate(y, rotor, sos, zi))
            rotor *= step
            out_amp[i] = amp
            # z-controller: hold, approach at a constant rate until A ≤ A_sp, then PI on the amplitude error
            if n < n_engage:
                u = z_far
            elif engaged == 0:
                u = u - approach_step
                u_int = u
                if amp <= setpoint and n >= n_lockin:
                    engaged = 1
            else:
                # e_A = A_sp − A;  u_I += K_I·T·e_A;  u = u_I + K_P·e_A
                err = setpoint - amp
                # switching: the high pair while s = 1 (and, by default, the error calls for an approach, A > A_sp)
                high = mode == 1 or (mode == 2 and switch == 1 and (err < 0.0 or any_direction))
                ki = ki_hi if high else ki_lo
                kp = kp_hi if high else kp_lo
                # bumpless transfer: at a switch of K_P the integrator takes up the change of the
                # proportional term, so u stays continuous (u_I + K_P·e is the same with either K_P)
                u_int += (kp_prev - kp) * err + ki * period * err
                kp_prev = kp
                u = u_int + kp * err
            out_u[i] = u
            out_sep[i] = plant[2] - h_half[2 * nsub * i]
            touched, extreme, closest = _plant_period(
                plant, g_rows[i], eta[i], u, h_half, 2 * nsub * i, nsub, dt,
                w0q, w0sq, wpq, wpsq, d, wa2, wb2, ca, cb,
            )
            out_contact[i] = touched
            out_force[i] = extreme
            out_gap[i] = closest
        since = _window_resync(ring, sums, since + (stop - begin))
        begin = stop
    counters[0] = pos
    counters[1] = filled
    counters[2] = since
    carried[0] = u_int
    carried[1] = u
    carried[2] = switch
    carried[3] = engaged
    carried[4] = kp_prev


# --------------------------------------------------------------------------- driver


class RasterRun(NamedTuple):
    """Everything one closed-loop run produced, per sample (for tests and the scenario).

    Attributes
    ----------
    params : RasterParams
    deflection_nm, dither_v, z_piezo_nm, amplitude_nm, rms_nm : numpy.ndarray
        Recorded deflection y, dither, controller output u, in-loop lock-in
        amplitude and in-loop innovation window RMS.
    switch, contact : numpy.ndarray of uint8
        In-loop switching signal; truth contact.
    force_n, topography_nm, separation_nm : numpy.ndarray
        Truth: force extreme per period (N), h under the tip (nm), l (nm).
    calibration : FreeAirCalibration or None
        The in-loop index normalisation and thresholds (None when the
        capture ends within the free-air hold).
    design : ObserverDesign
        The in-loop observer.
    window_samples : int
        Its window W.
    closest_nm : numpy.ndarray
        Truth: the closest tip-surface separation t_s = p + l over each
        sample period's RK4 step boundaries, nm (negative = indentation);
        not written to captures.
    """

    params: RasterParams
    deflection_nm: np.ndarray
    dither_v: np.ndarray
    z_piezo_nm: np.ndarray
    amplitude_nm: np.ndarray
    rms_nm: np.ndarray
    switch: np.ndarray
    contact: np.ndarray
    force_n: np.ndarray
    topography_nm: np.ndarray
    separation_nm: np.ndarray
    calibration: FreeAirCalibration | None
    design: ObserverDesign
    window_samples: int
    closest_nm: np.ndarray


def _initial_state(params: RasterParams, excitation: MultiSine) -> tuple[float, float]:
    """Free-air steady state at t = 0; a held dither's fundamental lags T/2, scaled by sinc(f/fs)."""
    fs = params.sample_rate_hz
    freqs = np.asarray(excitation.frequencies_hz)
    hold = np.sinc(freqs / fs) * np.exp(-1j * np.pi * freqs / fs) if params.drive_hold == "zoh" else 1.0
    response = params.dither_gain_nm_per_v * params.cantilever().frequency_response(freqs) * hold
    return excitation.steady_state(response, 0.0)


class _Loop:
    """The kernel's carried state and constants; ``run`` advances it over a range of samples."""

    def __init__(self, params: RasterParams, seed: int) -> None:
        from afmtool.estimators.filters import butterworth_lowpass_sos

        self.params = params
        fs = params.sample_rate_hz
        self.fs = fs
        self.n_total = sample_count(params.capture_s, fs, "capture_s")
        self.n_free = sample_count(params.free_air_s, fs, "free_air_s")
        rng = np.random.default_rng(seed)
        cantilever = params.cantilever()
        self.eta = thermal_accel_rms(cantilever, params.temperature_k, fs) * rng.standard_normal(self.n_total)
        self.noise = params.measurement_noise_nm * rng.standard_normal(self.n_total)
        self.strands = _dna_strands(params, seed) if params.topography == "dna" else None
        self.excitation, self.amplitude_v = params.dither()
        model = params.free_air_model()
        period_samples = fs / params.f0_hz
        self.design = ObserverDesign.from_decay(
            model.denominator_at(fs), model.numerator_at(fs), params.observer_decay_cycles, period_samples
        )
        self.window = index_window(fs, params.f0_hz, params.window_periods)
        a2, a1, a0 = self.design.numerator
        b1, b0 = self.design.denominator
        l1, l2 = self.design.gain
        self.obs = np.array([a2, b1, b0, a1 - a2 * b1, a0 - a2 * b0, l1, l2])
        self.xhat = np.zeros((1, 2))
        self.ring = np.zeros((1, self.window))
        self.sums = np.zeros(1)
        self.counters = np.zeros(3, dtype=np.int64)
        self.cal = np.array([math.nan, 1.0, 2.0])
        # LockIn's own design, so the in-loop amplitude is LockIn.process's to the bit
        self.sos = np.ascontiguousarray(butterworth_lowpass_sos(params.lockin_order, params.lowpass_hz(), fs))
        self.zi = np.zeros((1, self.sos.shape[0], 2), dtype=np.complex128)
        code = _CONTROLLER_CODE[params.controller]
        self.ctl = np.array([params.setpoint_nm, params.ki_low_per_s, params.kp_low, params.ki_high_per_s,
                             params.kp_high, float(code), float(params.switch_rule == "loss")])
        z_far = params.amplitude_nm + params.retract_nm
        # the lock-in has settled long before the approach; its first samples are never trusted
        n_lockin = min(self.n_free, int(math.ceil(10.0 * fs / params.lowpass_hz())))
        self.schedule = np.array([float(self.n_free), float(n_lockin), z_far, params.engage_rate_nm_per_s / fs])
        p0, v0 = _initial_state(params, self.excitation)
        self.plant = np.array([p0, v0, z_far, 0.0])
        self.carried = np.array([z_far, z_far, 0.0, 0.0, params.kp_low if code != 1 else params.kp_high])
        wp = 2.0 * math.pi * params.piezo_f0_hz
        w0 = cantilever.omega0_rad_s
        self.consts = (w0 / params.q, w0 * w0, wp / params.piezo_q, wp * wp)
        self.mass_kg = params.spring_constant_n_per_m / (w0 * w0)
        self.out = {
            "y": np.empty(self.n_total), "u": np.empty(self.n_total), "amp": np.empty(self.n_total),
            "rms": np.empty(self.n_total), "switch": np.empty(self.n_total, dtype=np.uint8),
            "contact": np.empty(self.n_total, dtype=np.uint8), "force": np.empty(self.n_total),
            "sep": np.empty(self.n_total), "h": np.empty(self.n_total), "dither": np.empty(self.n_total),
            "gap": np.empty(self.n_total),
        }

    def run(self, first: int, last: int, chunk_samples: int) -> None:
        params = self.params
        nsub = params.substeps
        per_sample = 2 * nsub
        half_step = 1.0 / (per_sample * self.fs)
        w0q, w0sq, wpq, wpsq = self.consts
        for start in range(first, last, chunk_samples):
            stop = min(start + chunk_samples, last)
            t_half = np.arange(per_sample * start, per_sample * stop + 1) * half_step
            x, yy = _scan_position(params, t_half)
            h_half = topography_nm(params, x, yy, self.strands)
            t = np.arange(start, stop) / self.fs
            dither = self.excitation(t)
            gain = params.dither_gain_nm_per_v
            if params.drive_hold == "zoh":
                # (gain·g)·ω0², in the order the held forcing has always been formed
                g_rows = np.repeat((gain * dither * w0sq)[:, None], per_sample + 1, axis=1)
            else:
                # the continuous dither at every RK4 stage time of each sample period
                offsets = np.arange(per_sample + 1) * half_step
                stages = self.excitation((t[:, None] + offsets[None, :]).ravel()).reshape(t.size, -1)
                g_rows = gain * stages * w0sq
            o = self.out
            sl = slice(start, stop)
            _raster_kernel(
                start, dither, np.ascontiguousarray(g_rows), self.eta[sl], self.noise[sl], h_half, params.dither_gain_nm_per_v, nsub,
                1.0 / (nsub * self.fs), 1.0 / self.fs, w0q, w0sq, wpq, wpsq, *params.force().as_args(),
                self.obs, self.xhat, self.ring, self.sums, self.counters,
                self.cal, self.sos, self.zi, params.f0_hz / self.fs,
                self.ctl, self.schedule, self.plant, self.carried,
                o["y"][sl], o["u"][sl], o["amp"][sl], o["rms"][sl], o["switch"][sl], o["contact"][sl],
                o["force"][sl], o["sep"][sl], o["gap"][sl],
            )
            o["h"][sl] = h_half[:-1:per_sample]
            o["dither"][sl] = dither

    def calibrate(self) -> FreeAirCalibration:
        """Normalise the in-loop index on the free-air hold (shared with ``probeloss``)."""
        skip = settle_samples(self.design, self.window, _SETTLE_RESIDUAL)
        if skip >= self.n_free - 16:
            raise ConfigError(f"free_air_s={self.params.free_air_s!r} is too short for the observer to settle")
        given = (self.params.index_on, self.params.index_off) if self.params.index_on else (None, None)
        calibration = calibrate_index(self.out["rms"][skip:self.n_free], on=given[0], off=given[1])
        self.cal[:] = (1.0 / calibration.level, calibration.thresholds.on, calibration.thresholds.off)
        return calibration


def run_raster(params: RasterParams, seed: int, *, chunk_samples: int = _DEFAULT_CHUNK_SAMPLES) -> RasterRun:
    """Run the closed loop; every per-sample signal, in-loop and truth.

    Parameters
    ----------
    params : RasterParams
        Scenario parameters.
    seed : int
        Seed of the thermal and measurement noise and of the DNA strands.
    chunk_samples : int, optional
        Samples per kernel call (bounds the memory of the topography grid;
        the result does not depend on it).

    Returns
    -------
    RasterRun
    """
    if not (isinstance(chunk_samples, int) and chunk_samples >= 1):
        raise ConfigError(f"chunk_samples={chunk_samples!r} must be an integer >= 1")
    loop = _Loop(params, seed)
    n_free = min(loop.n_free, loop.n_total)
    loop.run(0, n_free, chunk_samples)
    calibration = loop.calibrate() if n_free == loop.n_free else None
    n_scan = min(sample_count(params.scan_start_s, params.sample_rate_hz, "scan_start_s"), loop.n_total)
    loop.run(n_free, n_scan, chunk_samples)
    if n_scan < loop.n_total and not loop.carried[3]:
        raise ConfigError(
            f"the tip did not engage within engage_s={params.engage_s!r}; raise engage_s or engage_rate_nm_per_s"
        )
    loop.run(n_scan, loop.n_total, chunk_samples)
    o = loop.out
    return RasterRun(
        params, o["y"], o["dither"], o["u"], o["amp"], o["rms"], o["switch"], o["contact"],
        o["force"] * loop.mass_kg * 1e-9, o["h"], o["sep"], calibration, loop.design, loop.window, o["gap"],
    )


def _metadata(params: RasterParams, run: RasterRun, amplitude_v: float) -> dict:
    calibration = run.calibration
    index = (
        {"index_level_nm": None, "index_on": None, "index_off": None}
        if calibration is None
        else {
            "index_level_nm": float(calibration.level),
            "index_on": float(calibration.thresholds.on),
            "index_off": float(calibration.thresholds.off),
        }
    )
    return {
        "scenario": "raster",
        "cantilever": params.cantilever().to_metadata(),
        "drive": {
            "kind": params.drive,
            "frequency_hz": float(params.f0_hz),
            "amplitude_v": float(amplitude_v),
            "free_amplitude_nm": float(params.amplitude_nm),
            "dither_gain_nm_per_v": float(params.dither_gain_nm_per_v),
            "sideband_offset_hz": float(params.sideband_offset_hz) if params.drive == "three-sine" else 0.0,
            "hold": params.drive_hold,
        },
        "force": {"set": params.force_set, **params.force().to_metadata()},
        "free_air": {"start_s": 0.0, "end_s": float(min(params.free_air_s, params.capture_s))},
        "scan": {
            "lines": int(params.lines),
            "pixels_per_line": int(params.pixels_per_line),
            "scan_size_m": float(params.scan_size_m),
            "line_rate_hz": float(params.line_rate_hz),
            "trace_retrace": True,
            "start_s": float(params.scan_start_s),
        },
        "controller": {
            "mode": params.controller,
            "setpoint_nm": float(params.setpoint_nm),
            "ki_low_per_s": float(params.ki_low_per_s),
            "kp_low": float(params.kp_low),
            "ki_high_per_s": float(params.ki_high_per_s),
            "kp_high": float(params.kp_high),
            "switch_rule": params.switch_rule,
            "piezo_f0_hz": float(params.piezo_f0_hz),
            "piezo_q": float(params.piezo_q),
            "lockin_lowpass_hz": float(params.lowpass_hz()),
            "lockin_order": int(params.lockin_order),
            "observer_decay_cycles": float(params.observer_decay_cycles),
            "window_samples": int(run.window_samples),
            **index,
        },
        "noise": {
            "temperature_k": float(params.temperature_k),
            "measurement_noise_nm": float(params.measurement_noise_nm),
        },
        "integrator": {"method": "rk4", "substeps": int(params.substeps)},
    }


def simulate_raster(params: RasterParams, seed: int) -> SimulatedCapture:
    """Closed-loop tapping-mode raster scan: PI z-control on the lock-in amplitude, switched by the index."""
    return capture_from_run(run_raster(params, seed))


def capture_from_run(run: RasterRun) -> SimulatedCapture:
    """The recorded channels, truth and metadata of a run (what ``simulate raster`` writes)."""
    params = run.params
    _, amplitude_v = params.dither()
    channels = (
        ChannelSpec("dither", "V"),
        ChannelSpec("deflection", "nm"),
        ChannelSpec("z_piezo", "nm"),
        ChannelSpec("amplitude", "nm"),
    )
    data = {
        "dither": run.dither_v,
        "deflection": run.deflection_nm,
        "z_piezo": run.z_piezo_nm,
        "amplitude": run.amplitude_nm,
    }
    truth = {
        "contact": run.contact,
        "force_n": run.force_n.astype(np.float32),
        "topography_nm": run.topography_nm.astype(np.float32),
        "separation_nm": run.separation_nm.astype(np.float32),
        "switch": run.switch,
    }
    return SimulatedCapture(params.sample_rate_hz, channels, data, _metadata(params, run, amplitude_v), truth)


register_scenario("raster", RasterParams, simulate_raster)
