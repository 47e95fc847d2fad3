"""Thermal-sensor identification from the thermal current alone (thesis §6.5.2, §6.6.2).

Three routes, combinable:

* **I-V ramp** (``v_r``, ``thermal_current``): R = V_R/I_R, P = V_R·I_R;
  the knee P_k of the P-V_R curve is where the sensor breaks down at the
  known T_k, so K_TP = (T_k − T_r)/P_k (the slope of the line from (0, T_r)
  to (P_k, T_k), the DC gain of Γ_TP); then T = T_r + K_TP·P below the knee
  gives the table of g(T) and its polynomial fit (:func:`identify_iv`).
* **z force curve** (``z_piezo``, ``v_r``, ``thermal_current``), with g(T):
  T = g⁻¹(V/I), K_TP = (T − T_r)/P at every sample, and t_s = z_sn − z with
  the snap-in z_sn taken as t_s = 0 (:func:`identify_z_curve`).
* **V_R perturbation sweep** (``v_r``, ``thermal_current``), with g(T):
  C(jω) by eq. 6.11 and, given Γ_IR,ts from ``identify gamma``, H(jω) by
  eq. 6.12 (:func:`thermal_dynamics`).

K_TP is reported in K/W (the thesis quotes °C/mW: 1 K/mW = 1000 K/W).  The
thesis also writes "K_TP = P/T" in the z-curve step, the reciprocal of the
DC gain it defines one paragraph earlier; afmtool uses the DC gain
(T − T_r)/P throughout, consistent with C(jω)'s "111 °C/mW".
Currents are in A, voltages in V, temperatures in °C, separations in m.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import NamedTuple

import numpy as np
import scipy.optimize

from afmtool.errors import ConfigError, InputError
from afmtool.estimators.frequency_response import FrequencyResponse
from afmtool.models.thermal_sensor import ResistanceFit, c_from_gamma_ir_vr, h_from_gammas

__all__ = [
    "IvCurve",
    "iv_curve",
    "Knee",
    "detect_knee",
    "GTable",
    "g_table",
    "fit_resistance",
    "IvIdentification",
    "identify_iv",
    "KtpCurve",
    "identify_z_curve",
    "k_tp_from_current",
    "monotone_k_tp",
    "separation_from_current",
    "SweepOperatingPoint",
    "ThermalDynamics",
    "thermal_dynamics",
]


# --------------------------------------------------------------------------- I-V ramp


class IvCurve(NamedTuple):
    """Samples of an I-V ramp with V_R above a floor: V (V), I (A), R = V/I (Ω), P = V·I (W)."""

    v_r_v: np.ndarray
    current_a: np.ndarray
    resistance_ohm: np.ndarray
    power_w: np.ndarray


def iv_curve(v_r_v, current_a, *, min_voltage_fraction: float = 0.02) -> IvCurve:
    """R = V_R/I_R and P = V_R²/R = V_R·I_R for samples with V_R ≥ fraction·max V_R and I_R > 0.

    Near V_R = 0 the current carries no information about R (I ≈ 0 ± noise).
    """
    v = np.asarray(v_r_v, dtype=np.float64)
    i = np.asarray(current_a, dtype=np.float64)
    if v.shape != i.shape or v.ndim != 1:
        raise InputError(f"v_r and thermal_current must be 1-D of equal length, got {v.shape} and {i.shape}")
    if not 0 <= min_voltage_fraction < 1:
        raise ConfigError(f"min_voltage_fraction={min_voltage_fraction!r} must be in [0, 1)")
    top = float(np.max(np.abs(v))) if v.size else 0.0
    if top <= 0:
        raise InputError("V_R is zero throughout: not an I-V ramp")
    keep = (np.abs(v) >= min_voltage_fraction * top) & (i * np.sign(v) > 0)
    v, i = np.abs(v[keep]), np.abs(i[keep])
    return IvCurve(v, i, v / i, v * i)


class Knee(NamedTuple):
    """The breakdown knee of the P-V_R curve (§6.5.2, Fig. 6.7(a)).

    voltage_v, power_w : float
        V_k (V) and P_k (W).
    slope_below, slope_above : float
        d ln P/d ln V just below and above the knee (≈ 2 − d ln R/d ln V
        below; steep above, where R falls).
    rms_log_residual : float
        Of the broken-line fit, in ln P.
    n_above : int
        Samples above the knee.
    """

    voltage_v: float
    power_w: float
    slope_below: float
    slope_above: float
    rms_log_residual: float
    n_above: int


def _hinge_fit(x: np.ndarray, y: np.ndarray, xk: float) -> tuple[float, np.ndarray]:
    """SSE and coefficients of y ≈ a0 + a1·u₋ + a2·u₋² + c1·u₊, u = x − x_k (continuous at x_k)."""
    u = x - xk
    below, above = np.minimum(u, 0.0), np.maximum(u, 0.0)
    basis = np.column_stack((np.ones_like(x), below, below * below, above))
    coefficients, *_ = np.linalg.lstsq(basis, y, rcond=None)
    r = basis @ coefficients - y
    return float(r @ r), coefficients


def detect_knee(v_r_v, power_w, *, fit_fraction: float = 0.5, min_slope_change: float = 1.0) -> Knee:
    """Locate the knee P_k of the P-V_R relation by a broken-line fit in (ln V, ln P).

    Parameters
    ----------
    v_r_v, power_w : array_like
        V_R (V) and P (W) of an I-V ramp (:func:`iv_curve`), up and down legs together.
    fit_fraction : float
        Only V_R ≥ ``fit_fraction``·max V_R is fitted.
    min_slope_change : float
        The knee must raise d ln P/d ln V by at least this much; otherwise
        the ramp did not reach breakdown.

    Returns
    -------
    Knee

    Notes
    -----
    Below the knee P(V) is smooth, so ln P is modelled as a quadratic in
    u = ln V − ln V_k; above it as a straight line; the two meet at
    (ln V_k, ln P_k).  For each trial V_k the fit is linear least squares;
    V_k minimises the sum of squares (grid over the data, then a bounded
    scalar minimisation between the grid neighbours).  With the breakdown
    a kink of g(T) at T_k, the fitted meeting point is the knee exactly
    (up to noise): P_k = (T_k − T_r)/K_TP.

    Raises
    ------
    InputError
        With too few points, a knee at either end of the data, or a slope
        change below ``min_slope_change`` (no breakdown in the ramp).
    """
    v = np.asarray(v_r_v, dtype=np.float64)
    p = np.asarray(power_w, dtype=np.float64)
    if not 0 < fit_fraction < 1:
        raise ConfigError(f"fit_fraction={fit_fraction!r} must be in (0, 1)")
    keep = (v >= fit_fraction * np.max(v)) & (p > 0)
    x, y = np.log(v[keep]), np.log(p[keep])
    if x.size < 12:
        raise InputError(f"only {x.size} I-V points above {fit_fraction:g}·max V_R; cannot place a knee")
    xs = np.unique(x)
    if xs.size < 12:
        raise InputError(f"V_R takes only {xs.size} distinct values above {fit_fraction:g}·max V_R: not a ramp")
    grid = xs[4:-3] if xs.size > 16 else xs[1:-1]
    if grid.size > 400:
        grid = grid[:: int(math.ceil(grid.size / 400))]
    sse = np.array([_hinge_fit(x, y, g)[0] for g in grid])
    k = int(np.argmin(sse))
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, grid.size - 1)]
    if hi > lo:
        res = scipy.optimize.minimize_scalar(lambda g: _hinge_fit(x, y, g)[0], bounds=(lo, hi), method="bounded",
                                             options={"xatol": 1e-10})
        xk = float(res.x)
    else:
        xk = float(grid[k])
    sse_k, (a0, a1, _a2, c1) = _hinge_fit(x, y, xk)
    n_above = int(np.count_nonzero(x > xk))
    if n_above < 3 or n_above > x.size - 3:
        raise InputError("the P-V_R knee lies at the end of the ramp; ramp V_R beyond the breakdown")
    if c1 - a1 < min_slope_change:
        raise InputError(
            f"no breakdown knee: d ln P/d ln V changes by {c1 - a1:.3g} < {min_slope_change:g}; "
            "ramp V_R beyond the breakdown"
        )
    return Knee(
        voltage_v=math.exp(xk),
        power_w=math.exp(a0),
        slope_below=float(a1),
        slope_above=float(c1),
        rms_log_residual=math.sqrt(sse_k / x.size),
        n_above=n_above,
    )


class GTable(NamedTuple):
    """Binned g(T): bin-centre temperatures (°C), mean R (Ω), its standard error (Ω) and counts."""

    temperature_c: np.ndarray
    resistance_ohm: np.ndarray
    resistance_sem_ohm: np.ndarray
    count: np.ndarray


def g_table(temperature_c, resistance_ohm, bins: int) -> GTable:
    """Average R in ``bins`` equal temperature bins over the data's range (empty bins dropped)."""
    t = np.asarray(temperature_c, dtype=np.float64)
    r = np.asarray(resistance_ohm, dtype=np.float64)
    if not (isinstance(bins, int) and bins >= 2):
        raise ConfigError(f"bins={bins!r} must be an integer >= 2")
    edges = np.linspace(t.min(), t.max(), bins + 1)
    index = np.clip(np.digitize(t, edges) - 1, 0, bins - 1)
    count = np.bincount(index, minlength=bins)
    total = np.bincount(index, weights=r, minlength=bins)
    total2 = np.bincount(index, weights=r * r, minlength=bins)
    tsum = np.bincount(index, weights=t, minlength=bins)
    ok = count > 0
    mean = total[ok] / count[ok]
    var = np.maximum(total2[ok] / count[ok] - mean**2, 0.0)
    sem = np.sqrt(var / np.maximum(count[ok] - 1, 1))
    return GTable(tsum[ok] / count[ok], mean, sem, count[ok])


