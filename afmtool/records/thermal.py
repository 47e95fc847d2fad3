"""``identify thermal``'s results: g(T) and K_TP from an I-V ramp, K_TP(t_s) from a z curve, C(jω) and H(jω).

Each route's section is present when its capture was given (``--iv``, ``--z-curve``,
``--vr-sweep``); ``thermal_sensor`` is the model the run wrote to
``thermal_sensor.json`` (:class:`ThermalSensorRecord` mirrors
:class:`afmtool.models.thermal_model.ThermalModel`, which sits above this floor;
``ThermalModel.record()`` converts).
"""

from __future__ import annotations

from afmtool.records.base import Item, Record, optional, record
from afmtool.records.gamma import ResponseMethod

__all__ = [
    "ResistanceFitRecord", "KtpTableRecord", "ThermalSensorRecord", "IvRecord", "ZCurveRecord",
    "ThermalOperatingPointRecord", "CSummaryRecord", "HSummaryRecord", "DynamicsRecord", "ThermalResults",
]


@record
class ResistanceFitRecord(Record):
    """An identified g(T): R = Σ_i c_i·(T − T_r)^i for T_r ≤ T ≤ T_max (§6.5.2).

    Attributes
    ----------
    room_temperature_c : float
        T_r (°C).
    coefficients_ohm : tuple of float
        c_0, c_1, …: Ω, Ω/K, Ω/K², … (ascending powers of T − T_r in K).
    max_temperature_c : float
        T_max, the top of the data behind the fit (°C).
    form : str
        The polynomial, in words.
    """

    room_temperature_c: float
    coefficients_ohm: tuple[float, ...]
    max_temperature_c: float
    form: str


@record
class KtpTableRecord(Record):
    """K_TP against the tip-sample separation, from a z force curve (t_s from the snap-in).

    Attributes
    ----------
    separation_m : tuple of float
        t_s of each bin (m).
    k_tp_k_per_w : tuple of float
        K_TP there (K/W).
    """

    separation_m: tuple[float, ...]
    k_tp_k_per_w: tuple[float, ...]


@record
class ThermalSensorRecord(Record):
    """The thermal sensor model of the run, as ``thermal_sensor.json`` holds it.

    Attributes
    ----------
    g : ResistanceFitRecord or None
        g(T); None when neither this run nor the prior model has an I-V ramp.
    breakdown_temperature_c : float
        The breakdown temperature T_k (°C).
    k_tp_k_per_w : float or None
        K_TP from the I-V knee, at the ramp's separation (K/W).
    knee_power_w : float or None
        The knee power P_k (W).
    knee_voltage_v : float or None
        The knee voltage (V).
    k_tp_table : KtpTableRecord or None
        K_TP(t_s) from a z force curve.
    contact_k_tp_k_per_w : float or None
        K_TP in contact (K/W).
    k_tp_definition : str
        What K_TP is, in words.
    """

    g: ResistanceFitRecord | None
    breakdown_temperature_c: float
    k_tp_k_per_w: float | None
    knee_power_w: float | None
    knee_voltage_v: float | None
    k_tp_table: KtpTableRecord | None
    contact_k_tp_k_per_w: float | None
    k_tp_definition: str


@record
class IvRecord(Record):
    """The I-V ramp route: the breakdown knee, K_TP and g(T).

    Attributes
    ----------
    knee_voltage_v : float
        V_R at the knee (V).
    knee_power_mw : float
        The knee power P_k (mW).
    k_tp_k_per_w : float
        K_TP = (T_k − T_r)/P_k (K/W).
    k_tp_k_per_mw : float
        The same in K/mW.
    slope_below_knee : float
        d ln P/d ln V_R just below the knee.
    slope_above_knee : float
        The same just above the knee (steep, where R falls).
    knee_rms_log_residual : float
        RMS residual of the broken-line fit, in ln P.
    g_fit : ResistanceFitRecord
        The fitted g(T).
    g_rms_relative_residual : float
        RMS of (R − g(T))/g(T) over the samples below the knee.
    samples_used : int
        Ramp samples used.
    """

    knee_voltage_v: float
    knee_power_mw: float
    k_tp_k_per_w: float
    k_tp_k_per_mw: float
    slope_below_knee: float
    slope_above_knee: float
    knee_rms_log_residual: float
    g_fit: ResistanceFitRecord
    g_rms_relative_residual: float
    samples_used: int


@record
class ZCurveRecord(Record):
    """The z force curve route: K_TP against the separation from the snap-in.

    Attributes
    ----------
    snap_in_z_nm : float
        z at the snap-in (nm).
    snap_in_jump_ua : float
        The jump of the thermal current there (µA).
    contact_k_tp_k_per_mw : float
        Mean K_TP in contact on the approach leg, after snap-in (K/mW).
    separation_range_nm : tuple of 2 float
        The t_s range of the bins (nm).
    k_tp_range_k_per_mw : tuple of 2 float
        The K_TP range of the bins (K/mW).
    bins : int
        Separation bins.
    separation_convention : str
        How t_s is counted, in words.
    """

    snap_in_z_nm: float
    snap_in_jump_ua: float
    contact_k_tp_k_per_mw: float
    separation_range_nm: tuple[float, float]
    k_tp_range_k_per_mw: tuple[float, float]
    bins: int
    separation_convention: str


