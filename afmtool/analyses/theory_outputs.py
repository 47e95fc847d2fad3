"""The ``theory averaging`` and ``theory compare`` commands end to end."""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import NamedTuple

import numpy as np

from afmtool.analyses.theory import ReepRows, TheoryComparison, beat_modulation, compare_binned
from afmtool.analyses.theory_q_overlay import parse_q_values, write_q_overlay
from afmtool.config import load_toml, resolve_from
from afmtool.config.params import AveragingParams, TheoryCompareParams
from afmtool.errors import InputError
from afmtool.io.metadata import CaptureMetadata
from afmtool.io.reep_results import ReepResults, open_reep_results
from afmtool.io.results import ResultWriter
from afmtool.models.cantilever import Cantilever
from afmtool.models.force_spec import format_force_spec, parse_force_spec
from afmtool.models.forces import THESIS_FORCE_SETS, PiecewiseLinearForce
from afmtool.records.reep import ReepResults as ReepRecord
from afmtool.records.theory_averaging import AveragingForceRecord, AveragingLegRecord, AveragingResults, ForceSet
from afmtool.records.theory_compare import (
    BeatRecord,
    CompareForceRecord,
    ContactMethod,
    SeparationRecord,
    SeparationSource,
    TheoryCompareResults,
)
from afmtool.records.theory_fit import FitModel, TheoryFitResults
from afmtool.report.json_report import input_record
from afmtool.report.run import finish_run
from afmtool.runtime.outputs import OutputDir

__all__ = ["FittedForce", "capture_drive_lines", "chosen_force", "compare_results", "load_fitted_force",
           "run_averaging_command", "run_compare_command"]


def run_averaging_command(out: Path, config: Path | None, flags: Mapping) -> dict:
    """Theoretical force curve, approach and retract, with topography sensitivities."""
    from afmtool.models.averaging import SinusoidalDrive, theoretical_force_curve, topography_sensitivities
    from afmtool.report.images import APPROACH_STYLE, RETRACT_STYLE, write_multi_panel_png

    params = resolve_from(AveragingParams, "theory.averaging", load_toml(config) if config else None, flags)
    cantilever = Cantilever(params.f0_hz, params.q)
    force, force_name = chosen_force(params.force, params.force_set)
    q_values = parse_q_values(params.q_values)
    drive = SinusoidalDrive.for_free_amplitude(
        cantilever, params.free_amplitude_nm, params.f0_hz + params.drive_offset_hz
    )
    approach_path = np.linspace(params.separation_from_nm, params.separation_to_nm, params.points)
    legs = {
        "approach": theoretical_force_curve(approach_path, drive, cantilever, force),
        "retract": theoretical_force_curve(approach_path[::-1], drive, cantilever, force),
    }
    leg_records = {}
    with OutputDir(out) as staged:
        with ResultWriter(staged.path("theory.h5"), {}) as writer:
            for leg, curve in legs.items():
                sens = topography_sensitivities(
                    curve.amplitude_nm, curve.separation_nm, drive.omega_rad_s, cantilever, force
                )
                for name, values, units in (
                    ("separation_nm", curve.separation_nm, "nm"),
                    ("amplitude_nm", curve.amplitude_nm, "nm"),
                    ("phase_deg", np.degrees(curve.phase_rad), "deg"),
                    ("f0_e_hz", curve.f0_e_hz, "Hz"),
                    ("q_e", curve.q_e, ""),
                    ("n_stable", curve.n_stable, ""),
                    ("da_dl", sens.da_dl, "nm/nm"),
                    ("domega_e_dl", sens.domega_e_dl, "rad/s/nm"),
                    ("dq_e_dl", sens.dq_e_dl, "1/nm"),
                ):
                    writer.put(f"{leg}/{name}", values, units)
                leg_records[leg] = _leg_record(curve)
        styles = {"approach": APPROACH_STYLE, "retract": RETRACT_STYLE}
        panels = [
            {"y_label": label, "series": [(c.separation_nm, getter(c), leg, styles[leg]) for leg, c in legs.items()]}
            for label, getter in (
                ("amplitude (nm)", lambda c: c.amplitude_nm),
                ("phase (deg)", lambda c: np.degrees(c.phase_rad)),
                ("f0e (Hz)", lambda c: c.f0_e_hz),
                ("Qe (dimensionless)", lambda c: c.q_e),
            )
        ]
        write_multi_panel_png(
            staged.path("averaging.png"), panels, x_label="separation l (nm)",
            title=f"Averaging theory, {force_name} force (f0 {params.f0_hz:g} Hz, Q {params.q:g})",
        )
        results = AveragingResults(
            drive_amplitude_nm=drive.amplitude_nm, drive_frequency_hz=drive.frequency_hz,
            force=AveragingForceRecord(name=ForceSet(force_name), spec=format_force_spec(force)),
            approach=leg_records["approach"], retract=leg_records["retract"],
            q_overlay=write_q_overlay(staged, q_values, params, force, force_name, approach_path) if q_values else None,
        )
        return finish_run(staged, "theory averaging", [], "theory.averaging", params, results, [])


