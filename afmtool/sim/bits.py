"""Scenario ``bits``: probe-storage read-back, an electrostatically actuated lever over a bit stream (§7.6).

The lever of :mod:`afmtool.sim.electrostatic_plant` (eq. 7.11, thesis
parameters of §7.2 by default) is actuated through the substrate at
``actuation_hz`` (100 kHz, above the 57.2 kHz resonance) while the sample
moves under it by a random bit topography: after a bit-free nominal segment
of ``nominal_s``, cell k covers [nominal_s + k/R, nominal_s + (k+1)/R) at
height ``bit_height_nm``·b_k, with b_k independent fair bits and R =
``bit_rate_hz`` (the "minimum bit width corresponding to R": one cell is the
narrowest feature; runs of equal bits make wider ones).  Edges are raised
cosines ``edge_s`` long, centred on the cell boundaries.

Voltages (eq. 6.3): the lever legs carry a constant read voltage V_R
(channel ``v_r``), the substrate V_sub(t) = V_dc + V_ac·sin(2π f_a t)
(channel ``v_sub``), and the lever-sample voltage is V = α_R·V_R − V_sub.
The deflection (channel ``deflection``, nm) carries thermal noise at
``temperature_k`` and white measurement noise.

Ground truth (``/truth``, one value per sample): ``topography_nm``,
``bit`` (uint8, the bit under the tip; 0 in the nominal segment),
``bit_index`` (int32, the cell under the tip, −1 in the nominal segment;
a bit's time is the centre of its cell), ``l0_nm`` (ℓ0, constant) and
``deflection_clean``.
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
from afmtool.sim.electrostatic_plant import default_settle_s, simulate_plant
from afmtool.sim.tapping import thermal_accel_rms

__all__ = ["BitsParams", "BitPattern", "simulate_bits", "electrostatic_metadata"]

_TH = THESIS_CH7_PARAMS


def _positive(default, text, units, **kw):
    return param(default, text, units, minimum=0, exclusive_minimum=True, **kw)


@dataclass(frozen=True)
class BitsParams:
    """Parameters of the ``bits`` scenario (defaults: the thesis experiment of §7.6, 50 kHz bits)."""

    duration_s: float = _positive(0.02, "capture length", "s")
    sample_rate_hz: float = _positive(2e6, "sample rate", "Hz")
    substeps: int = param(4, "RK4 steps per sample period", "", minimum=1)
    f0_hz: float = _positive(57185.0, "resonant frequency f0 (§7.2)", "Hz")
    q: float = param(1.0148, "quality factor Q (§7.2)", "", minimum=0.5, exclusive_minimum=True)
    spring_constant_n_per_m: float = _positive(_TH.spring_constant_n_per_m, "spring constant k (eq. 7.10)", "N/m")
    k_esf_f_m: float = _positive(_TH.k_esf_f_m, "K_esf, no-½ convention (eq. 7.10)", "F·m")
    alpha_r: float = param(_TH.alpha_r, "α_R, share of V_R on the lever (eq. 7.10)", "")
    l0_nm: float = _positive(_TH.l0_m * 1e9, "ℓ0, lever-sample separation at p = 0 (eq. 7.10)", "nm")
    tip_height_nm: float = _positive(_TH.tip_height_m * 1e9, "tip height t_h (eq. 7.10)", "nm")
    actuation_hz: float = _positive(100e3, "substrate actuation frequency f_a", "Hz")
    read_voltage_v: float = param(4.0, "constant V_R on the lever legs (channel v_r)", "V")
    substrate_dc_v: float = param(-1.8, "DC part of V_sub", "V")
    substrate_ac_v: float = param(0.8, "amplitude of V_sub at actuation_hz", "V", minimum=0)
    bit_rate_hz: float = _positive(50e3, "bit rate R: one cell is 1/R long (the minimum bit width)", "Hz")
    bit_height_nm: float = param(4.0, "height of a 1 bit (thesis: below 5 nm)", "nm", minimum=0)
    edge_s: float = param(2e-6, "raised-cosine edge duration of the bits", "s", minimum=0)
    nominal_s: float = param(0.002, "bit-free nominal segment at the start", "s", minimum=0)
    temperature_k: float = param(300.0, "temperature of the thermal force noise", "K", minimum=0)
    measurement_noise_nm: float = param(0.05, "rms white noise added to the recorded deflection", "nm", minimum=0)
    settle_s: float = param(-1.0, "noise-free pre-roll before t = 0; < 0 = 12·2Q/ω0", "s")

    def __post_init__(self) -> None:
        validate_parameters(self)
        nyquist = self.sample_rate_hz / 2
        if self.f0_hz >= nyquist or 2 * self.actuation_hz >= nyquist:
            raise ConfigError(
                f"f0_hz={self.f0_hz!r} and 2·actuation_hz={2 * self.actuation_hz!r} must be below "
                f"sample_rate_hz/2 = {nyquist:g}"
            )
        if self.bit_rate_hz >= nyquist:
            raise ConfigError(f"bit_rate_hz={self.bit_rate_hz!r} must be below sample_rate_hz/2 = {nyquist:g}")
        if self.edge_s * self.bit_rate_hz >= 1:
            raise ConfigError(f"edge_s={self.edge_s!r} must be shorter than one bit cell 1/bit_rate_hz")
        if self.nominal_s > self.duration_s:
            raise ConfigError(f"nominal_s={self.nominal_s!r} must not exceed duration_s={self.duration_s!r}")
        if self.tip_height_nm >= self.l0_nm - self.bit_height_nm:
            raise ConfigError(f"tip_height_nm={self.tip_height_nm!r} must be below l0_nm - bit_height_nm")

    def cantilever(self) -> Cantilever:
        return Cantilever(self.f0_hz, self.q, self.spring_constant_n_per_m)

    def electrostatic(self) -> ElectrostaticParams:
        return ElectrostaticParams(
            self.spring_constant_n_per_m, self.k_esf_f_m, self.alpha_r, self.l0_nm * 1e-9, self.tip_height_nm * 1e-9
        )

    def voltage(self, t_s: np.ndarray) -> np.ndarray:
        """V = α_R·V_R − V_sub(t) (eq. 6.3), V."""
        return self.alpha_r * self.read_voltage_v - self.substrate_voltage(t_s)

    def substrate_voltage(self, t_s: np.ndarray) -> np.ndarray:
        """V_sub(t) = V_dc + V_ac·sin(2π f_a t), V."""
        t = np.asarray(t_s, dtype=np.float64)
        return self.substrate_dc_v + self.substrate_ac_v * np.sin(2.0 * np.pi * self.actuation_hz * t)


@dataclass(frozen=True)
class BitPattern:
    """A bit stream on the sample: cells of 1/rate_hz from start_s, raised-cosine edges."""

    bits: np.ndarray  #: uint8, one per cell
    start_s: float
    rate_hz: float
    height_nm: float
    edge_s: float

    def cell_index(self, t_s: np.ndarray) -> np.ndarray:
        """Index of the cell containing t (int64), −1 before start_s or after the last cell."""
        k = np.floor((np.asarray(t_s, dtype=np.float64) - self.start_s) * self.rate_hz).astype(np.int64)
        return np.where((k >= 0) & (k < len(self.bits)), k, -1)

    def level(self, t_s: np.ndarray) -> np.ndarray:
        """The bit under the tip without edges (uint8; 0 outside the cells)."""
        k = self.cell_index(t_s)
        padded = np.append(self.bits, 0).astype(np.uint8)  # index −1 reads the trailing 0
        return padded[k]

    def height(self, t_s: np.ndarray) -> np.ndarray:
        """Topography z(t), nm: the levels joined by raised-cosine edges of edge_s centred on boundaries."""
        t = np.asarray(t_s, dtype=np.float64)
        padded = np.concatenate(([0], self.bits, [0])).astype(np.float64)  # cell −1 and cell n are 0
        j = np.rint((t - self.start_s) * self.rate_hz).astype(np.int64)  # nearest boundary j (cells j−1 | j)
        j = np.clip(j, 0, len(self.bits))
        before = padded[j]  # level of cell j − 1
        after = padded[j + 1]  # level of cell j
        if self.edge_s > 0:
            x = (t - (self.start_s + j / self.rate_hz)) / self.edge_s + 0.5
            s = 0.5 - 0.5 * np.cos(np.pi * np.clip(x, 0.0, 1.0))
        else:
            s = (t >= self.start_s + j / self.rate_hz).astype(np.float64)
        return self.height_nm * (before + (after - before) * s)


def electrostatic_metadata(es: ElectrostaticParams) -> dict:
    """The ``electrostatic`` metadata object (no ℓ0: it is what the decoder estimates)."""
    return {
        "k_esf_f_m": es.k_esf_f_m,
        "alpha_r": es.alpha_r,
        "tip_height_m": es.tip_height_m,
        "convention": "F_esf = -K_esf*V^2/(l0 + p - z)^2, no 1/2, SI; V = alpha_R*V_R - V_sub",
    }


def simulate_bits(params: BitsParams, seed: int) -> SimulatedCapture:
    """Electrostatically actuated lever reading a random bit stream (§7.6), RK4.

    Parameters
    ----------
    params : BitsParams
        Scenario parameters.
    seed : int
        Seed of ``numpy.random.default_rng`` (bits, then thermal, then
        measurement noise).

    Returns
    -------
    SimulatedCapture
        Channels ``v_sub`` (V), ``v_r`` (V), ``deflection`` (nm); truth as in
        the module docstring; metadata ``cantilever``, ``electrostatic``,
        ``drive``, ``nominal`` (the bit-free segment) and ``bits``.
    """
    fs = params.sample_rate_hz
    n = sample_count(params.duration_s, fs, "duration_s")
    cantilever = params.cantilever()
    es = params.electrostatic()
    n_cells = sample_count(params.duration_s - params.nominal_s, params.bit_rate_hz, "bit cells", ceil=True)
    rng = np.random.default_rng(seed)
    pattern = BitPattern(
        rng.integers(0, 2, n_cells).astype(np.uint8), params.nominal_s, params.bit_rate_hz,
        params.bit_height_nm, params.edge_s,
    )
    sigma_eta = thermal_accel_rms(cantilever, params.temperature_k, fs) if params.temperature_k > 0 else 0.0
    accel_noise = sigma_eta * rng.standard_normal(n)
    measurement = params.measurement_noise_nm * rng.standard_normal(n)
    settle = default_settle_s(cantilever) if params.settle_s < 0 else params.settle_s
    clean = simulate_plant(
        params.voltage, pattern.height, accel_noise, sample_rate_hz=fs, substeps=params.substeps,
        cantilever=cantilever, electrostatic=es, settle_s=settle,
    )
    t = np.arange(n) / fs
    channels = (ChannelSpec("v_sub", "V"), ChannelSpec("v_r", "V"), ChannelSpec("deflection", "nm"))
    data = {
        "v_sub": params.substrate_voltage(t),
        "v_r": np.full(n, params.read_voltage_v),
        "deflection": clean + measurement,
    }
    truth = {
        "topography_nm": pattern.height(t),
        "bit": pattern.level(t),
        "bit_index": pattern.cell_index(t).astype(np.int32),
        "l0_nm": np.full(n, params.l0_nm),
        "deflection_clean": clean,
    }
    metadata = {
        "scenario": "bits",
        "cantilever": cantilever.to_metadata(),
        "electrostatic": electrostatic_metadata(es),
        "drive": {
            "kind": "electrostatic",
            "frequency_hz": float(params.actuation_hz),
            "substrate_dc_v": float(params.substrate_dc_v),
            "substrate_ac_v": float(params.substrate_ac_v),
            "read_voltage_v": float(params.read_voltage_v),
        },
        "bits": {
            "rate_hz": float(params.bit_rate_hz),
            "height_nm": float(params.bit_height_nm),
            "start_s": float(params.nominal_s),
            "count": n_cells,
        },
        "noise": {
            "temperature_k": float(params.temperature_k),
            "thermal_accel_rms_nm_per_s2": float(sigma_eta),
            "measurement_noise_nm": float(params.measurement_noise_nm),
        },
        "integrator": {"method": "rk4", "substeps": params.substeps, "settle_s": float(settle)},
    }
    if params.nominal_s > 0:
        metadata["nominal"] = {"start_s": 0.0, "end_s": float(params.nominal_s)}
    return SimulatedCapture(fs, channels, data, metadata, truth)


register_scenario("bits", BitsParams, simulate_bits)
