"""Scenario ``thermal-sweep``: the small-signal model of Fig. 6.17 driven by a chirp or stepped sines.

About an operating point (V_R0, V_sub0, t_s0) the lever and its thermal
sensor are linear (§6.6):

* Δp = Γ_p,V·ΔV_esf with Γ_p,V of eq. 6.14 (corrected, see
  :func:`afmtool.models.electrostatic.linearise_actuation`) and
  ΔV_esf = α_R·ΔV_R − ΔV_sub; Δt_s = Δp (the sample does not move);
* ΔI_R = Γ_IR,ts·Δt_s + Γ_IR,VR·ΔV_R + Γ_sp·ΔV_sub, with Γ_IR,ts and
  Γ_IR,VR from eqs. 6.10 and 6.9 (:mod:`afmtool.models.thermal_sensor`:
  C = K_TP·D, H = P0·K_TP′·D, D a 10 dB/decade low-pass) and the direct
  feed-through Γ_sp(s) = C_c·s/(1 + s/ω_c) of a coupling capacitance C_c
  (rising with frequency, Fig. 6.18).

The drive is a repeated linear chirp (:class:`afmtool.sim.sweeps.RepeatedChirp`)
or log-spaced stepped sines whose segments are written to the metadata
(:func:`afmtool.sim.sweeps.log_stepped_sine`).  ``input = "v_sub"`` perturbs V_sub (the Γ sweeps of §6.6.1);
``input = "v_r"`` perturbs V_R (the C(jω), H(jω) sweeps of §6.6.2, where
the electrostatic path α_R·ΔV_R still moves the lever a little).  With
``contact = true`` the tip is held on the sample: t_s0 = 0 and Δt_s = 0,
so only Γ_sp (or Γ_IR,VR) reaches the current, as in the feed-through
measurement of §6.6.1.

Each path is a continuous-time transfer function in zero-pole-gain form,
discretised by the bilinear transform at ``oversample``·fs (frequency
warping (2/T)tan(ωT/2)/ω − 1 < 0.3 % up to fs/2 at the default ×4) and
applied to the drive evaluated analytically at that rate, then sampled at
fs.  White noise is added to ``thermal_current`` (µA) and ``deflection``
(nm).  :meth:`ThermalSweepParams.model` returns the exact continuous-time
responses, the ground truth of every Γ.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import signal

from afmtool.config.samples import sample_count
from afmtool.errors import ConfigError
from afmtool.io.capture import ChannelSpec
from afmtool.models.electrostatic import ActuationSmallSignal, linearise_actuation
from afmtool.models.thermal_sensor import (
    DiffusionLowPass,
    OperatingPoint,
    gamma_ir_ts,
    gamma_ir_vr,
    operating_point,
)
from afmtool.sim import SimulatedCapture, param, validate_parameters
from afmtool.sim.probe import ProbeParams
from afmtool.sim.sweeps import LogSteppedSine, RepeatedChirp, log_stepped_sine

__all__ = ["ThermalSweepParams", "ThermalSweepModel", "Zpk", "simulate_thermal_sweep"]


class Zpk:
    """A continuous-time transfer function k·Π(s − z)/Π(s − p) (s in rad/s)."""

    __slots__ = ("zeros", "poles", "gain")

    def __init__(self, zeros, poles, gain: float) -> None:
        self.zeros = np.asarray(zeros, dtype=np.complex128)
        self.poles = np.asarray(poles, dtype=np.complex128)
        self.gain = float(gain)

    def response(self, frequency_hz) -> np.ndarray:
        s = 2j * np.pi * np.asarray(frequency_hz, dtype=np.float64)
        out = np.full(s.shape, self.gain, dtype=np.complex128)
        for z in self.zeros:
            out = out * (s - z)
        for p in self.poles:
            out = out / (s - p)
        return out

    def scaled(self, factor: float) -> Zpk:
        return Zpk(self.zeros, self.poles, self.gain * factor)

    def filter(self, u: np.ndarray, sample_rate_hz: float) -> np.ndarray:
        """Response to samples ``u`` from rest: bilinear transform, then second-order sections."""
        zd, pd, kd = signal.bilinear_zpk(self.zeros, self.poles, self.gain, sample_rate_hz)
        return signal.sosfilt(signal.zpk2sos(zd, pd, kd), u)


def _feedback_poles(dynamics: DiffusionLowPass, loop_gain: float, sign: float) -> np.ndarray:
    """Roots of P(s) + sign·x0·k_D·N(s): the poles (sign +1) or zeros (−1) of (1 ± x0·D) forms.

    D = k_D·N/P with N, P monic in s.  The polynomial is formed in the
    scaled variable σ = s/ω_c (roots between 1 and a few hundred) so its
    coefficients stay within double precision, then scaled back.
    """
    poles, zeros = dynamics.poles_zeros_rad_s()
    wc = poles[0]
    p_hat, z_hat = poles / wc, zeros / wc
    k_hat = np.prod(p_hat) / np.prod(z_hat)
    p_poly = np.poly(-p_hat)
    n_poly = np.poly(-z_hat)
    total = p_poly.copy()
    total[len(p_poly) - len(n_poly) :] += sign * loop_gain * k_hat * n_poly
    return np.roots(total) * wc


@dataclass(frozen=True)
class ThermalSweepModel:
    """The exact small-signal responses of the ``thermal-sweep`` scenario, in capture units.

    Currents in µA, separations and deflections in nm, voltages in V,
    temperatures in K, powers in W.

    Attributes
    ----------
    operating_point : OperatingPoint
        The sensor at (V_R0, t_s0), SI units.
    actuation : ActuationSmallSignal
        Γ_p,V of eq. 6.14 at (V_esf0, ℓ_s0), m/V.
    deflection_nm : float
        Static deflection p0, nm.
    contact : bool
        Whether Δt_s = 0 (tip held on the sample).
    """

    operating_point: OperatingPoint
    actuation: ActuationSmallSignal
    dynamics: DiffusionLowPass
    alpha_r: float
    feedthrough_f: float
    feedthrough_corner_hz: float
    deflection_nm: float
    contact: bool

    # -- zero-pole-gain forms (capture units) ------------------------------------------------

    def _loop_gain(self) -> float:
        op = self.operating_point
        return op.dg_dt_ohm_per_k * op.k_tp_k_per_w * op.current_a**2

    def _d(self) -> Zpk:
        poles, zeros = self.dynamics.poles_zeros_rad_s()
        return Zpk(-zeros, -poles, np.prod(poles) / np.prod(zeros))

    def ts_v_zpk(self) -> Zpk:
        """Δt_s/ΔV_sub = −Γ_p,V, nm/V (zero in contact)."""
        num, den = self.actuation.tf()
        gain = 0.0 if self.contact else -num[0] * 1e9
        return Zpk([], np.roots(den), gain)

    def ts_vr_zpk(self) -> Zpk:
        """Δt_s/ΔV_R = α_R·Γ_p,V, nm/V (zero in contact)."""
        return self.ts_v_zpk().scaled(-self.alpha_r)

    def ir_ts_zpk(self) -> Zpk:
        """Γ_IR,ts of eq. 6.10, µA/nm: c0·D/(1 + x0·D) with c0 = −(I0/R0)g′·P0·K_TP′."""
        op = self.operating_point
        d = self._d()
        c0 = -op.current_a / op.resistance_ohm * op.dg_dt_ohm_per_k * op.power_w * op.dk_tp_dts_k_per_w_m
        poles = _feedback_poles(self.dynamics, self._loop_gain(), +1.0)
        return Zpk(d.zeros, poles, c0 * d.gain * 1e6 * 1e-9)

    def ir_vr_zpk(self) -> Zpk:
        """Γ_IR,VR of eq. 6.9, µA/V: (1/R0)(1 − x0·D)/(1 + x0·D)."""
        op = self.operating_point
        zeros = _feedback_poles(self.dynamics, self._loop_gain(), -1.0)
        poles = _feedback_poles(self.dynamics, self._loop_gain(), +1.0)
        return Zpk(zeros, poles, 1e6 / op.resistance_ohm)

    def feedthrough_zpk(self) -> Zpk:
        """Γ_sp = C_c·s/(1 + s/ω_c), µA/V."""
        wc = 2 * np.pi * self.feedthrough_corner_hz
        return Zpk([0.0], [-wc], self.feedthrough_f * wc * 1e6)

    # -- responses -----------------------------------------------------------------------------

    def ts_v(self, frequency_hz) -> np.ndarray:
        """Γ_ts,V = Δt_s/ΔV_sub, nm/V."""
        return self.ts_v_zpk().response(frequency_hz)

    def ir_ts(self, frequency_hz) -> np.ndarray:
        """Γ_IR,ts (eq. 6.10), µA/nm."""
        op = self.operating_point
        d = self.dynamics.response(frequency_hz)
        c = op.k_tp_k_per_w * d
        h = op.power_w * op.dk_tp_dts_k_per_w_m * d
        return gamma_ir_ts(h, c, op) * 1e6 * 1e-9

    def ir_vr(self, frequency_hz) -> np.ndarray:
        """Γ_IR,VR (eq. 6.9, Δt_s = 0), µA/V."""
        op = self.operating_point
        return gamma_ir_vr(op.k_tp_k_per_w * self.dynamics.response(frequency_hz), op) * 1e6

    def feedthrough(self, frequency_hz) -> np.ndarray:
        """Γ_sp, µA/V."""
        return self.feedthrough_zpk().response(frequency_hz)

    def ir_v(self, frequency_hz) -> np.ndarray:
        """Γ_IR,V = Γ_IR,ts·Γ_ts,V + Γ_sp, µA/V (the measured V_sub → I_R response)."""
        return self.ir_ts(frequency_hz) * self.ts_v(frequency_hz) + self.feedthrough(frequency_hz)

    def ir_vr_measured(self, frequency_hz) -> np.ndarray:
        """ΔI_R/ΔV_R including the lever's motion, Γ_IR,VR + Γ_IR,ts·α_R·Γ_p,V, µA/V."""
        return self.ir_vr(frequency_hz) + self.ir_ts(frequency_hz) * self.ts_vr_zpk().response(frequency_hz)

    def c(self, frequency_hz) -> np.ndarray:
        """C(jω) = K_TP·D, K/W."""
        return self.operating_point.k_tp_k_per_w * self.dynamics.response(frequency_hz)

    def h(self, frequency_hz) -> np.ndarray:
        """H(jω) = P0·K_TP′·D, K/m."""
        op = self.operating_point
        return op.power_w * op.dk_tp_dts_k_per_w_m * self.dynamics.response(frequency_hz)