def _leg_record(curve) -> AveragingLegRecord:
    """The ranges of f0,e and Qe along one leg, and where it is bistable."""
    bistable = curve.separation_nm[curve.n_stable > 1]
    return AveragingLegRecord(
        f0_e_range_hz=(float(np.nanmin(curve.f0_e_hz)), float(np.nanmax(curve.f0_e_hz))),
        q_e_range=(float(np.nanmin(curve.q_e)), float(np.nanmax(curve.q_e))),
        bistable_separation_nm=(float(bistable.min()), float(bistable.max())) if bistable.size else None,
    )


def chosen_force(spec: str, force_set: str) -> tuple[PiecewiseLinearForce, str]:
    """A custom ``--force`` spec wins over a thesis ``--force-set``."""
    if spec:
        return parse_force_spec(spec), "custom"
    return THESIS_FORCE_SETS[force_set], force_set


_NO_FORCE = ("the capture has no force metadata (a real capture never has): give --fit FIT_DIR, the output of "
             "'afmtool theory fit' on this REEP run, or a force law with --force d=...,wa2=...,wb2=...,ca=...,cb=... "
             "or --force-set NAME")


def _force_from(metadata: CaptureMetadata, force_set: str, spec: str = "") -> tuple[PiecewiseLinearForce, str]:
    if spec or force_set:
        return chosen_force(spec, force_set)
    meta = metadata.force
    if meta is None:
        raise InputError(_NO_FORCE)
    force = PiecewiseLinearForce(meta.d_nm, meta.omega_a2_per_s2, meta.omega_b2_per_s2, meta.c_a_per_s, meta.c_b_per_s)
    return force, meta.set or "metadata"


class FittedForce(NamedTuple):
    """``theory fit``'s result as ``theory compare --fit`` uses it: the force, the contact point and the z scale."""

    force: PiecewiseLinearForce
    contact_z: float
    contact_z_std: float
    nm_per_unit: float
    record: CompareForceRecord


def load_fitted_force(fit_dir: Path) -> FittedForce:
    """Read fit.json of a ``theory fit`` output folder (or the file itself).

    Raises
    ------
    InputError
        If the folder holds no fit.json or it is not one ``theory fit`` wrote.
    """
    path = Path(fit_dir)
    path = path / "fit.json" if path.is_dir() else path
    try:
        fit = TheoryFitResults.from_json(json.loads(path.read_text(encoding="utf-8")))
    except FileNotFoundError:
        raise InputError(f"--fit {fit_dir}: no fit.json there (the output folder of 'afmtool theory fit')") from None
    except (OSError, ValueError, InputError) as exc:
        raise InputError(f"--fit {path}: not a fit.json of 'afmtool theory fit' ({type(exc).__name__}: {exc})") from None
    p, nm_per_unit, onset_std = fit.parameters, fit.nm_per_unit, fit.onset_d_plus_s_contact_z_nm.std
    # an open contact interval (no std): the onset's, which the curve always pins, in z units
    contact_std = p.contact_z.std if p.contact_z.std is not None else (onset_std or 0.0) / abs(nm_per_unit)
    if fit.model is FitModel.ATTRACTIVE or not p.omega_b2.value and not p.c_b.value:
        # no wall: the attraction sees only d − l = (d + s·z_c) − s·z, so the separation is as
        # certain as the onset, whatever the split between d and z_c
        contact_std = float(onset_std or contact_std * abs(nm_per_unit)) / abs(nm_per_unit)
    values = (p.d_nm.value, p.omega_a2.value, p.omega_b2.value, p.c_a.value, p.c_b.value)
    force = PiecewiseLinearForce(*(max(0.0, v) for v in values))
    record = CompareForceRecord(source="fit", fit=str(path), model=fit.model, d_nm=p.d_nm.value,
                                omega_a2=p.omega_a2.value, omega_b2=p.omega_b2.value, c_a=p.c_a.value, c_b=p.c_b.value)
    return FittedForce(force, p.contact_z.value, contact_std if math.isfinite(contact_std) else 0.0, nm_per_unit,
                       record)


