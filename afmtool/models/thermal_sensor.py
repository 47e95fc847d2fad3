"""Integrated thermal sensor of an electrostatically actuated lever (thesis §6.4.3, §6.5.2, §6.6).

Large-signal model (Fig. 6.2)
-----------------------------
A voltage V_R drives the current I_R = V_R/R through the sensor; the power
P = V_R²/R heats it.  The power-temperature map Γ_TP is, here, a linear
filter with DC gain K_TP(t_s) that depends on the tip-sample separation:

.. math:: T - T_r = K_{TP}(t_s)\\, D(s)[P], \\qquad R = g(T),

with D(s) a unit-DC-gain low-pass (:class:`DiffusionLowPass`).  K_TP is the
DC gain of Γ_TP as §6.5.2 defines it, the slope of the line from (0, T_r)
to (P_k, T_k), in K/W (the thesis quotes it in °C/mW).

Units: temperatures in °C (differences in K), resistance in Ω, current in
A, power in W, separations in m inside this module; analyses convert their
channels (µA, nm) at the boundary.

g(T) (:class:`ResistanceModel`): a quadratic in ΔT = T − T_r up to the
breakdown temperature T_k, where intrinsic carriers take over and the
resistance falls (thermal runaway, §6.5.2); above T_k,
g = g(T_k)·(ΔT/ΔT_k)^(−ν) with 0 < ν < 1, so that ΔT·g(T), and with it the
steady state, stays single valued.  The kink at T_k is the "knee" of the
P-V_R curve of an I-V ramp.

Small-signal model (Fig. 6.13, eqs. 6.8-6.12)
---------------------------------------------
About an operating point (V_R0, t_s0): ΔT = C·ΔP + H·Δt_s (eq. 6.8) with
C(s) = K_TP(t_s0)·D(s) and H(s) = P0·K_TP′(t_s0)·D(s).  Linearising
I = V/R and P = V²/R (ΔI = ΔV/R0 − (I0/R0)ΔR, ΔP = 2I0ΔV − I0²ΔR,
ΔR = g′(T0)ΔT) and eliminating ΔR gives

.. math::

    \\Gamma_{I_R V_R} = \\frac{1}{R_0}\\frac{1 - g' C I_0^2}{1 + g' C I_0^2}
        \\quad (6.9), \\qquad
    \\Gamma_{I_R t_s} = -\\frac{I_0}{R_0}\\frac{g' H}{1 + g' C I_0^2}
        \\quad (6.10),

and their inverses, eqs. 6.11 and 6.12 (:func:`c_from_gamma_ir_vr`,
:func:`h_from_gammas`).  All four are checked against each other in the
tests.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from afmtool.errors import ConfigError
from afmtool.records.thermal import ResistanceFitRecord

__all__ = [
    "ResistanceModel",
    "PowerTemperatureGain",
    "ThermalSensor",
    "DiffusionLowPass",
    "OperatingPoint",
    "SteadyState",
    "steady_state",
    "operating_point",
    "gamma_ir_vr",
    "gamma_ir_ts",
    "c_from_gamma_ir_vr",
    "h_from_gammas",
    "ResistanceFit",
]


def _finite(name: str, value: float, *, positive: bool = False, nonnegative: bool = False) -> None:
    ok = isinstance(value, (int, float, np.floating, np.integer)) and math.isfinite(value)
    ok = ok and (value > 0 if positive else value >= 0 if nonnegative else True)
    if not ok:
        bound = " > 0" if positive else " >= 0" if nonnegative else ""
        raise ConfigError(f"{name}={value!r} must be a finite number{bound}")


# --------------------------------------------------------------------------- g(T)


@dataclass(frozen=True)
class ResistanceModel:
    """The static resistance-temperature map R = g(T) (§6.4.3, Fig. 6.7(b)).

    Parameters
    ----------
    room_resistance_ohm : float
        R_r = g(T_r), Ω.
    alpha_per_k : float
        Linear coefficient α of g = R_r(1 + αΔT + βΔT²), 1/K.
    beta_per_k2 : float
        Quadratic coefficient β, 1/K².
    room_temperature_c : float
        T_r, °C.
    breakdown_temperature_c : float
        T_k, °C: intrinsic-carrier breakdown (thermal runaway), > T_r.
    intrinsic_exponent : float
        ν in (0, 1): above T_k, g = g(T_k)(ΔT/ΔT_k)^(−ν).

    Raises
    ------
    ConfigError
        For non-finite values, R_r ≤ 0, T_k ≤ T_r, ν outside (0, 1), or a
        g that is not increasing on [T_r, T_k].
    """

    room_resistance_ohm: float = 1200.0
    alpha_per_k: float = 1.5e-3
    beta_per_k2: float = 1.7e-6
    room_temperature_c: float = 25.0
    breakdown_temperature_c: float = 550.0
    intrinsic_exponent: float = 0.8

    def __post_init__(self) -> None:
        _finite("room_resistance_ohm", self.room_resistance_ohm, positive=True)
        for name in ("alpha_per_k", "beta_per_k2", "room_temperature_c", "breakdown_temperature_c"):
            _finite(name, getattr(self, name))
        if not self.breakdown_temperature_c > self.room_temperature_c:
            raise ConfigError(
                f"breakdown_temperature_c={self.breakdown_temperature_c!r} must exceed "
                f"room_temperature_c={self.room_temperature_c!r}"
            )
        if not 0 < self.intrinsic_exponent < 1:
            raise ConfigError(f"intrinsic_exponent={self.intrinsic_exponent!r} must be in (0, 1)")
        dt_k = self.breakdown_temperature_c - self.room_temperature_c
        if self.alpha_per_k < 0 or self.alpha_per_k + 2 * self.beta_per_k2 * dt_k <= 0:
            raise ConfigError(
                f"alpha_per_k={self.alpha_per_k!r}, beta_per_k2={self.beta_per_k2!r}: g(T) must increase "
                "from room temperature up to the breakdown temperature"
            )

    @property
    def breakdown_rise_k(self) -> float:
        """ΔT_k = T_k − T_r, K."""
        return self.breakdown_temperature_c - self.room_temperature_c

    @property
    def breakdown_resistance_ohm(self) -> float:
        """g(T_k), Ω."""
        dt = self.breakdown_rise_k
        return self.room_resistance_ohm * (1.0 + self.alpha_per_k * dt + self.beta_per_k2 * dt * dt)

    def resistance(self, temperature_c) -> np.ndarray:
        """g(T), Ω, at ``temperature_c`` (°C, ≥ T_r)."""
        dt = np.asarray(temperature_c, dtype=np.float64) - self.room_temperature_c
        below = self.room_resistance_ohm * (1.0 + self.alpha_per_k * dt + self.beta_per_k2 * dt * dt)
        with np.errstate(divide="ignore", invalid="ignore"):
            above = self.breakdown_resistance_ohm * (np.maximum(dt, 1e-300) / self.breakdown_rise_k) ** (
                -self.intrinsic_exponent
            )
        return np.where(dt <= self.breakdown_rise_k, below, above)

    def slope(self, temperature_c) -> np.ndarray:
        """g′(T) = dR/dT, Ω/K (the left derivative at T_k)."""
        dt = np.asarray(temperature_c, dtype=np.float64) - self.room_temperature_c
        below = self.room_resistance_ohm * (self.alpha_per_k + 2.0 * self.beta_per_k2 * dt)
        with np.errstate(divide="ignore", invalid="ignore"):
            above = -self.intrinsic_exponent * self.resistance(temperature_c) / np.maximum(dt, 1e-300)
        return np.where(dt <= self.breakdown_rise_k, below, above)


# --------------------------------------------------------------------------- K_TP(t_s)


@dataclass(frozen=True)
class PowerTemperatureGain:
    """K_TP(t_s), the DC gain of Γ_TP against the tip-sample separation (Fig. 6.8(b)).

    K_TP(t_s) = K_far − (K_far − K_contact)·λ/(λ + max(t_s, 0)): heat flows
    to the sample through the gap, so the lever runs cooler (a lower
    K/W) close to the sample; in contact (t_s ≤ 0) K_TP = K_contact.

    Parameters
    ----------
    far_k_per_w : float
        K_far, the gain far from the sample, K/W.
    contact_k_per_w : float
        K_contact, the gain in contact, K/W (0 < K_contact ≤ K_far).
    decay_length_m : float
        λ, m.
    """

    far_k_per_w: float = 1.25e5
    contact_k_per_w: float = 0.95e5
    decay_length_m: float = 300e-9

    def __post_init__(self) -> None:
        _finite("far_k_per_w", self.far_k_per_w, positive=True)
        _finite("contact_k_per_w", self.contact_k_per_w, positive=True)
        _finite("decay_length_m", self.decay_length_m, positive=True)
        if self.contact_k_per_w > self.far_k_per_w:
            raise ConfigError(
                f"contact_k_per_w={self.contact_k_per_w!r} must not exceed far_k_per_w={self.far_k_per_w!r}"
            )

    def gain(self, separation_m) -> np.ndarray:
        """K_TP(t_s), K/W."""
        ts = np.maximum(np.asarray(separation_m, dtype=np.float64), 0.0)
        lam = self.decay_length_m
        return self.far_k_per_w - (self.far_k_per_w - self.contact_k_per_w) * lam / (lam + ts)

    def slope(self, separation_m) -> np.ndarray:
        """dK_TP/dt_s, K/(W·m) (0 in contact)."""
        ts = np.asarray(separation_m, dtype=np.float64)
        lam = self.decay_length_m
        value = (self.far_k_per_w - self.contact_k_per_w) * lam / (lam + np.maximum(ts, 0.0)) ** 2
        return np.where(ts >= 0, value, 0.0)


# --------------------------------------------------------------------------- D(s)


@dataclass(frozen=True)
class DiffusionLowPass:
    """Unit-DC-gain low-pass rolling off at about 10 dB/decade (heat diffusion).

    Heat conduction into a lever gives a half-order roll-off, |D| ∝ f^(−1/2)
    (§6.6.1: "10 dB/decade as expected from theoretical calculations").
    It is realised as interlaced real poles and zeros, p_i = ω_c·r^(2i),
    z_i = ω_c·r^(2i+1), r = 10^(1/(2·pairs_per_decade)):

    .. math:: D(s) = \\frac{\\prod_{i<N-1}(1 + s/z_i)}{\\prod_{i<N}(1 + s/p_i)},

    whose magnitude alternates between −20 and 0 dB/decade around a mean of
    −10 dB/decade from ω_c up to the last pole, then falls at
    −20 dB/decade.  N is the fewest poles that reach ``top_hz``.

    Parameters
    ----------
    corner_hz : float
        ω_c/2π, the first pole, Hz.
    top_hz : float
        The half-order behaviour extends up to here, Hz (> corner_hz).
    pairs_per_decade : int
        Pole-zero pairs per decade (2: ripple about ±0.5 dB).
    """

    corner_hz: float = 7000.0
    top_hz: float = 2.0e6
    pairs_per_decade: int = 2

    def __post_init__(self) -> None:
        _finite("corner_hz", self.corner_hz, positive=True)
        _finite("top_hz", self.top_hz, positive=True)
        if not self.top_hz > self.corner_hz:
            raise ConfigError(f"top_hz={self.top_hz!r} must exceed corner_hz={self.corner_hz!r}")
        if not (isinstance(self.pairs_per_decade, int) and self.pairs_per_decade >= 1):
            raise ConfigError(f"pairs_per_decade={self.pairs_per_decade!r} must be an integer >= 1")

    def poles_zeros_rad_s(self) -> tuple[np.ndarray, np.ndarray]:
        """(poles, zeros) as positive corner frequencies ω, rad/s (the roots are −ω)."""
        step = 1.0 / (2 * self.pairs_per_decade)  # decades between a pole and the next zero
        n_poles = int(math.ceil(math.log10(self.top_hz / self.corner_hz) / (2 * step))) + 1
        wc = 2 * math.pi * self.corner_hz
        poles = wc * 10.0 ** (2 * step * np.arange(n_poles))
        zeros = wc * 10.0 ** (2 * step * np.arange(n_poles - 1) + step)
        return poles, zeros

    def tf(self) -> tuple[np.ndarray, np.ndarray]:
        """(numerator, denominator) in descending powers of s (rad/s), unit DC gain."""
        poles, zeros = self.poles_zeros_rad_s()
        num = np.array([1.0])
        for z in zeros:
            num = np.polymul(num, [1.0 / z, 1.0])
        den = np.array([1.0])
        for p in poles:
            den = np.polymul(den, [1.0 / p, 1.0])
        return num, den

    def response(self, frequency_hz) -> np.ndarray:
        """D(j2πf), dimensionless."""
        s = 2j * np.pi * np.asarray(frequency_hz, dtype=np.float64)
        poles, zeros = self.poles_zeros_rad_s()
        out = np.ones(s.shape, dtype=np.complex128)
        for z in zeros:
            out = out * (1.0 + s / z)
        for p in poles:
            out = out / (1.0 + s / p)
        return out


# --------------------------------------------------------------------------- the sensor


@dataclass(frozen=True)
class ThermalSensor:
    """g(T), K_TP(t_s) and the dynamics D(s) of Γ_TP together."""

    resistance: ResistanceModel = ResistanceModel()
    gain: PowerTemperatureGain = PowerTemperatureGain()
    dynamics: DiffusionLowPass = DiffusionLowPass()


class SteadyState(NamedTuple):
    """Quasi-static state of the sensor (arrays broadcast from the inputs)."""

    temperature_c: np.ndarray
    resistance_ohm: np.ndarray
    current_a: np.ndarray
    power_w: np.ndarray
    k_tp_k_per_w: np.ndarray


def steady_state(sensor: ThermalSensor, v_r_v, separation_m) -> SteadyState:
    """Quasi-static temperature, resistance, current and power (§6.5.2).

    Solves T − T_r = K_TP(t_s)·V_R²/g(T) for T.  Below the knee
    (K_TP·V² ≤ g(T_k)·ΔT_k) it is the cubic R_r(ΔT + αΔT² + βΔT³) = K_TP·V²,
    increasing and convex in ΔT ≥ 0, solved by Newton's method from the
    upper bound K_TP·V²/R_r (monotone convergence, no overshoot).  Above
    the knee, ΔT^(1−ν) = K_TP·V²·ΔT_k^(−ν)/g(T_k) in closed form.

    Parameters
    ----------
    sensor : ThermalSensor
    v_r_v : array_like
        V_R, V.
    separation_m : array_like
        t_s, m (≤ 0: in contact).

    Returns
    -------
    SteadyState
        At V_R = 0 the sensor is at room temperature with I = P = 0.
    """
    g = sensor.resistance
    v, ts = np.broadcast_arrays(np.asarray(v_r_v, dtype=np.float64), np.asarray(separation_m, dtype=np.float64))
    k = sensor.gain.gain(ts)
    drive = k * v * v  # K·Ω, = ΔT·g(T) at equilibrium
    knee = g.breakdown_resistance_ohm * g.breakdown_rise_k
    rr, a, b = g.room_resistance_ohm, g.alpha_per_k, g.beta_per_k2
    dt = drive / rr
    for _ in range(100):
        f = rr * (dt + a * dt * dt + b * dt**3) - drive
        step = f / (rr * (1.0 + 2 * a * dt + 3 * b * dt * dt))
        dt = dt - step
        if np.all(np.abs(step) <= 1e-13 * np.maximum(dt, 1.0)):
            break
    nu = g.intrinsic_exponent
    with np.errstate(divide="ignore", invalid="ignore"):
        above = (drive * g.breakdown_rise_k**-nu / g.breakdown_resistance_ohm) ** (1.0 / (1.0 - nu))
    dt = np.where(drive <= knee, dt, above)
    temperature = g.room_temperature_c + dt
    resistance = g.resistance(temperature)
    current = v / resistance
    return SteadyState(temperature, resistance, current, v * current, k)


class OperatingPoint(NamedTuple):
    """Nominal point (V_R0, t_s0) of the small-signal model (Fig. 6.13), SI units."""

    v_r_v: float
    separation_m: float
    temperature_c: float
    resistance_ohm: float
    current_a: float
    power_w: float
    dg_dt_ohm_per_k: float
    k_tp_k_per_w: float
    dk_tp_dts_k_per_w_m: float


def operating_point(sensor: ThermalSensor, v_r_v: float, separation_m: float) -> OperatingPoint:
    """The steady state at (V_R0, t_s0) and the slopes g′(T0), K_TP′(t_s0)."""
    _finite("v_r_v", v_r_v)
    _finite("separation_m", separation_m)
    st = steady_state(sensor, v_r_v, separation_m)
    t0 = float(st.temperature_c)
    if t0 > sensor.resistance.breakdown_temperature_c:
        raise ConfigError(f"v_r_v={v_r_v!r} heats the sensor to {t0:.0f} °C, beyond the breakdown temperature")
    return OperatingPoint(
        v_r_v=float(v_r_v),
        separation_m=float(separation_m),
        temperature_c=t0,
        resistance_ohm=float(st.resistance_ohm),
        current_a=float(st.current_a),
        power_w=float(st.power_w),
        dg_dt_ohm_per_k=float(sensor.resistance.slope(t0)),
        k_tp_k_per_w=float(st.k_tp_k_per_w),
        dk_tp_dts_k_per_w_m=float(sensor.gain.slope(separation_m)),
    )


# --------------------------------------------------------------------------- eqs. 6.9-6.12


def gamma_ir_vr(c_k_per_w, op: OperatingPoint) -> np.ndarray:
    """Γ_IR,VR = (1/R0)(1 − g′CI0²)/(1 + g′CI0²) (eq. 6.9), A/V.

    ``c_k_per_w`` is C(jω) (K/W) at the frequencies of interest.
    """
    x = op.dg_dt_ohm_per_k * np.asarray(c_k_per_w) * op.current_a**2
    return (1.0 - x) / (1.0 + x) / op.resistance_ohm


def gamma_ir_ts(h_k_per_m, c_k_per_w, op: OperatingPoint) -> np.ndarray:
    """Γ_IR,ts = −(I0/R0)·g′H/(1 + g′CI0²) (eq. 6.10), A/m."""
    x = op.dg_dt_ohm_per_k * np.asarray(c_k_per_w) * op.current_a**2
    return -op.current_a / op.resistance_ohm * op.dg_dt_ohm_per_k * np.asarray(h_k_per_m) / (1.0 + x)


def c_from_gamma_ir_vr(gamma_a_per_v, current_a: float, resistance_ohm: float, dg_dt_ohm_per_k: float) -> np.ndarray:
    """C(jω) = (1/(I0²g′))·(1 − R0Γ_IR,VR)/(1 + R0Γ_IR,VR) (eq. 6.11), K/W.

    Parameters
    ----------
    gamma_a_per_v : array_like of complex
        Measured Γ_IR,VR, A/V.
    current_a, resistance_ohm : float
        I_R0 (A) and R0 = V_R0/I_R0 (Ω) at the operating point.
    dg_dt_ohm_per_k : float
        g′(T0), Ω/K, from the g(T) identified by an I-V ramp.
    """
    _finite("current_a", current_a)
    _finite("resistance_ohm", resistance_ohm, positive=True)
    _finite("dg_dt_ohm_per_k", dg_dt_ohm_per_k)
    if current_a == 0 or dg_dt_ohm_per_k == 0:
        raise ConfigError(f"eq. 6.11 needs current_a={current_a!r} and dg_dt_ohm_per_k={dg_dt_ohm_per_k!r} nonzero")
    r_gamma = resistance_ohm * np.asarray(gamma_a_per_v)
    return (1.0 - r_gamma) / (1.0 + r_gamma) / (current_a**2 * dg_dt_ohm_per_k)


def h_from_gammas(
    gamma_ir_ts_a_per_m, gamma_ir_vr_a_per_v, current_a: float, resistance_ohm: float, dg_dt_ohm_per_k: float
) -> np.ndarray:
    """H(jω) = −R0/(I0g′)·Γ_IR,ts·2/(1 + R0Γ_IR,VR) (eq. 6.12), K/m.

    Both responses must be on the same frequencies and at the same
    operating point.
    """
    _finite("current_a", current_a)
    _finite("resistance_ohm", resistance_ohm, positive=True)
    _finite("dg_dt_ohm_per_k", dg_dt_ohm_per_k)
    if current_a == 0 or dg_dt_ohm_per_k == 0:
        raise ConfigError(f"eq. 6.12 needs current_a={current_a!r} and dg_dt_ohm_per_k={dg_dt_ohm_per_k!r} nonzero")
    r_gamma = resistance_ohm * np.asarray(gamma_ir_vr_a_per_v)
    return -resistance_ohm / (current_a * dg_dt_ohm_per_k) * np.asarray(gamma_ir_ts_a_per_m) * 2.0 / (1.0 + r_gamma)


# --------------------------------------------------------------------------- a fitted g(T)


@dataclass(frozen=True)
class ResistanceFit:
    """An identified g(T): R = Σ_i c_i·(T − T_r)^i for T_r ≤ T ≤ T_max (§6.5.2, Fig. 6.7(b)).

    Parameters
    ----------
    room_temperature_c : float
        T_r, °C.
    coefficients_ohm : tuple of float
        c_0, c_1, …: Ω, Ω/K, Ω/K², … (ascending powers of ΔT in K).
    max_temperature_c : float
        T_max, the top of the data behind the fit (the breakdown T_k for an
        I-V ramp), °C.

    Raises
    ------
    ConfigError
        For non-finite values, no coefficients, T_max ≤ T_r, or a g that
        is not increasing on [T_r, T_max] (then g⁻¹ is not single valued).
    """

    room_temperature_c: float
    coefficients_ohm: tuple[float, ...]
    max_temperature_c: float

    def __post_init__(self) -> None:
        _finite("room_temperature_c", self.room_temperature_c)
        _finite("max_temperature_c", self.max_temperature_c)
        if not self.coefficients_ohm or not all(math.isfinite(c) for c in self.coefficients_ohm):
            raise ConfigError(f"coefficients_ohm={self.coefficients_ohm!r} must be finite numbers (at least one)")
        object.__setattr__(self, "coefficients_ohm", tuple(float(c) for c in self.coefficients_ohm))
        if not self.max_temperature_c > self.room_temperature_c:
            raise ConfigError(
                f"max_temperature_c={self.max_temperature_c!r} must exceed room_temperature_c={self.room_temperature_c!r}"
            )
        grid = np.linspace(self.room_temperature_c, self.max_temperature_c, 512)
        if not np.all(self.slope(grid) > 0):
            raise ConfigError("the fitted g(T) does not increase over its range; g^-1 would not be single valued")

    def resistance(self, temperature_c) -> np.ndarray:
        """g(T), Ω."""
        dt = np.asarray(temperature_c, dtype=np.float64) - self.room_temperature_c
        return np.polynomial.polynomial.polyval(dt, self.coefficients_ohm)

    def slope(self, temperature_c) -> np.ndarray:
        """g′(T), Ω/K."""
        dt = np.asarray(temperature_c, dtype=np.float64) - self.room_temperature_c
        return np.polynomial.polynomial.polyval(dt, np.polynomial.polynomial.polyder(self.coefficients_ohm))

    def temperature(self, resistance_ohm) -> np.ndarray:
        """g⁻¹(R), °C; NaN outside [g(T_r), g(T_max)].

        Newton's method on the monotone polynomial from the linear
        interpolation of a 2049-point table (converges in a few steps).
        """
        r = np.asarray(resistance_ohm, dtype=np.float64)
        grid = np.linspace(self.room_temperature_c, self.max_temperature_c, 2049)
        table = self.resistance(grid)
        t = np.interp(r, table, grid)
        for _ in range(20):
            t = t - (self.resistance(t) - r) / self.slope(t)
        inside = (r >= table[0]) & (r <= table[-1])
        return np.where(inside, t, np.nan)

    def record(self) -> ResistanceFitRecord:
        """The fit as a result record (``identify thermal``'s ``iv.g_fit`` and ``thermal_sensor.g``)."""
        return ResistanceFitRecord(
            room_temperature_c=self.room_temperature_c,
            coefficients_ohm=self.coefficients_ohm,
            max_temperature_c=self.max_temperature_c,
            form="R = sum_i c_i (T - T_r)^i, T in degC, R in ohm",
        )

    def to_dict(self) -> dict:
        return self.record().to_json()  # every number is finite (checked on construction)

    @classmethod
    def from_dict(cls, data) -> ResistanceFit:
        try:
            return cls(float(data["room_temperature_c"]), tuple(data["coefficients_ohm"]),
                       float(data["max_temperature_c"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(f"not a g(T) fit: {exc}") from None
