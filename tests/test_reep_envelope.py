"""REEP across the envelope scientists record in (issue 27, item 7; items 2 and 3 where a cell shows them).

Every cell is a capture of ``tests/reference_sim.py`` (no code shared with
afmtool's simulator or models), run through REEP as ``afmtool reep`` runs it
and measured by :func:`tests.reep_envelope.run_cell`.  The grid covers
fs 0.5, 1 and 2 MHz; Q 20, 38, 100, 200, 400 and 600; f0 30–300 kHz
(fs/f0 from 4.4 to 40); free air and steady attractive, mixed and repulsive
tapping; 0.02–0.1 nm of measurement noise.  Each regime and Q appears at
more than one rate, and each rate at every Q.

Tolerances, per cell (the cell's ``Tol`` beside it):

* free air: |mean f0′ − f0| and |mean Q′/Q − 1| within a quarter of the
  stated per-row std (a mean over ~100 windows: a quarter of a row's std is
  ~2.5 std of the mean) or 0.5 Hz / 0.1 %, whichever is larger; the stated
  ±2σ covers the truth in 90–99 % of the rows; no row flagged.
* steady tapping (A ≥ 0.45 A0, the tip reaching the force in the period
  before the row): at most 10 % of rows flagged; the stated ±2σ covers
  REEP's own noise-free estimate (the expectation the noise scatters) in
  90–99 % of rows; and mean f0′ and Q′ within the stated per-row ±2σ plus a
  share τ of the theory's shift of the first-harmonic balance (averaging
  theory, ch. 4).  The theory is an approximation (a piecewise force is not
  a spring and a damper, and the side lines see the interaction's
  incremental response, not its describing function), so its error scales
  with the attraction's and the wall's shifts each, |Δ_a| + |Δ_wall|, not
  with their sum (in mixed tapping they cancel).  τ = 10 % where the tip
  stays off the wall (the thesis's own agreement), 20 % where it reaches the
  wall (averaging theory is ill-conditioned there: ``theory compare`` leaves
  such bins out of its verdict); whether a cell reaches the wall is measured
  (the least noise-free tip–sample separation), not declared.

CI runs :data:`SHORT` (a few cells, each a few seconds of CPU); the full
:data:`GRID` is marked slow.  ``python -m tests.test_reep_envelope`` prints
the table of every cell against its tolerance (the notes of issue 27 hold
one).
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass

import pytest

from tests.reep_envelope import Cell, run_cell


@dataclass(frozen=True)
class Tol:
    """A cell's tolerances (module docstring)."""

    coverage: tuple[float, float] = (0.90, 0.99)
    flagged_max: float = 0.0  # free air: none; tapping: 10 %
    theory_share: float = 0.10  # tapping off the wall: share of the theory's shift scale (module docstring)
    wall_share: float = 0.20  # tapping that reaches the repulsive wall
    mean_in_row_std: float = 0.25  # free air: |bias| / stated row std
    f0_floor_hz: float = 0.5
    q_floor: float = 0.001


FREE = Tol()
TAPPING = Tol(flagged_max=0.10)
WALL = TAPPING  # whether a cell reaches the wall is measured (min_separation_nm < 0), not declared

#: (cell, tolerance).  Free air: every rate at every Q, f0 from 30 to 300 kHz, fs/f0 from 4.4 to 40.
FREE_GRID = [
    (Cell(500e3, 30e3, 20.0, "free", 0.05), FREE),
    (Cell(500e3, 70e3, 38.0, "free", 0.1), FREE),
    (Cell(500e3, 100e3, 100.0, "free", 0.02), FREE),
    (Cell(500e3, 70e3, 200.0, "free", 0.05), FREE),
    (Cell(500e3, 50e3, 400.0, "free", 0.1), FREE),
    (Cell(500e3, 110e3, 600.0, "free", 0.02), FREE),
    (Cell(1e6, 150e3, 20.0, "free", 0.02), FREE),
    (Cell(1e6, 30e3, 38.0, "free", 0.05), FREE),
    (Cell(1e6, 200e3, 100.0, "free", 0.1), FREE),
    (Cell(1e6, 70e3, 200.0, "free", 0.02), FREE),
    (Cell(1e6, 120e3, 400.0, "free", 0.05), FREE),
    (Cell(1e6, 40e3, 600.0, "free", 0.1), FREE),
    (Cell(2e6, 300e3, 20.0, "free", 0.1), FREE),
    (Cell(2e6, 75e3, 38.0, "free", 0.02), FREE),
    (Cell(2e6, 50e3, 100.0, "free", 0.05), FREE),  # fs/f0 = 40
    (Cell(2e6, 75e3, 200.0, "free", 0.1), FREE),
    (Cell(2e6, 250e3, 400.0, "free", 0.02), FREE),
    (Cell(2e6, 30e3, 600.0, "free", 0.05), FREE),
]

#: Steady tapping: each regime at every Q, at all three rates.
TAPPING_GRID = [
    (Cell(500e3, 70e3, 20.0, "attractive", 0.05, hold_fraction=0.9), TAPPING),
    (Cell(1e6, 70e3, 38.0, "attractive", 0.02), TAPPING),
    (Cell(2e6, 150e3, 100.0, "attractive", 0.1), TAPPING),
    (Cell(500e3, 70e3, 200.0, "attractive", 0.05), TAPPING),
    (Cell(1e6, 30e3, 400.0, "attractive", 0.05), TAPPING),
    (Cell(2e6, 100e3, 600.0, "attractive", 0.02), TAPPING),
    (Cell(1e6, 100e3, 20.0, "mixed", 0.1), TAPPING),
    (Cell(2e6, 70e3, 38.0, "mixed", 0.05), TAPPING),
    (Cell(500e3, 50e3, 100.0, "mixed", 0.02), TAPPING),
    (Cell(1e6, 150e3, 200.0, "mixed", 0.05), TAPPING),
    (Cell(2e6, 300e3, 400.0, "mixed", 0.1), TAPPING),
    (Cell(500e3, 70e3, 600.0, "mixed", 0.05), TAPPING),
    (Cell(2e6, 200e3, 20.0, "repulsive", 0.02), WALL),
    (Cell(500e3, 70e3, 38.0, "repulsive", 0.05), WALL),
    (Cell(2e6, 150e3, 100.0, "repulsive", 0.05), WALL),
    (Cell(1e6, 70e3, 200.0, "repulsive", 0.1), WALL),
    (Cell(500e3, 40e3, 400.0, "repulsive", 0.02, free_amplitude_nm=40.0), WALL),
    (Cell(1e6, 120e3, 600.0, "repulsive", 0.05, free_amplitude_nm=40.0), WALL),
]

