"""The ``theory averaging`` and ``theory compare`` commands end to end."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType

import numpy as np

from afmtool.analyses.theory import TheoryComparison, compare_with_theory
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
from afmtool.report.json_report import input_record, to_jsonable
from afmtool.report.outputs import OutputDir
from afmtool.report.run import finish_run

__all__ = ["TheoryCompareResult", "chosen_force", "run_averaging_command", "run_compare_command"]


@dataclass(frozen=True)
class TheoryCompareResult:
    """What ``theory compare`` found.

    Attributes
    ----------
    force_set : str
        The force law compared with: a thesis set's name, "custom" or "metadata".
    free_amplitude_nm : float
        The free-air amplitude A0 the theory is evaluated for, nm.
    separation : Mapping
        Where the separation axis came from (``source``: "truth" or
        "z-piezo", and for z-piezo its units, scale and contact point).
    comparison : TheoryComparison
        REEP against averaging theory (eqs. 4.9-4.10) along the curve.
    passed : bool
        Both error fractions within ``--tolerance``.
    """

    force_set: str
    free_amplitude_nm: float
    separation: Mapping
    comparison: TheoryComparison
    passed: bool

    def to_json(self) -> dict:
        """The ``results`` section of report.json."""
        return to_jsonable({"force_set": self.force_set, "free_amplitude_nm": self.free_amplitude_nm,
                            "separation": dict(self.separation), **self.comparison.summary(), "pass": self.passed})


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
    results = {"drive_amplitude_nm": drive.amplitude_nm, "drive_frequency_hz": drive.frequency_hz,
               "force": {"name": force_name, "spec": format_force_spec(force)}}
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
                bistable = curve.separation_nm[curve.n_stable > 1]
                results[leg] = {
                    "f0_e_range_hz": [float(np.nanmin(curve.f0_e_hz)), float(np.nanmax(curve.f0_e_hz))],
                    "q_e_range": [float(np.nanmin(curve.q_e)), float(np.nanmax(curve.q_e))],
                    "bistable_separation_nm": [float(bistable.min()), float(bistable.max())] if bistable.size else None,
                }
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
        if q_values:
            results["q_overlay"] = write_q_overlay(staged, q_values, params, force, force_name, approach_path)
        return finish_run(staged, "theory averaging", [], "theory.averaging", params, results, [])


def chosen_force(spec: str, force_set: str) -> tuple[PiecewiseLinearForce, str]:
    """A custom ``--force`` spec wins over a thesis ``--force-set``."""
    if spec:
        return parse_force_spec(spec), "custom"
    return THESIS_FORCE_SETS[force_set], force_set


def _force_from(metadata: CaptureMetadata, force_set: str, spec: str = "") -> tuple[PiecewiseLinearForce, str]:
    if spec or force_set:
        return chosen_force(spec, force_set)
    meta = metadata.force
    if meta is None:
        raise InputError("the capture has no force metadata; give --force-set")
    force = PiecewiseLinearForce(meta.d_nm, meta.omega_a2_per_s2, meta.omega_b2_per_s2, meta.c_a_per_s, meta.c_b_per_s)
    return force, meta.set or "metadata"


def run_compare_command(reep_dir: Path, out: Path, config: Path | None, flags: Mapping) -> dict:
    """Put a REEP run beside averaging theory along its (simulated) force curve."""
    params = resolve_from(TheoryCompareParams, "theory.compare", load_toml(config) if config else None, flags)
    with open_reep_run(reep_dir) as reep:
        series = reep_series(reep, ("t", "f0_hz", "q", "amplitude"))
        # samples REEP flagged as untrustworthy are left out, as in its own summaries
        series["f0_hz"], series["q"] = reep.file.trusted("f0_hz", slice(None)), reep.file.trusted("q", slice(None))
        z_series = (reep.series["z"][()], reep.z_units) if "z" in reep.series else None
        reep_results, report_path, series_path = reep.report, reep_dir / "report.json", reep.path
        capture = reep_capture_path(reep)
    metadata, fs, truth_separation = capture_side(capture, reep_results)
    force, force_name = _force_from(metadata, params.force_set, params.force)
    cantilever = capture_cantilever(metadata, reep_results)
    free_amplitude = metadata.drive.free_amplitude_nm or float(
        np.nanmedian(series["amplitude"][: max(1, len(series["t"]) // 20)])
    )
    separation, separation_record = _separation(params, truth_separation, z_series, series, fs, reep_results,
                                                cantilever, force, free_amplitude)
    decimate = reep_results["decimate"]
    comparison = compare_with_theory(
        series["t"], series["f0_hz"], series["q"], series["amplitude"], separation,
        drive_frequency_hz=reep_results["drive_frequency_hz"], cantilever=cantilever, force=force,
        forgetting_factor=reep_results["forgetting_factor"] ** decimate,
        free_amplitude_nm=free_amplitude, amplitude_fraction=params.amplitude_fraction,
    )
    passed = comparison.f0_error_fraction <= params.tolerance and comparison.q_error_fraction <= params.tolerance
    result = TheoryCompareResult(force_name, float(free_amplitude), MappingProxyType(separation_record), comparison,
                                 passed)
    warnings = [] if passed else [
        f"REEP and averaging theory differ by more than {params.tolerance:.0%} of the theory's change"
    ]
    with OutputDir(out) as staged:
        _plot_comparison(staged.path("compare.png"), series, separation, comparison)
        inputs = [input_record(report_path, "reep report"), input_record(series_path, "reep series")]
        inputs += [input_record(capture)] if capture is not None and capture.is_file() else []
        return finish_run(staged, "theory compare", inputs, "theory.compare", params, result.to_json(), warnings)


def open_reep_run(reep_dir: Path) -> ReepResults:
    """A finished ``reep`` output folder: reep.h5 with the report.json beside it."""
    reep_dir = Path(reep_dir)
    if not (reep_dir / "report.json").is_file() or not (reep_dir / "reep.h5").is_file():
        raise InputError(f"{reep_dir}: not a reep output folder (needs report.json and reep.h5)")
    reep = open_reep_results(reep_dir, where="reep output")
    missing = [key for key in ("drive_frequency_hz", "decimate", "forgetting_factor")
               if not isinstance(reep.report.get(key), (int, float))]
    if missing:
        reep.close()
        raise InputError(f"{reep_dir / 'report.json'}: not the report of a reep run (no results.{missing[0]})")
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


def capture_side(capture: Path | None, reep_results: Mapping) -> tuple[CaptureMetadata, float, np.ndarray | None]:
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
    return CaptureMetadata(), float(reep_results.get("sample_rate_hz") or 0.0), None


def capture_cantilever(metadata: CaptureMetadata, reep_results: Mapping) -> Cantilever:
    """The capture's cantilever f0, Q; without them in its metadata, the free-air model REEP used."""
    if metadata.cantilever.f0_hz is not None and metadata.cantilever.q is not None:
        return Cantilever(metadata.cantilever.f0_hz, metadata.cantilever.q)
    model = reep_results.get("free_air_model")
    if not isinstance(model, Mapping) or not all(isinstance(model.get(k), (int, float)) for k in ("f0_hz", "q")):
        raise InputError("neither the capture's metadata nor the REEP report give the cantilever's f0 and Q")
    return Cantilever(float(model["f0_hz"]), float(model["q"]))