@dataclass(frozen=True)
class ThermalSweepParams(ProbeParams):
    """Parameters of the ``thermal-sweep`` scenario (defaults: a near-sample V_sub chirp)."""

    duration_s: float = param(0.5, "capture length", "s", minimum=0, exclusive_minimum=True)
    sample_rate_hz: float = param(1e6, "sample rate", "Hz", minimum=0, exclusive_minimum=True)
    oversample: int = param(4, "internal rate / sample rate (bilinear discretisation)", "", minimum=1)
    drive: str = param("chirp", "repeated linear chirp or log-spaced stepped sines", "", choices=("chirp", "stepped"))
    chirp_repeats: int = param(8, "chirp: sweeps start -> stop in the capture", "", minimum=1)
    input: str = param("v_sub", "perturbed voltage: V_sub (Gamma sweeps) or V_R (C, H sweeps)", "",
                       choices=("v_sub", "v_r"))
    contact: bool = param(False, "tip held on the sample (t_s0 = 0, no motion): the feed-through run", "")
    amplitude_v: float = param(0.1, "perturbation amplitude", "V", minimum=0, exclusive_minimum=True)
    start_hz: float = param(50.0, "lowest sweep frequency", "Hz", minimum=0, exclusive_minimum=True)
    stop_hz: float = param(200e3, "highest sweep frequency", "Hz", minimum=0, exclusive_minimum=True)
    steps_per_decade: int = param(10, "stepped: log-spaced steps per decade", "", minimum=1)
    min_dwell_s: float = param(1e-3, "stepped: shortest step (low steps hold equal numbers of periods)", "s",
                               minimum=0, exclusive_minimum=True)
    v_r_v: float = param(3.0, "sensor voltage V_R0", "V")
    v_sub_v: float = param(2.0, "substrate bias V_sub0", "V")
    separation_nm: float = param(100.0, "nominal tip-sample separation t_s0 near the sample (> d)", "nm",
                                 minimum=0, exclusive_minimum=True)
    feedthrough_pf: float = param(2.0, "coupling capacitance C_c of the feed-through Gamma_sp = C_c*s", "pF",
                                  minimum=0)
    feedthrough_corner_hz: float = param(1e6, "pole of the feed-through path", "Hz", minimum=0,
                                         exclusive_minimum=True)
    current_noise_ua: float = param(0.01, "rms white noise on the thermal current", "uA", minimum=0)
    deflection_noise_nm: float = param(0.02, "rms white noise on the optical deflection", "nm", minimum=0)
    store_truth: bool = param(True, "store the noise-free signals under /truth", "")

    def __post_init__(self) -> None:
        validate_parameters(self)
        self.validate_probe()
        if not self.stop_hz > self.start_hz:
            raise ConfigError(f"stop_hz={self.stop_hz!r} must exceed start_hz={self.start_hz!r}")
        if self.stop_hz >= self.sample_rate_hz / 2:
            raise ConfigError(f"stop_hz={self.stop_hz!r} must be below sample_rate_hz/2 = {self.sample_rate_hz / 2:g}")
        if self.duration_s * self.sample_rate_hz < 16:
            raise ConfigError(f"duration_s={self.duration_s!r} gives fewer than 16 samples")
        if not self.separation_nm > self.attractive_range_nm:
            raise ConfigError(
                f"separation_nm={self.separation_nm!r} must exceed attractive_range_nm={self.attractive_range_nm!r}: "
                "the small-signal model has no tip-sample force"
            )
        self.model()  # κ < 1 and a sensor below breakdown, or ConfigError

    def model(self) -> ThermalSweepModel:
        """The exact small-signal responses at this operating point (ground truth)."""
        es = self.electrostatic()
        ts0 = 0.0 if self.contact else self.separation_nm * 1e-9
        lever = self.separation_nm * 1e-9 + es.tip_height_m  # ℓ_s0 of the near-sample run
        v_esf0 = es.alpha_r * self.v_r_v - self.v_sub_v
        actuation = linearise_actuation(es, self.f0_hz, self.q, v_esf0, lever)
        # static balance k·p0 = −K_esf·V0²/ℓ_s0² (eq. 6.5; t_s0 > d, no tip-sample force)
        p0 = -es.k_esf_f_m * v_esf0**2 / (es.spring_constant_n_per_m * lever**2)
        sensor = self.thermal_sensor()
        return ThermalSweepModel(
            operating_point=operating_point(sensor, self.v_r_v, ts0),
            actuation=actuation,
            dynamics=sensor.dynamics,
            alpha_r=self.alpha_r,
            feedthrough_f=self.feedthrough_pf * 1e-12,
            feedthrough_corner_hz=self.feedthrough_corner_hz,
            deflection_nm=p0 * 1e9,
            contact=self.contact,
        )

    def excitation(self) -> RepeatedChirp | LogSteppedSine:
        """The perturbation (V): ``chirp_repeats`` chirps start → stop, or log-spaced steps filling the capture."""
        if self.drive == "chirp":
            return RepeatedChirp(self.amplitude_v, self.start_hz, self.stop_hz, self.duration_s / self.chirp_repeats)
        return log_stepped_sine(
            self.amplitude_v, self.start_hz, self.stop_hz, self.steps_per_decade, self.duration_s, self.min_dwell_s
        )