def fit_resistance(temperature_c, resistance_ohm, *, order: int, room_temperature_c: float,
                   max_temperature_c: float) -> ResistanceFit:
    """Least-squares polynomial R = Σ c_i (T − T_r)^i of degree ``order`` (§6.5.2, g(T) fit)."""
    if not (isinstance(order, int) and 1 <= order <= 6):
        raise ConfigError(f"order={order!r} must be an integer in 1..6")
    dt = np.asarray(temperature_c, dtype=np.float64) - room_temperature_c
    r = np.asarray(resistance_ohm, dtype=np.float64)
    if dt.size <= order:
        raise InputError(f"{dt.size} points cannot fit a degree-{order} g(T)")
    coefficients = np.polynomial.polynomial.polyfit(dt, r, order)
    return ResistanceFit(room_temperature_c, tuple(coefficients.tolist()), max_temperature_c)


class IvIdentification(NamedTuple):
    """Everything an I-V ramp gives.

    knee : Knee
    k_tp_k_per_w : float
        K_TP = (T_k − T_r)/P_k, K/W (at the ramp's tip-sample separation).
    g_fit : ResistanceFit
    table : GTable
    curve : IvCurve
    temperature_c : numpy.ndarray
        T = T_r + K_TP·P per sample of ``curve`` (meaningful below the knee).
    g_rms_relative_residual : float
        rms of (R − g(T))/g(T) over the samples below the knee.
    """

    knee: Knee
    k_tp_k_per_w: float
    g_fit: ResistanceFit
    table: GTable
    curve: IvCurve
    temperature_c: np.ndarray
    g_rms_relative_residual: float


