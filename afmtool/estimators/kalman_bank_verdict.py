"""Design points and verdict of the Kalman-bank validation of REEP (thesis §3.4.2).

The check (Figs. 3.2-3.9): filters built from REEP's equivalent model at a
few points z_i of a force curve must each have their least innovation RMS
at their own z_i (eq. 3.51: the filter whose model matches the plant has the
least innovation RMS), and an adaptive observer fed by REEP's f0′, Q′ must
have the least RMS throughout.  This module works on binned tables only
(REEP's model against z, the observers' RMS against z), so it is tested
without running a single filter.

Model distance
--------------
Models are compared by the distance of their poles in units of the
free-air half-width ω0/(2Q0) (the scale on which an observer's innovation
responds to a model error, eq. 5.17)::

    d = √[(2Q0·Δf0/f0)² + (ΔQ/Q0)²]

(Δf0 moves the pole's imaginary part by 2π·Δf0; ΔQ/Q moves its real part
by ω0/(2Q)·ΔQ/Q, to first order.)
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import numpy as np

from afmtool.errors import ConfigError, InputError

__all__ = [
    "ModelTable",
    "RmsTable",
    "DesignPoint",
    "model_distance",
    "auto_design_points",
    "design_points_at_z",
    "design_points_for_models",
    "parse_z_list",
    "parse_model_list",
    "VerdictTolerance",
    "FilterVerdict",
    "AdaptiveVerdict",
    "BankVerdict",
    "filter_verdicts",
    "adaptive_verdict",
    "bank_verdict",
]


class ModelTable(NamedTuple):
    """REEP's equivalent model binned against z along one leg of a force curve.

    Attributes
    ----------
    z : numpy.ndarray
        Bin centres, z_piezo units, ascending.
    count : numpy.ndarray
        Samples per bin.
    f0_hz, q : numpy.ndarray
        Mean f0′ (Hz) and Q′ per bin.
    amplitude : numpy.ndarray
        Mean lock-in amplitude per bin, deflection units (NaN where unknown).
    """

    z: np.ndarray
    count: np.ndarray
    f0_hz: np.ndarray
    q: np.ndarray
    amplitude: np.ndarray


class RmsTable(NamedTuple):
    """The observers' innovation RMS binned against z along one leg.

    Attributes
    ----------
    z : numpy.ndarray
        Bin centres, z_piezo units, ascending (bins of width ``z_bin`` at
        [k·z_bin, (k + 1)·z_bin)).
    count : numpy.ndarray
        Samples per bin.
    rms : numpy.ndarray, shape (N, B)
        Mean innovation RMS of each bank filter per bin, deflection units.
    adaptive : numpy.ndarray, shape (B,)
        Mean innovation RMS of the adaptive observer per bin.
    lowest : numpy.ndarray, shape (B,)
        Share of the bin's samples where the adaptive RMS was the least.
    """

    z: np.ndarray
    count: np.ndarray
    rms: np.ndarray
    adaptive: np.ndarray
    lowest: np.ndarray


class DesignPoint(NamedTuple):
    """One bank filter's model and where on the force curve it belongs.

    Attributes
    ----------
    f0_hz, q : float
        The filter's model (before any ``f0_scale``), Hz and dimensionless.
    z : float
        Design point, z_piezo units: where REEP had this model.
    source : str
        ``"auto"``, ``"at-z"`` or ``"models"``.
    distance : float
        Model distance (half-widths) between this model and REEP's at ``z``:
        0 when the model was taken from REEP there.
    """

    f0_hz: float
    q: float
    z: float
    source: str
    distance: float


def model_distance(f0_a, q_a, f0_b, q_b, *, f0_ref: float, q_ref: float):
    """Pole distance between models a and b in free-air half-widths (module docstring)."""
    df = (np.asarray(f0_a) - np.asarray(f0_b)) * 2.0 * q_ref / f0_ref
    dq = (np.asarray(q_a) - np.asarray(q_b)) / q_ref
    return np.hypot(df, dq)


def parse_z_list(text: str) -> tuple[float, ...]:
    """``"-8,-12.5"`` -> (−8.0, −12.5); errors name the option."""
    try:
        values = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise ConfigError(f"--at-z {text!r} must be numbers separated by commas") from None
    if not values or not all(map(math.isfinite, values)):
        raise ConfigError(f"--at-z {text!r} must be finite numbers separated by commas")
    return values


def parse_model_list(text: str, option: str = "--models") -> tuple[tuple[float, float], ...]:
    """``"80300:160,80100:140"`` -> ((80300.0, 160.0), (80100.0, 140.0))."""
    models = []
    for item in (v.strip() for v in text.split(",")):
        if not item:
            continue
        f0, sep, q = item.partition(":")
        try:
            pair = (float(f0), float(q))
        except ValueError:
            raise ConfigError(f"{option} item {item!r} must look like F0_HZ:Q") from None
        if not sep or not (math.isfinite(pair[0]) and pair[0] > 0 and math.isfinite(pair[1]) and pair[1] > 0.5):
            raise ConfigError(f"{option} item {item!r} must look like F0_HZ:Q with F0_HZ > 0 and Q > 0.5")
        models.append(pair)
    if not models:
        raise ConfigError(f"{option} {text!r} names no model")
    return tuple(models)


def _valid_bins(table: ModelTable) -> np.ndarray:
    return (table.count > 0) & np.isfinite(table.f0_hz) & np.isfinite(table.q)


def _walk_from_free_air(amplitude: np.ndarray, distance: np.ndarray, min_amplitude_fraction: float) -> np.ndarray:
    """Indices of the usable bins from the free-air end until the amplitude first falls below the threshold.

    The free-air end is the end with the larger amplitude (with no amplitude,
    the end whose model distance from free air is smaller); the free amplitude
    is the median of the first three bins walked.
    """
    ends = (0, amplitude.size - 1)
    if np.all(np.isfinite(amplitude[list(ends)])):
        start = ends[int(amplitude[ends[1]] > amplitude[ends[0]])]
    else:
        start = ends[int(distance[ends[1]] < distance[ends[0]])]
    order = np.arange(amplitude.size) if start == 0 else np.arange(amplitude.size)[::-1]
    free_amplitude = float(np.nanmedian(amplitude[order[:3]])) if np.any(np.isfinite(amplitude)) else math.nan
    walked = []
    for j in order:
        if math.isfinite(free_amplitude) and not amplitude[j] >= min_amplitude_fraction * free_amplitude:
            break
        walked.append(j)
    return np.asarray(walked, dtype=np.int64)


def auto_design_points(
    table: ModelTable,
    n_points: int,
    *,
    f0_ref: float,
    q_ref: float,
    min_amplitude_fraction: float,
    onset_fraction: float,
) -> tuple[DesignPoint, ...]:
    """N design points spread evenly in z over the part of a leg where REEP's model changes.

    Parameters
    ----------
    table : ModelTable
        REEP along the design leg.
    n_points : int
        N ≥ 1.
    f0_ref, q_ref : float
        The free-air model (scale of :func:`model_distance`).
    min_amplitude_fraction : float
        Only bins whose amplitude is at least this share of the free
        amplitude (the amplitude at the free-air end of the leg) count:
        REEP is ill-conditioned as the amplitude vanishes.
    onset_fraction : float
        The first point is where the model distance from free air first
        reaches this share of its largest value over the counted bins (in
        free air every filter would have the same model).

    Returns
    -------
    tuple of DesignPoint
        At bin centres, from the free-air end towards the sample.

    Raises
    ------
    InputError
        If the leg has too few usable bins for N distinct points.

    Notes
    -----
    The free-air end is the end of the leg with the larger amplitude (with
    no amplitude, the end whose model is nearer free air).  Bins are walked
    from it until the amplitude first falls below the threshold; the points
    are spread evenly in z from the onset bin to the last bin walked.
    """
    if not (isinstance(n_points, int) and n_points >= 1):
        raise ConfigError(f"n_points={n_points!r} must be an integer >= 1")
    valid = _valid_bins(table)
    index = np.flatnonzero(valid)
    if index.size == 0:
        raise InputError("REEP gives no usable model along the force curve (no finite f0', Q' against z)")
    distance = model_distance(table.f0_hz[index], table.q[index], f0_ref, q_ref, f0_ref=f0_ref, q_ref=q_ref)
    walked = _walk_from_free_air(table.amplitude[index], distance, min_amplitude_fraction)
    if walked.size == 0:
        raise InputError("no force-curve bin has REEP's amplitude above min_amplitude_fraction of the free amplitude")
    largest = float(np.max(distance[walked]))
    if not largest > 0:
        raise InputError("REEP's model does not change along the force curve: nothing to validate")
    reached = np.flatnonzero(distance[walked] >= onset_fraction * largest)
    span = walked[reached[0] :]
    z_span = table.z[index[span]]
    targets = np.linspace(z_span[0], z_span[-1], n_points)
    chosen = [int(span[np.argmin(np.abs(z_span - zt))]) for zt in targets]
    if len(set(chosen)) < n_points:
        raise InputError(
            f"only {len(set(chosen))} distinct force-curve bins between the onset (z = {z_span[0]:g}) and the last "
            f"usable bin (z = {z_span[-1]:g}) for {n_points} filters; lower n_filters or z_bin"
        )
    return tuple(
        DesignPoint(float(table.f0_hz[index[j]]), float(table.q[index[j]]), float(table.z[index[j]]), "auto", 0.0)
        for j in chosen
    )


def design_points_at_z(table: ModelTable, zs: Sequence[float]) -> tuple[DesignPoint, ...]:
    """REEP's model in the bin that holds each z (the nearest bin centre within one bin width).

    Raises
    ------
    InputError
        If a z lies outside the leg's usable bins.
    """
    valid = _valid_bins(table)
    z_valid = table.z[valid]
    if z_valid.size == 0:
        raise InputError("REEP gives no usable model along the force curve")
    width = float(np.min(np.diff(table.z))) if table.z.size > 1 else math.inf
    points = []
    for z in zs:
        j = int(np.argmin(np.abs(z_valid - z)))
        if abs(z_valid[j] - z) > width:
            raise InputError(
                f"--at-z {z:g} is outside the force curve REEP covers ({z_valid.min():g} to {z_valid.max():g})"
            )
        f0 = float(table.f0_hz[valid][j])
        q = float(table.q[valid][j])
        points.append(DesignPoint(f0, q, float(z), "at-z", 0.0))
    return tuple(points)


def design_points_for_models(
    table: ModelTable, models: Sequence[tuple[float, float]], *, f0_ref: float, q_ref: float
) -> tuple[DesignPoint, ...]:
    """Given models; the design point of each is the bin where REEP's model is nearest to it."""
    valid = _valid_bins(table)
    if not valid.any():
        raise InputError("REEP gives no usable model along the force curve")
    points = []
    for f0, q in models:
        d = model_distance(table.f0_hz[valid], table.q[valid], f0, q, f0_ref=f0_ref, q_ref=q_ref)
        j = int(np.argmin(d))
        points.append(DesignPoint(float(f0), float(q), float(table.z[valid][j]), "models", float(d[j])))
    return tuple(points)


