"""Scenario ``es-approach``: a quasi-static electrostatic approach curve with snap-in and snap-off (§6.5, §6.7.1).

V_sub is ramped linearly from 0 up to ``v_sub_max_v`` and back (a triangle,
as the thesis's 3 Hz ramps) at constant V_R and sample position.  The lever
follows the stable equilibrium of eq. 6.1 with the electrostatic force of
eq. 6.4 and the tip-sample force of eq. 6.2
(:func:`afmtool.sim.quasistatic.track_equilibrium`): along a-b of
Fig. 6.25(b) it obeys eq. 6.6, then it snaps into contact (c), stays there
while V_sub falls, and snaps off (d-e) at a lower voltage.  The thermal
sensor current is the quasi-static I_R = V_R/g(T) at the current t_s
(:func:`afmtool.models.thermal_sensor.steady_state`).

Channels: ``v_sub`` (V), ``v_r`` (V), ``deflection`` (optical, nm) and
``thermal_current`` (µA), each recorded with white noise (except the two
voltages).  Truth: ``deflection_clean`` (nm), ``tip_sample_separation_nm``
and ``contact`` (1 where t_s < 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from afmtool.config.samples import sample_count
from afmtool.errors import ConfigError
from afmtool.io.capture import ChannelSpec
from afmtool.models.thermal_sensor import steady_state
from afmtool.sim import SimulatedCapture, param, validate_parameters
from afmtool.sim.probe import ProbeParams
from afmtool.sim.quasistatic import track_equilibrium

__all__ = ["EsApproachParams", "triangle", "simulate_es_approach"]


@dataclass(frozen=True)
class EsApproachParams(ProbeParams):
    """Parameters of the ``es-approach`` scenario (probe: Table 6.1, thermal)."""

    duration_s: float = param(1.0, "capture length (one ramp up and down)", "s", minimum=0, exclusive_minimum=True)
    sample_rate_hz: float = param(10e3, "sample rate", "Hz", minimum=0, exclusive_minimum=True)
    v_sub_max_v: float = param(8.0, "top of the V_sub triangle (0 -> max -> 0)", "V")
    v_r_v: float = param(3.0, "constant sensor voltage V_R", "V")
    sample_z_nm: float = param(0.0, "sample position z (toward the lever); rest gap is l0 - t_h - z", "nm")
    deflection_noise_nm: float = param(0.1, "rms white noise on the optical deflection", "nm", minimum=0)
    current_noise_ua: float = param(0.05, "rms white noise on the thermal current", "uA", minimum=0)

    def __post_init__(self) -> None:
        validate_parameters(self)
        self.validate_probe()
        if self.duration_s * self.sample_rate_hz < 4:
            raise ConfigError(f"duration_s={self.duration_s!r} gives fewer than 4 samples")
        if not self.sample_z_nm < self.l0_nm - self.tip_height_nm:
            raise ConfigError(
                f"sample_z_nm={self.sample_z_nm!r} must leave a gap: below l0_nm - tip_height_nm = "
                f"{self.l0_nm - self.tip_height_nm:g}"
            )


def triangle(n: int, peak: float) -> np.ndarray:
    """0 → ``peak`` → 0 linearly over n samples (the peak at sample n//2)."""
    t = np.arange(n) / max(n - 1, 1)
    return peak * (1.0 - np.abs(2.0 * t - 1.0))


def simulate_es_approach(params: EsApproachParams, seed: int) -> SimulatedCapture:
    """Quasi-static electrostatic approach curve: V_sub up and down, snap-in and snap-off.

    Parameters
    ----------
    params : EsApproachParams
    seed : int
        Seed of ``numpy.random.default_rng`` (deflection, then current noise).

    Returns
    -------
    SimulatedCapture
    """
    fs = params.sample_rate_hz
    n = sample_count(params.duration_s, fs, "duration_s")
    es = params.electrostatic()
    force = params.tip_sample_force()
    v_sub = triangle(n, params.v_sub_max_v)
    v_r = np.full(n, params.v_r_v)
    voltage = es.alpha_r * v_r - v_sub
    z = params.sample_z_nm * 1e-9
    p = track_equilibrium(
        voltage,
        np.full(n, z),
        spring_constant_n_per_m=es.spring_constant_n_per_m,
        k_esf_f_m=es.k_esf_f_m,
        l0_m=es.l0_m,
        tip_height_m=es.tip_height_m,
        attractive_range_m=force.d_nm,
        attractive_stiffness_n_per_m=force.omega_a2,
        repulsive_stiffness_n_per_m=force.omega_b2,
    )
    ts = es.l0_m + p - es.tip_height_m - z
    state = steady_state(params.thermal_sensor(), v_r, ts)
    rng = np.random.default_rng(seed)
    deflection_nm = p * 1e9
    current_ua = state.current_a * 1e6
    data = {
        "v_sub": v_sub,
        "v_r": v_r,
        "deflection": deflection_nm + params.deflection_noise_nm * rng.standard_normal(n),
        "thermal_current": current_ua + params.current_noise_ua * rng.standard_normal(n),
    }
    channels = (
        ChannelSpec("v_sub", "V"),
        ChannelSpec("v_r", "V"),
        ChannelSpec("deflection", "nm"),
        ChannelSpec("thermal_current", "uA"),
    )
    metadata = {
        "scenario": "es-approach",
        **params.probe_metadata(),
        "ramp": {"kind": "v_sub triangle", "v_sub_max_v": float(params.v_sub_max_v), "v_r_v": float(params.v_r_v),
                 "sample_z_m": z},
        "noise": {"deflection_noise_nm": float(params.deflection_noise_nm),
                  "current_noise_ua": float(params.current_noise_ua)},
    }
    truth = {
        "deflection_clean": deflection_nm,
        "tip_sample_separation_nm": ts * 1e9,
        "contact": (ts < 0).astype(np.float64),
    }
    return SimulatedCapture(fs, channels, data, metadata, truth)