def identify_iv(
    v_r_v,
    current_a,
    *,
    breakdown_temperature_c: float = 550.0,
    room_temperature_c: float = 25.0,
    g_order: int = 2,
    table_bins: int = 40,
    knee_fit_fraction: float = 0.5,
) -> IvIdentification:
    """K_TP and g(T) from an I-V ramp with a known breakdown temperature (§6.5.2).

    Parameters
    ----------
    v_r_v : array_like
        V_R, V (ramped up past the breakdown and down).
    current_a : array_like
        I_R, A.
    breakdown_temperature_c, room_temperature_c : float
        T_k and T_r, °C.
    g_order : int
        Degree of the g(T) polynomial.
    table_bins : int
        Temperature bins of the g(T) table.
    knee_fit_fraction : float
        See :func:`detect_knee`.

    Returns
    -------
    IvIdentification

    Notes
    -----
    The ramp is quasi-static, so Γ_TP acts through its DC gain: at the
    ramp's fixed t_s, T − T_r = K_TP·P.  At the knee T = T_k, hence
    K_TP = (T_k − T_r)/P_k, and every sample below the knee gives a pair
    (T_r + K_TP·P, V/I) of the map R = g(T).
    """
    for name, value in (("breakdown_temperature_c", breakdown_temperature_c),
                        ("room_temperature_c", room_temperature_c)):
        if not math.isfinite(value):
            raise ConfigError(f"{name}={value!r} must be finite")
    if not breakdown_temperature_c > room_temperature_c:
        raise ConfigError(
            f"breakdown_temperature_c={breakdown_temperature_c!r} must exceed room_temperature_c={room_temperature_c!r}"
        )
    curve = iv_curve(v_r_v, current_a)
    knee = detect_knee(curve.v_r_v, curve.power_w, fit_fraction=knee_fit_fraction)
    # K_TP: slope of the line from (0, T_r) to (P_k, T_k)
    k_tp = (breakdown_temperature_c - room_temperature_c) / knee.power_w
    # T = T_r + K_TP·P (quasi-static, fixed t_s)
    temperature = room_temperature_c + k_tp * curve.power_w
    below = curve.v_r_v < knee.voltage_v
    table = g_table(temperature[below], curve.resistance_ohm[below], table_bins)
    g_fit = fit_resistance(temperature[below], curve.resistance_ohm[below], order=g_order,
                           room_temperature_c=room_temperature_c, max_temperature_c=breakdown_temperature_c)
    rel = curve.resistance_ohm[below] / g_fit.resistance(temperature[below]) - 1.0
    return IvIdentification(knee, k_tp, g_fit, table, curve, temperature, float(np.sqrt(np.mean(rel**2))))