# ---------------------------------------------------------------------------
# Verdict
# ---------------------------------------------------------------------------


class VerdictTolerance(NamedTuple):
    """How far the evidence may depart from the ideal and still pass.

    Attributes
    ----------
    z_bin : float
        Bin width, z_piezo units.
    z_tolerance_bins : int
        A filter's RMS minimum may lie this many bins from its design bin.
    rms_tolerance : float
        Or its mean RMS in the design bin may exceed the minimum by at most
        this share (a flat minimum, e.g. in free air).
    adaptive_fraction : float
        Share of the time the adaptive observer must have the least RMS.
    """

    z_bin: float
    z_tolerance_bins: int
    rms_tolerance: float
    adaptive_fraction: float

    def describe(self, z_units: str) -> str:
        units = f" {z_units}" if z_units else ""
        return (
            f"each filter's least mean innovation RMS (bins of {self.z_bin:g}{units} along the design leg) must lie in "
            f"its design bin{f' or within {self.z_tolerance_bins} bins of it' if self.z_tolerance_bins else ''}, "
            f"or its RMS in the design bin may exceed that least RMS by at most {self.rms_tolerance:.1%}; "
            f"the adaptive observer must have the least RMS for at least {self.adaptive_fraction:.0%} of the time "
            "after the warm-up"
        )