GRID = FREE_GRID + TAPPING_GRID

#: Cells that fail for a cause in the estimator not yet removed (strict: they must fail until it is).
KNOWN_FAILURES = {
    "repulsive-2MHz-200kHz-Q20-0.02nm": ("Q' 2.0 % below the first-harmonic Qe against 1.9 % allowed on the wall at "
                                         "Q 20: REEP's noise-free estimate is covered (0.93/0.97), so the gap is "
                                         "between the estimator's expectation and averaging theory"),
}


def _params(cells):
    return [pytest.param(cell, tol, id=cell.name,
                         marks=[pytest.mark.xfail(strict=True, reason=KNOWN_FAILURES[cell.name])]
                         if cell.name in KNOWN_FAILURES else [])
            for cell, tol in cells]

#: The CI cells: free air at 2 MHz and fs/f0 = 40, and the three regimes at Q 38 to 200.
SHORT = [
    GRID[15],  # free, 2 MHz, 75 kHz, Q 200
    GRID[14],  # free, 2 MHz, 50 kHz (fs/f0 = 40)
    TAPPING_GRID[3],  # attractive, 0.5 MHz, Q 200
    TAPPING_GRID[7],  # mixed, 2 MHz, Q 38
    TAPPING_GRID[14],  # repulsive, 2 MHz, Q 100
]


def check(cell: Cell, tol: Tol, measured: dict) -> list[str]:
    """The cell's failures against its tolerances (empty: it passes)."""
    failures = []
    low, high = tol.coverage
    for name in ("f0_coverage", "q_coverage"):
        if not low <= measured[name] <= high:
            failures.append(f"{name} {measured[name]:.3f} outside [{low}, {high}]")
    if measured["flagged"] > tol.flagged_max:
        failures.append(f"flagged {measured['flagged']:.3f} > {tol.flagged_max}")
    for name, limit in limits(cell, tol, measured).items():
        if not abs(measured[name]) <= limit:
            failures.append(f"|{name}| {abs(measured[name]):.4g} > {limit:.4g}")
    return failures


def limits(cell: Cell, tol: Tol, measured: dict) -> dict[str, float]:
    """The cell's error limits by measured quantity (module docstring)."""
    if cell.regime == "free":
        return {
            "f0_bias_hz": max(tol.mean_in_row_std * measured["f0_std_hz"], tol.f0_floor_hz),
            "q_bias": max(tol.mean_in_row_std * measured["q_std"], tol.q_floor),
        }
    share = tol.wall_share if measured["min_separation_nm"] < 0 else tol.theory_share
    return {
        "f0_bias_hz": share * measured["f0_shift_scale_hz"] + 2.0 * measured["f0_std_hz"],
        "q_bias": share * measured["q_shift_scale"] + 2.0 * measured["q_std"],
    }


def _judge(cell: Cell, tol: Tol) -> None:
    measured = run_cell(cell)
    print(cell.name, {k: (round(v, 4) if isinstance(v, float) else v) for k, v in measured.items()})
    failures = check(cell, tol, measured)
    assert not failures, f"{cell.name}: " + "; ".join(failures)


@pytest.mark.parametrize(("cell", "tol"), _params(SHORT))
def test_envelope_short(cell, tol):
    _judge(cell, tol)


@pytest.mark.slow
@pytest.mark.parametrize(("cell", "tol"), _params(GRID))
def test_envelope_grid(cell, tol):
    _judge(cell, tol)


def _table(cells) -> list[str]:
    head = ("| cell | D | flagged | f0′ err | f0′ tol | Q′ err | Q′ tol | f0′ ±2σ cov | Q′ ±2σ cov | f0e − f0, least t_s | "
            "stated f0′ std | pass |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for cell, tol in cells:
        started = time.process_time()
        m = run_cell(cell)
        lim = limits(cell, tol, m)
        fails = check(cell, tol, m)
        q_tol = f"{lim['q_bias']:.2%}"
        shift = f"{m['f0_shift_hz']:+.1f} Hz, {m['min_separation_nm']:+.1f} nm" if "f0_shift_hz" in m else "—"
        lines.append(
            f"| {cell.name} | {m['rate_reduction']} | {m['flagged']:.3f} (≤ {tol.flagged_max:g}) | "
            f"{m['f0_bias_hz']:+.2f} Hz | {lim['f0_bias_hz']:.2f} Hz | {m['q_bias']:+.2%} | {q_tol} | "
            f"{m['f0_coverage']:.3f} | {m['q_coverage']:.3f} | {shift} | {m['f0_std_hz']:.3g} Hz | "
            f"{'yes' if not fails else 'NO: ' + '; '.join(fails)} |"
        )
        print(lines[-1], f"({time.process_time() - started:.1f} s CPU)", file=sys.stderr, flush=True)
    return lines


if __name__ == "__main__":
    print("\n".join(_table(GRID)))