# --------------------------------------------------------------------------- z force curve


class KtpCurve(NamedTuple):
    """K_TP against the tip-sample separation from a thermal z force curve (Fig. 6.8(b)).

    separation_m : numpy.ndarray
        Bin centres of t_s = z_sn − z on the approach before snap-in, m (≥ 0).
    k_tp_k_per_w, k_tp_std_k_per_w : numpy.ndarray
        Mean and standard deviation of K_TP = (T − T_r)/P in each bin, K/W.
    count : numpy.ndarray
    snap_in_z_m : float
        z_sn, m (z positive toward the lever).
    snap_in_index : int
        Sample just before the snap-in jump.
    jump_a : float
        I_R jump at snap-in, A.
    contact_k_tp_k_per_w : float
        Mean K_TP in contact on the approach leg (after snap-in), K/W.
    per_sample_separation_m, per_sample_k_tp : numpy.ndarray
        The unbinned approach-leg values before snap-in (for plots).
    """

    separation_m: np.ndarray
    k_tp_k_per_w: np.ndarray
    k_tp_std_k_per_w: np.ndarray
    count: np.ndarray
    snap_in_z_m: float
    snap_in_index: int
    jump_a: float
    contact_k_tp_k_per_w: float
    per_sample_separation_m: np.ndarray
    per_sample_k_tp: np.ndarray