def _metadata(params: ThermalSweepParams, model: ThermalSweepModel, excitation) -> dict:
    op = model.operating_point
    meta = {
        "scenario": "thermal-sweep",
        **params.probe_metadata(),
        "drive": {
            "input": params.input,
            "frequency_hz": float(excitation.to_metadata()["frequency_hz"]),
            "amplitude_v": float(params.amplitude_v),
            "kind": params.drive,
            "start_hz": float(params.start_hz),
            "stop_hz": float(params.stop_hz),
        },
        "operating_point": {
            "v_r_v": float(params.v_r_v),
            "v_sub_v": float(params.v_sub_v),
            "contact": bool(params.contact),
            "separation_m": float(op.separation_m),
            "deflection_m": model.deflection_nm * 1e-9,
            "temperature_c": op.temperature_c,
            "resistance_ohm": op.resistance_ohm,
            "current_a": op.current_a,
            "power_w": op.power_w,
            "dg_dt_ohm_per_k": op.dg_dt_ohm_per_k,
            "k_tp_k_per_w": op.k_tp_k_per_w,
            "dk_tp_dts_k_per_w_m": op.dk_tp_dts_k_per_w_m,
        },
        "actuation": {
            "f0_hz": model.actuation.f0_hz,
            "q": model.actuation.q,
            "gain_m_per_v": model.actuation.gain_m_per_v,
            "stiffness_ratio": model.actuation.stiffness_ratio,
        },
        "feedthrough": {"capacitance_f": model.feedthrough_f, "corner_hz": float(params.feedthrough_corner_hz)},
        "noise": {
            "current_noise_ua": float(params.current_noise_ua),
            "deflection_noise_nm": float(params.deflection_noise_nm),
        },
    }
    if isinstance(excitation, LogSteppedSine):
        meta["segments"] = excitation.segments()
    return meta