class FilterVerdict(NamedTuple):
    """The verdict on one bank filter along the design leg.

    Attributes
    ----------
    passed : bool
    design_z : float
        Design point, z_piezo units.
    design_bin : tuple of 2 floats
        [lower, upper) edges of the design bin.
    min_z : float
        Centre of the bin of least mean RMS (NaN if no bin).
    min_bin_offset : int
        (min bin) − (design bin), bins; 0 is the ideal.
    design_rms, min_rms : float
        Mean RMS in the design bin and the least, deflection units.
    excess : float
        design_rms/min_rms − 1.
    over_adaptive : float
        design_rms over the adaptive observer's mean RMS in the design bin.
    reason : str
        Why it failed ("" when it passed).
    """

    passed: bool
    design_z: float
    design_bin: tuple[float, float]
    min_z: float
    min_bin_offset: int
    design_rms: float
    min_rms: float
    excess: float
    over_adaptive: float
    reason: str


class AdaptiveVerdict(NamedTuple):
    """The verdict on the adaptive observer.

    Attributes
    ----------
    passed : bool
    fraction : float
        Share of the post-warm-up output samples where its RMS was the least.
    required : float
        The share it needed.
    fraction_by_leg : Mapping[str, float]
        The same per leg (approach, retract), from the binned tables.
    fraction_within_span : float
        The same over the bins between the outermost design points (both
        legs): where the bank's models are, so the comparison is hardest.
    reason : str
    """

    passed: bool
    fraction: float
    required: float
    fraction_by_leg: Mapping[str, float]
    fraction_within_span: float
    reason: str


class BankVerdict(NamedTuple):
    """Overall verdict: every filter passes and the adaptive observer passes."""

    passed: bool
    filters: tuple[FilterVerdict, ...]
    adaptive: AdaptiveVerdict
    reasons: tuple[str, ...]


