"""``theory compare``'s figure and bin table: REEP's binned shifts beside averaging theory.

Apart from :mod:`afmtool.analyses.theory_outputs` so that the figure process
imports numpy and matplotlib for it, not the comparison.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["write_compare_png", "write_compare_table"]

_LEGS = (("approach", "o", "-"), ("retract", "s", "--"))
_LEFT_OUT = {"color": "0.6", "linestyle": "none", "marker": "x", "markersize": 5}


def _error_bars(x: np.ndarray, y: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertical segments y ± half at each x, as one line broken by NaN (x kept finite)."""
    xs = np.repeat(x, 3)
    ys = np.column_stack([y - half, y + half, np.full_like(y, np.nan)]).ravel()
    return xs, ys


def _panel(bins, shift_reep: str, shift_theory: str, std_reep: str, std_theory: str, label: str) -> dict:
    """One quantity's panel: REEP's bin shifts ±2σ_R, the theory's ±2σ_T, bins left out in grey."""
    series = []
    for leg, (name, marker, linestyle) in enumerate(_LEGS):
        on_leg = bins.leg == leg
        if not on_leg.any():
            continue
        x = bins.separation_nm[on_leg]
        ok = bins.conditioned[on_leg]
        reep = getattr(bins, shift_reep)[on_leg]
        theory = getattr(bins, shift_theory)[on_leg]
        colour = "C0" if leg == 0 else "C2"
        series.append((x, theory, f"averaging theory, {name}", {"color": "C3", "linestyle": linestyle}))
        series.append((*_error_bars(x, theory, 2 * getattr(bins, std_theory)[on_leg]), "",
                       {"color": "C3", "alpha": 0.35, "linewidth": 3}))
        series.append((x[ok], reep[ok], f"REEP, {name} (median ±2σ)",
                       {"color": colour, "linestyle": "none", "marker": marker, "markersize": 4}))
        series.append((*_error_bars(x[ok], reep[ok], 2 * getattr(bins, std_reep)[on_leg][ok]), "",
                       {"color": colour, "linewidth": 1}))
        if (~ok).any():
            series.append((x[~ok], reep[~ok], "left out: theory ill-conditioned" if leg == 0 else "", _LEFT_OUT))
    return {"y_label": label, "series": series}


def write_compare_png(path: Path, series: dict, separation: np.ndarray, comparison) -> None:
    """Binned shifts of f0′ and Q′ from free air, REEP against the theory, and each bin's z (eq. C.1)."""
    from afmtool.report.images import write_multi_panel_png

    bins = comparison.bins
    z_series = []
    for name, values, style in (("f0'", bins.f0_z, {"color": "C0", "marker": "o"}),
                                ("Q'", bins.q_z, {"color": "C1", "marker": "s"})):
        ok = bins.conditioned
        z_series.append((bins.separation_nm[ok], values[ok], f"z of {name}",
                         {**style, "linestyle": "none", "markersize": 4}))
    limits = np.array([bins.separation_nm.min(), bins.separation_nm.max()])
    for level in (-3.0, 3.0):
        z_series.append((limits, np.full(2, level), "±3" if level > 0 else "", {"color": "0.4", "linestyle": ":"}))
    panels = [
        _panel(bins, "f0_shift_reep_hz", "f0_shift_theory_hz", "f0_reep_std_hz", "f0_theory_std_hz",
               "f0' − free air (Hz)"),
        _panel(bins, "q_shift_reep", "q_shift_theory", "q_reep_std", "q_theory_std", "Q' − free air (dimensionless)"),
        {"y_label": "z, eq. C.1 (standard deviations)", "series": z_series},
    ]
    verdict = "PASS" if comparison.passed else ("INCONCLUSIVE" if comparison.verdict.startswith("inconclusive")
                                                else "FAIL")
    write_multi_panel_png(path, panels, x_label="separation l (nm)",
                          title=f"REEP vs averaging theory, {bins.leg.size} bins of separation: {verdict}")


def write_compare_table(path: Path, comparison) -> None:
    """compare_bins.csv: one row per separation bin (:meth:`ComparisonBins.table`)."""
    from afmtool.io.rows import RowWriter

    with open(path, "w", encoding="utf-8", newline="") as handle, RowWriter(handle, "csv") as rows:
        rows.append(comparison.bins.table())
