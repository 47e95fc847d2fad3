"""``afmtool theory fit``: the piecewise-linear force fitted to a measured force curve (ch. 4, ref. [38]).

The estimator, its error model and its profile-likelihood intervals are in
:mod:`afmtool.estimators.force_fit`.  Here: REEP's approach read from its
output folder (any capture format REEP read, through the readers), the
per-row errors (REEP's own ``f0_std_hz``, ``q_std`` where reep.h5 has them),
which parameters the curve determines and why not, and the files
(fit.json, fit.h5, fit.png) that ``theory compare --fit`` reads back.

Status of a parameter: *identified* when its 2σ interval is closed and its
std (statistical and systematic) is at most ``max_relative_std`` of its
value; *poorly identifiable* when the interval is closed but wider; *not
identifiable* when the profile leaves it open on a side (only a bound), when
the curve does not probe it (the attractive model holds ω_b² = c_b = 0), or
when it enters only through the onset d + s·z_c.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from afmtool.errors import InputError
from afmtool.estimators.force_fit import FIT_NAMES, FIT_UNITS, ForceFit, ForceFitData, fit_force
from afmtool.records.reep import ReepResults
from afmtool.records.theory_fit import (
    FitModel,
    FitParameterName,
    FitParameterRecord,
    FitParametersRecord,
    FitResidualsRecord,
    OnsetRecord,
    ParameterStatus,
    TheoryFitResults,
    WallTestRecord,
)

__all__ = ["FIT_NAMES", "FIT_UNITS", "parameter_status", "run_theory_fit_command"]


def _approach(reep_dir: Path, params):
    """REEP's series on the approach, the REEP report, the capture's metadata and the z scale."""
    from afmtool.analyses.theory_outputs import capture_side, open_reep_run, reep_capture_path, reep_series
    from afmtool.analyses.theory_separation import z_sensitivity_nm

    with open_reep_run(reep_dir) as reep:
        if "z" not in reep.series:
            raise InputError(f"{reep.path}: no z series (the capture had no z_piezo): not a force curve")
        series = reep_series(reep, ("t", "f0_hz", "q", "amplitude", "z"))
        for name in ("f0_std_hz", "q_std", "flag"):
            if name in reep.series:
                series[name] = reep.series[name][()]
        units, reep_results, capture = reep.z_units, reep.results, reep_capture_path(reep)
        series["linear"] = np.broadcast_to(_linear_model_holds(reep, reep_results), series["t"].shape)
    nm_per_unit = z_sensitivity_nm(units, params.z_sensitivity)
    turn = int(np.argmin(series["z"] * np.sign(nm_per_unit)))
    approach = {k: v[: turn + 1] for k, v in series.items()}
    metadata, _, _ = capture_side(capture, reep_results)
    return approach, reep_results, metadata, nm_per_unit, capture


def _row_sigma(s: dict, key: str, std_key: str, early: slice, floor: float) -> np.ndarray:
    """σ_R per row (eq. F.3): REEP's own std where reep.h5 has it, else the free-air scatter; at least ``floor``."""
    if std_key in s:
        row = np.nan_to_num(s[std_key], nan=float(np.nanmedian(s[std_key])))
    else:
        row = np.full(len(s[key]), float(np.nanstd(s[key][early])))
    return np.maximum(row, floor)


