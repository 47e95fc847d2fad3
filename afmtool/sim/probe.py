"""Parameters of an electrostatically actuated lever with an integrated thermal sensor (thesis ch. 6).

:class:`ProbeParams` is the base of the ``thermal-sweep``, ``iv-ramp`` and
``es-approach`` scenario parameters, so the three simulate the same probe.
Defaults are the thermally identified values of Table 6.1 (k, ℓ0, K_esf,
α_R, t_h, f0, Q), the tip-sample force fitted in §6.7.1 (k_a = 0.29 N/m,
k_r = 3.4 N/m, d = 65 nm) and a thermal sensor with T_k = 550 °C whose knee
lies near 3.4 V far from the sample (Fig. 6.7) and whose K_TP is about
100 K/mW near the sample (§6.6.2 quotes 111 °C/mW).
"""

from __future__ import annotations

from dataclasses import dataclass

from afmtool.models.cantilever import Cantilever
from afmtool.models.electrostatic import ElectrostaticParams
from afmtool.models.forces import PiecewiseLinearForce
from afmtool.models.thermal_sensor import DiffusionLowPass, PowerTemperatureGain, ResistanceModel, ThermalSensor
from afmtool.sim import param

__all__ = ["ProbeParams"]


@dataclass(frozen=True)
class ProbeParams:
    """The probe shared by the chapter-6 scenarios (SI conversions by the methods)."""

    f0_hz: float = param(51858.0, "free-air resonant frequency f0 (Table 6.1, thermal)", "Hz", minimum=0,
                         exclusive_minimum=True)
    q: float = param(2.3715, "free-air quality factor Q (Table 6.1)", "", minimum=0, exclusive_minimum=True)
    spring_constant_n_per_m: float = param(0.13975, "spring constant k", "N/m", minimum=0, exclusive_minimum=True)
    k_esf_f_m: float = param(1.64991e-21, "electrostatic constant K_esf (eq. 6.4, no 1/2)", "F*m", minimum=0,
                             exclusive_minimum=True)
    alpha_r: float = param(0.2156, "share alpha_R of V_R on the lever surface (eq. 6.3)", "")
    l0_nm: float = param(1243.0, "lever-sample separation l0 at zero deflection and z = 0", "nm", minimum=0,
                         exclusive_minimum=True)
    tip_height_nm: float = param(711.75, "tip height t_h", "nm", minimum=0, exclusive_minimum=True)
    attractive_stiffness_n_per_m: float = param(0.29, "tip-sample attractive stiffness |k_a| (eq. 6.2)", "N/m",
                                                minimum=0)
    repulsive_stiffness_n_per_m: float = param(3.4, "tip-sample repulsive stiffness |k_r| (eq. 6.2)", "N/m",
                                               minimum=0)
    attractive_range_nm: float = param(65.0, "range d of the attractive force (eq. 6.2)", "nm", minimum=0)
    room_resistance_ohm: float = param(1200.0, "sensor resistance at room temperature, g(T_r)", "ohm", minimum=0,
                                       exclusive_minimum=True)
    resistance_alpha_per_k: float = param(1.5e-3, "g(T) = R_r(1 + a*dT + b*dT^2) below T_k: a", "1/K")
    resistance_beta_per_k2: float = param(1.7e-6, "g(T) below T_k: b", "1/K^2")
    room_temperature_c: float = param(25.0, "room temperature T_r", "degC")
    breakdown_temperature_c: float = param(550.0, "intrinsic breakdown temperature T_k (knee)", "degC")
    intrinsic_exponent: float = param(0.8, "above T_k, g = g(T_k)(dT/dT_k)^-nu: nu", "", minimum=0,
                                      exclusive_minimum=True, maximum=0.999)
    k_tp_far_k_per_mw: float = param(125.0, "K_TP far from the sample (DC gain of Gamma_TP)", "K/mW", minimum=0,
                                     exclusive_minimum=True)
    k_tp_contact_k_per_mw: float = param(95.0, "K_TP in contact", "K/mW", minimum=0, exclusive_minimum=True)
    k_tp_decay_nm: float = param(300.0, "K_TP(t_s) = K_far - (K_far - K_contact)*lam/(lam + t_s): lam", "nm",
                                 minimum=0, exclusive_minimum=True)
    thermal_corner_hz: float = param(5400.0, "first pole of the 10 dB/decade power-temperature dynamics D(s)",
                                     "Hz", minimum=0, exclusive_minimum=True)

    def cantilever(self) -> Cantilever:
        return Cantilever(self.f0_hz, self.q, self.spring_constant_n_per_m)

    def electrostatic(self) -> ElectrostaticParams:
        """The electrostatic parameters in SI units."""
        return ElectrostaticParams(
            spring_constant_n_per_m=self.spring_constant_n_per_m,
            k_esf_f_m=self.k_esf_f_m,
            alpha_r=self.alpha_r,
            l0_m=self.l0_nm * 1e-9,
            tip_height_m=self.tip_height_nm * 1e-9,
        )

    def tip_sample_force(self) -> PiecewiseLinearForce:
        """Eq. 6.2 in :mod:`afmtool.models.forces` form with unit "mass": F in N for t_s in m.

        With ω_a² = |k_a| and ω_b² = |k_r| (N/m) and lengths in m,
        :func:`~afmtool.models.forces.force_per_mass` returns the force in N.
        """
        return PiecewiseLinearForce(
            self.attractive_range_nm * 1e-9, self.attractive_stiffness_n_per_m, self.repulsive_stiffness_n_per_m,
            0.0, 0.0,
        )

    def thermal_sensor(self) -> ThermalSensor:
        return ThermalSensor(
            resistance=ResistanceModel(
                room_resistance_ohm=self.room_resistance_ohm,
                alpha_per_k=self.resistance_alpha_per_k,
                beta_per_k2=self.resistance_beta_per_k2,
                room_temperature_c=self.room_temperature_c,
                breakdown_temperature_c=self.breakdown_temperature_c,
                intrinsic_exponent=self.intrinsic_exponent,
            ),
            gain=PowerTemperatureGain(
                far_k_per_w=self.k_tp_far_k_per_mw * 1e3,
                contact_k_per_w=self.k_tp_contact_k_per_mw * 1e3,
                decay_length_m=self.k_tp_decay_nm * 1e-9,
            ),
            dynamics=DiffusionLowPass(corner_hz=self.thermal_corner_hz),
        )

    def validate_probe(self) -> None:
        """Build every model once so a bad combination fails before any work (ConfigError)."""
        self.electrostatic()
        self.tip_sample_force()
        self.thermal_sensor()

    def probe_metadata(self) -> dict:
        """The probe's ground truth as capture metadata (SI where the key says so)."""
        sensor = self.thermal_sensor()
        return {
            "cantilever": {
                "f0_hz": float(self.f0_hz),
                "q": float(self.q),
                "spring_constant_n_per_m": float(self.spring_constant_n_per_m),
            },
            "electrostatic": {
                "k_esf_f_m": float(self.k_esf_f_m),
                "alpha_r": float(self.alpha_r),
                "l0_m": self.l0_nm * 1e-9,
                "tip_height_m": self.tip_height_nm * 1e-9,
                "convention": "F_esf = -K_esf*(alpha_R*V_R - V_sub)^2/l_s^2, no 1/2 (afmtool.models.electrostatic)",
            },
            "tip_sample_force": {
                "attractive_stiffness_n_per_m": float(self.attractive_stiffness_n_per_m),
                "repulsive_stiffness_n_per_m": float(self.repulsive_stiffness_n_per_m),
                "attractive_range_m": self.attractive_range_nm * 1e-9,
            },
            "thermal_sensor": {
                "room_temperature_c": float(self.room_temperature_c),
                "breakdown_temperature_c": float(self.breakdown_temperature_c),
                "room_resistance_ohm": float(self.room_resistance_ohm),
                "breakdown_resistance_ohm": float(sensor.resistance.breakdown_resistance_ohm),
                "k_tp_far_k_per_w": float(sensor.gain.far_k_per_w),
                "k_tp_contact_k_per_w": float(sensor.gain.contact_k_per_w),
            },
        }
