"""Scenario ``vphi-step``: a step in the sample's surface potential under an actuated lever (§7.7).

The lever of :mod:`afmtool.sim.electrostatic_plant` (eq. 7.11) is actuated
through the substrate at ``actuation_hz`` (57,185.01 Hz in the thesis, at
the free resonance) while the sample stays flat.  At ``step_time_s`` the
surface potential V_φ steps by ``step_v``.  The potential adds to the
substrate voltage the lever sees, V = α_R·V_R − (V_sub + V_φ), but is not
recorded: the channels ``v_sub`` and ``v_r`` hold only what is applied, so
an observer built on them sees the step as a model mismatch.  The thesis
runs it at Q = 1.0148, 100.0148 and 1000.0148 (set ``q``): the deflection
and its amplitude settle in about 2Q/ω0 per e-fold, the EKF innovation in a
time set by the filter, not by Q.

The default is noise-free, like the thesis's simulation (set
``temperature_k`` and ``measurement_noise_nm`` to add noise).  Ground truth:
``v_phi_v`` (V) and ``deflection_clean`` (nm); metadata ``nominal`` is the
segment before the step.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from afmtool.config.samples import sample_count
from afmtool.errors import ConfigError
from afmtool.io.capture import ChannelSpec
from afmtool.models.cantilever import Cantilever
from afmtool.models.electrostatic import THESIS_CH7_PARAMS, ElectrostaticParams
from afmtool.sim import SimulatedCapture, param, register_scenario, validate_parameters
from afmtool.sim.bits import electrostatic_metadata
from afmtool.sim.electrostatic_plant import default_settle_s, simulate_plant
from afmtool.sim.tapping import thermal_accel_rms

__all__ = ["VphiParams", "simulate_vphi"]

_TH = THESIS_CH7_PARAMS


def _positive(default, text, units, **kw):
    return param(default, text, units, minimum=0, exclusive_minimum=True, **kw)


@dataclass(frozen=True)
class VphiParams:
    """Parameters of the ``vphi-step`` scenario (defaults: §7.7 with Q = 1.0148)."""

    duration_s: float = _positive(0.06, "capture length", "s")
    sample_rate_hz: float = _positive(2e6, "sample rate", "Hz")
    substeps: int = param(4, "RK4 steps per sample period", "", minimum=1)
    f0_hz: float = _positive(57185.0, "resonant frequency f0 (§7.2)", "Hz")
    q: float = param(1.0148, "quality factor Q (§7.7: 1.0148, 100.0148, 1000.0148)", "", minimum=0.5,
                     exclusive_minimum=True)
    spring_constant_n_per_m: float = _positive(_TH.spring_constant_n_per_m, "spring constant k (eq. 7.10)", "N/m")
    k_esf_f_m: float = _positive(_TH.k_esf_f_m, "K_esf, no-½ convention (eq. 7.10)", "F·m")
    alpha_r: float = param(_TH.alpha_r, "α_R, share of V_R on the lever (eq. 7.10)", "")
    l0_nm: float = _positive(_TH.l0_m * 1e9, "ℓ0, lever-sample separation at p = 0 (eq. 7.10)", "nm")
    tip_height_nm: float = _positive(_TH.tip_height_m * 1e9, "tip height t_h (eq. 7.10)", "nm")
    actuation_hz: float = _positive(57185.01, "substrate actuation frequency (§7.7)", "Hz")
    read_voltage_v: float = param(4.0, "constant V_R on the lever legs (channel v_r)", "V")
    substrate_dc_v: float = param(0.0, "DC part of V_sub", "V")
    substrate_ac_v: float = param(0.002, "amplitude of V_sub at actuation_hz", "V", minimum=0)
    step_v: float = param(0.1, "surface-potential step ΔV_φ (§7.7)", "V")
    step_time_s: float = _positive(
        0.025, "time of the step (sample 5e4 at 2 MHz, as in Figs. 7.9-7.12; at or after duration_s: no step)", "s"
    )
    temperature_k: float = param(0.0, "temperature of the thermal force noise (0 = none)", "K", minimum=0)
    measurement_noise_nm: float = param(0.0, "rms white noise added to the recorded deflection", "nm", minimum=0)
    settle_s: float = param(-1.0, "noise-free pre-roll before t = 0; < 0 = 12·2Q/ω0", "s")

    def __post_init__(self) -> None:
        validate_parameters(self)
        nyquist = self.sample_rate_hz / 2
        if self.f0_hz >= nyquist or 2 * self.actuation_hz >= nyquist:
            raise ConfigError(
                f"f0_hz={self.f0_hz!r} and 2·actuation_hz={2 * self.actuation_hz!r} must be below "
                f"sample_rate_hz/2 = {nyquist:g}"
            )
        if self.tip_height_nm >= self.l0_nm:
            raise ConfigError(f"tip_height_nm={self.tip_height_nm!r} must be below l0_nm={self.l0_nm!r}")

    def cantilever(self) -> Cantilever:
        return Cantilever(self.f0_hz, self.q, self.spring_constant_n_per_m)

    def electrostatic(self) -> ElectrostaticParams:
        return ElectrostaticParams(
            self.spring_constant_n_per_m, self.k_esf_f_m, self.alpha_r, self.l0_nm * 1e-9, self.tip_height_nm * 1e-9
        )

    def substrate_voltage(self, t_s: np.ndarray) -> np.ndarray:
        """Applied V_sub(t) = V_dc + V_ac·sin(2π f_a t), V (what the channel records)."""
        t = np.asarray(t_s, dtype=np.float64)
        return self.substrate_dc_v + self.substrate_ac_v * np.sin(2.0 * np.pi * self.actuation_hz * t)

    def surface_potential(self, t_s: np.ndarray) -> np.ndarray:
        """V_φ(t): 0 before the step, ``step_v`` from it on, V."""
        return np.where(np.asarray(t_s, dtype=np.float64) >= self.step_time_s, self.step_v, 0.0)

    def voltage(self, t_s: np.ndarray) -> np.ndarray:
        """V = α_R·V_R − (V_sub + V_φ), V (what the lever feels)."""
        return self.alpha_r * self.read_voltage_v - self.substrate_voltage(t_s) - self.surface_potential(t_s)


def simulate_vphi(params: VphiParams, seed: int) -> SimulatedCapture:
    """A surface-potential step under an electrostatically actuated lever (§7.7), RK4.

    Parameters
    ----------
    params : VphiParams
        Scenario parameters.
    seed : int
        Seed of ``numpy.random.default_rng`` (thermal, then measurement noise).

    Returns
    -------
    SimulatedCapture
        Channels ``v_sub`` (V, applied, without V_φ), ``v_r`` (V) and
        ``deflection`` (nm); truth ``v_phi_v`` and ``deflection_clean``.
    """
    fs = params.sample_rate_hz
    n = sample_count(params.duration_s, fs, "duration_s")
    cantilever = params.cantilever()
    es = params.electrostatic()
    rng = np.random.default_rng(seed)
    sigma_eta = thermal_accel_rms(cantilever, params.temperature_k, fs) if params.temperature_k > 0 else 0.0
    accel_noise = sigma_eta * rng.standard_normal(n)
    measurement = params.measurement_noise_nm * rng.standard_normal(n)
    settle = default_settle_s(cantilever) if params.settle_s < 0 else params.settle_s
    clean = simulate_plant(
        params.voltage, lambda t: np.zeros_like(t), accel_noise, sample_rate_hz=fs, substeps=params.substeps,
        cantilever=cantilever, electrostatic=es, settle_s=settle,
    )
    t = np.arange(n) / fs
    channels = (ChannelSpec("v_sub", "V"), ChannelSpec("v_r", "V"), ChannelSpec("deflection", "nm"))
    data = {
        "v_sub": params.substrate_voltage(t),
        "v_r": np.full(n, params.read_voltage_v),
        "deflection": clean + measurement,
    }
    truth = {"v_phi_v": params.surface_potential(t), "deflection_clean": clean}
    metadata = {
        "scenario": "vphi-step",
        "cantilever": cantilever.to_metadata(),
        "electrostatic": electrostatic_metadata(es),
        "drive": {
            "kind": "electrostatic",
            "frequency_hz": float(params.actuation_hz),
            "substrate_dc_v": float(params.substrate_dc_v),
            "substrate_ac_v": float(params.substrate_ac_v),
            "read_voltage_v": float(params.read_voltage_v),
        },
        "nominal": {"start_s": 0.0, "end_s": float(min(params.step_time_s, n / fs))},
        "vphi_step": {"step_v": float(params.step_v), "time_s": float(params.step_time_s)},
        "noise": {
            "temperature_k": float(params.temperature_k),
            "thermal_accel_rms_nm_per_s2": float(sigma_eta),
            "measurement_noise_nm": float(params.measurement_noise_nm),
        },
        "integrator": {"method": "rk4", "substeps": params.substeps, "settle_s": float(settle)},
    }
    return SimulatedCapture(fs, channels, data, metadata, truth)


register_scenario("vphi-step", VphiParams, simulate_vphi)