def _bin_index(z, z_bin: float) -> np.ndarray:
    return np.floor(np.asarray(z, dtype=np.float64) / z_bin + 1e-9).astype(np.int64)


def filter_verdicts(
    table: RmsTable,
    points: Sequence[DesignPoint],
    f0_scale: float,
    tol: VerdictTolerance,
    z_units: str = "",
) -> tuple[FilterVerdict, ...]:
    """Where each filter's least mean RMS falls against its design bin (the tolerance of ``tol``)."""
    bins = _bin_index(table.z, tol.z_bin)
    units = f" {z_units}" if z_units else ""
    out = []
    for k, point in enumerate(points):
        design = int(_bin_index(point.z, tol.z_bin))
        edges = (design * tol.z_bin, (design + 1) * tol.z_bin)
        label = f"filter {k + 1} (f0 {point.f0_hz * f0_scale:.1f} Hz, Q {point.q:.1f}, design z {point.z:g}{units})"
        rms = table.rms[k]
        usable = (table.count > 0) & np.isfinite(rms)
        at_design = usable & (bins == design)
        if not usable.any() or not at_design.any():
            reason = f"{label}: the design bin [{edges[0]:g}, {edges[1]:g}){units} was not visited on this leg"
            nan = math.nan
            out.append(FilterVerdict(False, point.z, edges, nan, 0, nan, nan, nan, nan, reason))
            continue
        j_min = int(np.flatnonzero(usable)[np.argmin(rms[usable])])
        j_design = int(np.flatnonzero(at_design)[0])
        design_rms, min_rms = float(rms[j_design]), float(rms[j_min])
        offset = int(bins[j_min] - design)
        excess = design_rms / min_rms - 1.0 if min_rms > 0 else math.inf
        adaptive = float(table.adaptive[j_design])
        over_adaptive = design_rms / adaptive if adaptive > 0 else math.inf
        passed = abs(offset) <= tol.z_tolerance_bins or excess <= tol.rms_tolerance
        reason = ""
        if not passed:
            reason = (
                f"{label}: least RMS {min_rms:.4g} at z = {table.z[j_min]:g}{units}, {abs(offset)} bins "
                f"({abs(table.z[j_min] - point.z):.3g}{units}) from its design bin, where its RMS is {excess:.1%} "
                f"higher (tolerance {tol.z_tolerance_bins} bins or {tol.rms_tolerance:.1%})"
            )
            if over_adaptive > 2.0:
                reason += (
                    f"; at its design point its RMS is {over_adaptive:.3g} times the adaptive observer's, so its model "
                    "does not match the cantilever there"
                )
        out.append(
            FilterVerdict(passed, point.z, edges, float(table.z[j_min]), offset, design_rms, min_rms, excess,
                          over_adaptive, reason)
        )
    return tuple(out)


def adaptive_verdict(
    fraction: float,
    tables: Mapping[str, RmsTable],
    points: Sequence[DesignPoint],
    tol: VerdictTolerance,
    hint: str = "",
) -> AdaptiveVerdict:
    """Whether the adaptive observer had the least RMS for at least ``tol.adaptive_fraction`` of the time.

    ``hint`` is appended to the reason when it fails (e.g. REEP's window
    measured in z along the ramp).
    """
    by_leg = {}
    in_span = [0.0, 0.0]
    z_lo = min(p.z for p in points) - tol.z_bin / 2
    z_hi = max(p.z for p in points) + tol.z_bin / 2
    for leg, table in tables.items():
        counted = table.count > 0
        weights = table.count[counted]
        by_leg[leg] = float(np.sum(table.lowest[counted] * weights) / np.sum(weights)) if weights.size else math.nan
        span = counted & (table.z >= z_lo) & (table.z <= z_hi)
        in_span[0] += float(np.sum(table.lowest[span] * table.count[span]))
        in_span[1] += float(np.sum(table.count[span]))
    within = in_span[0] / in_span[1] if in_span[1] else math.nan
    passed = bool(fraction >= tol.adaptive_fraction)
    reason = "" if passed else (
        f"the adaptive observer had the least RMS for {fraction:.1%} of the time, below the required "
        f"{tol.adaptive_fraction:.0%}: REEP's f0', Q' are not the closest models throughout{hint}"
    )
    return AdaptiveVerdict(passed, float(fraction), tol.adaptive_fraction, by_leg, within, reason)


def bank_verdict(filters: Sequence[FilterVerdict], adaptive: AdaptiveVerdict) -> BankVerdict:
    """Pass when every filter and the adaptive observer pass; the reasons list every failure."""
    reasons = tuple(f.reason for f in filters if not f.passed) + ((adaptive.reason,) if not adaptive.passed else ())
    return BankVerdict(not reasons, tuple(filters), adaptive, reasons)