def k_tp_from_current(v_r_v, current_a, g_fit: ResistanceFit) -> np.ndarray:
    """K_TP = (g⁻¹(V/I) − T_r)/(V·I) per sample, K/W (NaN where R is outside the fit's range)."""
    v = np.asarray(v_r_v, dtype=np.float64)
    i = np.asarray(current_a, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        temperature = g_fit.temperature(v / i)
        return (temperature - g_fit.room_temperature_c) / (v * i)


def identify_z_curve(
    z_m, v_r_v, current_a, g_fit: ResistanceFit, *, bin_m: float = 10e-9, min_jump_sigmas: float = 10.0
) -> KtpCurve:
    """K_TP(t_s) from a z force curve at constant V_R (§6.5.2, Fig. 6.8).

    Parameters
    ----------
    z_m : array_like
        Sample position, m, increasing toward the lever on the approach
        (thesis convention), then decreasing.
    v_r_v, current_a : array_like
        V_R (V) and I_R (A).
    g_fit : ResistanceFit
        From :func:`identify_iv` (or a saved thermal model).
    bin_m : float
        Width of the t_s bins, m.
    min_jump_sigmas : float
        The snap-in is the largest one-sample jump of I_R on the approach
        and must exceed this many robust standard deviations of the
        sample-to-sample differences.

    Returns
    -------
    KtpCurve

    Notes
    -----
    t_s = z_sn − z assumes the tip is at the sample when it snaps in and
    that the lever does not bend before (§6.5.2).  When the snap-in is
    caused by the attractive tip-sample force it happens at t_s ≈ d (the
    force's range) rather than 0, and every t_s here is short by that
    distance: thermal data alone cannot see it.
    """
    z = np.asarray(z_m, dtype=np.float64)
    v = np.asarray(v_r_v, dtype=np.float64)
    i = np.asarray(current_a, dtype=np.float64)
    if not (z.shape == v.shape == i.shape and z.ndim == 1 and z.size >= 16):
        raise InputError(f"z_piezo, v_r and thermal_current must be 1-D of one length >= 16, got {z.shape}")
    if not (math.isfinite(bin_m) and bin_m > 0):
        raise ConfigError(f"bin_m={bin_m!r} must be a finite number > 0")
    turn = int(np.argmax(z))
    if turn < 8:
        raise InputError("z_piezo does not increase first (approach toward the lever, thesis convention)")
    steps = np.abs(np.diff(i[: turn + 1]))
    robust = 1.4826 * float(np.median(np.abs(steps - np.median(steps)))) + float(np.median(steps))
    k = int(np.argmax(steps))
    if not steps[k] > min_jump_sigmas * max(robust, np.finfo(float).tiny):
        raise InputError("no snap-in: the thermal current shows no jump on the approach")
    z_sn = float(z[k])
    k_tp = k_tp_from_current(v, i, g_fit)
    ts = z_sn - z[: k + 1]
    kk = k_tp[: k + 1]
    ok = np.isfinite(kk)
    if np.count_nonzero(ok) < 2:
        raise InputError("the thermal current before snap-in is outside the g(T) fit's range")
    edges = np.arange(0.0, float(ts[ok].max()) + bin_m, bin_m)
    index = np.clip(np.digitize(ts[ok], edges) - 1, 0, edges.size - 2)
    nb = edges.size - 1
    count = np.bincount(index, minlength=nb)
    mean = np.bincount(index, weights=kk[ok], minlength=nb)
    mean2 = np.bincount(index, weights=kk[ok] ** 2, minlength=nb)
    centre = np.bincount(index, weights=ts[ok], minlength=nb)
    filled = count > 0
    m = mean[filled] / count[filled]
    std = np.sqrt(np.maximum(mean2[filled] / count[filled] - m**2, 0.0))
    contact = k_tp[k + 1 : turn + 1]
    contact = contact[np.isfinite(contact)]
    return KtpCurve(
        separation_m=centre[filled] / count[filled],
        k_tp_k_per_w=m,
        k_tp_std_k_per_w=std,
        count=count[filled],
        snap_in_z_m=z_sn,
        snap_in_index=k,
        jump_a=float(i[k + 1] - i[k]),
        contact_k_tp_k_per_w=float(np.mean(contact)) if contact.size else math.nan,
        per_sample_separation_m=ts[ok],
        per_sample_k_tp=kk[ok],
    )


def monotone_k_tp(k_tp_k_per_w) -> np.ndarray:
    """Non-decreasing least-squares fit (pool-adjacent-violators) of K_TP along increasing t_s.

    K_TP grows with t_s (the lever runs hotter away from the sample); noise
    can break that in flat stretches, and then t_s(K_TP) is not single valued.
    """
    values = [float(x) for x in np.asarray(k_tp_k_per_w, dtype=np.float64)]
    blocks: list[list[float]] = []  # [sum, count]
    for value in values:
        blocks.append([value, 1.0])
        while len(blocks) > 1 and blocks[-2][0] / blocks[-2][1] > blocks[-1][0] / blocks[-1][1]:
            s, c = blocks.pop()
            blocks[-1][0] += s
            blocks[-1][1] += c
    return np.concatenate([np.full(int(c), s / c) for s, c in blocks]) if blocks else np.empty(0)


def separation_from_current(
    v_r_v, current_a, g_fit: ResistanceFit, separation_m, k_tp_k_per_w
) -> np.ndarray:
    """t_s from I_R through K_TP: R = V/I, T = g⁻¹(R), K = (T − T_r)/P, t_s = K_TP⁻¹(K), m (§6.5.2, Fig. 6.9).

    The K_TP(t_s) table is made monotone (:func:`monotone_k_tp`) and
    inverted by linear interpolation over its strictly increasing points;
    K outside the table's range gives NaN.
    """
    ts = np.asarray(separation_m, dtype=np.float64)
    order = np.argsort(ts)
    ts = ts[order]
    k_mono = monotone_k_tp(np.asarray(k_tp_k_per_w, dtype=np.float64)[order])
    first = np.concatenate(([True], np.diff(k_mono) > 0))
    # within a tied block keep its mean separation
    groups = np.cumsum(first) - 1
    k_unique = k_mono[first]
    t_unique = np.bincount(groups, weights=ts) / np.bincount(groups)
    if k_unique.size < 2:
        raise InputError("the K_TP(t_s) table is flat: it cannot convert current to separation")
    k = k_tp_from_current(v_r_v, current_a, g_fit)
    inside = (k >= k_unique[0]) & (k <= k_unique[-1])
    return np.where(inside, np.interp(k, k_unique, t_unique), np.nan)


# --------------------------------------------------------------------------- C(jω), H(jω)


class SweepOperatingPoint(NamedTuple):
    """The operating point of a V_R sweep, and what g(T) gives there.

    v_r_v, current_a : float
        V_R0 (V) and I_R0 (A): the sweep's means.
    resistance_ohm : float
        R0 = V_R0/I_R0, Ω.
    temperature_c : float
        T0 = g⁻¹(R0), °C.
    dg_dt_ohm_per_k : float
        g′(T0), Ω/K.
    """

    v_r_v: float
    current_a: float
    resistance_ohm: float
    temperature_c: float
    dg_dt_ohm_per_k: float


class ThermalDynamics(NamedTuple):
    """C(jω) (eq. 6.11, K/W) and H(jω) (eq. 6.12, K/m; None without Γ_IR,ts) at one operating point.

    operating_point : SweepOperatingPoint
        V_R0, I_R0, R0, T0 and g′(T0) used.
    """

    c: FrequencyResponse
    h: FrequencyResponse | None
    operating_point: SweepOperatingPoint


def _transform(fr: FrequencyResponse, values: np.ndarray, relative_error: np.ndarray) -> FrequencyResponse:
    mag = np.abs(values)
    return FrequencyResponse(
        frequency_hz=fr.frequency_hz,
        response=values,
        coherence=fr.coherence,
        magnitude_std=mag * relative_error,
        phase_std_rad=relative_error,
        method=fr.method,
        n_averages=fr.n_averages,
    )


def thermal_dynamics(
    ir_vr_a_per_v: FrequencyResponse,
    v_r0_v: float,
    current0_a: float,
    g_fit: ResistanceFit,
    ir_ts_a_per_m: FrequencyResponse | None = None,
) -> ThermalDynamics:
    """C(jω) and H(jω) from a V_R perturbation sweep (§6.6.2).

    Parameters
    ----------
    ir_vr_a_per_v : FrequencyResponse
        Γ_IR,VR in A/V (with Δt_s = 0, or with the lever's motion removed).
    v_r0_v, current0_a : float
        The operating point V_R0 (V) and I_R0 (A): the sweep's means.
    g_fit : ResistanceFit
        g(T), for T0 = g⁻¹(R0) and g′(T0).
    ir_ts_a_per_m : FrequencyResponse, optional
        Γ_IR,ts in A/m on the same frequencies, at the same operating point.

    Returns
    -------
    ThermalDynamics

    Notes
    -----
    Eq. 6.11: C = (1/(I0²g′))·(1 − R0Γ)/(1 + R0Γ); eq. 6.12:
    H = −R0/(I0g′)·Γ_IR,ts·2/(1 + R0Γ_IR,VR).  Their relative errors:
    δC/C = 2R0·δΓ/|1 − R0²Γ²| and δH/H from δΓ_IR,ts/Γ_IR,ts and
    R0·δΓ/|1 + R0Γ| in quadrature (first order, the g′ error not included).
    """
    if not (math.isfinite(v_r0_v) and v_r0_v != 0 and math.isfinite(current0_a) and current0_a != 0):
        raise ConfigError(f"v_r0_v={v_r0_v!r} and current0_a={current0_a!r} must be finite and nonzero")
    r0 = v_r0_v / current0_a
    t0 = float(g_fit.temperature(r0))
    if not math.isfinite(t0):
        raise InputError(f"R0 = {r0:.6g} ohm is outside the g(T) fit's range: no temperature for it")
    slope = float(g_fit.slope(t0))
    gamma = ir_vr_a_per_v.response
    c = c_from_gamma_ir_vr(gamma, current0_a, r0, slope)
    d_gamma = ir_vr_a_per_v.magnitude_std
    with np.errstate(divide="ignore", invalid="ignore"):
        rel_c = 2.0 * r0 * d_gamma / np.abs(1.0 - (r0 * gamma) ** 2)
    c_fr = _transform(ir_vr_a_per_v, c, rel_c)
    h_fr = None
    if ir_ts_a_per_m is not None:
        if ir_ts_a_per_m.frequency_hz.shape != gamma.shape or not np.allclose(
            ir_ts_a_per_m.frequency_hz, ir_vr_a_per_v.frequency_hz, rtol=1e-9
        ):
            raise InputError("Gamma_IR,ts and Gamma_IR,VR must be on the same frequencies (resample first)")
        h = h_from_gammas(ir_ts_a_per_m.response, gamma, current0_a, r0, slope)
        with np.errstate(divide="ignore", invalid="ignore"):
            rel_h = np.sqrt((ir_ts_a_per_m.magnitude_std / np.abs(ir_ts_a_per_m.response)) ** 2
                            + (r0 * d_gamma / np.abs(1.0 + r0 * gamma)) ** 2)
        h_fr = replace(
            _transform(ir_vr_a_per_v, h, rel_h), coherence=np.fmin(ir_vr_a_per_v.coherence, ir_ts_a_per_m.coherence)
        )
    point = SweepOperatingPoint(v_r_v=v_r0_v, current_a=current0_a, resistance_ohm=r0, temperature_c=t0,
                                dg_dt_ohm_per_k=slope)
    return ThermalDynamics(c_fr, h_fr, point)