def simulate_thermal_sweep(params: ThermalSweepParams, seed: int) -> SimulatedCapture:
    """Small-signal sweep of an electrostatically actuated lever with a thermal sensor (Fig. 6.17).

    Parameters
    ----------
    params : ThermalSweepParams
    seed : int
        Seed of ``numpy.random.default_rng`` (current, then deflection noise).

    Returns
    -------
    SimulatedCapture
        Channels ``v_sub`` (V), ``thermal_current`` (µA), ``deflection``
        (nm), and ``v_r`` (V) when ``input="v_r"``; truth
        ``thermal_current_clean`` and ``deflection_clean`` unless
        ``store_truth`` is false.
    """
    fs = params.sample_rate_hz
    n = sample_count(params.duration_s, fs, "duration_s")
    os_ = params.oversample
    fine_rate = fs * os_
    model = params.model()
    excitation = params.excitation()
    u = excitation(np.arange(n * os_) / fine_rate)
    if params.input == "v_sub":
        ts = model.ts_v_zpk().filter(u, fine_rate)
        current = model.ir_ts_zpk().filter(ts, fine_rate) + model.feedthrough_zpk().filter(u, fine_rate)
    else:
        ts = model.ts_vr_zpk().filter(u, fine_rate)
        current = model.ir_vr_zpk().filter(u, fine_rate) + model.ir_ts_zpk().filter(ts, fine_rate)
    drive, ts, current = u[::os_], ts[::os_], current[::os_]
    op = model.operating_point
    current_ua = op.current_a * 1e6 + current
    deflection_nm = model.deflection_nm + ts
    rng = np.random.default_rng(seed)
    data = {
        "v_sub": params.v_sub_v + (drive if params.input == "v_sub" else np.zeros(n)),
        "thermal_current": current_ua + params.current_noise_ua * rng.standard_normal(n),
        "deflection": deflection_nm + params.deflection_noise_nm * rng.standard_normal(n),
    }
    channels = [ChannelSpec("v_sub", "V"), ChannelSpec("thermal_current", "uA"), ChannelSpec("deflection", "nm")]
    if params.input == "v_r":
        data["v_r"] = params.v_r_v + drive
        channels.insert(1, ChannelSpec("v_r", "V"))
    truth = {"thermal_current_clean": current_ua, "deflection_clean": deflection_nm} if params.store_truth else {}
    return SimulatedCapture(fs, tuple(channels), data, _metadata(params, model, excitation), truth)
