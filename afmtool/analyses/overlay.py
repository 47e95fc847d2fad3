"""``afmtool overlay RUN_DIR... --out DIR``: several REEP runs side by side.

The thesis compares runs more often than it reads one: the mica-ageing
series of Fig. 3.17 (the same spot after 0, 45 min, 2 h and 16 h), the
multi-Q sensitivities of Figs. 4.6-4.9, REEP against sweeps at several
separations (Fig. 3.1b).  ``overlay`` reads finished ``reep`` folders (their
``reep.h5``, ``report.json``), nothing is estimated again, and writes:

* one figure per quantity against z (or the separation from each run's
  contact point): f0', Q', amplitude, phase and, where the runs have them,
  the interaction quantities (force gradient, tip-sample damping, Φ_c, Φ_d,
  energy per cycle), one line per run, labelled;
* one figure per quantity against time (f0', Q', amplitude, phase);
* ``overlay.csv``: every plotted point in tidy form (one row per run,
  curve, x and quantity), for a notebook;
* ``report.json`` with each run's label, free-air f0' and Q' and the
  extremes of its approach, and ``report.html``: the page.

Labels come from ``--labels`` (one per run, in order), or ``--label-key``:
``q`` or ``f0`` (each run's free-air Q' or f0'), or a key of the capture's
metadata (``time``, ``sample``, ``experiment.time``: dotted for nested
keys), else the run folder's name.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from afmtool.errors import ConfigError, InputError
from afmtool.records.overlay import CurveLeg, OverlayAxis, OverlayResults, OverlayRunRecord
from afmtool.records.reep import ReepResults
from afmtool.runtime.outputs import OutputDir

__all__ = ["FORCE_CURVE_QUANTITIES", "OverlayRun", "TIME_QUANTITIES", "read_runs", "run_overlay_command"]

#: Force-curve quantities overlaid, with their label and units ("" = from the file).
FORCE_CURVE_QUANTITIES: Mapping[str, tuple[str, str]] = {
    "f0_hz": ("f0'", "Hz"), "q": ("Q'", ""), "amplitude": ("amplitude", ""), "phase_deg": ("phase", "deg"),
    "force_gradient_n_per_m": ("force gradient k_e − k", "N/m"), "damping_ts_n_s_per_m": ("tip–sample damping c_ts", "N*s/m"),
    "phi_c_n": ("Φ_c", "N"), "phi_d_n": ("Φ_d", "N"), "energy_per_cycle_ev": ("E_ts per cycle", "eV"),
}
#: Time-series quantities overlaid.
TIME_QUANTITIES: Mapping[str, tuple[str, str]] = {
    "f0_hz": ("f0'", "Hz"), "q": ("Q'", ""), "amplitude": ("amplitude", ""), "phase_deg": ("phase", "deg"),
}
#: Most points per run in a time-series figure and in the CSV.
_TIME_POINTS = 4000


@dataclass
class OverlayRun:
    """One REEP run as the overlay reads it: its label and curves (x, values per quantity)."""

    folder: Path
    label: str
    results: ReepResults | None  #: its report.json's (None without one)
    z_units: str
    amplitude_units: str
    curves: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)  # leg -> {"z": ..., quantity: ...}
    units: dict[str, str] = field(default_factory=dict)
    time: dict[str, np.ndarray] = field(default_factory=dict)
    inputs: tuple = ()

    @property
    def free_f0_hz(self) -> float | None:
        segment, model = self._free()
        return _finite(segment.f0_hz.mean if segment is not None else None, model.f0_hz if model is not None else None)

    @property
    def free_q(self) -> float | None:
        segment, model = self._free()
        return _finite(segment.q.mean if segment is not None else None, model.q if model is not None else None)

    def _free(self):
        """(REEP's free-air segment, the free-air model), each None where the run has none."""
        if self.results is None:
            return None, None
        return self.results.segments.free_air, self.results.free_air_model


def _finite(value: float | None, fallback: float | None) -> float | None:
    """``value`` (REEP's free-air mean) where the run has it, else ``fallback`` (the model's); None unless finite."""
    if value is None or math.isnan(value):  # a mean over no row is NaN (written as null)
        value = fallback
    return float(value) if value is not None and math.isfinite(value) else None


# --------------------------------------------------------------------------- reading


def _read_one(folder: Path) -> OverlayRun:
    from afmtool.io.reep_results import open_reep_results

    with open_reep_results(folder, where="RUN_DIR") as reep:
        handle = reep.file
        run = OverlayRun(Path(folder), Path(folder).resolve().name, reep.results, reep.z_units,
                         handle.units("amplitude") if "amplitude" in handle.names() else "", inputs=reep.inputs)
        for leg in ("approach", "retract"):
            names = handle.names(f"force_curve/{leg}")
            if "z" not in names:
                continue
            curve = {"z": np.asarray(handle[f"force_curve/{leg}/z"][()], dtype=float)}
            for quantity in FORCE_CURVE_QUANTITIES:
                if quantity in names:
                    curve[quantity] = np.asarray(handle[f"force_curve/{leg}/{quantity}"][()], dtype=float)
                    units = handle.units(f"force_curve/{leg}/{quantity}")
                    # reep's tables leave the amplitude's units to the series (the deflection's)
                    run.units[quantity] = units or (run.amplitude_units if quantity == "amplitude" else "")
            run.curves[leg] = curve
        rows = handle.read_rows([q for q in TIME_QUANTITIES if q in handle.names()], max_points=_TIME_POINTS)
        rows.pop("_rows", None)
        flags = handle.read_rows(["flag"], max_points=_TIME_POINTS).get("flag") if "flag" in handle.names() else None
        for name, values in rows.items():
            values = np.asarray(values, dtype=float)
            if name in ("f0_hz", "q") and flags is not None:
                values = np.where(np.asarray(flags) == 0, values, np.nan)  # a flagged fit is not shown
            run.time[name] = values
    run.units.setdefault("amplitude", run.amplitude_units)
    return run


def _metadata_value(run: OverlayRun, key: str):
    """``key`` (dotted) of the metadata of the capture the run read; InputError if it cannot be found."""
    from afmtool.io.registry import open_capture

    capture = next((item.get("path") for item in run.inputs if item.get("role") == "capture"), None)
    if not capture or capture == "-" or not Path(capture).exists():
        raise InputError(f"{run.folder}: --label-key {key}: the run's capture {capture!r} is not there to read it from")
    with open_capture(capture) as reader:
        value = reader.info.metadata
        for part in key.split("."):
            if not isinstance(value, Mapping) or part not in value:
                raise InputError(f"{run.folder}: --label-key {key}: the metadata of {capture} have no {key!r}")
            value = value[part]
    return value


def _label(run: OverlayRun, key: str) -> str:
    from afmtool.report.numbers import format_value

    if key.lower() in ("q", "f0"):
        value = run.free_q if key.lower() == "q" else run.free_f0_hz
        if value is None:
            raise InputError(f"{run.folder}: --label-key {key}: the run has no free-air {key}")
        return f"Q = {format_value(value)}" if key.lower() == "q" else f"f0 = {format_value(value)} Hz"
    value = _metadata_value(run, key)
    return f"{key} = {format_value(value)}" if isinstance(value, (int, float)) else str(value)


def read_runs(folders: Sequence[Path], labels: Sequence[str] | None = None, label_key: str | None = None) -> list[OverlayRun]:
    """Every run, labelled by ``labels`` (one per run), ``label_key`` or its folder name.

    Raises
    ------
    ConfigError
        Fewer than two runs, or a ``labels`` list of another length.
    InputError
        A folder that is not a ``reep`` output, or a label key the run cannot give.
    """
    if len(folders) < 2:
        raise ConfigError("overlay needs two or more RUN_DIR")
    if labels is not None and len(labels) != len(folders):
        raise ConfigError(f"--labels gives {len(labels)} labels for {len(folders)} runs; give one per run")
    runs = [_read_one(Path(folder)) for folder in folders]
    for i, run in enumerate(runs):
        if labels is not None:
            run.label = labels[i]
        elif label_key:
            run.label = _label(run, label_key)
    if len({run.label for run in runs}) < len(runs):
        raise ConfigError(f"two runs have the same label ({', '.join(run.label for run in runs)}); give --labels")
    return runs


# --------------------------------------------------------------------------- x axis


def _contact_z(curve: Mapping[str, np.ndarray], drop: float) -> float | None:
    """The z where the approach's amplitude first falls below ``drop`` of its free value (the bins' first)."""
    z, amplitude = curve["z"], curve.get("amplitude")
    if amplitude is None or not np.isfinite(amplitude).any():
        return None
    order = np.argsort(z)[::-1] if np.nanmean(amplitude[np.argsort(z)[-3:]]) >= np.nanmean(amplitude[np.argsort(z)[:3]]) \
        else np.argsort(z)
    free = np.nanmedian(amplitude[order[: max(3, len(order) // 10)]])
    below = np.flatnonzero(amplitude[order] < drop * free)
    return float(z[order[below[0]]]) if below.size else None


def _x(run: OverlayRun, leg: str, vs: str, contact: Mapping[str, float | None]) -> np.ndarray:
    z = run.curves[leg]["z"]
    if vs == "z":
        return z
    z_c = contact.get(run.label)
    return np.abs(z - z_c) if z_c is not None else np.full_like(z, np.nan)


# --------------------------------------------------------------------------- writing


def _tidy_rows(runs: Sequence[OverlayRun], vs: str, x_units: str, contact: Mapping) -> list[list]:
    rows: list[list] = []
    for run in runs:
        for leg, curve in run.curves.items():
            x = _x(run, leg, vs, contact)
            for quantity in FORCE_CURVE_QUANTITIES:
                if quantity in curve:
                    units = run.units.get(quantity, "")
                    rows.extend([run.label, str(run.folder), "force_curve", leg, vs, xi, x_units, quantity, v, units]
                                for xi, v in zip(x.tolist(), curve[quantity].tolist()))
        t = run.time.get("t")
        if t is not None:
            for quantity in TIME_QUANTITIES:
                if quantity in run.time:
                    units = run.units.get(quantity, "") or TIME_QUANTITIES[quantity][1]
                    rows.extend([run.label, str(run.folder), "time_series", "", "t", ti, "s", quantity, v, units]
                                for ti, v in zip(t.tolist(), run.time[quantity].tolist()))
    return rows


def _write_csv(path: Path, rows: list[list]) -> None:
    with open(path, "w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow(["label", "run", "kind", "leg", "x_name", "x", "x_units", "quantity", "value", "units"])
        writer.writerows([*row[:5], _csv_number(row[5]), row[6], row[7], _csv_number(row[8]), row[9]] for row in rows)


def _csv_number(value: float) -> str:
    return "" if value is None or not math.isfinite(value) else repr(float(value))


def _colours(n: int) -> list[str]:
    """One colour per run, in order (viridis, dark to light: the order of a series in time)."""
    from matplotlib import colormaps
    from matplotlib.colors import to_hex

    cmap = colormaps["viridis"]
    return [to_hex(cmap(0.9 * i / max(1, n - 1))) for i in range(n)]


def _figure_specs(runs: Sequence[OverlayRun], vs: str, x_units: str, legs: Sequence[str], contact: Mapping):
    """(file name, panels, x label, title) of every figure: one per quantity."""
    colours = _colours(len(runs))
    specs = []
    for quantity, (label, default_units) in FORCE_CURVE_QUANTITIES.items():
        series = []
        for run, colour in zip(runs, colours):
            for leg in legs:
                curve = run.curves.get(leg)
                if curve is None or quantity not in curve:
                    continue
                style = {"color": colour, "linestyle": "-" if leg == "approach" else "--"}
                name = run.label if len(legs) == 1 else f"{run.label} ({leg})"
                series.append((_x(run, leg, vs, contact), curve[quantity], name, style))
        if series:
            units = runs[0].units.get(quantity) or default_units or "dimensionless"
            panels = [{"y_label": f"{label} ({units})", "series": series}]
            x_label = f"z_piezo ({x_units})" if vs == "z" else f"separation from the contact point ({x_units})"
            specs.append((f"overlay_{quantity}.png", panels, x_label, f"{label} against {vs}, {len(runs)} runs"))
    for quantity, (label, default_units) in TIME_QUANTITIES.items():
        series = [(run.time["t"], run.time[quantity], run.label, {"color": colour})
                  for run, colour in zip(runs, colours) if quantity in run.time and "t" in run.time]
        if series:
            units = runs[0].units.get(quantity) or default_units or "dimensionless"
            specs.append((f"overlay_time_{quantity}.png", [{"y_label": f"{label} ({units})", "series": series}],
                          "time t (s)", f"{label} against time, {len(runs)} runs"))
    return specs


def _run_summary(run: OverlayRun, contact: Mapping) -> OverlayRunRecord:
    curve = run.results.force_curve if run.results is not None else None
    approach = curve.approach if curve is not None else None
    return OverlayRunRecord(
        label=run.label, folder=str(run.folder), free_air_f0_hz=run.free_f0_hz, free_air_q=run.free_q,
        largest_df0_hz=approach.largest_df0_hz if approach is not None else None,
        largest_df0_z=approach.largest_df0_z if approach is not None else None,
        smallest_q=approach.smallest_q if approach is not None else None, contact_z=contact.get(run.label),
        force_curve_legs=tuple(CurveLeg(leg) for leg in sorted(run.curves)), time_rows=int(len(run.time.get("t", ()))),
    )


def _spread(values: Sequence[float | None]) -> float | None:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    return float(max(finite) - min(finite)) if len(finite) > 1 else None


def _results(runs: Sequence[OverlayRun], vs: str, x_units: str, contact: Mapping) -> OverlayResults:
    summaries = tuple(_run_summary(run, contact) for run in runs)
    return OverlayResults(
        runs=summaries,
        n_runs=len(runs),
        vs=OverlayAxis(vs),
        x_units=x_units,
        contact_rule="separation = |z - z_c|, z_c where the approach amplitude first falls below 0.95 of free air"
        if vs == "separation" else None,
        free_air_f0_hz_spread=_spread([s.free_air_f0_hz for s in summaries]),
        free_air_q_spread=_spread([s.free_air_q for s in summaries]),
        largest_df0_hz_spread=_spread([s.largest_df0_hz for s in summaries]),
        first=summaries[0],
        last=summaries[-1],
    )


def run_overlay_command(folders: Sequence[Path], out: Path, *, labels: Sequence[str] | None = None,
                        label_key: str | None = None, vs: str = "z", leg: str = "approach", figures=None) -> dict:
    """Read the runs, write the figures, ``overlay.csv``, ``report.json`` and ``report.html``; return the report."""
    from afmtool.report.figure_process import FigureProcess
    from afmtool.report.images import write_multi_panel_png
    from afmtool.report.json_report import input_record
    from afmtool.report.run import finish_run

    if vs not in ("z", "separation"):
        raise ConfigError(f"--vs {vs!r}: give z or separation")
    if leg not in ("approach", "retract", "both"):
        raise ConfigError(f"--leg {leg!r}: give approach, retract or both")
    legs = ("approach", "retract") if leg == "both" else (leg,)
    runs = read_runs(folders, labels, label_key)
    units = {run.z_units for run in runs if run.curves}
    if len(units) > 1:
        raise InputError(f"the runs' z are in different units ({', '.join(sorted(units))}); overlay runs of one instrument")
    x_units = next(iter(units), "")
    contact = {run.label: _contact_z(run.curves["approach"], 0.95) if "approach" in run.curves else None for run in runs}
    figures = figures or FigureProcess()
    inputs = [input_record(Path(run.folder) / "report.json", "run") for run in runs if (Path(run.folder) / "report.json").is_file()]
    with OutputDir(out) as staged, figures.stopped_on_failure():
        page = staged.path("report.html")  # named (and there) now, so that report.json lists it
        page.touch()
        for name, panels, x_label, title in _figure_specs(runs, vs, x_units, legs, contact):
            figures.draw(write_multi_panel_png, staged.path(name), panels, x_label=x_label, title=title)
        _write_csv(staged.path("overlay.csv"), _tidy_rows(runs, vs, x_units, contact))
        figures.wait()
        report = finish_run(staged, "overlay", inputs, "overlay", _OverlaySettings(vs, leg, label_key or "", labels),
                            _results(runs, vs, x_units, contact), [])
        from afmtool.report.html import render_report_html

        page.write_text(render_report_html(page.parent), encoding="utf-8")
    return report


@dataclass(frozen=True)
class _OverlaySettings:
    """The overlay's settings, as config.toml and report.json record them."""

    vs: str
    leg: str
    label_key: str
    labels: Sequence[str] | None