@record
class ThermalOperatingPointRecord(Record):
    """The operating point of the V_R sweep (its means) and what g(T) gives there.

    Attributes
    ----------
    v_r_v : float
        V_R0 (V).
    current_a : float
        I_R0 (A).
    resistance_ohm : float
        R0 = V_R0/I_R0 (Ω).
    temperature_c : float
        T0 = g⁻¹(R0) (°C).
    dg_dt_ohm_per_k : float
        g′(T0) (Ω/K).
    """

    v_r_v: float
    current_a: float
    resistance_ohm: float
    temperature_c: float
    dg_dt_ohm_per_k: float


@record
class CSummaryRecord(Record):
    """C(jω) (eq. 6.11) summarised over its coherent band; every field absent when it has no summary.

    Attributes
    ----------
    dc_gain_k_per_mw : float
        C(0), signed (K/mW).
    bandwidth_hz : float
        −3 dB bandwidth (Hz); null where |C| never falls 3 dB.
    roll_off_db_per_decade : float
        Roll-off above the bandwidth (dB/decade); null without a bandwidth.
    roll_off_band_hz : tuple of 2 float
        The band of the roll-off fit (Hz).
    """

    # optional(): a response with no summary (too few coherent bins) is written {}
    dc_gain_k_per_mw: float | None = optional()
    bandwidth_hz: float | None = optional()
    roll_off_db_per_decade: float | None = optional()
    roll_off_band_hz: tuple[float, float] | None = optional()


@record
class HSummaryRecord(Record):
    """H(jω) (eq. 6.12) summarised over its coherent band; every field absent when it has no summary.

    Attributes
    ----------
    dc_gain_k_per_nm : float
        H(0), signed (K/nm).
    bandwidth_hz : float
        −3 dB bandwidth (Hz); null where |H| never falls 3 dB.
    roll_off_db_per_decade : float
        Roll-off above the bandwidth (dB/decade); null without a bandwidth.
    roll_off_band_hz : tuple of 2 float
        The band of the roll-off fit (Hz).
    """

    # optional(): a response with no summary (too few coherent bins) is written {}
    dc_gain_k_per_nm: float | None = optional()
    bandwidth_hz: float | None = optional()
    roll_off_db_per_decade: float | None = optional()
    roll_off_band_hz: tuple[float, float] | None = optional()


@record
class DynamicsRecord(Record):
    """The V_R sweep route: C(jω) by eq. 6.11 and, with ``--gamma``, H(jω) by eq. 6.12.

    Attributes
    ----------
    method : ResponseMethod
        How Γ_IR,VR was estimated.
    operating_point : ThermalOperatingPointRecord
        The sweep's operating point.
    lever_motion_removed : bool
        The lever's motion under α_R·ΔV_R was removed (``--gamma`` and a deflection channel).
    c : CSummaryRecord
        C(jω).
    h : HSummaryRecord or None
        H(jω), with ``--gamma``.
    """

    method: ResponseMethod
    operating_point: ThermalOperatingPointRecord
    lever_motion_removed: bool
    c: CSummaryRecord
    h: HSummaryRecord | None = optional()


@record
class ThermalResults(Record):
    """The thermal sensor from its current alone (thesis §6.5.2, §6.6.2), one section per route run.

    Attributes
    ----------
    breakdown_temperature_c : float
        The breakdown temperature T_k assumed (°C).
    room_temperature_c : float
        The room temperature T_r assumed (°C).
    iv : IvRecord or None
        The I-V ramp route (``--iv``).
    z_curve : ZCurveRecord or None
        The z force curve route (``--z-curve``).
    dynamics : DynamicsRecord or None
        The V_R sweep route (``--vr-sweep``).
    thermal_sensor : ThermalSensorRecord
        The model written to ``thermal_sensor.json``: this run's findings, completed by ``--model``'s.
    """

    breakdown_temperature_c: float
    room_temperature_c: float
    iv: IvRecord | None = optional()
    z_curve: ZCurveRecord | None = optional()
    dynamics: DynamicsRecord | None = optional()
    thermal_sensor: ThermalSensorRecord

    HEADLINE = (
        Item("K_TP (I-V knee)", "iv.k_tp_k_per_mw", "K/mW"),
        Item("knee power", "iv.knee_power_mw", "mW"),
        Item("knee voltage", "iv.knee_voltage_v", "V"),
        Item("K_TP in contact (z curve)", "z_curve.contact_k_tp_k_per_mw", "K/mW"),
        Item("snap-in z", "z_curve.snap_in_z_nm", "nm"),
        Item("C(jω) DC gain", "dynamics.c.dc_gain_k_per_mw", "K/mW"),
        Item("C(jω) −3 dB bandwidth", "dynamics.c.bandwidth_hz", "Hz"),
        Item("H(jω) DC gain", "dynamics.h.dc_gain_k_per_nm", "K/nm"),
        Item("H(jω) −3 dB bandwidth", "dynamics.h.bandwidth_hz", "Hz"),
    )
