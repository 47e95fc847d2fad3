"""The ``theory observer`` command end to end: parameters, evaluation, files, report.

Writes ``observer.h5`` (``maps/...`` over observer models per gain,
``lines/...`` along the force-curve direction), ``observer_maps_<cycles>.png``
per gain, ``observer_lines.png``, ``report.json`` and ``config.toml``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from afmtool.config import load_toml, resolve_from
from afmtool.config.params import ObserverTheoryParams
from afmtool.errors import ConfigError
from afmtool.estimators.observer_design import (
    METRIC_UNITS,
    DesignSettings,
    Direction,
    DirectionalLines,
    ObserverMap,
    direction_from_averaging,
    direction_from_reep_tables,
    directional_lines,
    observer_map,
    recommend,
)
from afmtool.io.results import ResultWriter
from afmtool.records.common import DriveHold
from afmtool.records.theory_observer import (
    DirectionRecord,
    DiscreteObserverRecord,
    GainMapRecord,
    LineRecord,
    MapsRecord,
    NoiseRecord,
    ObserverDriveRecord,
    ObserverResults,
    PlantRecord,
    RecommendationRecord,
)
from afmtool.report.json_report import input_record
from afmtool.report.run import finish_run
from afmtool.runtime.outputs import OutputDir

__all__ = ["run_observer_theory_command", "parse_cycles"]

_MAP_PANELS = ("ae2", "dae2_ds", "snr_eta", "snr_nu", "peak_transient", "settling_cycles")
_LINE_PANELS = ("ae2", "dae2_ds", "s_eta", "n_eta", "n_nu", "snr_nu", "peak_transient")
_STYLES = ("-", "--", ":", "-.")


def parse_cycles(text: str) -> tuple[float, ...]:
    """``"4,50"`` -> (4.0, 50.0): gains as drive periods per 1/e of the error."""
    try:
        values = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise ConfigError(f"cycles={text!r} must be numbers separated by commas") from None
    if not values or not all(math.isfinite(v) and v > 0 for v in values):
        raise ConfigError(f"cycles={text!r} must be positive numbers separated by commas")
    return values


def _plant(params: ObserverTheoryParams) -> tuple[float, float, float, list]:
    if not params.model:
        return params.f0_hz, params.q, params.gain, []
    from afmtool.models.free_air import load_free_air_model

    path = Path(params.model)
    model = load_free_air_model(path)
    return model.f0_hz, model.q, model.gain, [input_record(path / "free_air.json" if path.is_dir() else path, "model")]


def _direction(params: ObserverTheoryParams, f0: float, q: float, drive_hz: float) -> tuple[Direction, list]:
    if params.f0_low_hz > 0:
        q_low = params.q_low or q
        return Direction(f0, q, params.f0_low_hz, q_low, "given"), []
    if params.reep:
        from afmtool.analyses.accumulators import ReepBinner
        from afmtool.io.reep_results import open_reep_results

        with open_reep_results(params.reep) as reep:
            if not all(name in reep.series for name in ("z", "f0_hz", "q", "amplitude")):
                raise ConfigError(f"--reep {reep.path}: needs z, f0_hz, q and amplitude series")
            binner = ReepBinner(0.5, 0, 0.0)
            series, step = reep.series, 1 << 16
            names = ("t", "z", "f0_hz", "q", "amplitude")
            for start in range(0, len(series["t"]), step):
                binner.append({k: np.asarray(series[k][start : start + step]) for k in names})
            source = f"REEP {reep.path}"
            direction = direction_from_reep_tables(f0, q, binner.tables(), params.setpoint_fraction, source)
            return direction, [input_record(reep.path, "reep series")]
    direction = direction_from_averaging(
        f0, q, params.force_set, params.free_amplitude_nm, params.setpoint_fraction, drive_hz
    )
    return direction, []


def _observers(params: ObserverTheoryParams, direction: Direction) -> tuple[tuple[float, float], ...]:
    if params.observers:
        from afmtool.estimators.kalman_bank_verdict import parse_model_list

        return parse_model_list(params.observers, "observers")
    return ((direction.f0_free_hz, direction.q_free), (direction.f0_low_hz, direction.q_low))


def run_observer_theory_command(out: Path, config: Path | None, flags: Mapping) -> dict:
    """Maps, lines and (optionally) a recommendation; every output written atomically."""
    from afmtool.models.observer_theory import thermal_psd

    params = resolve_from(ObserverTheoryParams, "theory.observer", load_toml(config) if config else None, flags)
    f0, q, gain, inputs = _plant(params)
    drive_hz = params.drive_frequency_hz or f0
    w0, w = 2 * math.pi * f0, 2 * math.pi * drive_hz
    c0 = gain * w0 * w0
    response = abs(c0 / complex(w0 * w0 - w * w, w * w0 / q))
    settings = DesignSettings(
        drive_frequency_hz=drive_hz,
        drive_amplitude=params.free_amplitude_nm / response,
        numerator=(0.0, c0),
        eta_psd=thermal_psd(w0, q, params.spring_constant_n_per_m, params.temperature_k) / (gain * gain),
        nu_psd=params.measurement_asd**2,
        residual=params.residual,
    )
    direction, more_inputs = _direction(params, f0, q, drive_hz)
    inputs += more_inputs
    cycles = parse_cycles(params.cycles)
    grid = observer_map(direction, (f0, q), cycles, settings, points=params.grid_points, margin=params.grid_margin)
    lines = directional_lines(direction, _observers(params, direction), cycles, settings, points=params.line_points)
    recommendation = _recommendation(grid, params, f0, q, gain, drive_hz) if params.recommend else None
    results = ObserverResults(
        plant=PlantRecord(f0_hz=f0, q=q, gain=gain, numerator_c1_c0=settings.numerator),
        direction=DirectionRecord(**direction._asdict()),
        drive=ObserverDriveRecord(frequency_hz=drive_hz, amplitude=settings.drive_amplitude,
                                  free_amplitude=params.free_amplitude_nm),
        noise=NoiseRecord(
            eta_psd_per_hz=settings.eta_psd, nu_psd_per_hz=settings.nu_psd,
            convention="one-sided PSDs; variance = (S/2pi) * integral_0^inf |H(jw)|^2 dw (eq. 5.20 with its 1/pi)",
        ),
        cycles=cycles,
        maps=_map_summary(grid),
        lines=_line_summary(lines),
        recommendation=recommendation,
    )
    warnings = []
    if recommendation is not None:
        if recommendation.at_grid_edge:
            warnings.append(
                "the recommended observer model lies on the edge of the map: the sensitivity may keep growing beyond "
                "it (raise grid_margin, or give slower gains in --cycles to meet the settling limit)"
            )
    with OutputDir(out) as staged:
        with ResultWriter(staged.path("observer.h5"), {}, {"afmtool_command": "theory observer"}) as writer:
            _write_h5(writer, grid, lines)
        for j, c in enumerate(cycles):
            _plot_maps(staged.path(f"observer_maps_{c:g}cycles.png"), grid, j, direction)
        _plot_lines(staged.path("observer_lines.png"), lines)
        return finish_run(staged, "theory observer", inputs, "theory.observer", params, results, warnings)


def _recommendation(
    grid: ObserverMap, params: ObserverTheoryParams, f0: float, q: float, gain: float, drive_hz: float
) -> RecommendationRecord:
    from afmtool.estimators.observer import ObserverDesign
    from afmtool.models.discretisation import discrete_denominator
    from afmtool.models.free_air import FreeAirModel

    pick = recommend(grid, params.max_cycles)
    fs = params.sample_rate_hz
    # a model given by continuous parameters, discretised for how the drive reaches the plant
    numerator = FreeAirModel(f0, q, gain).numerator_at(fs, params.drive_hold, match_hz=drive_hz)
    denominator = discrete_denominator(pick.f_k_hz, pick.q_k, fs)
    design = ObserverDesign.from_decay(
        (float(denominator.b1), float(denominator.b0)), numerator, pick.cycles, fs / drive_hz, residual=params.residual
    )
    return RecommendationRecord(
        **pick._asdict(),
        max_cycles=params.max_cycles,
        criterion="largest |dA_e^2/ds| along the force-curve direction (eq. 5.16) among observer models and gains "
        f"whose error after a unit plant-state step stays below {params.residual:.3g} after max_cycles drive periods",
        discrete=DiscreteObserverRecord(sample_rate_hz=fs, drive_hold=DriveHold(params.drive_hold),
                                        numerator=design.numerator, denominator=design.denominator, gain=design.gain),
    )


def _finite_range(values: np.ndarray) -> tuple[float | None, float | None]:
    finite = values[np.isfinite(values)]
    return (float(finite.min()), float(finite.max())) if finite.size else (None, None)


def _map_summary(grid: ObserverMap) -> MapsRecord:
    per_gain = {}
    for c, m in zip(grid.cycles, grid.metrics, strict=True):
        iq, jf = np.unravel_index(int(np.argmin(m.ae2)), m.ae2.shape)
        per_gain[f"{c:g}_cycles"] = GainMapRecord(
            ae2_min_at=(float(grid.f_k_hz[jf]), float(grid.q_k[iq])),
            **{name: _finite_range(getattr(m, name)) for name in _MAP_PANELS},
        )
    return MapsRecord(nominal=tuple(grid.nominal), f_k_hz_range=_finite_range(grid.f_k_hz),
                      q_k_range=_finite_range(grid.q_k), per_gain=per_gain)


def _line_summary(lines: DirectionalLines) -> tuple[LineRecord, ...]:
    rows = []
    for (fk, qk), per_gain in zip(lines.observers, lines.metrics, strict=True):
        for c, m in zip(lines.cycles, per_gain, strict=True):
            k = int(np.argmin(m.ae2))
            rows.append(LineRecord(
                observer=(fk, qk),
                cycles=c,
                ae2_min_at_s=float(lines.s[k]),
                ae2_range=_finite_range(m.ae2),
                dae2_ds_range=_finite_range(m.dae2_ds),
                snr_nu_range=_finite_range(m.snr_nu),
                peak_transient_range=_finite_range(m.peak_transient),
            ))
    return tuple(rows)


def _write_h5(writer: ResultWriter, grid: ObserverMap, lines: DirectionalLines) -> None:
    writer.put("maps/f_k_hz", grid.f_k_hz, "Hz")
    writer.put("maps/q_k", grid.q_k)
    for c, m in zip(grid.cycles, grid.metrics, strict=True):
        for name, values in m._asdict().items():
            writer.put(f"maps/{c:g}_cycles/{name}", values, METRIC_UNITS[name][1], {"rows": "q_k", "columns": "f_k_hz"})
    writer.put("lines/s", lines.s)
    writer.put("lines/f_e_hz", lines.f_e_hz, "Hz")
    writer.put("lines/q_e", lines.q_e)
    for i, ((fk, qk), per_gain) in enumerate(zip(lines.observers, lines.metrics, strict=True)):
        for c, m in zip(lines.cycles, per_gain, strict=True):
            attrs = {"observer_f0_hz": fk, "observer_q": qk, "cycles": c}
            for name, values in m._asdict().items():
                writer.put(f"lines/observer{i + 1}_{c:g}_cycles/{name}", values, METRIC_UNITS[name][1], attrs)


def _log10(values: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(values > 0, np.log10(values), np.nan)


def _plot_maps(path: Path, grid: ObserverMap, j: int, direction: Direction) -> None:
    """log10 maps over (f_k, Q_k), the force-curve direction drawn, the nominal plant marked."""
    # reuse the project's PNG figure (atomic write, default style) and NaN colour
    from afmtool.report.images import _colormap, _png_figure

    m = grid.metrics[j]
    extent = (grid.f_k_hz[0] / 1e3, grid.f_k_hz[-1] / 1e3, grid.q_k[0], grid.q_k[-1])
    with _png_figure(path, 12.0, 7.5) as fig:
        axes = fig.subplots(2, 3, squeeze=False).ravel()
        for ax, name in zip(axes, _MAP_PANELS, strict=True):
            values = np.abs(getattr(m, name)) if name == "dae2_ds" else getattr(m, name)
            shown = values if name == "settling_cycles" else _log10(values)
            im = ax.imshow(
                np.ma.masked_invalid(shown), origin="lower", extent=extent, aspect="auto", cmap=_colormap("viridis")
            )
            label, units = METRIC_UNITS[name]
            title = f"|{label}|" if name == "dae2_ds" else label
            ax.set_title(title + ("" if name == "settling_cycles" else ", log10"), fontsize="small")
            line_f = [direction.f0_free_hz / 1e3, direction.f0_low_hz / 1e3]
            ax.plot(line_f, [direction.q_free, direction.q_low], "w--", linewidth=1)
            ax.plot(grid.nominal[0] / 1e3, grid.nominal[1], "r+", markersize=10)
            ax.set_xlabel("observer f_k (kHz)")
            ax.set_ylabel("observer Q_k (dimensionless)")
            shown_units = units or "dimensionless"
            fig.colorbar(im, ax=ax, label=f"{title} ({shown_units})" if name == "settling_cycles"
                         else f"log10 {title} ({shown_units})")
        fig.suptitle(f"Observer design maps (ch. 5), plant at f {grid.nominal[0]:.0f} Hz, Q {grid.nominal[1]:.1f}; "
                     f"gain: 1/e in {grid.cycles[j]:g} drive periods")


def _plot_lines(path: Path, lines: DirectionalLines) -> None:
    from afmtool.report.images import write_multi_panel_png

    panels = []
    for name in _LINE_PANELS:
        series = []
        for i, ((fk, qk), per_gain) in enumerate(zip(lines.observers, lines.metrics, strict=True)):
            for j, (c, m) in enumerate(zip(lines.cycles, per_gain, strict=True)):
                values = np.abs(getattr(m, name)) if name == "dae2_ds" else getattr(m, name)
                style = {"color": f"C{i}", "linestyle": _STYLES[j % len(_STYLES)]}
                label = f"observer {fk:.0f} Hz, Q {qk:.0f}, {c:g} periods" if not panels else ""
                series.append((lines.s, _log10(values), label, style))
        label, units = METRIC_UNITS[name]
        quantity = f"log10 {'|' + label + '|' if name == 'dae2_ds' else label}"[:34]
        panels.append({"series": series, "y_label": f"{quantity} ({units or 'dimensionless'})"})
    write_multi_panel_png(
        path, panels, x_label="s along the force-curve direction (dimensionless: 0 free air, 1 on-sample)",
        title="Observer trade-offs along the force curve (Figs. 5.9-5.20)",
    )
