"""Setting up the ch. 7 EKF from a nominal segment: ℓ0 (§7.4) and the noise levels.

A nominal segment is a stretch of the capture with the lever over the
nominal sample (no bits, no potential change), with the voltage and the
deflection recorded together.

* :func:`estimate_l0` — §7.4: ℓ0 minimises the RMS of the EKF innovation
  over the segment.  A coarse grid over a bracket finds the basin, golden-
  section search refines the minimum, and the grid curve is checked for a
  unique minimum (one interior local minimum, a clear dip).
* :func:`estimate_measurement_noise` — the white floor of the deflection's
  Welch PSD far above the resonance (band 0.3-0.45 f_s by default), where
  neither the thermal motion nor the actuation lines reach: σ_ν = √(S·f_s/2).
* :func:`estimate_process_noise` — the force-noise level that makes the
  filter consistent on the segment: mean ε²/S = 1 (the normalised innovation
  squared; larger process noise makes S larger and ε smaller, so the mean
  is monotone and bisection on log σ_F finds it).
* :func:`tune_ekf` — the three together, as ``decode`` runs them: each
  level given or estimated on the nominal segment, with where it came from
  (moved out of :mod:`afmtool.analyses.decode`, issue 29 item 6).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from afmtool.config.params import DecodeParams, parse_bracket_nm
from afmtool.errors import ConfigError, InputError
from afmtool.estimators.ekf import EkfDesign, EkfModel, InnovationStats, discretise, ekf_run, thermal_force_asd
from afmtool.models.electrostatic import ElectrostaticParams
from afmtool.records.decode import L0Record, L0Source, MeasurementNoiseSource, NoiseRecord, ProcessNoiseSource

__all__ = [
    "L0Search",
    "estimate_l0",
    "innovation_stats",
    "estimate_measurement_noise",
    "ProcessNoiseFit",
    "estimate_process_noise",
    "EkfTuning",
    "tune_ekf",
]

_GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0
#: A dip is "clear" when the curve rises by this factor over its minimum somewhere in the bracket.
_MIN_DIP_RATIO = 1.05
#: Other local minima of the grid within this factor of the best make the minimum non-unique.
_RIVAL_RATIO = 1.10
#: Smallest measurement noise the EKF assumes, nm (a noise-free capture would make R = 0).
MIN_MEASUREMENT_NOISE_NM = 1e-4


def _check_segment(y, v) -> tuple[np.ndarray, np.ndarray]:
    y = np.ascontiguousarray(y, dtype=np.float64)
    v = np.ascontiguousarray(v, dtype=np.float64)
    if y.ndim != 1 or y.shape != v.shape:
        raise ConfigError(f"deflection and voltage must be 1-D of one length, got {y.shape} and {v.shape}")
    if not (np.isfinite(y).all() and np.isfinite(v).all()):
        raise InputError("the nominal segment has NaN or inf samples")
    return y, v


def innovation_stats(
    model: EkfModel, deflection_nm, voltage_v, sample_rate_hz: float, warmup: int
) -> InnovationStats:
    """Innovation RMS (nm) and mean ε²/S of the EKF over a segment, after ``warmup`` samples."""
    y, v = _check_segment(deflection_nm, voltage_v)
    _check_warmup(warmup, y.size)
    return _stats(discretise(model, sample_rate_hz), y, v, warmup)


def _check_warmup(warmup: int, size: int) -> None:
    if not (isinstance(warmup, (int, np.integer)) and 0 <= warmup < size):
        raise ConfigError(f"warmup={warmup!r} must leave samples in a segment of {size}")


def _stats(design: EkfDesign, y: np.ndarray, v: np.ndarray, warmup: int) -> InnovationStats:
    return ekf_run(design, y, v, stats_from=int(warmup)).state.stats()


class L0Search(NamedTuple):
    """Result of :func:`estimate_l0`; lengths in m, RMS in nm."""

    l0_m: float  #: the minimiser
    rms_nm: float  #: innovation RMS at the minimiser
    curve_l0_m: np.ndarray  #: every ℓ0 evaluated (grid and golden section), sorted
    curve_rms_nm: np.ndarray  #: innovation RMS at each
    grid_points: int
    unique: bool  #: one interior minimum with a clear dip
    note: str  #: why the minimum is not unique ("" if it is)


def _grid_check(grid: np.ndarray, rms: np.ndarray) -> str:
    k = int(np.argmin(rms))
    if k in (0, grid.size - 1):
        return f"the innovation RMS is smallest at the edge of the bracket ({grid[k] * 1e9:.1f} nm); widen it"
    if rms.max() < _MIN_DIP_RATIO * rms[k]:
        return "the innovation RMS hardly changes with l0 over the bracket (no clear minimum)"
    interior = np.flatnonzero((rms[1:-1] <= rms[:-2]) & (rms[1:-1] <= rms[2:])) + 1
    rivals = [int(j) for j in interior if j != k and rms[j] <= _RIVAL_RATIO * rms[k]]
    if rivals:
        where = ", ".join(f"{grid[j] * 1e9:.1f} nm" for j in rivals)
        return f"other local minima of the innovation RMS come close to the best one (at {where})"
    return ""


def estimate_l0(
    model: EkfModel,
    deflection_nm,
    voltage_v,
    sample_rate_hz: float,
    *,
    bracket_m: tuple[float, float],
    grid_points: int = 41,
    tolerance_m: float = 1e-11,
    warmup: int = 0,
    geometric: bool = False,
) -> L0Search:
    """ℓ0 that minimises the innovation RMS over a nominal segment (§7.4).

    Parameters
    ----------
    model : EkfModel
        The EKF; its own ℓ0 is ignored.
    deflection_nm, voltage_v : array_like
        The nominal segment: deflection (nm) and lever-sample voltage (V).
    sample_rate_hz : float
        f_s, Hz.
    bracket_m : (float, float)
        Search bracket for ℓ0, m; both above the tip height.
    grid_points : int, optional
        Coarse grid size (≥ 5).
    tolerance_m : float, optional
        Final bracket width of the golden-section search, m.
    warmup : int, optional
        Samples left out of the RMS at the start (the filter's transient).
    geometric : bool, optional
        A geometric coarse grid (for a wide bracket: the force goes as 1/ℓ0²)
        instead of an even one.

    Returns
    -------
    L0Search
    """
    y, v = _check_segment(deflection_nm, voltage_v)
    low, high = (float(b) for b in bracket_m)
    if not (math.isfinite(low) and math.isfinite(high) and model.electrostatic.tip_height_m < low < high):
        raise ConfigError(f"bracket_m={bracket_m!r} must be finite, increasing and above the tip height")
    if not (isinstance(grid_points, int) and grid_points >= 5):
        raise ConfigError(f"grid_points={grid_points!r} must be an integer >= 5")
    if not tolerance_m > 0:
        raise ConfigError(f"tolerance_m={tolerance_m!r} must be > 0")
    _check_warmup(warmup, y.size)
    design = discretise(model, sample_rate_hz)
    evaluated: dict[float, float] = {}

    def rms(l0: float) -> float:
        if l0 not in evaluated:
            evaluated[l0] = _stats(design.with_l0(l0), y, v, warmup).rms_nm
        return evaluated[l0]

    grid = np.geomspace(low, high, grid_points) if geometric else np.linspace(low, high, grid_points)
    grid_rms = np.array([rms(float(g)) for g in grid])
    note = _grid_check(grid, grid_rms)
    k = int(np.argmin(grid_rms))
    a, b = float(grid[max(k - 1, 0)]), float(grid[min(k + 1, grid.size - 1)])
    c, d = b - _GOLDEN * (b - a), a + _GOLDEN * (b - a)
    while b - a > tolerance_m:
        if rms(c) < rms(d):
            b, d = d, c
            c = b - _GOLDEN * (b - a)
        else:
            a, c = c, d
            d = a + _GOLDEN * (b - a)
    best = min(evaluated, key=evaluated.get)
    order = sorted(evaluated)
    return L0Search(
        float(best), float(evaluated[best]), np.array(order), np.array([evaluated[x] for x in order]),
        grid_points, not note, note,
    )


def estimate_measurement_noise(
    deflection_nm, sample_rate_hz: float, *, band: tuple[float, float] = (0.3, 0.45), nperseg: int = 1024
) -> float:
    """Rms white measurement noise per sample (nm) from the PSD floor in ``band`` × f_s.

    The one-sided Welch PSD S of white noise of variance σ² is 2σ²/f_s, so
    σ = √(S̄·f_s/2), with S̄ the mean PSD over the band after leaving out
    bins above three times the band's median (spectral lines).
    """
    from afmtool.estimators.filters import welch_psd

    y = np.asarray(deflection_nm, dtype=np.float64)
    if y.size < 2 * nperseg:
        raise InputError(f"the segment has {y.size} samples; the noise floor needs at least {2 * nperseg}")
    freqs, power = welch_psd(y, sample_rate_hz, nperseg)
    lo, hi = band
    in_band = (freqs >= lo * sample_rate_hz) & (freqs <= hi * sample_rate_hz)
    values = power[in_band]
    values = values[values <= 3.0 * np.median(values)]
    return float(math.sqrt(values.mean() * sample_rate_hz / 2.0))


class ProcessNoiseFit(NamedTuple):
    """Result of :func:`estimate_process_noise`."""

    asd_n_per_rthz: float  #: force-noise ASD σ_F, N/√Hz
    mean_nis: float  #: mean ε²/S at σ_F (1 when not clamped)
    clamped: bool  #: the consistent level is outside the search range; σ_F is at its end


def estimate_process_noise(
    model: EkfModel,
    deflection_nm,
    voltage_v,
    sample_rate_hz: float,
    *,
    warmup: int = 0,
    search_n_per_rthz: tuple[float, float] = (1e-19, 1e-9),
    iterations: int = 40,
) -> ProcessNoiseFit:
    """Force-noise ASD that makes the mean normalised innovation squared equal 1.

    Bisection on log σ_F within ``search_n_per_rthz``; the model's
    measurement noise and ℓ0 are used as they are.
    """
    y, v = _check_segment(deflection_nm, voltage_v)
    _check_warmup(warmup, y.size)
    low, high = (math.log(float(s)) for s in search_n_per_rthz)
    if not low < high:
        raise ConfigError(f"search_n_per_rthz={search_n_per_rthz!r} must be two increasing levels > 0")
    design = discretise(model, sample_rate_hz)

    def nis(log_asd: float) -> float:
        return _stats(design.with_noise(math.exp(log_asd), model.measurement_noise_nm), y, v, warmup).mean_nis

    at_low, at_high = nis(low), nis(high)
    if at_low <= 1.0:
        return ProcessNoiseFit(math.exp(low), at_low, True)
    if at_high >= 1.0:
        return ProcessNoiseFit(math.exp(high), at_high, True)
    for _ in range(iterations):
        middle = 0.5 * (low + high)
        if nis(middle) > 1.0:
            low = middle
        else:
            high = middle
    best = 0.5 * (low + high)
    return ProcessNoiseFit(math.exp(best), nis(best), False)


# --------------------------------------------------------------------------- decode's tuning


class EkfTuning(NamedTuple):
    """The tuned EKF model and what the report says about each level."""

    model: EkfModel
    l0: L0Record  #: ℓ0 and how it was set
    noise: NoiseRecord  #: each noise level and its source
    l0_curve_nm: tuple[np.ndarray, np.ndarray] | None  #: (ℓ0, innovation RMS), nm, when ℓ0 was searched
    warnings: list


def tune_ekf(electrostatic: ElectrostaticParams, f0_hz: float, q: float, params: DecodeParams,
             sample_rate_hz: float, segment: tuple[np.ndarray, np.ndarray] | None, warmup: int,
             l0_bracket_m: tuple[float, float, bool]) -> EkfTuning:
    """Measurement noise, ℓ0 and process noise: given in ``params``, or from the nominal segment.

    Parameters
    ----------
    electrostatic : ElectrostaticParams
        The actuation model; its ``l0_m`` is the guess.
    f0_hz, q : float
        The lever's resonance, Hz, and quality factor.
    params : DecodeParams
        ``l0_nm``, ``measurement_noise_nm``, ``process_noise_n_per_rthz``
        (0: estimate), ``temperature_k``, ``l0_bracket_nm``, ``l0_grid_points``.
    sample_rate_hz : float
        f_s, Hz.
    segment : (deflection nm, voltage V) or None
        The nominal segment; without it every level must be given.
    warmup : int
        Samples of the segment left out of every statistic.
    l0_bracket_m : (low, high, geometric)
        The ℓ0 search bracket when ``params.l0_bracket_nm`` gives none.
    """
    warnings: list[str] = []
    fs = sample_rate_hz
    thermal = thermal_force_asd(electrostatic.spring_constant_n_per_m, f0_hz, q, params.temperature_k) \
        if params.temperature_k > 0 else 0.0
    if segment is None:
        missing = [n for n, v in (("l0_nm", params.l0_nm), ("measurement_noise_nm", params.measurement_noise_nm),
                                  ("process_noise_n_per_rthz", params.process_noise_n_per_rthz)) if not v]
        if missing:
            raise ConfigError(
                f"no nominal segment (give --nominal START:END or capture metadata nominal) to estimate "
                f"{', '.join(missing)}; or give them"
            )
    y, v = segment if segment is not None else (None, None)
    r_nm, r_source = _measurement_noise(f0_hz, params, fs, y, warnings)
    q_start = params.process_noise_n_per_rthz or thermal
    if not q_start > 0:
        raise ConfigError("the process noise is 0: give --process-noise or a temperature_k > 0")
    model = EkfModel(f0_hz, q, electrostatic, q_start, r_nm)
    if params.l0_nm:
        l0 = L0Record(estimate_nm=params.l0_nm, source=L0Source.PARAMETER)
        curve = None
    else:
        model, l0, curve = _search_l0(model, params, l0_bracket_m, segment, fs, warmup, warnings)
    if params.process_noise_n_per_rthz:
        q_asd, q_source = params.process_noise_n_per_rthz, ProcessNoiseSource.PARAMETER
    else:
        fit = estimate_process_noise(model, y, v, fs, warmup=warmup)
        model = model.with_noise(fit.asd_n_per_rthz, r_nm)
        q_asd, q_source = fit.asd_n_per_rthz, ProcessNoiseSource.MEAN_NIS
        if fit.clamped:
            warnings.append(
                f"process noise: no consistent level in the search range (mean NIS {fit.mean_nis:.3g}); "
                f"using {fit.asd_n_per_rthz:.3g} N/sqrt(Hz)"
            )
    stats = innovation_stats(model, y, v, fs, warmup) if segment is not None else None
    noise = NoiseRecord(
        thermal_force_asd_n_per_rthz=thermal, temperature_k=params.temperature_k, measurement_source=r_source,
        measurement_noise_nm=r_nm, process_noise_n_per_rthz=q_asd, process_source=q_source,
        nominal_innovation_rms_nm=stats.rms_nm if stats is not None else None,
        nominal_mean_nis=stats.mean_nis if stats is not None else None,
    )
    return EkfTuning(model, l0, noise, curve, warnings)


def _measurement_noise(f0_hz: float, params: DecodeParams, fs: float, y,
                       warnings: list) -> tuple[float, MeasurementNoiseSource]:
    """R of the EKF, nm, and where it came from: given, or the PSD floor of the nominal segment."""
    if params.measurement_noise_nm:
        return params.measurement_noise_nm, MeasurementNoiseSource.PARAMETER
    if 0.3 * fs < 3.0 * f0_hz:
        raise ConfigError(
            f"the PSD floor above 0.3·fs = {0.3 * fs:g} Hz is not clear of the resonance f0 = {f0_hz:g} Hz; "
            "give --measurement-noise"
        )
    r_nm = estimate_measurement_noise(y, fs)
    if not r_nm >= MIN_MEASUREMENT_NOISE_NM:
        warnings.append(
            f"the deflection's noise floor is {r_nm:.3g} nm (a noise-free capture?); the EKF assumes "
            f"{MIN_MEASUREMENT_NOISE_NM:g} nm"
        )
        r_nm = MIN_MEASUREMENT_NOISE_NM
    return r_nm, MeasurementNoiseSource.PSD_FLOOR


def _search_l0(model: EkfModel, params: DecodeParams, l0_bracket_m: tuple[float, float, bool], segment,
               fs: float, warmup: int, warnings: list) -> tuple:
    """ℓ0 by §7.4 on the nominal segment: (model with it, the report's ``l0``, the RMS curve in nm)."""
    y, v = segment
    geometric = False
    if params.l0_bracket_nm:
        low, high = parse_bracket_nm(params.l0_bracket_nm)
    else:
        low_m, high_m, geometric = l0_bracket_m
        low, high = max(low_m, 1.01 * model.electrostatic.tip_height_m) * 1e9, high_m * 1e9
    search = estimate_l0(
        model, y, v, fs, bracket_m=(low * 1e-9, high * 1e-9), grid_points=params.l0_grid_points, warmup=warmup,
        geometric=geometric,
    )
    l0_result = L0Record(
        estimate_nm=search.l0_m * 1e9, source=L0Source.SEARCH, rms_at_minimum_nm=search.rms_nm,
        bracket_nm=(low, high), grid_points=search.grid_points, evaluations=int(search.curve_l0_m.size),
        unique_minimum=search.unique, process_noise_used_n_per_rthz=model.process_noise_n_per_rthz,
    )
    if not search.unique:
        warnings.append(f"l0: no unique minimum of the innovation RMS: {search.note}")
    return model.with_l0(search.l0_m), l0_result, (search.curve_l0_m * 1e9, search.curve_rms_nm)
