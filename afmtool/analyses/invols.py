"""``afmtool identify invols``: the InvOLS from the contact part of a force curve.

curve → deflection and z (z in nm through the units boundary; a deflection in
V kept in V) → one leg (approach by default) → contact point and contact
slope (:func:`afmtool.estimators.invols.fit_contact_slope`) → InvOLS with
its uncertainty, beside the capture's own InvOLS (metadata
``cantilever.deflection_sensitivity_nm_per_v``, e.g. an Asylum wave note's)
→ ``invols.png`` and ``report.json``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from afmtool.config import load_toml, resolve_from
from afmtool.config.params import InvolsParams
from afmtool.errors import InputError
from afmtool.estimators.invols import ContactFit, approach_part, fit_contact_slope
from afmtool.estimators.stages import RecordStage
from afmtool.io.capture import CaptureReader
from afmtool.io.units import calibration_record, parse_unit
from afmtool.pipeline import run_stream
from afmtool.records.invols import InvolsResults, Leg
from afmtool.report.json_report import input_record
from afmtool.report.run import finish_run
from afmtool.runtime.outputs import OutputDir

__all__ = ["identify_invols", "run_invols_command"]

#: Most points drawn in invols.png.
_PLOT_POINTS = 20000


def _leg(z: np.ndarray, leg: str) -> slice:
    approach = approach_part(z)
    if leg == "approach":
        return approach
    if leg == "retract":
        return slice(approach.stop - 1, z.size)
    return slice(0, z.size)


def identify_invols(reader: CaptureReader, params: InvolsParams, warnings: list[str]) -> tuple[InvolsResults, dict]:
    """Fit the contact slope of one leg; return (results, plot data).

    Raises
    ------
    InputError
        A missing channel, a z that is not a length, or no contact part.
    """
    names = (params.z_channel, params.deflection_channel)
    info = reader.info
    # the leg and its contact point are found on the whole curve: it is kept (one float64 array per channel)
    (curve,) = run_stream(reader, [RecordStage(names)], channels=names, chunk_samples=1 << 20)
    z, d = curve[params.z_channel], curve[params.deflection_channel]
    z_units, d_units = info.units(params.z_channel), info.units(params.deflection_channel)
    for name, units in ((params.z_channel, z_units), (params.deflection_channel, d_units)):
        try:
            parse_unit(units)
        except ValueError:
            raise InputError(f"{info.source}: channel {name!r} has units {units!r}, which afmtool cannot parse; "
                             f"give --units {name}=UNIT") from None
    if z_units and parse_unit(z_units).kind != "length":
        raise InputError(f"{info.source}: channel {params.z_channel!r} is in {z_units!r}; z must be a length here")
    if not z_units:
        warnings.append(f"channel {params.z_channel!r} has no units; assumed nm")
    part = _leg(z, params.leg)
    fit = fit_contact_slope(z[part], d[part], skip_fraction=params.skip_fraction)
    d_kind = parse_unit(d_units).kind if d_units else "none"
    note = info.capture_metadata.cantilever.deflection_sensitivity_nm_per_v
    invols = implied = (None, None)
    if d_kind == "voltage":
        # V/nm → nm/V; δ(1/s) = δs/s²
        invols = (1.0 / abs(fit.slope), fit.slope_std / fit.slope**2)
    elif d_kind in ("length", "none"):
        # the file's deflection is already detector volts × the capture's InvOLS: a hard-contact slope of 1
        # confirms that InvOLS, any other slope s asks for InvOLS/s
        if note is not None:
            implied = (float(note) / abs(fit.slope), float(note) * fit.slope_std / fit.slope**2)
        if abs(fit.slope) < 0.9:
            warnings.append(
                f"contact slope {fit.slope:.3g} nm/nm is well below 1: a soft sample (indentation), or the "
                "capture's InvOLS is off; only a hard sample calibrates the InvOLS"
            )
    else:
        raise InputError(f"{info.source}: channel {params.deflection_channel!r} is in {d_units!r}; "
                         "a deflection must be in V or a length")
    results = InvolsResults(
        leg=Leg(params.leg), points=int(z[part].size), contact_z_nm=fit.contact_z_nm,
        contact_side="z above the contact point" if fit.contact_side > 0 else "z below the contact point",
        fitted_points=fit.n_fitted, fitted_z_range_nm=tuple(fit.z_range_nm), contact_slope=fit.slope,
        contact_slope_std=fit.slope_std, contact_slope_units=f"{d_units or 'deflection units'}/nm",
        rms_residual=fit.rms_residual, capture_invols_nm_per_v=float(note) if note is not None else None,
        note="the InvOLS is 1/|slope| only on a hard (incompressible) sample; on a soft one the tip indents "
        "and |slope| is smaller",
        invols_nm_per_v=invols[0], invols_std_nm_per_v=invols[1],
        implied_invols_nm_per_v=implied[0], implied_invols_std_nm_per_v=implied[1],
    )
    plot = {"z": z[part], "d": d[part], "fit": fit, "z_units": "nm", "d_units": d_units}
    return results, plot


def _plot(path: Path, plot: Mapping) -> None:
    from afmtool.report.images import write_line_plot_png

    z, d, fit = plot["z"], plot["d"], plot["fit"]
    fit: ContactFit
    step = max(1, z.size // _PLOT_POINTS)
    lo, hi = fit.z_range_nm
    line_z = np.linspace(lo, hi, 50)
    write_line_plot_png(
        path,
        [
            (z[::step], d[::step], "force curve", {"color": "0.5", "linestyle": "none", "marker": ".", "markersize": 2}),
            (line_z, fit.intercept + fit.slope * line_z, f"contact fit, slope {fit.slope:.4g}", {"color": "C3"}),
        ],
        x_label="z (nm)",
        y_label=f"deflection ({plot['d_units'] or 'as recorded'})",
        title="Contact slope (InvOLS = 1/slope on a hard sample)",
        markers=[(fit.contact_z_nm, "contact")],
    )


def run_invols_command(
    reader: CaptureReader, source: str | Path, out: Path, config: Path | None, flags: Mapping
) -> dict:
    """Resolve parameters, fit, write ``invols.png``, ``config.toml`` and ``report.json``; return the report."""
    params = resolve_from(InvolsParams, "identify.invols", load_toml(config) if config else None, flags)
    warnings: list[str] = []
    results, plot = identify_invols(reader, params, warnings)
    if not all(math.isfinite(v) for v in (results.contact_slope, results.contact_slope_std)):
        raise InputError(f"{reader.info.source}: the contact part has no z spread to fit a slope to")
    inputs = [{**input_record(source), **calibration_record(reader)}]
    with OutputDir(out) as staged:
        _plot(staged.path("invols.png"), plot)
        return finish_run(staged, "identify invols", inputs, "identify.invols", params, results, warnings)