def _load(reep_dir: Path, params) -> ForceFitData:
    from afmtool.analyses.theory import beat_modulation, jump_neighbourhood
    from afmtool.analyses.theory_outputs import capture_cantilever, capture_drive_lines
    from afmtool.estimators.force_fit import MODEL_FLOOR

    s, reep_results, metadata, nm_per_unit, capture = _approach(reep_dir, params)
    cantilever = capture_cantilever(metadata, reep_results)
    start = max(2, len(s["t"]) // 20)
    early = slice(max(1, start // 4), start)  # free air, after REEP has converged
    free_amplitude = metadata.drive.free_amplitude_nm or float(np.nanmedian(s["amplitude"][early]))
    free = tuple(float(np.nanmedian(s[k][early])) for k in ("f0_hz", "q", "amplitude"))
    dt = float(np.median(np.diff(s["t"]))) if len(s["t"]) > 1 else 1.0
    finite = np.isfinite(s["f0_hz"]) & np.isfinite(s["q"]) & np.isfinite(s["amplitude"])
    # rows REEP flagged as invalid, and rows its linear model does not describe (σ̂² far above free air)
    trusted = (s["flag"] == 0 if "flag" in s else np.ones(len(s["t"]), dtype=bool)) & s["linear"]
    mask = finite & trusted & (s["t"] > params.skip_s) & (s["amplitude"] > params.amplitude_fraction * free_amplitude)
    mask &= ~jump_neighbourhood(np.nan_to_num(s["amplitude"]), 1.0 / dt)
    thinned = np.zeros_like(mask)
    thinned[np.flatnonzero(mask)[:: max(1, math.ceil(mask.sum() / params.max_samples))]] = True
    for k in ("f0_hz", "q", "amplitude"):
        s[k] = np.nan_to_num(s[k], nan=float(np.nanmedian(s[k])))
    sigma = []
    for key, std_key, floor in (("f0_hz", "f0_std_hz", 1e-3), ("q", "q_std", 1e-4 * cantilever.q),
                                ("amplitude", "", 0.01 * free_amplitude)):
        row = _row_sigma(s, key, std_key, early, floor)
        shift = s[key] - free[("f0_hz", "q", "amplitude").index(key)]
        sigma.append(np.sqrt(row * row + (MODEL_FLOOR * shift) ** 2))  # eq. F.3
    drive_hz = float(reep_results.drive_frequency_hz)
    lines, _ = capture_drive_lines(capture, metadata, drive_hz, cantilever.f0_hz)
    return ForceFitData(s["z"], s["f0_hz"], s["q"], s["amplitude"], thinned, nm_per_unit, drive_hz, cantilever,
                        free_amplitude, reep_results.forgetting_factor ** reep_results.decimate, *sigma, free,
                        beat_modulation(lines, drive_hz, cantilever))


#: The fit leaves out rows whose σ̂² exceeds this multiple of its free-air level.
_MAX_SIGMA2_RATIO = 4.0


def _linear_model_holds(reep, reep_results: ReepResults) -> np.ndarray | bool:
    """Rows whose σ̂² is within ``_MAX_SIGMA2_RATIO`` of its free-air level (True where it is unknown).

    REEP's flags mark only invalid rows; a σ̂² far above the free-air level
    (impacts on a stiff wall, where the linear model does not describe the
    window) is a valid row for REEP but not one averaging theory can be
    fitted to: the fit leaves those out, as REEP's flags did before issue 27.
    """
    level = reep_results.validity.free_air_levels.sigma2
    sigma2 = reep.series.get("sigma2")
    if not level or sigma2 is None:
        return True
    values = sigma2[()]
    return ~(values > _MAX_SIGMA2_RATIO * level)


def parameter_status(fit: ForceFit, j: int, max_relative_std: float,
                     contact_tolerance: float) -> tuple[ParameterStatus, str]:
    """(status, reason) of parameter j (module docstring); the contact point's std is held to ``contact_tolerance`` (z units)."""
    name, interval, value = FIT_NAMES[j], fit.intervals[j], float(fit.theta[j])
    if not fit.free[j]:
        if name in ("omega_b2", "c_b"):
            return ParameterStatus.NOT_IDENTIFIABLE, (f"the curve does not probe a repulsive wall: a wall lowers the scaled chi^2 by "
                                        f"{fit.wall_test:.3g}, less than chi^2_3(0.99) = 11.3; held at 0")
        return ParameterStatus.NOT_IDENTIFIABLE, "without a wall, d and the contact point enter only as the onset d + s*contact_z"
    if name == "contact_z" and fit.model == "attractive":
        return ParameterStatus.NOT_IDENTIFIABLE, "without a wall, d and the contact point enter only as the onset d + s*contact_z"
    if not (math.isfinite(interval.low) and math.isfinite(interval.high)):
        side = "above" if not math.isfinite(interval.high) else "below"
        return ParameterStatus.NOT_IDENTIFIABLE, f"the profile likelihood never rises by 4c {side} it: the curve bounds it on one side only"
    if name == "contact_z":
        ok = interval.std <= contact_tolerance
        return (ParameterStatus.IDENTIFIED if ok else ParameterStatus.POORLY_IDENTIFIABLE), (
            f"std {interval.std:.3g} (z units), {'within' if ok else 'over'} 10 % of the free amplitude")
    relative = interval.std / abs(value) if value else math.inf
    if relative > max_relative_std:
        return ParameterStatus.POORLY_IDENTIFIABLE, f"relative std {relative:.3g} > {max_relative_std:g} (2-sigma interval " \
                                      f"{interval.low:.4g} to {interval.high:.4g})"
    return ParameterStatus.IDENTIFIED, f"relative std {relative:.3g}; 2-sigma interval {interval.low:.4g} to {interval.high:.4g}"


def _finite(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def _record(fit: ForceFit, data: ForceFitData, max_relative_std: float) -> TheoryFitResults:
    """fit.json: each parameter's value, 2σ interval, std, systematic part and status, and the fit's numbers."""
    tolerance = 0.1 * data.free_amplitude_nm / abs(data.nm_per_unit)
    parameters = {}
    for j, name in enumerate(FIT_NAMES):
        status, reason = parameter_status(fit, j, max_relative_std, tolerance)
        interval = fit.intervals[j]
        parameters[name] = FitParameterRecord(
            value=float(fit.theta[j]), std=_finite(interval.std), units=FIT_UNITS[name],
            interval_2sigma=(_finite(interval.low), _finite(interval.high)), systematic=_finite(interval.systematic),
            fitted=bool(fit.free[j]), status=status, reason=reason)
    identified = {FitParameterName(n): parameters[n].status is ParameterStatus.IDENTIFIED for n in FIT_NAMES}
    return TheoryFitResults(
        parameters=FitParametersRecord(**parameters),
        model=FitModel(fit.model),
        wall_test=WallTestRecord(statistic=fit.wall_test, threshold=11.34,
                                 meaning="chi^2 drop of the wall model in units of c (chi^2_3 at 0.99)"),
        uncertainty="profile likelihood, 2-sigma where chi^2 rises by 4c (c = max(1, chi^2/nu) x tau_int), "
                    "widened by the refits with every shift scaled by 1 +- tau (systematic)",
        chi2_scale=fit.chi2_scale,
        separation_offset_nm=float(-data.nm_per_unit * fit.theta[5]),
        onset_d_plus_s_contact_z_nm=OnsetRecord(value=float(fit.theta[0] + data.nm_per_unit * fit.theta[5]),
                                                std=_finite(fit.onset.std),
                                                interval_2sigma=(_finite(fit.onset.low), _finite(fit.onset.high))),
        repulsive_share=fit.repulsive_share,
        nm_per_unit=data.nm_per_unit,
        identified=tuple(n for n, ok in identified.items() if ok),
        not_identified=tuple(n for n, ok in identified.items() if not ok),
        rms_residual=FitResidualsRecord(f0_hz=fit.rms[0], q=fit.rms[1], amplitude_nm=fit.rms[2]),
        fitted_samples=int(data.fit_mask.sum()),
        free_amplitude_nm=data.free_amplitude_nm,
        beat_modulation=data.beat,
    )


def run_theory_fit_command(reep_dir: Path, out: Path, config: Path | None, flags: Mapping) -> dict:
    """Fit the force to REEP's approach and write fit.json, fit.h5 and fit.png."""
    from afmtool.config import load_toml, resolve_from
    from afmtool.config.params import TheoryFitParams
    from afmtool.report.json_report import input_record
    from afmtool.report.run import finish_run
    from afmtool.runtime.outputs import OutputDir

    params = resolve_from(TheoryFitParams, "theory.fit", load_toml(config) if config else None, flags)
    data = _load(Path(reep_dir), params)
    fit = fit_force(data)
    results = _record(fit, data, params.max_relative_std)
    warnings = [f"{name.value} is not determined by this curve: {getattr(results.parameters, name.value).reason}"
                for name in results.not_identified]
    with OutputDir(out) as staged:
        staged.path("fit.json").write_text(json.dumps(results.to_json(), indent=2) + "\n", encoding="utf-8")
        _write_fit_files(staged, fit, data)
        inputs = [input_record(Path(reep_dir) / "report.json", "reep report"),
                  input_record(Path(reep_dir) / "reep.h5", "reep series")]
        return finish_run(staged, "theory fit", inputs, "theory.fit", params, results, warnings)


def _write_fit_files(staged, fit: ForceFit, data: ForceFitData) -> None:
    """fit.h5 (the approach and the fitted theory) and fit.png (the curves with the theory over them)."""
    from afmtool.io.results import ResultWriter
    from afmtool.report.images import write_multi_panel_png

    separation = data.nm_per_unit * (data.z - fit.theta[5])
    f0e, qe, amplitude = fit.prediction
    m = data.fit_mask
    with ResultWriter(staged.path("fit.h5"), {}) as writer:
        for name, values, units in (("separation_nm", separation, "nm"), ("f0_hz", data.f0_hz, "Hz"),
                                    ("q", data.q, ""), ("amplitude_nm", data.amplitude_nm, "nm"),
                                    ("f0_e_fit_hz", f0e, "Hz"), ("q_e_fit", qe, ""),
                                    ("amplitude_fit_nm", amplitude, "nm"), ("fitted", m.astype(np.uint8), "")):
            writer.put(f"approach/{name}", values, units)
    dots = {"linestyle": "none", "marker": ".", "markersize": 2, "color": "C0"}
    line = {"color": "C3"}
    panels = [
        {"y_label": label, "series": [(separation[m], measured[m], "REEP (fitted samples)", dots),
                                      (separation, model, f"averaging theory, fitted force ({fit.model} model)", line)]}
        for label, measured, model in (("f0' (Hz)", data.f0_hz, f0e), ("Q' (dimensionless)", data.q, qe),
                                       ("amplitude (nm)", data.amplitude_nm, amplitude))
    ]
    write_multi_panel_png(staged.path("fit.png"), panels, x_label="separation l from the fitted contact point (nm)",
                          title="Force parameters fitted to the approach (averaging theory, eq. 4.8)")