def _separation(params, truth, z_series, series, fs, reep_results, cantilever, force, free_amplitude):
    """The separation per REEP sample and a record of where it came from."""
    from afmtool.analyses.theory_separation import separation_from_z, z_sensitivity_nm

    use_truth = params.separation == "truth" or (params.separation == "auto" and truth is not None)
    if use_truth:
        if truth is None:
            raise InputError("--separation truth: the REEP input has no /truth/separation_nm")
        index = np.round(series["t"] * fs).astype(int)
        return truth[index], {"source": "truth"}
    if z_series is None:
        raise InputError("no /truth separation and no z_piezo in reep.h5: the force curve has no separation axis")
    z, units = z_series
    estimate = separation_from_z(
        z, series["amplitude"], nm_per_unit=z_sensitivity_nm(units, params.z_sensitivity),
        drive_frequency_hz=reep_results["drive_frequency_hz"], cantilever=cantilever, force=force,
        free_amplitude_nm=free_amplitude, contact_z=float(params.contact_z) if params.contact_z else None,
    )
    return estimate.separation_nm, {
        "source": "z-piezo", "z_units": units, "nm_per_unit": estimate.nm_per_unit,
        "contact_z": estimate.contact_z, "contact_method": estimate.method,
        "amplitude_rms_residual_nm": estimate.amplitude_rms_residual_nm,
    }


def _plot_comparison(path: Path, series, separation, comparison) -> None:
    from afmtool.report.images import write_multi_panel_png

    m = comparison.mask
    panels = [
        {"y_label": "f0' (Hz)", "series": [(separation[m], series["f0_hz"][m], "REEP", {"color": "C0", "linestyle": "none", "marker": ","}),
                                          (separation[m], comparison.f0_theory_hz[m], "averaging theory", {"color": "C3", "linestyle": "none", "marker": ","})]},
        {"y_label": "Q' (dimensionless)", "series": [(separation[m], series["q"][m], "REEP", {"color": "C0", "linestyle": "none", "marker": ","}),
                                    (separation[m], comparison.q_theory[m], "averaging theory", {"color": "C3", "linestyle": "none", "marker": ","})]},
    ]
    write_multi_panel_png(path, panels, x_label="separation l (nm)", title="REEP vs averaging theory (thesis Figs. 3.11-3.14)")