def run_compare_command(reep_dir: Path, out: Path, config: Path | None, flags: Mapping) -> dict:
    """Put a REEP run beside averaging theory along its force curve, binned, with a verdict (§3.4.3)."""
    params = resolve_from(TheoryCompareParams, "theory.compare", load_toml(config) if config else None, flags)
    fitted = load_fitted_force(Path(params.fit)) if params.fit else None
    data = _load_compare_inputs(Path(reep_dir))
    metadata, fs, truth_separation = capture_side(data.capture, data.reep_results)
    if fitted is not None:
        force, force_name, force_record = fitted.force, "fit", fitted.record
    else:
        force, force_name = _force_from(metadata, params.force_set, params.force)
        force_record = CompareForceRecord(source=force_name, spec=format_force_spec(force))
    cantilever = capture_cantilever(metadata, data.reep_results)
    series = data.series
    free_amplitude = metadata.drive.free_amplitude_nm or float(
        np.nanmedian(series["amplitude"][: max(1, len(series["t"]) // 20)])
    )
    separation, separation_record, separation_std = _separation(
        params, truth_separation, data.z_series, series, fs, data.reep_results, cantilever, force, free_amplitude,
        fitted)
    drive_hz = float(data.reep_results.drive_frequency_hz)
    lines, lines_source = capture_drive_lines(data.capture, metadata, drive_hz, cantilever.f0_hz)
    beat = beat_modulation(lines, drive_hz, cantilever)
    try:
        comparison = compare_binned(
            series["t"], ReepRows(series["f0_hz"], series["q"], series.get("f0_std_hz"), series.get("q_std")),
            series["amplitude"], separation, drive_frequency_hz=drive_hz, cantilever=cantilever, force=force,
            row_lambda=data.reep_results.forgetting_factor ** data.reep_results.decimate,
            free_amplitude_nm=free_amplitude, beat=beat, separation_std_nm=separation_std,
            amplitude_fraction=params.amplitude_fraction, bin_nm=params.bin_nm, tolerance=params.tolerance,
            flag=series.get("flag"),
        )
    except ValueError as exc:
        raise InputError(f"{reep_dir}: {exc}") from None
    result = compare_results(force_record, float(free_amplitude), separation_record, comparison,
                             BeatRecord(modulation=beat, lines=tuple(lines), lines_from=lines_source))
    with OutputDir(out) as staged:
        from afmtool.analyses.theory_compare_figure import write_compare_png, write_compare_table

        write_compare_png(staged.path("compare.png"), series, separation, comparison)
        write_compare_table(staged.path("compare_bins.csv"), comparison)
        inputs = [input_record(data.report_path, "reep report"), input_record(data.series_path, "reep series")]
        inputs += [input_record(data.capture)] if data.capture is not None and data.capture.is_file() else []
        inputs += [input_record(Path(fitted.record.fit), "theory fit")] if fitted is not None else []
        return finish_run(staged, "theory compare", inputs, "theory.compare", params, result,
                          _compare_warnings(result, lines_source))


def compare_results(force: CompareForceRecord, free_amplitude_nm: float, separation: SeparationRecord,
                    comparison: TheoryComparison, beat: BeatRecord) -> TheoryCompareResults:
    """What ``theory compare`` found: the force and axis it compared on, and the comparison's numbers and verdict."""
    summary = comparison.summary()
    shared = {f.name: getattr(summary, f.name) for f in dataclasses.fields(summary)}
    return TheoryCompareResults(force_set=force.source, force=force, free_amplitude_nm=free_amplitude_nm,
                                separation=separation, beat=beat, **shared, pass_=comparison.passed)


def _compare_warnings(result: TheoryCompareResults, lines_source: str) -> list[str]:
    """The verdict when it is not a pass, the bins left out and why, and an unknown drive."""
    warnings = [] if result.pass_ else [f"REEP and averaging theory: {result.verdict}"]
    for reason, count in result.ill_conditioned_reasons.items():
        warnings.append(f"{count} of {result.bins} separation bins left out of the verdict: {reason}")
    if lines_source == "unknown":
        warnings.append("the drive's lines are not known (no metadata, no dither channel): the envelope's beat is "
                        "taken as 0, so a multi-line drive's effect on the theory is not in its uncertainty")
    return warnings


class _CompareInputs(NamedTuple):
    """What ``theory compare`` reads from a REEP output folder."""

    series: dict
    z_series: tuple | None
    reep_results: ReepRecord
    report_path: Path
    series_path: Path
    capture: Path | None


def _load_compare_inputs(reep_dir: Path) -> _CompareInputs:
    with open_reep_run(reep_dir) as reep:
        series = reep_series(reep, ("t", "f0_hz", "q", "amplitude"))
        for name in ("f0_std_hz", "q_std", "flag"):
            if name in reep.series:
                series[name] = reep.series[name][()]
        z_series = (reep.series["z"][()], reep.z_units) if "z" in reep.series else None
        return _CompareInputs(series, z_series, reep.results, reep_dir / "report.json", reep.path,
                              reep_capture_path(reep))


def capture_drive_lines(capture: Path | None, metadata: CaptureMetadata, drive_hz: float,
                        f0_hz: float) -> tuple[list[tuple[float, float]], str]:
    """The drive's lines (Hz, V) and where they came from: the metadata, else the capture's dither, else none.

    The dither is read only over its first 65,536 samples (the lines'
    amplitudes by least squares at the frequencies found there).
    """
    drive = metadata.drive
    if drive.lines:
        return [(line.frequency_hz, line.amplitude_v) for line in drive.lines], "metadata drive.lines"
    raw = _raw_drive_metadata(capture)
    if raw.get("lines_hz") and raw.get("lines_v") and len(raw["lines_hz"]) == len(raw["lines_v"]):
        return [(float(f), float(a)) for f, a in zip(raw["lines_hz"], raw["lines_v"])], "metadata drive.lines_hz"
    offset, scale = drive.sideband_offset_hz, raw.get("sideband_scale")
    if offset is not None and isinstance(scale, (int, float)):
        if offset == 0:
            return [(drive_hz, 1.0)], "metadata: a single line"
        return ([(drive_hz, 1.0), (drive_hz - offset, float(scale)), (drive_hz + offset, float(scale))],
                "metadata sideband_offset_hz and sideband_scale")
    measured = _dither_lines(capture, f0_hz)
    return (measured, "the capture's dither") if measured else ([], "unknown")


def _raw_drive_metadata(capture: Path | None) -> dict:
    if capture is None or not capture.exists():
        return {}
    from afmtool.io.registry import open_capture

    reader = open_capture(capture)
    try:
        drive = reader.info.metadata.get("drive")
        return dict(drive) if isinstance(drive, Mapping) else {}
    finally:
        reader.close()


def _dither_lines(capture: Path | None, f0_hz: float) -> list[tuple[float, float]]:
    """The dither's lines near f0 (Hz) and their amplitudes (V), from its first 65,536 samples; [] without one."""
    from afmtool.estimators.drive_lines import excitation_lines
    from afmtool.estimators.stages import SegmentStage
    from afmtool.io.registry import open_capture
    from afmtool.pipeline import run_stream

    if capture is None or not capture.exists():
        return []
    reader = open_capture(capture)
    try:
        if "dither" not in reader.info.channel_names:
            return []
        n = min(1 << 16, reader.info.n_samples or 1 << 16)
        stage = SegmentStage(("dither",), 0, n)
        (segment,) = run_stream(reader, [stage], channels=("dither",), chunk_samples=n, prologue=stage.until_end)
        fs = reader.info.sample_rate_hz
    finally:
        reader.close()
    dither = segment["dither"]
    frequencies = excitation_lines(dither, fs, f0_hz)
    if not frequencies:
        return []
    t = np.arange(dither.size) / fs
    basis = np.column_stack([f(2 * np.pi * fr * t) for fr in frequencies for f in (np.cos, np.sin)])
    coef, *_ = np.linalg.lstsq(basis, dither - dither.mean(), rcond=None)
    return [(fr, float(np.hypot(coef[2 * i], coef[2 * i + 1]))) for i, fr in enumerate(frequencies)]


def open_reep_run(reep_dir: Path) -> ReepResults:
    """A finished ``reep`` output folder: reep.h5 with the report.json beside it."""
    reep_dir = Path(reep_dir)
    if not (reep_dir / "report.json").is_file() or not (reep_dir / "reep.h5").is_file():
        raise InputError(f"{reep_dir}: not a reep output folder (needs report.json and reep.h5)")
    reep = open_reep_results(reep_dir, where="reep output")
    try:
        if reep.results is None:  # read now: a report of another command is refused before any work
            raise InputError(f"{reep_dir / 'report.json'}: not the report of a reep run (no results)")
    except InputError:
        reep.close()
        raise
    return reep


def reep_series(reep: ReepResults, names: tuple[str, ...]) -> dict[str, np.ndarray]:
    """The series ``names`` of an open REEP output, read whole."""
    missing = [name for name in names if name not in reep.series]
    if missing:
        raise InputError(f"{reep.path}: no {', '.join(missing)} series")
    return {name: reep.series[name][()] for name in names}


def reep_capture_path(reep: ReepResults) -> Path | None:
    """The capture the REEP run read (its report's first input), or None if the report names none."""
    path = reep.inputs[0].get("path") if reep.inputs else None
    return Path(path) if isinstance(path, str) and path != "-" else None


def capture_side(capture: Path | None, reep_results: ReepRecord) -> tuple[CaptureMetadata, float, np.ndarray | None]:
    """(metadata, sample rate, /truth/separation_nm or None) of REEP's input capture.

    The capture is opened through the reader registry, so any format REEP
    read will do; only its metadata and ground truth are read, not its samples.
    """
    if capture is not None and capture.exists():
        from afmtool.io.registry import open_capture

        reader = open_capture(capture)
        try:
            truth = reader.truth().get("separation_nm") if "separation_nm" in reader.info.truth_names else None
            return reader.info.capture_metadata, float(reader.info.sample_rate_hz), truth
        finally:
            reader.close()
    # the capture moved: what the REEP report recorded is enough for z-piezo separations
    return CaptureMetadata(), float(reep_results.sample_rate_hz), None


def capture_cantilever(metadata: CaptureMetadata, reep_results: ReepRecord) -> Cantilever:
    """The capture's cantilever f0, Q; without them in its metadata, the free-air model REEP used."""
    if metadata.cantilever.f0_hz is not None and metadata.cantilever.q is not None:
        return Cantilever(metadata.cantilever.f0_hz, metadata.cantilever.q)
    model = reep_results.free_air_model
    if model is None or not all(math.isfinite(v) for v in (model.f0_hz, model.q)):
        raise InputError("neither the capture's metadata nor the REEP report give the cantilever's f0 and Q")
    return Cantilever(float(model.f0_hz), float(model.q))


def _separation(params, truth, z_series, series, fs, reep_results, cantilever, force, free_amplitude, fitted=None):
    """The separation per REEP row, a record of where it came from, and its uncertainty σ_l (nm)."""
    from afmtool.analyses.theory_separation import separation_from_z, z_sensitivity_nm

    if fitted is not None and params.separation != "truth":
        if z_series is None:
            raise InputError("--fit: reep.h5 has no z series, so the fitted contact point cannot place the rows")
        z, units = z_series
        std = abs(fitted.nm_per_unit) * fitted.contact_z_std
        return fitted.nm_per_unit * (z - fitted.contact_z), SeparationRecord(
            source=SeparationSource.FIT, z_units=units, nm_per_unit=fitted.nm_per_unit, contact_z=fitted.contact_z,
            contact_method=ContactMethod.FITTED, separation_std_nm=std), std
    use_truth = params.separation == "truth" or (params.separation == "auto" and truth is not None)
    if use_truth:
        if truth is None:
            raise InputError("--separation truth: the REEP input has no /truth/separation_nm")
        index = np.round(series["t"] * fs).astype(int)
        return truth[index], SeparationRecord(source=SeparationSource.TRUTH), 0.0
    if z_series is None:
        raise InputError("no /truth separation and no z_piezo in reep.h5: the force curve has no separation axis")
    z, units = z_series
    estimate = separation_from_z(
        z, series["amplitude"], nm_per_unit=z_sensitivity_nm(units, params.z_sensitivity),
        drive_frequency_hz=reep_results.drive_frequency_hz, cantilever=cantilever, force=force,
        free_amplitude_nm=free_amplitude, contact_z=float(params.contact_z) if params.contact_z else None,
    )
    std = abs(estimate.nm_per_unit) * estimate.contact_z_std if math.isfinite(estimate.contact_z_std) else 0.0
    residual = estimate.amplitude_rms_residual_nm
    return estimate.separation_nm, SeparationRecord(
        source=SeparationSource.Z_PIEZO, z_units=units, nm_per_unit=estimate.nm_per_unit,
        contact_z=estimate.contact_z, contact_method=ContactMethod(estimate.method),
        amplitude_rms_residual_nm=math.nan if residual is None else residual, contact_z_std=estimate.contact_z_std,
        separation_std_nm=std,
    ), std
