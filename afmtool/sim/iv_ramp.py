"""Scenario ``iv-ramp``: quasi-static ramps of the thermal sensor (§6.5.2, Figs. 6.7 and 6.8).

Two ramps, chosen by ``ramp``:

* ``"v_r"`` (an I-V curve, Fig. 6.7): V_R goes 0 → ``v_r_max_v`` → 0 at a
  fixed tip-sample separation ``separation_nm``; past the knee at T_k the
  resistance falls (intrinsic breakdown) and the P-V_R curve bends up.
  Channels ``v_r`` (V) and ``thermal_current`` (µA).
* ``"z"`` (a thermal z force curve, Fig. 6.8(a)): at constant V_R the
  sample moves ``z_range_nm`` toward the lever and back, starting with the
  tip ``z_start_separation_nm`` from it; the lever follows the quasi-static
  equilibrium with the electrostatic force of α_R·V_R and the tip-sample
  force (:func:`afmtool.sim.quasistatic.track_equilibrium`), so it snaps
  in at t_s ≈ d (with |k_a| > k) and snaps off on the way back.  Channels
  ``z_piezo`` (nm, positive toward the lever), ``v_r`` (V),
  ``thermal_current`` (µA) and ``deflection`` (nm).

The current is the quasi-static I_R = V_R/g(T) with T − T_r = K_TP(t_s)·P
(:func:`afmtool.models.thermal_sensor.steady_state`).  Truth:
``temperature_c``, ``resistance_ohm``, ``k_tp_k_per_w`` and
``tip_sample_separation_nm``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from afmtool.config.samples import sample_count
from afmtool.errors import ConfigError
from afmtool.io.capture import ChannelSpec
from afmtool.models.thermal_sensor import steady_state
from afmtool.sim import SimulatedCapture, param, validate_parameters
from afmtool.sim.es_approach import triangle
from afmtool.sim.probe import ProbeParams
from afmtool.sim.quasistatic import track_equilibrium

__all__ = ["IvRampParams", "simulate_iv_ramp"]


@dataclass(frozen=True)
class IvRampParams(ProbeParams):
    """Parameters of the ``iv-ramp`` scenario."""

    duration_s: float = param(0.5, "capture length (one ramp up and down)", "s", minimum=0, exclusive_minimum=True)
    sample_rate_hz: float = param(20e3, "sample rate", "Hz", minimum=0, exclusive_minimum=True)
    ramp: str = param("v_r", "what is ramped: V_R (I-V curve) or the sample position (z force curve)", "",
                      choices=("v_r", "z"))
    v_r_max_v: float = param(3.5, "v_r ramp: top of the V_R triangle", "V", minimum=0, exclusive_minimum=True)
    v_r_v: float = param(3.0, "z ramp: constant V_R", "V")
    separation_nm: float = param(2000.0, "v_r ramp: fixed tip-sample separation", "nm", minimum=0,
                                 exclusive_minimum=True)
    z_start_separation_nm: float = param(800.0, "z ramp: tip-sample separation at the start", "nm", minimum=0,
                                         exclusive_minimum=True)
    z_range_nm: float = param(900.0, "z ramp: travel of the sample toward the lever", "nm", minimum=0,
                              exclusive_minimum=True)
    current_noise_ua: float = param(0.05, "rms white noise on the thermal current", "uA", minimum=0)
    deflection_noise_nm: float = param(0.1, "z ramp: rms white noise on the optical deflection", "nm", minimum=0)

    def __post_init__(self) -> None:
        validate_parameters(self)
        self.validate_probe()
        if self.duration_s * self.sample_rate_hz < 4:
            raise ConfigError(f"duration_s={self.duration_s!r} gives fewer than 4 samples")


def _v_r_ramp(params: IvRampParams, n: int) -> tuple[dict, dict, dict]:
    v_r = triangle(n, params.v_r_max_v)
    ts = np.full(n, params.separation_nm * 1e-9)
    return {"v_r": v_r}, {"v_r": v_r, "ts": ts}, {"v_r_max_v": float(params.v_r_max_v),
                                                  "separation_m": params.separation_nm * 1e-9}


def _z_ramp(params: IvRampParams, n: int) -> tuple[dict, dict, dict]:
    es = params.electrostatic()
    force = params.tip_sample_force()
    z_nm = triangle(n, params.z_range_nm)
    # the sample starts where the unloaded tip is z_start_separation_nm away: z0 = ℓ0 − t_h − t_s0
    z0 = es.l0_m - es.tip_height_m - params.z_start_separation_nm * 1e-9
    z = z0 + z_nm * 1e-9
    v_r = np.full(n, params.v_r_v)
    p = track_equilibrium(
        es.alpha_r * v_r,
        z,
        spring_constant_n_per_m=es.spring_constant_n_per_m,
        k_esf_f_m=es.k_esf_f_m,
        l0_m=es.l0_m,
        tip_height_m=es.tip_height_m,
        attractive_range_m=force.d_nm,
        attractive_stiffness_n_per_m=force.omega_a2,
        repulsive_stiffness_n_per_m=force.omega_b2,
    )
    ts = es.l0_m + p - es.tip_height_m - z
    channels = {"z_piezo": z_nm, "v_r": v_r, "deflection": p * 1e9}
    ramp = {"v_r_v": float(params.v_r_v), "z_range_nm": float(params.z_range_nm), "z_offset_m": float(z0)}
    return channels, {"v_r": v_r, "ts": ts}, ramp


def simulate_iv_ramp(params: IvRampParams, seed: int) -> SimulatedCapture:
    """Quasi-static I-V ramp (V_R) or thermal z force curve of the integrated thermal sensor.

    Parameters
    ----------
    params : IvRampParams
    seed : int
        Seed of ``numpy.random.default_rng`` (current, then deflection noise).

    Returns
    -------
    SimulatedCapture
    """
    fs = params.sample_rate_hz
    n = sample_count(params.duration_s, fs, "duration_s")
    clean, state_in, ramp_meta = (_v_r_ramp if params.ramp == "v_r" else _z_ramp)(params, n)
    state = steady_state(params.thermal_sensor(), state_in["v_r"], state_in["ts"])
    rng = np.random.default_rng(seed)
    data = dict(clean)
    data["thermal_current"] = state.current_a * 1e6 + params.current_noise_ua * rng.standard_normal(n)
    units = {"v_r": "V", "z_piezo": "nm", "deflection": "nm", "thermal_current": "uA"}
    if "deflection" in data:
        data["deflection"] = clean["deflection"] + params.deflection_noise_nm * rng.standard_normal(n)
    order = ("z_piezo", "v_r", "thermal_current", "deflection")
    channels = tuple(ChannelSpec(name, units[name]) for name in order if name in data)
    metadata = {
        "scenario": "iv-ramp",
        **params.probe_metadata(),
        "ramp": {"kind": params.ramp, **ramp_meta},
        "noise": {"current_noise_ua": float(params.current_noise_ua)},
    }
    truth = {
        "temperature_c": np.asarray(state.temperature_c, dtype=np.float64),
        "resistance_ohm": np.asarray(state.resistance_ohm, dtype=np.float64),
        "k_tp_k_per_w": np.asarray(state.k_tp_k_per_w, dtype=np.float64),
        "tip_sample_separation_nm": state_in["ts"] * 1e9,
    }
    return SimulatedCapture(fs, channels, data, metadata, truth)
